"""Training losses of the pose nets: the 4D-NET loss of the paper (eq. 7) and the full loss.

docs/DESIGN.md §7: ``|p - p^| / |p| + lambda * G(R, R^)`` with p the target,
p^ the prediction and R, R^ the rotations ``R_O_C'`` built from (p, theta) and (p^, theta^).
"""

from __future__ import annotations

import torch

from perception.geometry_torch import (
    check_batch_shape,
    geodesic_distance,
    rotation_from_p_angle,
    safe_norm,
)
from perception.nets import PoseOutput
from posegrasp.core.errors import InvalidArgumentError


def eq7_terms(
    p_pred: torch.Tensor,
    angle_pred: torch.Tensor,
    p_gt: torch.Tensor,
    theta_gt: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The two terms of eq. 7 per sample: relative distance error and geodesic angle [rad].

    Args:
        p_pred: Predicted positions of C' in O [m], (B, 3).
        angle_pred: Predicted roll, (B,) [rad] or (B, 2) unnormalised (cos, sin).
        p_gt: Target positions [m], (B, 3).
        theta_gt: Target roll, (B,) [rad] or (B, 2) (cos, sin).

    Returns:
        ``|p - p^| / |p|`` and ``G(R, R^)``, each of shape (B,).
    """
    b = check_batch_shape(p_pred, (3,), "p_pred")
    if check_batch_shape(p_gt, (3,), "p_gt") != b:
        raise InvalidArgumentError(f"p_gt has batch {p_gt.shape[0]} but p_pred has batch {b}")
    dist = safe_norm(p_pred - p_gt) / safe_norm(p_gt)
    R_pred = rotation_from_p_angle(p_pred, angle_pred, "theta_or_cs_pred")
    R_gt = rotation_from_p_angle(p_gt, theta_gt, "theta_gt")
    return dist, geodesic_distance(R_gt, R_pred)


def pose_loss_4d(
    p_pred: torch.Tensor,
    theta_or_cs_pred: torch.Tensor,
    p_gt: torch.Tensor,
    theta_gt: torch.Tensor,
    lam: float,
) -> torch.Tensor:
    """4D-NET loss (eq. 7), averaged over the batch; ``lam`` weighs the rotation [1/rad]."""
    dist, rot = eq7_terms(p_pred, theta_or_cs_pred, p_gt, theta_gt)
    return (dist + lam * rot).mean()


def posenet_loss(
    out: PoseOutput,
    uv_unit: torch.Tensor,
    p: torch.Tensor,
    theta: torch.Tensor,
    variant: str,
    lam: float = 1.0,
) -> tuple[torch.Tensor, dict[str, float]]:
    """2D loss (Euclidean distance in the unit crop) + 4D loss (eq. 7).

    For "paper" the roll term uses theta directly; for "ours" the (cos, sin) output, plus a
    small penalty that keeps |(cos, sin)| near 1 and an absolute log-distance error.
    """
    l2d = torch.linalg.norm(out.uv_unit - uv_unit, dim=1).mean()
    angle = out.cs if variant == "ours" else out.theta
    dist_b, rot_b = eq7_terms(out.p, angle, p, theta)
    dist, rot = dist_b.mean(), rot_b.mean()
    if variant == "ours":
        norm_pen = (torch.linalg.norm(out.cs, dim=1) - 1).square().mean()
        # The vector term mixes distance with viewpoint: while the viewpoint is uncertain it
        # pays to shrink |p|. A separate scale-free distance term keeps the range honest.
        rng = torch.log(torch.linalg.norm(out.p, dim=1)) - torch.log(torch.linalg.norm(p, dim=1))
        range_err = rng.abs().mean()
    else:
        norm_pen = torch.zeros((), device=p.device)
        range_err = torch.zeros((), device=p.device)
    total = 10.0 * l2d + dist + lam * rot + 0.1 * norm_pen + range_err
    parts = {"l2d": l2d, "dist": dist, "rot": rot, "range": range_err, "total": total}
    return total, {k: float(v.detach()) for k, v in parts.items()}
