"""Render-and-compare refinement of a pose estimate against the detector's mask and the image.

The hybrid estimate (`perception.hybrid`) is a few degrees and a few millimetres off. This module
pulls it onto the evidence in the image (docs/DESIGN.md §7, "Render-and-compare refinement"):

1. Every part is a convex primitive (box, cylinder, sphere), so its silhouette is the convex
   hull of its projected vertices and the object's is the union of those hulls. Samples of the
   hull edges on the union's outer contour are the contour points (3D point in O, image normal).
2. Each contour point gets a residual [px]: the signed distance (positive outside) of its pixel to
   the mask boundary and, with the image, the offset along its normal to the strongest colour
   edge within `RefineConfig.edge_search_px` that lies near that boundary.
3. Levenberg-Marquardt steps on the 6 DoF (rotation about the object's origin, translation, both
   in the camera frame) minimise the Huber-weighted squares of those residuals.

The detector's mask is the *visible* mask: contour points where the object could not be seen
(under other detected objects, `occluder`, or beyond the image border) are left out. The refined
pose is accepted only when the silhouette IoU with the mask, over the observable pixels, does not
drop by more than `RefineConfig.accept_iou_drop`; otherwise the input pose is returned.

    refiner = PoseRefiner()
    T, info = refiner.refine("phone", T_C_O, K, mask, rgb=rgb, occluder=others)
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass

import cv2
import numpy as np

from perception.metrics import rotation_error_deg
from perception.overlay import mask_box, window_intrinsics
from perception.parts import ConvexParts, Parts, SilhouetteSource
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.transforms import axis_angle, check_intrinsics, rigid_problem

_Opt = np.ndarray | None
#: The refinement stops when a model vertex comes closer than this to the camera plane [m].
MIN_DEPTH_M = 1e-3


@dataclass(frozen=True)
class RefineConfig:
    """Settings of `PoseRefiner`.

    Attributes:
        iterations: Levenberg-Marquardt steps in all.
        mask_only_iterations: the first steps that use the mask alone (wider basin).
        spacing_px: spacing of the contour samples along hull edges [px].
        edge_search_px: half-length of the search for an image edge along each normal [px].
        edge_gate_px: an image edge counts only within this distance of the mask boundary [px].
        edge_min: smallest accepted colour gradient (RGB vector norm) [levels / px].
        mask_weight: weight of the mask residuals once image edges are used.
        huber_px: Huber threshold of the residuals [px].
        occluder_margin_px: the occluder mask is grown by this much [px].
        margin: the working window is the mask's box grown by this fraction of its size.
        accept_iou_drop: the refinement is kept unless the IoU with the mask drops by more.
        max_rotation_deg: a refinement that turns the object further is rejected [deg].
        max_shift: ... or moves it further than this fraction of its distance.
    """

    iterations: int = 6
    mask_only_iterations: int = 3
    spacing_px: float = 2.5
    edge_search_px: float = 4.0
    edge_gate_px: float = 3.0
    edge_min: float = 8.0
    mask_weight: float = 0.5
    huber_px: float = 1.5
    occluder_margin_px: int = 3
    margin: float = 0.25
    accept_iou_drop: float = 0.01
    max_rotation_deg: float = 20.0
    max_shift: float = 0.1

    def __post_init__(self) -> None:
        for key, value in vars(self).items():
            if not (np.isfinite(value) and value >= 0) or (key == "iterations" and value < 1):
                raise InvalidArgumentError(
                    f"RefineConfig.{key} must be finite and >= 0 (iterations >= 1), got {value}"
                )


def _sample(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of an image (h, w[, C]) at pixel coordinates x, y (M, S) -> (M, S[, C]),
    borders replicated."""
    out = cv2.remap(
        img,
        x.astype(np.float32),
        y.astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out.reshape(x.shape + img.shape[2:])


@dataclass
class _Window:
    """The working window around the mask, top-left pixel (x0, y0) in the image."""

    x0: int
    y0: int
    mask: np.ndarray  # the detector's mask in the window, (h, w) bool
    sdf: np.ndarray  # signed distance to its boundary [px], > 0 outside, (h, w) float32
    hidden: np.ndarray  # pixels where the object could not be seen, (h, w) bool
    rgb: np.ndarray | None  # the whole image, (H, W, 3) uint8


def _window(
    mask: np.ndarray, box: tuple[int, int, int, int], rgb: _Opt, occluder: _Opt, cfg: RefineConfig
) -> _Window:
    """Cut the window around the mask's box (`mask_box`) and compute its signed distance field."""
    bx0, by0, bx1, by1 = box
    H, W = mask.shape
    pad = int(8 + cfg.margin * max(bx1 - bx0, by1 - by0))
    x0, y0 = max(0, bx0 - pad), max(0, by0 - pad)
    x1, y1 = min(W, bx1 + pad), min(H, by1 + pad)
    m = np.ascontiguousarray(mask[y0:y1, x0:x1])
    m8 = m.view(np.uint8)
    sdf: np.ndarray = cv2.distanceTransform(1 - m8, cv2.DIST_L2, cv2.DIST_MASK_3)
    sdf -= cv2.distanceTransform(m8, cv2.DIST_L2, cv2.DIST_MASK_3)
    sdf -= 0.5 * np.sign(sdf)  # the boundary lies half-way between pixel centres
    hidden = np.zeros(m.shape, bool)
    if occluder is not None:
        occ = np.ascontiguousarray(occluder[y0:y1, x0:x1]).view(np.uint8)
        k = 2 * cfg.occluder_margin_px + 1
        hidden = cv2.dilate(occ, np.ones((k, k), np.uint8)).astype(bool) & ~m
    return _Window(int(x0), int(y0), m, sdf, hidden, rgb)


@dataclass(frozen=True)
class RefineTarget:
    """What poses are refined against, validated and prepared once for any number of starts
    (`PoseRefiner.prepare`): the intrinsics, and the working window around the mask with its
    distance field (None for an empty mask), cut with `margins` (`RefineConfig.margin`,
    `RefineConfig.occluder_margin_px`)."""

    K: np.ndarray
    window: _Window | None
    margins: tuple[float, int]


class PoseRefiner:
    """Refines pose estimates of the known objects against masks and images.

    Args:
        config: the settings (defaults: `RefineConfig()`).
        parts: where each object's convex parts come from (default: `ConvexParts`, the
            objects' own).
    """

    def __init__(
        self, config: RefineConfig | None = None, parts: SilhouetteSource | None = None
    ) -> None:
        self.config = config or RefineConfig()
        self._source = parts or ConvexParts()

    def parts(self, name: str) -> Parts:
        """The convex parts of an object (the `parts` source's).

        Raises:
            UnknownNameError: name is not a known object (the message lists them).
        """
        return self._source.parts(name)

    def refine(
        self,
        name: str,
        T_C_O: np.ndarray,
        K: np.ndarray,
        mask: np.ndarray,
        rgb: np.ndarray | None = None,
        occluder: np.ndarray | None = None,
        axis: np.ndarray | None = None,
    ) -> tuple[np.ndarray, dict]:
        """Refine one pose estimate.

        Args:
            name: object class, one of `posegrasp.world.objects.OBJECT_NAMES`.
            T_C_O: estimated pose in the camera (OpenCV) frame, shape (4, 4), metres.
            K: intrinsics, shape (3, 3) [px].
            mask: the object's visible mask (e.g. the detector's), shape (H, W), bool.
            rgb: the image, shape (H, W, 3), uint8; None refines against the mask alone.
            occluder: pixels where something else may hide the object (e.g. the other detected
                objects' masks), shape (H, W), bool; None: nothing.
            axis: turn the object only about this axis (unit, camera frame; e.g. the vertical
                of an object resting on a level surface); None: any rotation.

        Returns:
            (T_C_O (4, 4), info): the refined pose (the input when the refinement is rejected)
            and ``iterations``, ``points`` (contour points in the last step), ``edge_points``,
            ``iou_before``, ``iou_after`` (silhouette IoU with the mask over the observable
            pixels), ``accepted``, ``rotation_deg`` and ``shift_m`` (the change applied) and
            ``time_ms``.

        Raises:
            UnknownNameError: an unknown object name.
            InvalidArgumentError: a pose that is not rigid or lies behind the camera, a bad K, a
                mask, image or occluder of the wrong shape or type, or an axis that is not a unit
                vector.
        """
        t_start = time.perf_counter()
        self.parts(name)  # an unknown name fails before the inputs are checked
        _check_pose(T_C_O)
        target = self.prepare(K, mask, rgb, occluder)
        return self.refine_prepared(name, T_C_O, target, axis, t_start)

    def prepare(
        self,
        K: np.ndarray,
        mask: np.ndarray,
        rgb: np.ndarray | None = None,
        occluder: np.ndarray | None = None,
    ) -> RefineTarget:
        """Check and prepare what `refine_prepared` refines poses against (arguments as in
        `refine`), once for every start on the same detection.

        Raises:
            InvalidArgumentError: as `refine` for K, the mask, the image and the occluder.
        """
        K, mask, rgb, occluder = _check_inputs(K, mask, rgb, occluder)
        cfg = self.config
        box = mask_box(mask)
        win = None if box is None else _window(mask, box, rgb, occluder, cfg)
        return RefineTarget(K, win, (cfg.margin, cfg.occluder_margin_px))

    def refine_prepared(
        self,
        name: str,
        T_C_O: np.ndarray,
        target: RefineTarget,
        axis: np.ndarray | None = None,
        t_start: float | None = None,
    ) -> tuple[np.ndarray, dict]:
        """`refine` against a prepared target (`prepare`, by a refiner of the same margins);
        the same results (`t_start` as in `refine_parts`).

        Raises:
            UnknownNameError: an unknown object name.
            InvalidArgumentError: as `refine_parts`.
        """
        return self.refine_parts(self.parts(name), T_C_O, target, axis, t_start)

    def refine_parts(
        self,
        parts: Parts,
        T_C_O: np.ndarray,
        target: RefineTarget,
        axis: np.ndarray | None = None,
        t_start: float | None = None,
    ) -> tuple[np.ndarray, dict]:
        """`refine` of the object made of `parts` against a prepared target (`prepare`, by a
        refiner of the same margins); `t_start` is when the call began (`time.perf_counter`,
        for ``time_ms``; None: now).

        Raises:
            InvalidArgumentError: a pose that is not rigid or lies behind the camera, an axis
                that is not a unit vector, or a target prepared with other margins.
        """
        t_start = time.perf_counter() if t_start is None else t_start
        T0 = _check_pose(T_C_O)
        self._check_margins(target)
        axis = _check_axis(axis)
        info: dict = {"iterations": 0, "points": 0, "edge_points": 0, "accepted": False}
        if (win := target.window) is None:
            info |= {"iou_before": 0.0, "iou_after": 0.0, "reason": "empty mask"}
            return T0.copy(), info | {"time_ms": (time.perf_counter() - t_start) * 1000}
        Kw = window_intrinsics(target.K, win.x0, win.y0)
        verts, slices = parts.stacked
        T, iou_before = self._descend(T0, Kw, verts, slices, win, axis, info)
        info |= self._verdict(T, T0, Kw, verts, slices, win, iou_before)
        info |= {"time_ms": (time.perf_counter() - t_start) * 1000}
        return (T if info["accepted"] else T0.copy()), info

    def _check_margins(self, target: RefineTarget) -> None:
        """Fail unless `target` was prepared with this refiner's margins."""
        cfg = self.config
        if target.margins != (cfg.margin, cfg.occluder_margin_px):
            raise InvalidArgumentError(
                f"the target was prepared with margins {target.margins}, this refiner uses "
                f"{(cfg.margin, cfg.occluder_margin_px)}"
            )

    def _descend(
        self,
        T0: np.ndarray,
        Kw: np.ndarray,
        verts: np.ndarray,
        slices: np.ndarray,
        win: _Window,
        axis: np.ndarray | None,
        info: dict,
    ) -> tuple[np.ndarray, float | None]:
        """The Levenberg-Marquardt steps from `T0` (`RefineConfig.iterations` at most).

        Args:
            T0: the start pose in the camera frame, shape (4, 4), metres.
            Kw: the window's intrinsics, shape (3, 3) [px].
            verts: the parts' vertices in O, shape (n, 3) [m]; `slices`: each part's first
                vertex, and n last (`Parts.stacked`).
            win: the working window.
            axis: the only axis of rotation (unit, camera frame), or None: any rotation.
            info: updated in place with ``iterations``, ``points`` and ``edge_points``.

        Returns:
            (T (4, 4), iou_before): the pose after the last step, and the silhouette IoU at
            `T0` (None when the model could not be drawn there).
        """
        cfg = self.config
        T, lam = T0.copy(), 1e-3
        last: _Linearisation | None = None
        iou_before = None
        for it in range(cfg.iterations):
            c = _contour(T, Kw, verts, slices, win, cfg)
            if c is None:
                break
            sil, X_O, p, n = c
            if iou_before is None:
                iou_before = _iou(sil, win)
            if len(p) < 12:  # too little visible outline to compare (hidden or off the window)
                info |= {"iterations": it, "points": len(p), "edge_points": 0}
                break
            use_edges = win.rgb is not None and it >= cfg.mask_only_iterations
            r, J, n_edge = _residuals(T, Kw, X_O, p, n, win, cfg, use_edges)
            if axis is not None:  # one rotation parameter: the turn about the axis
                J = np.column_stack([J[:, :3] @ axis, J[:, 3:]])
            info |= {"iterations": it + 1, "points": len(p), "edge_points": n_edge}
            T, step, lam, last = _damped_step(T, r, J, lam, last, cfg.huber_px, use_edges)
            T, converged = _apply_step(T, step, axis)
            if converged:
                break
        return T, iou_before

    def _verdict(
        self,
        T: np.ndarray,
        T0: np.ndarray,
        Kw: np.ndarray,
        verts: np.ndarray,
        slices: np.ndarray,
        win: _Window,
        iou_before: float | None,
    ) -> dict:
        """Whether the refined pose `T` is kept over the start `T0` (both (4, 4), camera
        frame, metres; the other arguments as in `_descend`).

        Returns:
            ``iou_before``, ``iou_after``, ``accepted``, ``rotation_deg`` and ``shift_m``, as
            `refine`'s info (the last three: 0 when rejected).
        """
        cfg = self.config
        final = _draw(T, Kw, verts, slices, win.mask.shape)
        iou_after = _iou(final[1], win) if final is not None else 0.0
        iou_before = iou_before if iou_before is not None else 0.0
        rot = rotation_error_deg(T[:3, :3], T0[:3, :3])
        shift = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]))
        accepted = (
            final is not None
            and iou_after >= iou_before - cfg.accept_iou_drop
            and rot <= cfg.max_rotation_deg
            and shift <= cfg.max_shift * float(np.linalg.norm(T0[:3, 3]))
        )
        return {
            "iou_before": float(iou_before),
            "iou_after": float(iou_after if accepted else iou_before),
            "accepted": bool(accepted),
            "rotation_deg": rot if accepted else 0.0,
            "shift_m": shift if accepted else 0.0,
        }


