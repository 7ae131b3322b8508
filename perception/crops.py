"""Square crops around detections, and the pixel maps between image and crop.

docs/DESIGN.md §4, §7.

Coordinates are continuous pixel coordinates (docs/DESIGN.md §4): the centre of pixel
(0, 0) is (0, 0), so pixel (i, j) covers [i - 0.5, i + 0.5] x [j - 0.5, j + 0.5].

A *square box* ``(x0, y0, side)`` is the image region [x0, x0 + side] x [y0, y0 + side] [px].
A crop of ``size`` pixels covers exactly that region: the crop's outer edges (-0.5 and
size - 0.5 in crop coordinates) land on the box edges, so with ``s = side / size``::

    u_image = x0 + (u_crop + 0.5) * s        u_crop = (u_image - x0) / s - 0.5

*Unit* crop coordinates put the crop's outer edges at 0 and 1: ``unit = (u_crop + 0.5) / size``.
"""

from __future__ import annotations

import numpy as np

from posegrasp.core.errors import InvalidArgumentError

SquareBox = tuple[float, float, float]


def _check_box_xyxy(box_xyxy: object) -> np.ndarray:
    """Validate a detection box (x0, y0, x1, y1) [px] with x1 > x0 and y1 > y0."""
    box = np.asarray(box_xyxy, dtype=np.float64)
    if box.shape != (4,) or not np.all(np.isfinite(box)):
        raise InvalidArgumentError(
            f"box_xyxy must be 4 finite numbers (x0, y0, x1, y1), got {box_xyxy!r}"
        )
    if box[2] <= box[0] or box[3] <= box[1]:
        raise InvalidArgumentError(f"box_xyxy must have x1 > x0 and y1 > y0, got {box.tolist()}")
    return box


def _check_square_box(square_box: object) -> tuple[float, float, float]:
    """Validate a square box (x0, y0, side) [px] with side > 0."""
    box = np.asarray(square_box, dtype=np.float64)
    if box.shape != (3,) or not np.all(np.isfinite(box)) or box[2] <= 0.0:
        raise InvalidArgumentError(
            f"square_box must be finite (x0, y0, side) with side > 0, got {square_box!r}"
        )
    return float(box[0]), float(box[1]), float(box[2])


def _check_size(size: int) -> int:
    """Validate a crop size in pixels."""
    if int(size) != size or size <= 0:
        raise InvalidArgumentError(f"size must be a positive integer, got {size!r}")
    return int(size)


def _check_uv(uv: object, name: str) -> np.ndarray:
    """Validate pixel coordinates of shape (2,) or (N, 2)."""
    arr = np.asarray(uv, dtype=np.float64)
    if arr.ndim not in (1, 2) or arr.shape[-1] != 2:
        raise InvalidArgumentError(f"{name} must have shape (2,) or (N, 2), got {arr.shape}")
    return arr


def square_box(
    box_xyxy: np.ndarray | tuple[float, float, float, float],
    scale: float = 1.0,
    shift: tuple[float, float] = (0.0, 0.0),
) -> SquareBox:
    """The square box around a detection box.

    Args:
        box_xyxy: Detection box (x0, y0, x1, y1) [px], continuous coordinates.
        scale: Side of the square as a multiple of max(width, height); > 0.
        shift: Shift of the square's centre from the box centre, as fractions of the side.

    Returns:
        ``(x0, y0, side)`` [px] of the square, side = max(w, h) * scale, centred at the box
        centre + shift * side.
    """
    box = _check_box_xyxy(box_xyxy)
    if not np.isfinite(scale) or scale <= 0.0:
        raise InvalidArgumentError(f"scale must be positive, got {scale}")
    shift_arr = np.asarray(shift, dtype=np.float64)
    if shift_arr.shape != (2,) or not np.all(np.isfinite(shift_arr)):
        raise InvalidArgumentError(f"shift must be 2 finite numbers, got {shift!r}")
    side = float(max(box[2] - box[0], box[3] - box[1]) * scale)
    cu = 0.5 * (box[0] + box[2]) + shift_arr[0] * side
    cv = 0.5 * (box[1] + box[3]) + shift_arr[1] * side
    return float(cu - 0.5 * side), float(cv - 0.5 * side), side


