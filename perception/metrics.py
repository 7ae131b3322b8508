"""Pose-error metrics of one estimate (docs/DESIGN.md §9).

Summaries over many errors (recall, AUC, statistics) are in `perception.summaries`; BOP's own
summaries, the average recalls AR_MSSD, AR_MSPD and AR_VSD, are here beside the errors they
average (`ar_mssd`, `ar_mspd`, `ar_vsd`), with BOP's symmetry sets (`symmetry_set`) and VSD
(`vsd`, on the software rasteriser `render_depth`). MSSD, MSPD, the symmetry sets and VSD agree
with the BOP toolkit's ``pose_error`` and ``misc.get_symmetry_transformations`` to rounding, but
for MSPD with a model point at or behind the camera plane: inf here, a meaningless finite number
there.

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
      "BOP challenge 2020 on 6D object localization", ECCV Workshops 2020 (MSSD, MSPD, VSD,
      average recall).
    - Hodan et al., "On evaluation of 6D object pose estimation", ECCV Workshops 2016 (VSD).
    - Staszak & Belter, ICINCO 2019, eqs. 8-9 (centre error, relative distance error, rotation
      error).
    - Xiang et al., "PoseCNN", RSS 2018 (area under the ADD accuracy-threshold curve).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import NamedTuple, cast

import numpy as np
from scipy.spatial import cKDTree

from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world.meshes import points_diameter

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
    return closest_symmetry(R_est, t_est, R_gt, t_gt, pts, syms)[1]


def closest_symmetry(
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    pts: np.ndarray,
    syms: Sequence[Symmetry],
) -> tuple[int, float]:
    """The symmetry S whose equivalent true pose ``(R_gt R_S, R_gt t_S + t_gt)`` the estimate is
    closest to, by MSSD's distance: ``argmin_S max_x || (R_est x + t_est) - (R_gt (R_S x + t_S)
    + t_gt) ||``, the first such S on a tie (so the identity, when it comes first).

    The pose errors of an estimate of a symmetric object are measured against that equivalent
    pose (`symmetric_pose`), the one BOP's MSSD, and so a judgement of correctness made with it,
    matches the estimate to. It may differ from the S of the smallest rotation error
    (`rotation_error_sym_deg`): MSSD also weighs the translation, t_S included, and a turn by
    how far it moves the model's farthest points.

    Args:
        R_est, t_est: Estimated pose (3, 3), (3,) or (3, 1) [m].
        R_gt, t_gt: Ground-truth pose.
        pts: Model points in O (N, 3) [m].
        syms: Symmetry set of the object (see module docstring).

    Returns:
        (the index of S in syms, its distance [m]: the MSSD of :func:`mssd`).
    """
    pts = _points(pts)
    R_gt, t_gt = _rot(R_gt, "R_gt"), _vec3(t_gt, "t_gt")
    est = _transform(pts, _rot(R_est, "R_est"), _vec3(t_est, "t_est"))
    errors = []
    for R_s, t_s in _syms(syms):
        gt = _transform(pts, R_gt @ R_s, R_gt @ t_s + t_gt)
        errors.append(np.linalg.norm(est - gt, axis=1).max())
    best = min(range(len(errors)), key=errors.__getitem__)
    return best, float(errors[best])


def symmetric_pose(T_gt: np.ndarray, sym: Symmetry) -> np.ndarray:
    """The true pose turned by a symmetry, ``T_gt S``: as true as T_gt, the object looking the
    same.

    Args:
        T_gt: Ground-truth pose T_C_O (4, 4) [m].
        sym: One symmetry ``{"R": (3, 3), "t": (3,) or (3, 1) [m]}`` of the object, T_O_O'.

    Returns:
        T_C_O' (4, 4) [m]: rotation ``R_gt R_S``, translation ``R_gt t_S + t_gt``; T_gt's own
        values, to the bit, for the identity.
    """
    T_gt = np.asarray(T_gt, dtype=np.float64)
    if T_gt.shape != (4, 4) or not np.all(np.isfinite(T_gt)):
        raise InvalidArgumentError(f"T_gt must be a finite (4, 4) matrix, got shape {T_gt.shape}")
    ((R_s, t_s),) = _syms([sym])
    out = T_gt.copy()
    if np.array_equal(R_s, np.eye(3)) and not np.any(t_s):
        return out
    out[:3, :3] = T_gt[:3, :3] @ R_s
    out[:3, 3] = T_gt[:3, :3] @ t_s + T_gt[:3, 3]
    return out


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
    return points_diameter(_points(pts))


def error_components(T_est: np.ndarray, T_true: np.ndarray) -> dict[str, float]:
    """A pose error split the way `sim.episodes.pose_noise.PoseNoise` applies it, relative to the
    true camera ray u.

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