#: A linearisation the damped steps return to when a step raised the cost: the pose (4, 4), the
#: Gauss-Newton matrix (P, P), the gradient (P,) (P: 6, or 4 about an axis) and the cost [px^2].
_Linearisation = tuple[np.ndarray, np.ndarray, np.ndarray, float]


def _check_axis(axis: np.ndarray | None) -> np.ndarray | None:
    """The validated float64 axis of rotation, shape (3,), unit; None stays None."""
    if axis is not None:
        axis = np.asarray(axis, np.float64)
        if axis.shape != (3,) or not abs(float(np.linalg.norm(axis)) - 1.0) < 1e-6:
            raise InvalidArgumentError(f"axis must be a unit 3-vector, got {axis!r}")
    return axis


def _damped_step(
    T: np.ndarray,
    r: np.ndarray,
    J: np.ndarray,
    lam: float,
    last: _Linearisation | None,
    huber_px: float,
    use_edges: bool,
) -> tuple[np.ndarray, np.ndarray, float, _Linearisation]:
    """One Levenberg-Marquardt step on the Huber-weighted residuals.

    When the cost rose since the last accepted linearisation (mask-only steps), the step is
    taken again from that linearisation with four times the damping; otherwise from this one,
    with half the damping.

    Args:
        T: the current pose, shape (4, 4), metres.
        r: the residuals, shape (R,) [px]; `J`: their Jacobians, shape (R, P).
        lam: the damping; `last`: the last accepted linearisation (None: none yet).
        huber_px: the Huber threshold [px]; `use_edges`: whether `r` holds image edges.

    Returns:
        (T, step, lam, last): the pose the step starts from, the step (P,) in (rotation [rad],
        translation [m]), and the damping and linearisation for the next step.
    """
    w = np.minimum(1.0, huber_px / np.maximum(np.abs(r), 1e-9))
    cost = float(np.mean(w * r * r * (2 - w)))
    if last is not None and cost > last[3] and not use_edges:
        T, H, g, _ = last[0], last[1], last[2], last[3]
        lam *= 4.0
    else:
        H = (J * w[:, None]).T @ J
        g = (J * w[:, None]).T @ r
        last = (T.copy(), H, g, cost)
        lam = max(lam / 2, 1e-6)
    step = -np.linalg.solve(H + lam * np.diag(np.diag(H)) + 1e-12 * np.eye(len(g)), g)
    return T, step, lam, last


