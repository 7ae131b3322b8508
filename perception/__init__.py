"""Perception at run time: the 4D pose representation, crops, pose metrics and the hybrid
estimator (docs/DESIGN.md §5-§9).

Importing this package is cheap: it does not import torch. `HybridPoseEstimator` and
`PoseDetection` are loaded on first use (``from perception import HybridPoseEstimator`` imports
torch and torchvision, never the training code under `perception.training`).
"""

from typing import Any

from perception.crops import (
    crop_affine,
    crop_and_resize,
    crop_to_image,
    from_unit,
    image_to_crop,
    random_square_box,
    square_box,
    to_unit,
)
from perception.geometry import (
    axes_from_p,
    decode,
    encode,
    pixel_ray,
    project,
    r_corr,
    ray_correction,
    rotation_from_p_theta,
)
from perception.metrics import (
    add,
    add_metric_name,
    adi,
    ar_mspd,
    ar_mssd,
    ar_vsd,
    average_recall,
    box_iou,
    center_error_px,
    closest_symmetry,
    diameter,
    error_components,
    identity_symmetry,
    mask_iou,
    mspd,
    mssd,
    render_depth,
    rotation_error_deg,
    rotation_error_sym_deg,
    symmetric_pose,
    symmetries_from_models_info,
    symmetry_set,
    translation_error_pct,
    vsd,
)
from perception.summaries import (
    add_auc,
    invalid_rate,
    iou_accuracy,
    outlier_rate,
    recall,
    recall_5cm5deg,
    summary_stats,
)
from posegrasp.core.transforms import (
    intrinsics,
    invert_transform,
    make_transform,
    rot_x,
    rot_y,
    rot_z,
)

#: Names loaded from `perception.hybrid` on first access (it imports torch).
_LAZY = ("HybridPoseEstimator", "PoseDetection")


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from perception import hybrid

        return getattr(hybrid, name)
    raise AttributeError(f"module 'perception' has no attribute {name!r}")


__all__ = [
    "HybridPoseEstimator",
    "PoseDetection",
    "add",
    "add_auc",
    "add_metric_name",
    "adi",
    "ar_mspd",
    "ar_mssd",
    "ar_vsd",
    "average_recall",
    "axes_from_p",
    "box_iou",
    "center_error_px",
    "closest_symmetry",
    "crop_affine",
    "crop_and_resize",
    "crop_to_image",
    "decode",
    "diameter",
    "encode",
    "error_components",
    "from_unit",
    "identity_symmetry",
    "image_to_crop",
    "intrinsics",
    "invalid_rate",
    "invert_transform",
    "iou_accuracy",
    "make_transform",
    "mask_iou",
    "mspd",
    "mssd",
    "outlier_rate",
    "pixel_ray",
    "project",
    "r_corr",
    "random_square_box",
    "ray_correction",
    "recall",
    "recall_5cm5deg",
    "render_depth",
    "rot_x",
    "rot_y",
    "rot_z",
    "rotation_error_deg",
    "rotation_error_sym_deg",
    "rotation_from_p_theta",
    "square_box",
    "summary_stats",
    "symmetric_pose",
    "symmetries_from_models_info",
    "symmetry_set",
    "to_unit",
    "translation_error_pct",
    "vsd",
]
