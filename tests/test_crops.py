"""Tests of square boxes, crop resampling and the image <-> crop pixel maps."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from perception import crops

finite = {"allow_nan": False, "allow_infinity": False}


def blob_image(centre: np.ndarray, sigma: float, height: int, width: int) -> np.ndarray:
    """A (H, W, 3) uint8 image of a Gaussian blob at sub-pixel ``centre`` (u, v) [px]."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    g = np.exp(-((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / (2.0 * sigma**2))
    img = np.round(255.0 * g).astype(np.uint8)
    return np.repeat(img[:, :, None], 3, axis=2)


def centroid(img: np.ndarray) -> np.ndarray:
    """Intensity centroid (u, v) [px] of the first channel."""
    w = img[:, :, 0].astype(np.float64)
    v, u = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    return np.array([(w * u).sum(), (w * v).sum()]) / w.sum()


def test_square_box_by_hand() -> None:
    # A 40 x 20 box centred at (30, 20).
    assert crops.square_box((10.0, 10.0, 50.0, 30.0)) == pytest.approx((10.0, 0.0, 40.0))
    # Scale 1.5: side 60 around the same centre.
    assert crops.square_box((10.0, 10.0, 50.0, 30.0), scale=1.5) == pytest.approx(
        (0.0, -10.0, 60.0)
    )
    # Shift by (0.25, -0.5) of the side (40): centre (40, 0).
    box = crops.square_box((10.0, 10.0, 50.0, 30.0), shift=(0.25, -0.5))
    assert box == pytest.approx((20.0, -20.0, 40.0))


