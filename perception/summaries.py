"""Summaries of many pose errors: recalls, the ADD AUC, statistics, outlier and IoU rates.

docs/DESIGN.md §9. Inputs are arrays of per-pose errors in the unit their names say;
NaN counts as a failure.

References:
    - Hodan et al., "BOP: Benchmark for 6D object pose estimation", ECCV 2018 (recall).
    - Xiang et al., "PoseCNN", RSS 2018 (area under the ADD accuracy-threshold curve).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from posegrasp.core.errors import InvalidArgumentError


def _values_1d(values: object, name: str) -> np.ndarray:
    """Validate a non-empty 1D array of numbers."""
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if arr.size == 0:
        raise InvalidArgumentError(f"{name} must not be empty")
    return arr


def recall(errors: np.ndarray | Sequence[float], threshold: float) -> float:
    """Fraction of errors strictly below ``threshold`` (BOP: a pose is correct if e < th).

    NaN errors count as failures. E.g. ADD(-S) recall: ``recall(errors_m, 0.1 * diameter)``.

    Args:
        errors: Errors, any shape, non-empty.
        threshold: Threshold in the errors' unit.

    Returns:
        The recall in [0, 1].
    """
    e = _values_1d(errors, "errors")
    return float(np.mean(np.nan_to_num(e, nan=np.inf) < threshold))


def add_auc(errors_m: np.ndarray | Sequence[float], max_threshold: float = 0.1) -> float:
    """Area under the accuracy-threshold curve of ADD(-S) errors (Xiang et al., PoseCNN 2018).

    ``(1 / max) * integral_0^max recall(errors, th) d th``, computed exactly (no
    threshold grid): each error e contributes ``max(0, 1 - e / max)``.

    Args:
        errors_m: ADD or ADI errors [m], non-empty; NaN counts as a failure.
        max_threshold: Upper end of the threshold range [m] (10 cm by default).

    Returns:
        The normalised area in [0, 1].
    """
    if not max_threshold > 0.0:
        raise InvalidArgumentError(f"max_threshold must be positive, got {max_threshold}")
    e = np.nan_to_num(_values_1d(errors_m, "errors_m"), nan=np.inf)
    if np.any(e < 0.0):
        raise InvalidArgumentError("errors_m must be non-negative")
    return float(np.mean(np.clip(1.0 - e / max_threshold, 0.0, 1.0)))


def recall_5cm5deg(
    trans_err_m: np.ndarray | Sequence[float], rot_err_deg: np.ndarray | Sequence[float]
) -> float:
    """Fraction of poses with translation error < 5 cm and rotation error < 5 deg.

    Args:
        trans_err_m: Translation errors |t_est - t_gt| [m], (N,).
        rot_err_deg: Rotation errors [deg], (N,).

    Returns:
        The recall in [0, 1].
    """
    t = np.nan_to_num(_values_1d(trans_err_m, "trans_err_m"), nan=np.inf)
    r = np.nan_to_num(_values_1d(rot_err_deg, "rot_err_deg"), nan=np.inf)
    if t.shape != r.shape:
        raise InvalidArgumentError(
            f"trans_err_m and rot_err_deg differ in length: {t.size} vs {r.size}"
        )
    return float(np.mean((t < 0.05) & (r < 5.0)))


def summary_stats(values: np.ndarray | Sequence[float]) -> dict[str, float]:
    """Mean, population std (ddof=0), median and 90th percentile (linear interpolation).

    Args:
        values: Non-empty finite values, any unit.

    Returns:
        ``{"mean", "std", "median", "p90"}`` in the unit of ``values``.
    """
    v = _values_1d(values, "values")
    if not np.all(np.isfinite(v)):
        raise InvalidArgumentError("values must be finite")
    return {
        "mean": float(np.mean(v)),
        "std": float(np.std(v)),
        "median": float(np.median(v)),
        "p90": float(np.percentile(v, 90.0)),
    }


def outlier_rate(rot_err_deg: np.ndarray | Sequence[float], threshold: float = 15.0) -> float:
    """Fraction of rotation errors above ``threshold`` [deg] (NaN counts as outlier)."""
    r = np.nan_to_num(_values_1d(rot_err_deg, "rot_err_deg"), nan=np.inf)
    return float(np.mean(r > threshold))


def iou_accuracy(ious: np.ndarray | Sequence[float], threshold: float = 0.5) -> float:
    """Fraction of silhouette IoUs strictly above ``threshold`` (NaN fails).

    The reading of the paper's "acc IoU" (Table 2) that `perception.training.tables` compares
    with; `invalid_rate` is its complement.

    Args:
        ious: Silhouette IoUs in [0, 1], non-empty.
        threshold: IoU a pose must exceed, in [0, 1).

    Returns:
        The accuracy in [0, 1].
    """
    if not 0.0 <= threshold < 1.0:
        raise InvalidArgumentError(f"threshold must be in [0, 1), got {threshold}")
    v = np.nan_to_num(_values_1d(ious, "ious"), nan=-np.inf)
    return float(np.mean(v > threshold))


def invalid_rate(ious: np.ndarray | Sequence[float], threshold: float = 0.5) -> float:
    """Fraction of invalid poses: silhouette IoU at most ``threshold`` (NaN counts as invalid).

    The paper's invalid poses (section 3.2, Fig. 9) are those whose projected silhouette does not
    match the object's; here that means IoU <= ``threshold``, so
    ``invalid_rate(x, th) == 1 - iou_accuracy(x, th)``.

    Args:
        ious: Silhouette IoUs in [0, 1], non-empty.
        threshold: Largest IoU of an invalid pose, in [0, 1).

    Returns:
        The rate in [0, 1].
    """
    return 1.0 - iou_accuracy(ious, threshold)
