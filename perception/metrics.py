"""Pose-error metrics of one estimate (docs/DESIGN.md §9).

Summaries over many errors (recall, AUC, statistics) are in `perception.summaries`.

Pure numpy functions with the BOP signature ``(R_est, t_est, R_gt, t_gt, ...)``. Units inside
are SI: metres and radians, except where a name says otherwise (``_deg``, ``_px``, ``_pct``).
Rotations are (3, 3) ``R_C_O`` and translations (3,) or (3, 1) ``t_C_O`` [m], mapping model
points (object frame O, [m]) into the camera frame C.

A symmetry set ``syms`` is a list of dicts ``{"R": (3, 3), "t": (3, 1) [m]}``: transforms S of
the object frame that leave the object's appearance unchanged (BOP's convention; the identity
must be included, see :func:`identity_symmetry`).

References:
    - Hinterstoisser et al., "Model based training, detection and pose estimation of
      texture-less 3D objects in heavily cluttered scenes", ACCV 2012 (ADD, ADI).
    - Hodan et al., "BOP: Benchmark for 6D object pose estimation", ECCV 2018, and Hodan et al.,
      "BOP challenge 2020 on 6D object localization", ECCV Workshops 2020 (MSSD, MSPD, recall).
    - Staszak & Belter, ICINCO 2019, eqs. 8-9 (centre error, relative distance error, rotation
      error).
    - Xiang et al., "PoseCNN", RSS 2018 (area under the ADD accuracy-threshold curve).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from posegrasp.core.errors import InvalidArgumentError

Symmetry = dict[str, np.ndarray]


def _rot(R: object, name: str) -> np.ndarray:
    """Validate a finite (3, 3) matrix."""
    arr = np.asarray(R, dtype=np.float64)
    if arr.shape != (3, 3) or not np.all(np.isfinite(arr)):
        raise InvalidArgumentError(f"{name} must be a finite (3, 3) matrix, got shape {arr.shape}")
    return arr


def _vec3(t: object, name: str) -> np.ndarray:
    """Validate a finite translation of shape (3,) or (3, 1); returns (3,)."""
    arr = np.asarray(t, dtype=np.float64)
    if arr.shape not in ((3,), (3, 1)) or not np.all(np.isfinite(arr)):
        raise InvalidArgumentError(
            f"{name} must be a finite vector of shape (3,) or (3, 1), got {arr.shape}"
        )
    return arr.reshape(3)


def _points(pts: object) -> np.ndarray:
    """Validate model points (N, 3) [m], N >= 1."""
    arr = np.asarray(pts, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0 or not np.all(np.isfinite(arr)):
        raise InvalidArgumentError(
            f"pts must be a finite (N, 3) array with N >= 1, got shape {arr.shape}"
        )
    return arr


def _syms(syms: Sequence[Symmetry]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Validate a symmetry list; returns [(R (3, 3), t (3,))]."""
    if len(syms) == 0:
        raise InvalidArgumentError("syms must hold at least one transform (include the identity)")
    out = []
    for i, sym in enumerate(syms):
        if "R" not in sym or "t" not in sym:
            raise InvalidArgumentError(
                f"syms[{i}] must be a dict with keys 'R' and 't', got {sorted(sym)}"
            )
        out.append((_rot(sym["R"], f"syms[{i}]['R']"), _vec3(sym["t"], f"syms[{i}]['t']")))
    return out