# --- BOP: symmetry sets and average recall ---------------------------------------------------

#: BOP's largest step of a discretised continuous symmetry, as a fraction of the diameter that
#: the point farthest from the axis travels (``max_sym_disc_step`` of the BOP 2019 evaluation).
BOP_MAX_SYM_DISC_STEP = 0.01
#: BOP 2019 correctness thresholds of MSSD and VSD, as fractions of the object's diameter (MSSD)
#: or plain (VSD), 0.05..0.5 step 0.05, computed as the BOP toolkit does.
BOP_THRESHOLDS = np.arange(0.05, 0.51, 0.05)
#: BOP 2019 MSPD thresholds [px] for a 640 px wide image, 5..50 step 5.
BOP_MSPD_THRESHOLDS_PX = np.arange(5, 51, 5).astype(np.float64)
#: The image width the MSPD thresholds are given for [px].
BOP_REFERENCE_WIDTH = 640
#: BOP 2019 VSD misalignment tolerances tau, as fractions of the object's diameter.
BOP_VSD_TAUS = np.arange(0.05, 0.51, 0.05)
#: BOP 2019 VSD visibility tolerance delta [m] (15 mm; 5 mm for ITODD only).
BOP_VSD_DELTA = 0.015


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by angle [rad] about a unit axis (Rodrigues), shape (3, 3)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def symmetry_set(
    discrete: Sequence[np.ndarray] = (),
    continuous: Sequence[dict[str, np.ndarray]] = (),
    max_sym_disc_step: float = BOP_MAX_SYM_DISC_STEP,
) -> list[Symmetry]:
    """The symmetry set of an object, as the BOP toolkit builds it
    (``misc.get_symmetry_transformations``).

    A continuous symmetry is discretised into ``ceil(pi / max_sym_disc_step)`` rotations by
    ``2 pi k / n`` about its axis through its offset point; every discrete symmetry (and the
    identity, always first among them) is composed with every discretised rotation
    (continuous after discrete).

    Args:
        discrete: transforms T_O_O' besides the identity, each (4, 4) with t [m], or a row-major
            16-list (BOP's ``symmetries_discrete``).
        continuous: dicts with ``axis`` (3,) (any length) and ``offset`` (3,) [m], a point on
            the axis (BOP's ``symmetries_continuous``).
        max_sym_disc_step: see `BOP_MAX_SYM_DISC_STEP`.

    Returns:
        The set in `mssd`'s format (identity included).
    """
    disc = [(np.eye(3), np.zeros(3))]
    for i, T in enumerate(discrete):
        T = np.asarray(T, np.float64).reshape(4, 4)
        disc.append((_rot(T[:3, :3], f"discrete[{i}] R"), _vec3(T[:3, 3], f"discrete[{i}] t")))
    if not continuous:
        return [{"R": R, "t": t.reshape(3, 1)} for R, t in disc]
    if not math.isfinite(max_sym_disc_step) or max_sym_disc_step <= 0:
        raise InvalidArgumentError(f"max_sym_disc_step must be > 0, got {max_sym_disc_step}")
    n = math.ceil(math.pi / max_sym_disc_step)
    cont = []
    for i, sym in enumerate(continuous):
        axis = _vec3(sym["axis"], f"continuous[{i}] axis")
        norm = float(np.linalg.norm(axis))
        if norm == 0.0:
            raise InvalidArgumentError(f"continuous[{i}] axis must be non-zero")
        offset = _vec3(sym["offset"], f"continuous[{i}] offset")
        for k in range(n):
            R = _axis_rotation(axis / norm, k * 2.0 * math.pi / n)
            cont.append((R, offset - R @ offset))
    return [
        {"R": R_c @ R_d, "t": (R_c @ t_d + t_c).reshape(3, 1)}
        for R_d, t_d in disc
        for R_c, t_c in cont
    ]