def _apply_step(
    T: np.ndarray, step: np.ndarray, axis: np.ndarray | None
) -> tuple[np.ndarray, bool]:
    """The pose `T` (4, 4) moved by `step` (rotation about the object's origin, then
    translation, both in the camera frame; its rotation a turn about `axis` when given), and
    whether the step was small enough to stop."""
    if axis is not None:
        step = np.concatenate([step[0] * axis, step[1:]])
    T = T.copy()
    if (angle := float(np.linalg.norm(step[:3]))) > 0:
        T[:3, :3] = axis_angle(step[:3], angle) @ T[:3, :3]
    T[:3, 3] += step[3:]
    return T, bool(angle < 1e-5 and np.abs(step[3:]).max() < 1e-6)


def _check_pose(T_C_O: np.ndarray) -> np.ndarray:
    """The validated float64 pose: rigid, its origin in front of the camera."""
    if (problem := rigid_problem(T_C_O, 1e-4)) is not None:
        raise InvalidArgumentError(f"T_C_O {problem}")
    T = np.asarray(T_C_O, np.float64)
    if T[2, 3] <= 0:
        raise InvalidArgumentError(f"T_C_O must lie in front of the camera, got z = {T[2, 3]} m")
    return T


def _check_inputs(
    K: np.ndarray, mask: np.ndarray, rgb: _Opt, occluder: _Opt
) -> tuple[np.ndarray, np.ndarray, _Opt, _Opt]:
    """Validated float64 K, bool mask and occluder, uint8 image."""
    K = check_intrinsics(K)
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != bool or min(mask.shape) < 2:
        raise InvalidArgumentError(
            f"mask must be an (H, W) bool array, got shape {mask.shape} dtype {mask.dtype}"
        )
    rgb, occluder = (None if a is None else np.asarray(a) for a in (rgb, occluder))
    for key, arr, shape, dtype in (
        ("rgb", rgb, (*mask.shape, 3), np.uint8),
        ("occluder", occluder, mask.shape, np.bool_),
    ):
        if arr is not None and (arr.shape != shape or arr.dtype != dtype):
            raise InvalidArgumentError(
                f"{key} must be a {np.dtype(dtype)} array of shape {shape} (the mask's H, W), "
                f"got shape {arr.shape} dtype {arr.dtype}"
            )
    return K, mask, rgb, occluder