def _transform(pts: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Apply x -> R x + t to (N, 3) points."""
    return pts @ R.T + t


def identity_symmetry() -> list[Symmetry]:
    """The symmetry set of an object with no symmetry: ``[{"R": I, "t": 0 (3, 1)}]``."""
    return [{"R": np.eye(3), "t": np.zeros((3, 1))}]


def add(
    R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray
) -> float:
    """Average Distance of model points, ADD [m] (Hinterstoisser et al. 2012; BOP ``add``).

    ``mean_x || (R_est x + t_est) - (R_gt x + t_gt) ||``.

    Args:
        R_est, t_est: Estimated pose (3, 3), (3,) or (3, 1) [m].
        R_gt, t_gt: Ground-truth pose.
        pts: Model points in O (N, 3) [m].

    Returns:
        The error [m].
    """
    pts = _points(pts)
    est = _transform(pts, _rot(R_est, "R_est"), _vec3(t_est, "t_est"))
    gt = _transform(pts, _rot(R_gt, "R_gt"), _vec3(t_gt, "t_gt"))
    return float(np.linalg.norm(est - gt, axis=1).mean())


def adi(
    R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray
) -> float:
    """Average distance to the closest model point, ADI / ADD-S [m] (Hinterstoisser et al. 2012).

    ``mean_{x1} min_{x2} || (R_gt x1 + t_gt) - (R_est x2 + t_est) ||`` (BOP ``adi``), with the
    nearest neighbours found by a k-d tree.

    Args:
        R_est, t_est: Estimated pose (3, 3), (3,) or (3, 1) [m].
        R_gt, t_gt: Ground-truth pose.
        pts: Model points in O (N, 3) [m].

    Returns:
        The error [m]; never larger than :func:`add`.
    """
    pts = _points(pts)
    est = _transform(pts, _rot(R_est, "R_est"), _vec3(t_est, "t_est"))
    gt = _transform(pts, _rot(R_gt, "R_gt"), _vec3(t_gt, "t_gt"))
    dists, _ = cKDTree(est).query(gt, k=1)
    return float(np.mean(dists))


def mssd(
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    pts: np.ndarray,
    syms: Sequence[Symmetry],
) -> float:
    """Maximum Symmetry-aware Surface Distance, MSSD [m] (Hodan et al. 2020; BOP ``mssd``).

    ``min_S max_x || (R_est x + t_est) - (R_gt (R_S x + t_S) + t_gt) ||`` over the symmetries S.

    Args:
        R_est, t_est: Estimated pose (3, 3), (3,) or (3, 1) [m].
        R_gt, t_gt: Ground-truth pose.
        pts: Model points in O (N, 3) [m].
        syms: Symmetry set of the object (see module docstring).

    Returns:
        The error [m].
    """
    pts = _points(pts)
    R_gt, t_gt = _rot(R_gt, "R_gt"), _vec3(t_gt, "t_gt")
    est = _transform(pts, _rot(R_est, "R_est"), _vec3(t_est, "t_est"))
    errors = []
    for R_s, t_s in _syms(syms):
        gt = _transform(pts, R_gt @ R_s, R_gt @ t_s + t_gt)
        errors.append(np.linalg.norm(est - gt, axis=1).max())
    return float(min(errors))


def _project_or_inf(K: np.ndarray, pts_C: np.ndarray) -> np.ndarray:
    """Project (N, 3) camera points with K; points with z <= 0 give inf."""
    h = pts_C @ K.T
    z = h[:, 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = h[:, :2] / z
    return np.where(z > 0.0, uv, np.inf)


def mspd(
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    K: np.ndarray,
    pts: np.ndarray,
    syms: Sequence[Symmetry],
) -> float:
    """Maximum Symmetry-aware Projection Distance, MSPD [px] (Hodan et al. 2020; BOP ``mspd``).

    ``min_S max_x || proj(R_est x + t_est) - proj(R_gt (R_S x + t_S) + t_gt) ||`` with the
    pinhole projection ``proj`` of K. A point at or behind the camera plane gives inf.

    Args:
        R_est, t_est: Estimated pose (3, 3), (3,) or (3, 1) [m].
        R_gt, t_gt: Ground-truth pose.
        K: Intrinsics (3, 3).
        pts: Model points in O (N, 3) [m].
        syms: Symmetry set of the object.

    Returns:
        The error [px].
    """
    pts = _points(pts)
    K = _rot(K, "K")
    R_gt, t_gt = _rot(R_gt, "R_gt"), _vec3(t_gt, "t_gt")
    uv_est = _project_or_inf(K, _transform(pts, _rot(R_est, "R_est"), _vec3(t_est, "t_est")))
    errors = []
    for R_s, t_s in _syms(syms):
        uv_gt = _project_or_inf(K, _transform(pts, R_gt @ R_s, R_gt @ t_s + t_gt))
        with np.errstate(invalid="ignore"):
            d = np.linalg.norm(uv_est - uv_gt, axis=1)
        errors.append(np.inf if not np.all(np.isfinite(d)) else d.max())
    return float(min(errors))


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Angle of the relative rotation [deg] (paper eq. 9; BOP ``re``).

    ``arccos((trace(R_est^T R_gt) - 1) / 2)``, the argument clipped to [-1, 1].

    Args:
        R_est: Estimated rotation (3, 3).
        R_gt: Ground-truth rotation (3, 3).

    Returns:
        The angle [deg], in [0, 180].
    """
    R_est, R_gt = _rot(R_est, "R_est"), _rot(R_gt, "R_gt")
    cos = (np.trace(R_est.T @ R_gt) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, float(cos)))))