def symmetries_from_models_info(
    entry: dict, max_sym_disc_step: float = BOP_MAX_SYM_DISC_STEP, mm: bool = True
) -> list[Symmetry]:
    """The symmetry set of one object's entry of a BOP ``models_info.json``.

    Args:
        entry: with optional ``symmetries_discrete`` (row-major 16-lists) and
            ``symmetries_continuous`` (``{"axis": [3], "offset": [3]}``).
        max_sym_disc_step: see `BOP_MAX_SYM_DISC_STEP`.
        mm: the entry's translations and offsets are in mm (BOP's unit); the set's are in m.

    Returns:
        The set in `mssd`'s format, t [m].
    """
    scale = 1e-3 if mm else 1.0
    discrete = []
    for T in entry.get("symmetries_discrete", []):
        T = np.array(T, np.float64).reshape(4, 4)
        T[:3, 3] *= scale
        discrete.append(T)
    continuous = [
        {"axis": np.asarray(s["axis"], float), "offset": np.asarray(s["offset"], float) * scale}
        for s in entry.get("symmetries_continuous", [])
    ]
    return symmetry_set(discrete, continuous, max_sym_disc_step)


def _errors(errors: object, name: str) -> np.ndarray:
    """Non-empty errors as floats; None and NaN (no estimate) become inf."""
    if isinstance(errors, np.ndarray):
        arr = errors.astype(np.float64)
    else:
        arr = np.array(
            [np.nan if e is None else e for e in cast(Iterable[object], errors)], np.float64
        )
    if arr.size == 0:
        raise InvalidArgumentError(f"{name} must not be empty")
    return np.nan_to_num(arr, nan=np.inf, posinf=np.inf)


def average_recall(errors: object, thresholds: object) -> float:
    """Recall averaged over thresholds: ``mean_th mean_i [errors_i < th]`` (BOP: a pose is
    correct when its error is strictly below the threshold).

    Args:
        errors: (N,) errors, or (N, T) with one threshold per column; None, NaN or inf is an
            image without an estimate, counted as wrong.
        thresholds: (T,) thresholds in the errors' unit, or (N, T) one row per error.

    Returns:
        The average recall in [0, 1].
    """
    e = _errors(errors, "errors")
    th = np.asarray(thresholds, np.float64)
    if th.size == 0 or not np.all(np.isfinite(th)):
        raise InvalidArgumentError("thresholds must be non-empty and finite")
    correct = (e[:, None] if e.ndim == 1 else e) < th
    return float(np.mean(correct))


def ar_mssd(errors_m: object, diameters_m: object) -> float:
    """BOP's AR_MSSD: MSSD recall averaged over the thresholds 0.05..0.5 x the object diameter
    (`BOP_THRESHOLDS`).

    Args:
        errors_m: (N,) MSSD errors [m] (None or NaN: no estimate).
        diameters_m: the objects' diameters [m], one (N,) or a single value.

    Returns:
        AR_MSSD in [0, 1].
    """
    e = _errors(errors_m, "errors_m")
    d = np.broadcast_to(np.asarray(diameters_m, np.float64), e.shape)
    if not np.all(np.isfinite(d)) or np.any(d <= 0):
        raise InvalidArgumentError("diameters_m must be finite and positive")
    return average_recall(e, d[:, None] * BOP_THRESHOLDS[None, :])


def ar_mspd(errors_px: object, image_width: int = BOP_REFERENCE_WIDTH) -> float:
    """BOP's AR_MSPD: MSPD recall averaged over the thresholds 5..50 px, scaled by
    ``image_width / 640`` (`BOP_MSPD_THRESHOLDS_PX`).

    Args:
        errors_px: (N,) MSPD errors [px] (None or NaN: no estimate).
        image_width: the images' width [px].

    Returns:
        AR_MSPD in [0, 1].
    """
    if not image_width > 0:
        raise InvalidArgumentError(f"image_width must be positive, got {image_width}")
    return average_recall(errors_px, BOP_MSPD_THRESHOLDS_PX * (image_width / BOP_REFERENCE_WIDTH))