def _iou(sil: np.ndarray, win: _Window) -> float:
    """Silhouette IoU of a rendered window mask with the detector's over the observable pixels."""
    seen = ~win.hidden
    inter = np.count_nonzero(sil & win.mask & seen)
    union = np.count_nonzero((sil | win.mask) & seen)
    return inter / union if union else 0.0


def _draw(
    T: np.ndarray, Kw: np.ndarray, verts: np.ndarray, slices: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]] | None:
    """The model drawn at T in a window of `shape`: vertex pixels (n, 2), silhouette (h, w) bool
    and each part's hull (vertex indices), or None when a vertex is behind the camera."""
    Xc = verts @ T[:3, :3].T + T[:3, 3]
    if Xc[:, 2].min() < MIN_DEPTH_M:
        return None
    uv = (Xc @ Kw.T)[:, :2] / Xc[:, 2:3]
    pts, pts16 = uv.astype(np.float32), np.round(uv * 16).astype(np.int32)
    sil = np.zeros(shape, np.uint8)
    hulls = []
    for i0, i1 in itertools.pairwise(slices):
        hull = cv2.convexHull(pts[i0:i1], returnPoints=False)[:, 0] + i0
        cv2.fillConvexPoly(sil, pts16[hull], 1, cv2.LINE_8, 4)
        hulls.append(hull)
    return uv, sil.view(bool), hulls


