"""The pose nets over arrays of crops: predictions, decoding to full-image poses, per-crop errors
(docs/DESIGN.md §9) and their means.

The crop arrays are `perception.training.data.crop_sets.build_crops`' layout.
"""

from __future__ import annotations

import numpy as np
import torch

from perception.crops import crop_to_image, from_unit
from perception.geometry import decode
from perception.nets import CROP, PoseNet, normalise

#: (W, H) of the paper's images [px] (section 2.8), the frame of ``center_256_px``.
PAPER_IMAGE = (256, 256)


@torch.no_grad()
def predict(
    model: PoseNet, crops: np.ndarray, cls: np.ndarray, scale: np.ndarray, batch: int = 512
) -> dict[str, np.ndarray]:
    """Network outputs for arrays of crops: uv_unit (N, 2), p (N, 3), theta (N,)."""
    model.eval()
    uv, p, th = [], [], []
    for i in range(0, len(crops), batch):
        out = model(
            normalise(torch.from_numpy(crops[i : i + batch])),
            torch.from_numpy(cls[i : i + batch]),
            torch.from_numpy(scale[i : i + batch]).float(),
        )
        uv.append(out.uv_unit.numpy())
        p.append(out.p.numpy())
        th.append(out.theta.numpy())
    if not uv:
        return {"uv_unit": np.zeros((0, 2)), "p": np.zeros((0, 3)), "theta": np.zeros(0)}
    return {"uv_unit": np.concatenate(uv), "p": np.concatenate(p), "theta": np.concatenate(th)}


def decode_predictions(pred: dict, data: dict) -> dict[str, np.ndarray]:
    """Full-image origin pixels (N, 2) and poses T_C_O (N, 4, 4) from network outputs."""
    n = len(pred["p"])
    uv_img = np.zeros((n, 2))
    T = np.zeros((n, 4, 4))
    for i in range(n):
        box = tuple(data["box"][i])
        uv_img[i] = crop_to_image(from_unit(pred["uv_unit"][i].astype(float), CROP), box, CROP)
        T[i] = decode(pred["p"][i].astype(float), float(pred["theta"][i]), uv_img[i], data["K"][i])
    return {"uv": uv_img, "T_C_O": T}


def pose_metrics(
    dec: dict, data: dict, image_size: tuple[int, int] | None = None
) -> dict[str, np.ndarray]:
    """Per-crop errors: centre [px] in the full image and in the 64x64 crop, distance [%],
    rotation [deg].

    With ``image_size`` = (W, H) [px] of the images, also ``center_256_px``: the centre error
    in pixels of the image rescaled to the paper's `PAPER_IMAGE` (256x256), each axis on its own:
    ``sqrt((du * 256 / W)^2 + (dv * 256 / H)^2)`` (x by 0.4 and y by 0.5333 for 640x480).
    ``center_crop_px`` is ``center_px * 64 / side`` of the crop's square box."""
    T, Tg = dec["T_C_O"], data["T_C_O"]
    duv = dec["uv"] - data["uv"]
    centre = np.linalg.norm(duv, axis=1)
    dist = np.linalg.norm(T[:, :3, 3] - Tg[:, :3, 3], axis=1) / np.linalg.norm(Tg[:, :3, 3], axis=1)
    Rrel = np.einsum("nji,njk->nik", T[:, :3, :3], Tg[:, :3, :3])
    cosang = np.clip((np.trace(Rrel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    out = {
        "center_px": centre,
        "center_crop_px": centre * CROP / data["box"][:, 2],
        "distance_pct": 100 * dist,
        "rotation_deg": np.rad2deg(np.arccos(cosang)),
    }
    if image_size is not None:
        scale = np.asarray(PAPER_IMAGE, float) / np.asarray(image_size, float)
        out["center_256_px"] = np.linalg.norm(duv * scale, axis=1)
    return out


def evaluate_arrays(model: PoseNet, data: dict) -> dict[str, float]:
    """Mean errors over a crop set (`pose_metrics`) and the outlier rate (rotation > 15 deg).

    Returns:
        ``center_px``, ``center_crop_px`` [px], ``distance_pct`` [%], ``rotation_deg`` [deg]
        (means) and ``outlier_rate`` in [0, 1].
    """
    pred = predict(model, data["crops"], data["cls"], data["scale"])
    m = pose_metrics(decode_predictions(pred, data), data)
    return {k: float(np.mean(v)) for k, v in m.items()} | {
        "outlier_rate": float(np.mean(m["rotation_deg"] > 15))
    }