def ar_vsd(errors: object) -> float:
    """BOP's AR_VSD: VSD recall averaged over the tolerances tau (`BOP_VSD_TAUS`, the columns)
    and the thresholds 0.05..0.5 (`BOP_THRESHOLDS`).

    Args:
        errors: (N, len(BOP_VSD_TAUS)) VSD errors, one column per tau (`vsd`); a row of None
            or NaN: no estimate.

    Returns:
        AR_VSD in [0, 1].
    """
    n_taus = len(BOP_VSD_TAUS)
    if not isinstance(errors, np.ndarray):
        errors = [
            [np.nan] * n_taus if row is None else row for row in cast(Iterable[object], errors)
        ]
    e = _errors(errors, "errors")
    if e.ndim != 2 or e.shape[1] != n_taus:
        raise InvalidArgumentError(
            f"errors must have shape (N, {n_taus}), one column per tau, got {e.shape}"
        )
    return average_recall(e.reshape(-1), BOP_THRESHOLDS)


# --- BOP: Visible Surface Discrepancy --------------------------------------------------------

#: Most pixel samples the rasteriser tests at once (bounds its memory to some 100 MB).
_RASTER_CHUNK = 1 << 21


def _spans(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For counts (N,) >= 0: the owner i (repeated counts[i] times) and the rank 0..counts[i]-1
    of every element of the concatenated ranges."""
    owner = np.repeat(np.arange(len(counts)), counts)
    rank = np.arange(owner.size) - np.repeat(np.cumsum(counts) - counts, counts)
    return owner, rank


def render_depth(
    vertices: np.ndarray,
    faces: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
) -> np.ndarray:
    """Depth image of a triangle mesh at a pose: a software z-buffer rasteriser (scanlines).

    A pixel is covered by a triangle when its centre (pixel (x, y) has its centre at (x, y),
    docs/DESIGN.md §4) lies inside or on the triangle's projection; its depth is the
    perspective-correct interpolation of the vertices' depths (1/z is affine in the image), the
    nearest over the triangles covering it. Triangles with a vertex at or behind the camera
    plane are not drawn. On the objects' meshes it agrees with MuJoCo's OpenGL depth to within
    0.1 mm and a few edge pixels.

    Args:
        vertices: mesh vertices in O (V, 3) [m].
        faces: vertex indices (F, 3).
        R, t: the pose R_C_O (3, 3), t_C_O (3,) or (3, 1) [m].
        K: intrinsics (3, 3) [px].
        width, height: image size [px].

    Returns:
        Depth along the optical axis, shape (height, width) [m]; 0 where no triangle is.
    """
    v = _transform(_points(vertices), _rot(R, "R"), _vec3(t, "t"))
    K = _rot(K, "K")
    f = np.asarray(faces, np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or f.size == 0 or f.min() < 0 or f.max() >= len(v):
        raise InvalidArgumentError(f"faces must be (F, 3) indices into the {len(v)} vertices")
    inv_depth = np.zeros(height * width)
    _scan_triangles(_drawn_triangles(v, f, K, width, height), inv_depth, width)
    with np.errstate(divide="ignore"):
        depth = np.where(inv_depth > 0, 1.0 / inv_depth, 0.0)
    return depth.reshape(height, width)


class _Triangles(NamedTuple):
    """The projected triangles `render_depth` draws, T of them, each (T,) unless noted.

    Attributes:
        A, B, C: the plane of inverse depth, 1/z = A u + B v + C at pixel (u, v) [1/m].
        a, b, c: (T, 3) each: edge i -> i+1 of the triangle is  a x + b y + c >= 0  inside.
        y_lo: the first image row whose centre the triangle's bounding box spans.
        rows: how many rows it spans (>= 1).
        x_lo, x_hi: the box's columns, clipped to the image [px] (x_lo <= x_hi).
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    y_lo: np.ndarray
    rows: np.ndarray
    x_lo: np.ndarray
    x_hi: np.ndarray


def _drawn_triangles(
    v: np.ndarray, f: np.ndarray, K: np.ndarray, width: int, height: int
) -> _Triangles:
    """The triangles of vertices `v` (V, 3) in the camera frame [m] and faces `f` (F, 3) that
    get drawn in a (height, width) image with intrinsics K (3, 3) [px]: all their vertices in
    front of the camera plane, a projection of non-zero area and a bounding box that meets a
    pixel centre of the image."""
    z = v[:, 2]
    f = f[np.all(z[f] > 1e-9, axis=1)]
    uv = (v[:, :2] / np.where(z > 1e-9, z, 1.0)[:, None]) * [K[0, 0], K[1, 1]] + K[:2, 2]
    p = uv[f]  # (F, 3 corners, 2)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    y_lo = np.maximum(np.ceil(p[:, :, 1].min(axis=1)), 0).astype(np.int64)
    y_hi = np.minimum(np.floor(p[:, :, 1].max(axis=1)), height - 1).astype(np.int64)
    x_lo = np.maximum(p[:, :, 0].min(axis=1), 0.0)
    x_hi = np.minimum(p[:, :, 0].max(axis=1), width - 1.0)
    keep = (np.abs(area) > 1e-12) & (y_hi >= y_lo) & (x_hi >= x_lo)
    f, p, e1, e2, area = f[keep], p[keep], e1[keep], e2[keep], area[keep]
    y_lo, y_hi, x_lo, x_hi = y_lo[keep], y_hi[keep], x_lo[keep], x_hi[keep]
    # 1/z = A u + B v + C over each triangle.
    iz = 1.0 / z[f]
    g1, g2 = iz[:, 1] - iz[:, 0], iz[:, 2] - iz[:, 0]
    A = (e2[:, 1] * g1 - e1[:, 1] * g2) / area
    B = (e1[:, 0] * g2 - e2[:, 0] * g1) / area
    C = iz[:, 0] - A * p[:, 0, 0] - B * p[:, 0, 1]
    # Edge i -> j is  a x + b y + c >= 0  inside (oriented by the sign of the area).
    s = np.sign(area)[:, None]
    pi, pj = p, p[:, [1, 2, 0]]
    a = -s * (pj[:, :, 1] - pi[:, :, 1])
    b = s * (pj[:, :, 0] - pi[:, :, 0])
    c = -(a * pi[:, :, 0] + b * pi[:, :, 1])
    return _Triangles(A, B, C, a, b, c, y_lo, y_hi - y_lo + 1, x_lo, x_hi)


def _scan_triangles(tris: _Triangles, inv_depth: np.ndarray, width: int) -> None:
    """Draw the triangles into `inv_depth` (height * width,), the image's inverse depth
    [1/m] row by row (0: nothing yet), keeping the largest (the nearest surface) at each
    pixel; in chunks of at most about `_RASTER_CHUNK` pixel samples."""
    bound = tris.rows * (np.floor(tris.x_hi) - np.ceil(tris.x_lo) + 1).clip(0).astype(np.int64)
    ends = np.cumsum(bound)
    start = 0
    while start < len(tris.A):
        base = ends[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(ends, base + _RASTER_CHUNK, side="right")))
        _scan_rows(tris, start, stop, inv_depth, width)
        start = stop