def _contour(
    T: np.ndarray,
    Kw: np.ndarray,
    verts: np.ndarray,
    slices: np.ndarray,
    win: _Window,
    cfg: RefineConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The model drawn at T in the window, and its outer contour points.

    Returns:
        (silhouette (h, w) bool, contour points in O (M, 3) [m], their pixels (M, 2) and outward
        unit normals (M, 2) in window coordinates), or None when a vertex is behind the camera.
    """
    drawn = _draw(T, Kw, verts, slices, win.mask.shape)
    if drawn is None:
        return None
    uv, sil, hulls = drawn
    sizes = np.array([len(h) for h in hulls])
    a = np.concatenate(hulls)
    nxt = np.arange(1, len(a) + 1)
    nxt[np.cumsum(sizes) - 1] = np.cumsum(sizes) - sizes  # each hull closes on its first vertex
    b = a[nxt]
    d = uv[b] - uv[a]
    length = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2)
    keep = length > 1e-6
    a, b, d, length = a[keep], b[keep], d[keep], length[keep]
    # cv2.convexHull lists the hull with positive signed area: (d_y, -d_x) points outwards.
    normal = np.stack([d[:, 1], -d[:, 0]], 1) / length[:, None]
    count = np.maximum(1, np.round(length / cfg.spacing_px)).astype(np.int64)
    edge = np.repeat(np.arange(len(a)), count)
    k = np.arange(len(edge)) - np.repeat(np.cumsum(count) - count, count)
    s = ((k + 0.5) / count[edge])[:, None]
    X_O = verts[a[edge]] * (1 - s) + verts[b[edge]] * s
    Xp = X_O @ T[:3, :3].T + T[:3, 3]
    p = (Xp @ Kw.T)[:, :2] / Xp[:, 2:3]
    n = normal[edge]
    h, w = sil.shape
    q = np.round(p + 1.5 * n).astype(np.int64)
    inq = (q[:, 0] >= 0) & (q[:, 0] < w) & (q[:, 1] >= 0) & (q[:, 1] < h)
    outer = ~inq
    outer[inq] = ~sil[q[inq, 1], q[inq, 0]]
    pi = np.round(p).astype(np.int64)
    inside = (pi[:, 0] >= 1) & (pi[:, 0] < w - 1) & (pi[:, 1] >= 1) & (pi[:, 1] < h - 1)
    ok = outer & inside
    ok[ok] = ~win.hidden[pi[ok, 1], pi[ok, 0]]
    return sil, X_O[ok], p[ok], n[ok]


def _residuals(
    T: np.ndarray,
    Kw: np.ndarray,
    X_O: np.ndarray,
    p: np.ndarray,
    n: np.ndarray,
    win: _Window,
    cfg: RefineConfig,
    use_edges: bool,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Residuals [px] (R,) and their Jacobians (R, 6) in (rotation [rad], translation [m]) of the
    contour points, and how many came from image edges."""
    Xc = X_O @ T[:3, :3].T + T[:3, 3]
    Y = Xc - T[:3, 3]
    z = Xc[:, 2]
    fx, fy, xz, yz = Kw[0, 0] / z, Kw[1, 1] / z, Xc[:, 0] / z, Xc[:, 1] / z

    def jac(g: np.ndarray) -> np.ndarray:
        """Jacobians (M, 6) of g . p for image directions g (M, 2)."""
        out = np.empty((len(g), 6))
        c0 = np.multiply(g[:, 0], fx, out=out[:, 3])
        c1 = np.multiply(g[:, 1], fy, out=out[:, 4])
        c2 = np.negative(c0 * xz + c1 * yz, out=out[:, 5])
        y0, y1, y2 = Y[:, 0], Y[:, 1], Y[:, 2]
        out[:, 0] = y1 * c2 - y2 * c1
        out[:, 1] = y2 * c0 - y0 * c2
        out[:, 2] = y0 * c1 - y1 * c0
        return out

    d = np.array([[0.0, 0.0], [0.5, 0.0], [-0.5, 0.0], [0.0, 0.5], [0.0, -0.5]])
    q = p[None] + d[:, None]
    sd = _sample(win.sdf, q[..., 0], q[..., 1])
    r_mask = sd[0]
    J_mask = jac(np.stack([sd[1] - sd[2], sd[3] - sd[4]], 1))
    if not use_edges or win.rgb is None:
        return r_mask, J_mask, 0
    offs = np.arange(-cfg.edge_search_px, cfg.edge_search_px + 1e-9, 0.5)
    P = p[:, None, :] + offs[None, :, None] * n[:, None, :]
    col = _sample(win.rgb, P[..., 0] + win.x0, P[..., 1] + win.y0).astype(np.float32)
    mag = np.linalg.norm(np.diff(col, axis=1), axis=2) / 0.5
    sdp = _sample(win.sdf, P[..., 0], P[..., 1])
    mag[np.abs(sdp[:, 1:] + sdp[:, :-1]) > 2 * cfg.edge_gate_px] = 0.0
    k = np.argmax(mag, axis=1)
    rows = np.arange(len(k))
    good = (mag[rows, k] >= cfg.edge_min) & (k > 0) & (k < mag.shape[1] - 1)
    kg, rg = k[good], rows[good]
    m0, m1, m2 = mag[rg, kg - 1], mag[rg, kg], mag[rg, kg + 1]
    den = np.minimum(m0 - 2 * m1 + m2, -1e-9)  # a maximum: den <= 0
    frac = np.clip(0.5 * (m0 - m2) / den, -0.5, 0.5)
    s_edge = offs[kg] + 0.25 + 0.5 * frac
    r_edge = -s_edge
    J_edge = jac(n)[good]
    wm = np.sqrt(cfg.mask_weight)
    r = np.concatenate([r_edge, wm * r_mask])
    J = np.concatenate([J_edge, wm * J_mask])
    return r, J, int(good.sum())
