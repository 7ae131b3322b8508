"""Pictures of poses: the projected model outline and axes drawn on an image."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from posegrasp.world.objects import load_object


def silhouette(
    T_C_O: np.ndarray,
    K: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    shape: tuple[int, int],
) -> np.ndarray:
    """Binary mask of a mesh rendered at pose T_C_O with intrinsics K.

    Args:
        T_C_O: object pose in the camera frame, shape (4, 4).
        K: intrinsics, shape (3, 3).
        vertices: mesh vertices in O [m], shape (N, 3).
        faces: triangle indices, shape (F, 3).
        shape: (H, W) of the mask.

    Returns:
        Mask, shape (H, W), bool; triangles behind the camera are skipped.
    """
    import cv2

    pc = vertices @ T_C_O[:3, :3].T + T_C_O[:3, 3]
    mask = np.zeros(shape, np.uint8)
    front = pc[:, 2] > 1e-6
    uv = np.zeros((len(pc), 2))
    uv[front] = (pc[front] @ K.T)[:, :2] / pc[front, 2:3]
    keep = front[faces].all(axis=1)
    tris = np.round(uv[faces[keep]] * 16).astype(np.int32)  # 4 bits of sub-pixel precision
    for tri in tris:
        cv2.fillConvexPoly(mask, tri, 1, lineType=cv2.LINE_8, shift=4)
    return mask.astype(bool)


def mask_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """The bounding box of a mask's pixels, (x0, y0, x1, y1) with x1 and y1 exclusive, from its
    row and column projections; None for an empty mask."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return None
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def mask_window(mask: np.ndarray, margin: float = 0.4) -> tuple[int, int, int, int] | None:
    """The mask's bounding box grown by `margin` times its width and height on each side and
    clipped to the image: (x0, y0, x1, y1), x1 and y1 exclusive; None for an empty mask."""
    box = mask_box(mask)
    if box is None:
        return None
    bx0, by0, bx1, by1 = box
    bw, bh = bx1 - bx0, by1 - by0
    x0, y0 = max(0, int(bx0 - margin * bw)), max(0, int(by0 - margin * bh))
    x1 = min(mask.shape[1], int(bx1 - 1 + margin * bw) + 1)
    y1 = min(mask.shape[0], int(by1 - 1 + margin * bh) + 1)
    return x0, y0, x1, y1


def window_intrinsics(K: np.ndarray, x0: float, y0: float) -> np.ndarray:
    """The intrinsics of the image window whose top-left pixel is (x0, y0), (3, 3) float64."""
    return np.asarray(K, np.float64) - np.array([[0, 0, x0], [0, 0, y0], [0, 0, 0]])


def silhouette_agreement(
    name: str, poses: list[np.ndarray], K: np.ndarray, mask: np.ndarray, hidden: list[np.ndarray]
) -> np.ndarray:
    """IoU of each pose's rendered silhouette with the detected (visible) mask, over the pixels
    no other detection covers, in a window of 1.8 times the mask's box; (len(poses),)."""
    box = mask_window(mask)
    if box is None:
        return np.zeros(len(poses))
    x0, y0, x1, y1 = box
    seen = ~np.logical_or.reduce([h[y0:y1, x0:x1] for h in hidden]) if hidden else True
    visible = mask[y0:y1, x0:x1] & seen
    Kw = window_intrinsics(K, x0, y0)
    mesh = load_object(name).mesh
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    out = np.zeros(len(poses))
    for i, T in enumerate(poses):
        sil = silhouette(T, Kw, v, f, visible.shape) & seen
        union = np.count_nonzero(sil | visible)
        out[i] = np.count_nonzero(sil & visible) / union if union else 0.0
    return out


def draw_pose(
    image: np.ndarray,
    T_C_O: np.ndarray,
    K: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    color: tuple[int, int, int] = (0, 255, 0),
    axis_length: float = 0.06,
    label: str | None = None,
    label_below: bool = False,
) -> np.ndarray:
    """A copy of an RGB image with the pose's model outline and axes drawn on it.

    Axes: x red, y green, z blue, `axis_length` [m] long from the object's origin. The label goes
    above the outline, or below it with `label_below`.
    """
    import cv2

    out = np.ascontiguousarray(image.copy())
    mask = silhouette(T_C_O, K, vertices, faces, out.shape[:2]).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, color, 2, lineType=cv2.LINE_AA)
    pts = np.array([[0, 0, 0], [axis_length, 0, 0], [0, axis_length, 0], [0, 0, axis_length]])
    pc = pts @ T_C_O[:3, :3].T + T_C_O[:3, 3]
    if np.all(pc[:, 2] > 1e-6):
        uv = (pc @ K.T)[:, :2] / pc[:, 2:3]
        o = tuple(np.round(uv[0]).astype(int))
        for i, c in zip((1, 2, 3), ((255, 0, 0), (0, 255, 0), (0, 0, 255)), strict=True):
            cv2.line(out, o, tuple(np.round(uv[i]).astype(int)), c, 2, lineType=cv2.LINE_AA)
    if label:
        if contours:
            pts2 = np.concatenate([c[:, 0] for c in contours])
            x = pts2[:, 0].min()
            y = pts2[:, 1].max() + 16 if label_below else pts2[:, 1].min() - 6
        else:
            x, y = 5, 20
        cv2.putText(
            out,
            label,
            (int(x), min(out.shape[0] - 4, max(12, int(y)))),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5,
            color,
            1,
            cv2.LINE_AA,
        )
    return out


def draw_estimate(
    image: np.ndarray,
    K: np.ndarray,
    T_true: np.ndarray,
    T_est: np.ndarray | None,
    vertices: np.ndarray,
    faces: np.ndarray,
) -> np.ndarray:
    """A copy of an image with the true pose drawn in white (label "true") and, when there is
    one, the estimate in green (label "estimate", below its outline)."""
    img = draw_pose(image, T_true, K, vertices, faces, color=(255, 255, 255), label="true")
    if T_est is None:
        return img
    return draw_pose(
        img, T_est, K, vertices, faces, color=(0, 255, 0), label="estimate", label_below=True
    )


def draw_detections(rgb: np.ndarray, K: np.ndarray, found: Sequence[Any]) -> np.ndarray:
    """The image with every detection's estimated pose drawn: projected model outline, axes
    (x red, y green, z blue) and ``class score``.

    Args:
        rgb: image, shape (H, W, 3), uint8.
        K: its intrinsics, shape (3, 3) [px].
        found: detections with ``name``, ``score`` and ``T_C_O``
            (`perception.hybrid.PoseDetection`).
    """
    img = rgb
    colours = ((0, 255, 0), (255, 255, 0), (255, 0, 255), (0, 255, 255), (255, 128, 0))
    for i, d in enumerate(found):
        mesh = load_object(d.name).mesh
        img = draw_pose(
            img,
            d.T_C_O,
            K,
            np.asarray(mesh.vertices),
            np.asarray(mesh.faces),
            color=colours[i % len(colours)],
            label=f"{d.name} {d.score:.2f}",
        )
    return img