def _scan_rows(tris: _Triangles, start: int, stop: int, inv_depth: np.ndarray, width: int) -> None:
    """Draw triangles start..stop-1 of `tris` into `inv_depth` (`_scan_triangles`): on each
    row of each, the pixel centres inside all three edges and within its box."""
    tri, k = _spans(tris.rows[start:stop])
    tri += start
    y = (tris.y_lo[tri] + k).astype(np.float64)
    r = tris.b[tri] * y[:, None] + tris.c[tri]  # (n, 3): a x + r >= 0
    at = tris.a[tri]
    with np.errstate(divide="ignore", invalid="ignore"):
        cut = -r / at
    lo = np.where(at > 0, cut, -np.inf).max(axis=1)
    hi = np.where(at < 0, cut, np.inf).min(axis=1)
    flat = np.any((at == 0) & (r < 0), axis=1)
    x0 = np.ceil(np.maximum(lo - 1e-9, tris.x_lo[tri])).astype(np.int64)
    x1 = np.floor(np.minimum(hi + 1e-9, tris.x_hi[tri])).astype(np.int64)
    n = np.where(flat, 0, x1 - x0 + 1).clip(0)
    seg, rank = _spans(n)
    ts, px, py = tri[seg], x0[seg] + rank, y[seg]
    A, B, C = tris.A, tris.B, tris.C
    np.maximum.at(inv_depth, py.astype(np.int64) * width + px, A[ts] * px + B[ts] * py + C[ts])


