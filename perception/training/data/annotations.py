"""The annotation record of a rendered image: its entries of the four BOP scene files.

Poses and boxes follow `perception.training.data.bop` (BOP files in millimetres, ``scene_posegrasp``
in metres, pixel (0, 0) centred at (0, 0)). The full silhouette of an object that leaves the image
is counted outside it too, so ``visib_fract`` counts cut-off pixels as not visible.
"""

from __future__ import annotations

from typing import Any, cast

import cv2
import numpy as np
import trimesh
from scipy.spatial import ConvexHull

from perception.geometry import project
from perception.training.data.bop import MM_PER_M, bbox_xywh, box_xyxy, obj_id, pose_to_bop
from perception.training.data.distributions import RenderedImage
from posegrasp.core.transforms import invert_transform
from posegrasp.world.distractor_bank import bank_id, bank_mesh
from posegrasp.world.objects import load_object


def object_mesh(name: str) -> trimesh.Trimesh:
    """The mesh in O [m] of an annotated object: a built-in or user object's, or a bank mesh's
    (``bank-NNN``, `posegrasp.world.distractor_bank.bank_name`)."""
    mesh_id = bank_id(name)
    if mesh_id is None:
        return load_object(name).mesh
    mesh = bank_mesh(mesh_id)
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)


def object_diameter(name: str) -> float:
    """An annotated object's BOP diameter [m]: the largest distance between two vertices of its
    mesh (`object_mesh`)."""
    mesh_id = bank_id(name)
    if mesh_id is None:
        return load_object(name).diameter
    v = bank_mesh(mesh_id).vertices
    hull = v[ConvexHull(v).vertices]
    return float(np.linalg.norm(hull[:, None] - hull[None], axis=-1).max())


def full_silhouette(
    mesh: trimesh.Trimesh, T_C_O: np.ndarray, K: np.ndarray, mask: np.ndarray
) -> tuple[int, list[int]]:
    """Pixel count and BOP box of the whole silhouette, including any part outside the image.

    Inside the image the rendered mask is used. Only when the projected mesh leaves the image,
    its triangles are rasterised on a larger canvas (4 x 4 samples per pixel, fewer on very large
    canvases; a pixel counts if more than half of them are covered) for the part outside.

    Args:
        mesh: the object's mesh in O [m] (`object_mesh`).
        T_C_O: the object's pose in the camera (OpenCV), shape (4, 4) [m].
        K: intrinsics, shape (3, 3) [px].
        mask: the rendered silhouette inside the image, shape (H, W), bool.

    Returns:
        The silhouette's pixel count and its BOP box [x, y, w, h] [px] (x, y may be negative).
    """
    h, w = mask.shape
    verts = np.asarray(mesh.vertices) @ T_C_O[:3, :3].T + T_C_O[:3, 3]
    if np.any(verts[:, 2] <= 1e-3):
        return int(mask.sum()), bbox_xywh(mask)
    uv = verts[:, :2] / verts[:, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    if lo[0] >= -0.5 and lo[1] >= -0.5 and hi[0] <= w - 0.5 and hi[1] <= h - 0.5:
        return int(mask.sum()), bbox_xywh(mask)
    # Canvas [ox, ox + cw) x [oy, oy + ch) in image pixels, at most 5x the image.
    ox = int(np.floor(max(min(lo[0], 0.0), -2.0 * w)))
    oy = int(np.floor(max(min(lo[1], 0.0), -2.0 * h)))
    cw = int(np.ceil(min(max(hi[0], w), 3.0 * w))) - ox + 1
    ch = int(np.ceil(min(max(hi[1], h), 3.0 * h))) - oy + 1
    ss = 4 if ch * cw <= 4 * h * w else 2
    fine = np.zeros((ch * ss, cw * ss), np.uint8)
    pts = np.round(((uv - [ox, oy] + 0.5) * ss - 0.5) * 16).astype(np.int32)
    for tri in np.asarray(mesh.faces):
        cv2.fillConvexPoly(fine, pts[tri], 1, cv2.LINE_8, 4)
    # (ch, cw * ss), then (ch, cw): samples covered per pixel; arrays, as ss >= 2
    rows = cast(np.ndarray, sum(fine[i::ss].astype(np.uint16) for i in range(ss)))
    covered = cast(np.ndarray, sum(rows[:, j::ss] for j in range(ss)))
    canvas = (covered > ss * ss // 2).astype(np.uint8)
    canvas[-oy : -oy + h, -ox : -ox + w] = mask
    x, y, bw, bh = bbox_xywh(canvas)
    return int(canvas.sum()), [x + ox, y + oy, bw, bh]


def annotate(image: RenderedImage, seed: int, dist: str) -> dict[str, Any]:
    """The record of an image: its entries of the four scene files.

    Args:
        image: the rendered image with its instances.
        seed: the seed it was rendered from.
        dist: its distribution.

    Returns:
        ``{"scene_gt": [...], "scene_camera": {...}, "scene_gt_info": [...],
        "scene_posegrasp": {...}}``, one list entry per instance.
    """
    gts, infos, pg_objs = [], [], []
    T_W_C = invert_transform(image.T_C_W)
    for obj in image.objects:
        px_all, bbox_obj = full_silhouette(object_mesh(obj.name), obj.T_C_O, image.K, obj.mask)
        px_visib = int(obj.mask_visib.sum())
        gts.append({**pose_to_bop(obj.T_C_O), "obj_id": obj_id(obj.name)})
        infos.append(
            {
                "bbox_obj": bbox_obj,
                "bbox_visib": bbox_xywh(obj.mask_visib),
                "px_count_all": px_all,
                "px_count_valid": int(obj.mask.sum()),
                "px_count_visib": px_visib,
                "visib_fract": px_visib / px_all if px_all else 0.0,
            }
        )
        pg_objs.append(
            {
                **obj.extra,
                "class": obj.name,
                "obj_id": obj_id(obj.name),
                "T_C_O": obj.T_C_O.tolist(),
                "uv": project(image.K, obj.T_C_O[:3, 3]).tolist(),
                "box_xyxy": box_xyxy(obj.mask_visib),
                "visib_fract": infos[-1]["visib_fract"],
            }
        )
    camera = {
        "cam_K": [float(x) for x in image.K.reshape(-1)],
        "depth_scale": 1.0,
        "cam_R_w2c": [float(x) for x in image.T_C_W[:3, :3].reshape(-1)],
        "cam_t_w2c": [float(x) * MM_PER_M for x in image.T_C_W[:3, 3]],
    }
    pg = {
        **image.extra,
        "dist": dist,
        "seed": seed,
        "T_W_C": T_W_C.tolist(),
        "objects": pg_objs,
    }
    return {
        "scene_gt": gts,
        "scene_camera": camera,
        "scene_gt_info": infos,
        "scene_posegrasp": pg,
    }