def rotation_error_sym_deg(R_est: np.ndarray, R_gt: np.ndarray, syms: Sequence[Symmetry]) -> float:
    """Symmetry-aware rotation error [deg]: ``min_S rotation_error_deg(R_est, R_gt R_S)``.

    Args:
        R_est: Estimated rotation (3, 3).
        R_gt: Ground-truth rotation (3, 3).
        syms: Symmetry set of the object (only the rotations are used).

    Returns:
        The smallest angle [deg] over the symmetries.
    """
    R_gt = _rot(R_gt, "R_gt")
    return min(rotation_error_deg(R_est, R_gt @ R_s) for R_s, _ in _syms(syms))


def translation_error_pct(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Relative distance error [%] (paper eq. 9): ``|t_gt - t_est| / |t_gt| * 100``.

    Args:
        t_est: Estimated translation (3,) or (3, 1) [m].
        t_gt: Ground-truth translation, non-zero.

    Returns:
        The error [%].
    """
    t_est, t_gt = _vec3(t_est, "t_est"), _vec3(t_gt, "t_gt")
    norm = float(np.linalg.norm(t_gt))
    if norm == 0.0:
        raise InvalidArgumentError("t_gt must be non-zero")
    return float(np.linalg.norm(t_gt - t_est)) / norm * 100.0


def center_error_px(uv_est: np.ndarray, uv_gt: np.ndarray) -> float | np.ndarray:
    """Centre error [px] (paper eq. 8): ``sqrt((u^ - u)^2 + (v^ - v)^2)``.

    Args:
        uv_est: Estimated origin pixel(s), (2,) or (N, 2) [px].
        uv_gt: True origin pixel(s), same shape.

    Returns:
        A float for (2,) inputs, else an (N,) array [px].
    """
    a, b = np.asarray(uv_est, dtype=np.float64), np.asarray(uv_gt, dtype=np.float64)
    if a.shape != b.shape or a.ndim not in (1, 2) or a.shape[-1] != 2:
        raise InvalidArgumentError(
            f"uv_est and uv_gt must share a shape (2,) or (N, 2): {a.shape}, {b.shape}"
        )
    d = np.linalg.norm(a - b, axis=-1)
    return float(d) if d.ndim == 0 else d


def add_metric_name(syms: Sequence[Symmetry], atol: float = 1e-9) -> str:
    """The ADD(-S) variant for an object: ``"ADD"`` when its symmetry set holds only the
    identity, ``"ADD-S"`` (:func:`adi`) when it holds another transform (Hinterstoisser et al.
    2012). ``atol`` bounds the entries of R [-] and t [m] that still count as the identity."""
    eye = np.eye(3)
    identity = [
        np.allclose(R, eye, atol=atol) and np.allclose(t, 0.0, atol=atol) for R, t in _syms(syms)
    ]
    return "ADD" if all(identity) else "ADD-S"


def mask_iou(mask_a: np.ndarray, mask_b: np.ndarray) -> float:
    """Intersection over union of two binary masks (paper Table 2's IoU).

    Args:
        mask_a: (H, W) mask; non-zero means inside.
        mask_b: (H, W) mask.

    Returns:
        |A and B| / |A or B| in [0, 1]; 1.0 when both masks are empty (they agree).
    """
    a, b = np.asarray(mask_a).astype(bool), np.asarray(mask_b).astype(bool)
    if a.shape != b.shape or a.ndim != 2:
        raise InvalidArgumentError(
            f"masks must be 2D with the same shape, got {a.shape} and {b.shape}"
        )
    union = int(np.count_nonzero(a | b))
    if union == 0:
        return 1.0
    return int(np.count_nonzero(a & b)) / union


def box_iou(box_a: np.ndarray | Sequence[float], box_b: np.ndarray | Sequence[float]) -> float:
    """Intersection over union of two axis-aligned boxes (x0, y0, x1, y1) [px].

    Returns:
        Area of the intersection over the area of the union, in [0, 1]; 0.0 when the union is
        empty.
    """
    a, b = np.asarray(box_a, np.float64), np.asarray(box_b, np.float64)
    if a.shape != (4,) or b.shape != (4,):
        raise InvalidArgumentError(f"boxes must have shape (4,), got {a.shape} and {b.shape}")
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    area = lambda x: max(0.0, x[2] - x[0]) * max(0.0, x[3] - x[1])  # noqa: E731
    union = area(a) + area(b) - inter
    return float(inter / union) if union > 0 else 0.0


def diameter(pts: np.ndarray) -> float:
    """Largest distance between two model points [m] (the d of the ADD(-S) < 0.1 d test).

    Args:
        pts: Model points (N, 3) [m].

    Returns:
        The diameter [m] (exact over the points, via their convex hull when N is large).
    """
    pts = _points(pts)
    if pts.shape[0] > 64:
        from scipy.spatial import ConvexHull, QhullError

        try:
            pts = pts[ConvexHull(pts).vertices]
        except QhullError:  # degenerate (flat or collinear) point sets: use all points
            pass
    best = 0.0
    for start in range(0, pts.shape[0], 1024):
        diff = pts[start : start + 1024, None, :] - pts[None, :, :]
        best = max(best, float((diff * diff).sum(axis=-1).max()))
    return math.sqrt(best)


def error_components(T_est: np.ndarray, T_true: np.ndarray) -> dict[str, float]:
    """A pose error split the way `sim.pose_noise.PoseNoise` applies it, relative to the true
    camera ray u.

    Returns:
        ``ray_m``: |translation error along u| [m]; ``lateral_m``: its norm across u [m];
        ``inplane_deg``: the rotation error's twist about u; ``outplane_deg``: its swing about an
        axis perpendicular to u (swing-twist decomposition of R_est R_true^T) [deg].
    """
    T_est, T_true = np.asarray(T_est, float), np.asarray(T_true, float)
    u = T_true[:3, 3] / np.linalg.norm(T_true[:3, 3])
    dt = T_est[:3, 3] - T_true[:3, 3]
    along = float(dt @ u)
    R = T_est[:3, :3] @ T_true[:3, :3].T
    # Unit quaternion (w, v) of R, w >= 0.
    w = np.sqrt(max(0.0, 1.0 + np.trace(R))) / 2.0
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if w > 1e-6:
        v = v / (4.0 * w)
    else:  # a half turn: v is the axis
        _vals, vecs = np.linalg.eigh((R + np.eye(3)) / 2.0)
        v = vecs[:, -1]
    twist = float(v @ u)
    # Swing q_s = q_t^-1 q with the twist q_t = (w, twist u) / |.|; its angle by atan2 (stable).
    n = np.hypot(w, twist)
    tw, tv = (w / n, twist / n * u) if n > 1e-12 else (1.0, np.zeros(3))
    sw = tw * w + tv @ v
    sv = tw * v - w * tv - np.cross(tv, v)
    return {
        "ray_m": abs(along),
        "lateral_m": float(np.linalg.norm(dt - along * u)),
        "inplane_deg": float(np.degrees(2.0 * np.arctan2(abs(twist), w))),
        "outplane_deg": float(np.degrees(2.0 * np.arctan2(np.linalg.norm(sv), abs(sw)))),
    }