def _distance_image(depth: np.ndarray, K: np.ndarray, x0: int, y0: int) -> np.ndarray:
    """Distance from the camera centre of each pixel's point, of a depth window whose top-left
    pixel is (x0, y0); 0 stays 0 (BOP ``misc.depth_im_to_dist_im_fast``)."""
    h, w = depth.shape
    xs = (np.arange(x0, x0 + w) - K[0, 2]) / K[0, 0]
    ys = (np.arange(y0, y0 + h) - K[1, 2]) / K[1, 1]
    return depth * np.sqrt(xs[None, :] ** 2 + ys[:, None] ** 2 + 1.0)


def vsd(
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    depth_test: np.ndarray,
    K: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    diameter: float,
    delta: float = BOP_VSD_DELTA,
    taus: Sequence[float] | np.ndarray = BOP_VSD_TAUS,
) -> np.ndarray:
    """Visible Surface Discrepancy, VSD (Hodan et al. 2016, 2018; BOP ``vsd``, step cost,
    distances normalised by the diameter, visibility ``bop19``).

    The model is rendered (`render_depth`) at both poses; V_gt is where its gt rendering is
    not behind the test image's surface by more than delta (or the test depth is missing),
    V_est likewise for the estimate, plus V_gt wherever the estimate is drawn. With the
    distance images D (distance from the camera centre), the error at tolerance tau is
    ``(|{p in V_est & V_gt: |D_est - D_gt| / diameter >= tau}| + |V_est ^ V_gt|) /
    |V_est | V_gt|``, and 1 when the union is empty.

    Args:
        R_est, t_est: estimated pose (3, 3), (3,) or (3, 1) [m].
        R_gt, t_gt: ground-truth pose.
        depth_test: the test image's depth along the optical axis, shape (H, W) [m]; 0 where
            missing.
        K: intrinsics (3, 3) [px].
        vertices: the model's mesh vertices in O (V, 3) [m].
        faces: its triangles (F, 3).
        diameter: the model's diameter [m].
        delta: visibility tolerance [m] (`BOP_VSD_DELTA`).
        taus: misalignment tolerances, fractions of the diameter (`BOP_VSD_TAUS`).

    Returns:
        The errors in [0, 1], one per tau, shape (len(taus),).
    """
    depth_test = np.asarray(depth_test, np.float64)
    if depth_test.ndim != 2 or not np.all(np.isfinite(depth_test)):
        raise InvalidArgumentError(
            f"depth_test must be a finite (H, W) image, got {depth_test.shape}"
        )
    if not math.isfinite(diameter) or diameter <= 0:
        raise InvalidArgumentError(f"diameter must be positive, got {diameter}")
    K = _rot(K, "K")
    h, w = depth_test.shape
    d_est = render_depth(vertices, faces, R_est, t_est, K, w, h)
    d_gt = render_depth(vertices, faces, R_gt, t_gt, K, w, h)
    drawn = (d_est > 0) | (d_gt > 0)
    taus = np.asarray(taus, np.float64)
    if not drawn.any():
        return np.ones(len(taus))
    ys, xs = np.nonzero(drawn)
    win = np.s_[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1]
    x0, y0 = int(xs.min()), int(ys.min())
    dist_test = _distance_image(depth_test[win], K, x0, y0)
    dist_est = _distance_image(d_est[win], K, x0, y0)
    dist_gt = _distance_image(d_gt[win], K, x0, y0)
    missing = dist_test == 0
    visib_gt = (dist_gt > 0) & ((dist_gt - dist_test <= delta) | missing)
    visib_est = (dist_est > 0) & ((dist_est - dist_test <= delta) | missing)
    visib_est |= visib_gt & (dist_est > 0)
    inter = visib_gt & visib_est
    union = int(np.count_nonzero(visib_gt | visib_est))
    if union == 0:
        return np.ones(len(taus))
    dists = np.abs(dist_gt[inter] - dist_est[inter]) / diameter
    outside = union - int(np.count_nonzero(inter))
    return np.array([(np.count_nonzero(dists >= tau) + outside) / union for tau in taus])