@pytest.mark.parametrize(
    ("box", "match"),
    [
        ((0.0, 0.0, 0.0, 5.0), "x1 > x0"),
        ((0.0, 0.0, 1.0), "4 finite"),
        ((0, 0, np.nan, 1), "4 finite"),
    ],
)
def test_square_box_rejects_bad_boxes(box: tuple[float, ...], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        crops.square_box(box)


def test_random_square_box_is_seeded_and_bounded() -> None:
    box = (100.0, 50.0, 160.0, 90.0)  # 60 x 40, centre (130, 70)
    a = [crops.random_square_box(box, np.random.default_rng(3)) for _ in range(2)]
    assert a[0] == a[1]
    rng = np.random.default_rng(4)
    samples = np.array([crops.random_square_box(box, rng) for _ in range(500)])
    side = samples[:, 2]
    assert side.min() >= 0.9 * 60.0 and side.max() <= 1.3 * 60.0
    assert side.max() - side.min() > 0.3 * 60.0  # the scale actually varies
    centre = samples[:, :2] + side[:, None] / 2.0
    shift = (centre - (130.0, 70.0)) / side[:, None]
    assert np.abs(shift).max() <= 0.1 + 1e-12
    assert np.abs(shift).max() > 0.09
    with pytest.raises(ValueError, match="scale_range"):
        crops.random_square_box(box, rng, scale_range=(1.3, 0.9))


@settings(max_examples=100, deadline=None)
@given(
    x0=st.floats(-500.0, 500.0, **finite),
    y0=st.floats(-500.0, 500.0, **finite),
    side=st.floats(1.0, 1000.0, **finite),
    size=st.integers(1, 256),
    u=st.floats(-1000.0, 1000.0, **finite),
    v=st.floats(-1000.0, 1000.0, **finite),
)
def test_image_crop_maps_are_inverse(
    x0: float, y0: float, side: float, size: int, u: float, v: float
) -> None:
    box = (x0, y0, side)
    uv = np.array([u, v])
    np.testing.assert_allclose(
        crops.crop_to_image(crops.image_to_crop(uv, box, size), box, size), uv, atol=1e-9
    )
    np.testing.assert_allclose(crops.from_unit(crops.to_unit(uv, size), size), uv, atol=1e-9)
    # The affine matrix used for resampling is the same map.
    M = crops.crop_affine(box, size)
    np.testing.assert_allclose(
        M[:, :2] @ uv + M[:, 2], crops.crop_to_image(uv, box, size), rtol=1e-9, atol=1e-9
    )


def test_crop_edges_land_on_box_edges() -> None:
    box, size = (10.0, 20.0, 32.0), 64
    edges = np.array([[-0.5, -0.5], [size - 0.5, size - 0.5]])
    np.testing.assert_allclose(crops.crop_to_image(edges, box, size), [[10.0, 20.0], [42.0, 52.0]])
    np.testing.assert_allclose(crops.to_unit(edges, size), [[0.0, 0.0], [1.0, 1.0]])
    # Centre of the box <-> centre of the crop <-> (0.5, 0.5).
    np.testing.assert_allclose(crops.image_to_crop(np.array([26.0, 36.0]), box, size), [31.5, 31.5])


def test_identity_crop_returns_the_image() -> None:
    rng = np.random.default_rng(5)
    img = rng.integers(0, 256, size=(48, 48, 3), dtype=np.uint8)
    out = crops.crop_and_resize(img, (-0.5, -0.5, 48.0), size=48)
    np.testing.assert_array_equal(out, img)


def test_integer_shift_crop_is_exact_and_outside_is_black() -> None:
    rng = np.random.default_rng(6)
    img = rng.integers(1, 256, size=(40, 50, 3), dtype=np.uint8)
    # Box of side 30 starting at pixel edge (35.5, -10.5): columns 36..65, rows -10..19.
    out = crops.crop_and_resize(img, (35.5, -10.5, 30.0), size=30)
    assert out.shape == (30, 30, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out[10:, :14], img[0:20, 36:50])
    assert np.all(out[:10] == 0)  # rows above the image
    assert np.all(out[:, 14:] == 0)  # columns right of the image


def test_bright_pixel_lands_where_predicted() -> None:
    img = np.zeros((60, 80, 3), dtype=np.uint8)
    u, v = 47, 22
    img[v, u] = 255
    size, side = 64, 32.0  # 2x upsampling
    target = np.array([40, 13])  # integer crop pixel where the bright pixel should land
    x0, y0 = np.array([u, v]) - (target + 0.5) * side / size
    box = (float(x0), float(y0), side)
    np.testing.assert_allclose(crops.image_to_crop(np.array([u, v]), box, size), target)
    out = crops.crop_and_resize(img, box, size)[:, :, 0].astype(int)
    assert out[target[1], target[0]] == 255
    assert np.unravel_index(out.argmax(), out.shape) == (target[1], target[0])
    # Half a source pixel away on each side, bilinear gives half the intensity, symmetrically.
    for dv, du in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        assert out[target[1] + dv, target[0] + du] in (127, 128)
    assert out.sum() == pytest.approx(255 * 4, rel=0.01)  # a 2x-upsampled tent


@pytest.mark.parametrize("seed", range(6))
def test_blob_centroid_matches_mapping(seed: int) -> None:
    rng = np.random.default_rng(seed)
    centre = rng.uniform([30.0, 30.0], [130.0, 90.0])
    img = blob_image(centre, sigma=4.0, height=120, width=160)
    side = rng.uniform(50.0, 120.0)  # both up- and downsampling into 64 px
    # The blob stays at least 5 sigma inside the box, so the crop does not cut it.
    offset = rng.uniform(0.4, 0.6, size=2) * side
    box = (centre[0] - offset[0], centre[1] - offset[1], side)
    out = crops.crop_and_resize(img, box, size=64)
    predicted = crops.image_to_crop(centre, box, 64)
    np.testing.assert_allclose(centroid(out), predicted, atol=0.05)


def test_crop_and_resize_grayscale_and_validation() -> None:
    img = np.arange(100, dtype=np.uint8).reshape(10, 10)
    out = crops.crop_and_resize(img, (-0.5, -0.5, 10.0), size=10)
    np.testing.assert_array_equal(out, img)
    with pytest.raises(ValueError, match="uint8"):
        crops.crop_and_resize(img.astype(np.float32), (0.0, 0.0, 5.0))
    with pytest.raises(ValueError, match="side > 0"):
        crops.crop_and_resize(img, (0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="size must be a positive integer"):
        crops.crop_and_resize(img, (0.0, 0.0, 5.0), size=0)