def random_square_box(
    box_xyxy: np.ndarray | tuple[float, float, float, float],
    rng: np.random.Generator,
    max_shift: float = 0.1,
    scale_range: tuple[float, float] = (0.9, 1.3),
) -> SquareBox:
    """An imprecise square box, as used for training crops (paper 2.8, docs/DESIGN.md §7).

    Args:
        box_xyxy: Detection box (x0, y0, x1, y1) [px].
        rng: Random generator.
        max_shift: Each centre shift component is uniform in [-max_shift, max_shift] (fractions
            of the side).
        scale_range: The scale is uniform in [low, high].

    Returns:
        ``(x0, y0, side)`` [px].
    """
    low, high = scale_range
    if not 0.0 < low <= high:
        raise InvalidArgumentError(f"scale_range must satisfy 0 < low <= high, got {scale_range}")
    if max_shift < 0.0:
        raise InvalidArgumentError(f"max_shift must be >= 0, got {max_shift}")
    scale = float(rng.uniform(low, high))
    shift = rng.uniform(-max_shift, max_shift, size=2)
    return square_box(box_xyxy, scale=scale, shift=(float(shift[0]), float(shift[1])))


def crop_affine(square_box: SquareBox, size: int) -> np.ndarray:
    """The 2x3 affine map from crop pixel coordinates to image pixel coordinates."""
    x0, y0, side = _check_square_box(square_box)
    s = side / _check_size(size)
    return np.array([[s, 0.0, x0 + 0.5 * s], [0.0, s, y0 + 0.5 * s]])


def crop_and_resize(image: np.ndarray, square_box: SquareBox, size: int = 64) -> np.ndarray:
    """Cut a square region out of an image and resample it to size x size (bilinear).

    Parts of the box outside the image are filled with 0.

    Args:
        image: (H, W, C) or (H, W) uint8 image.
        square_box: ``(x0, y0, side)`` [px].
        size: Output side [px].

    Returns:
        (size, size, C) or (size, size) uint8 crop.
    """
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise InvalidArgumentError("image must be a uint8 array of shape (H, W) or (H, W, C)")
    import cv2  # deferred: keeps `import perception` light

    size = _check_size(size)
    M = crop_affine(square_box, size)
    return cv2.warpAffine(
        np.ascontiguousarray(image),
        M,
        (size, size),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )


def image_to_crop(uv: np.ndarray, square_box: SquareBox, size: int) -> np.ndarray:
    """Map image pixel coordinates to crop pixel coordinates.

    Args:
        uv: Image coordinates [px], (2,) or (N, 2).
        square_box: ``(x0, y0, side)`` [px].
        size: Crop side [px].

    Returns:
        Crop coordinates [px], same shape as ``uv``.
    """
    uv = _check_uv(uv, "uv")
    x0, y0, side = _check_square_box(square_box)
    s = side / _check_size(size)
    return (uv - np.array([x0, y0])) / s - 0.5


def crop_to_image(uv_crop: np.ndarray, square_box: SquareBox, size: int) -> np.ndarray:
    """Map crop pixel coordinates to image pixel coordinates (inverse of image_to_crop).

    Args:
        uv_crop: Crop coordinates [px], (2,) or (N, 2).
        square_box: ``(x0, y0, side)`` [px].
        size: Crop side [px].

    Returns:
        Image coordinates [px], same shape as ``uv_crop``.
    """
    uv_crop = _check_uv(uv_crop, "uv_crop")
    x0, y0, side = _check_square_box(square_box)
    s = side / _check_size(size)
    return np.array([x0, y0]) + (uv_crop + 0.5) * s


def to_unit(uv_crop: np.ndarray, size: int) -> np.ndarray:
    """Crop pixel coordinates to unit coordinates (crop edges at 0 and 1), shape kept."""
    return (_check_uv(uv_crop, "uv_crop") + 0.5) / _check_size(size)


def from_unit(uv_unit: np.ndarray, size: int) -> np.ndarray:
    """Unit crop coordinates to crop pixel coordinates (inverse of to_unit), shape kept."""
    return _check_uv(uv_unit, "uv_unit") * _check_size(size) - 0.5
