"""Batched, differentiable torch versions of the 4D representation (docs/DESIGN.md §5, §6, §7).

Mirrors :mod:`perception.geometry` for batches of shape (B, ...). Every function keeps the
input dtype and device and has finite gradients everywhere, including at the singularity where
the virtual camera looks straight along the object's z axis: branches are chosen with
``torch.where`` and the unused branch is fed safe values so that no NaN reaches the gradient.

Frames and units as in :mod:`perception.geometry`: ``p`` is the position of the virtual camera
C' in the object frame O [m], theta its roll [rad], ``uv`` the origin's pixel [px].
"""

from __future__ import annotations

import torch

from perception.geometry import SINGULAR_EPS
from posegrasp.core.errors import InvalidArgumentError

# Default margin that keeps the arccos argument away from +-1 (finite gradient).
ARCCOS_EPS = 1e-7


def check_batch_shape(x: torch.Tensor, trailing: tuple[int, ...], name: str) -> int:
    """Check that ``x`` has shape (B, *trailing) and return B (clear message)."""
    if not isinstance(x, torch.Tensor):
        raise InvalidArgumentError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    expected = "(B" + "".join(f", {d}" for d in trailing) + ")"
    if x.ndim != 1 + len(trailing) or tuple(x.shape[1:]) != trailing:
        raise InvalidArgumentError(f"{name} must have shape {expected}, got {tuple(x.shape)}")
    return int(x.shape[0])


def safe_norm(x: torch.Tensor, tiny: float = 1e-30) -> torch.Tensor:
    """Euclidean norm over the last axis, (B, n) -> (B,), with a finite gradient at zero."""
    sq = (x * x).sum(dim=-1)
    return torch.sqrt(torch.clamp(sq, min=tiny))


def axes_from_p(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Batched theta = 0 axes of C' in O (see :func:`perception.geometry.axes_from_p`).

    Args:
        p: Positions of C' in O [m], shape (B, 3).

    Returns:
        x, y, z, each (B, 3), unit vectors expressed in O.
    """
    check_batch_shape(p, (3,), "p")
    z = -p / safe_norm(p).unsqueeze(-1)
    zx, zy = z[:, 0], z[:, 1]
    s2 = zx * zx + zy * zy
    singular = s2 < SINGULAR_EPS
    zero = torch.zeros_like(zx)
    one = torch.ones_like(zx)
    # Regular branch; the denominator is replaced by 1 where singular so sqrt never sees 0.
    s = torch.sqrt(torch.where(singular, one, s2))
    x_reg = torch.stack((zy / s, -zx / s, zero), dim=-1)
    # Singular branch: (1, 0, 0) made orthogonal to z; its norm is ~1 inside the band, so the
    # denominator is replaced by 1 outside it (where it could approach 0 for z ~ +-x).
    x_sing = torch.stack((one, zero, zero), dim=-1) - zx.unsqueeze(-1) * z
    x_sing_norm = torch.where(singular, safe_norm(x_sing), one)
    x_sing = x_sing / x_sing_norm.unsqueeze(-1)
    x = torch.where(singular.unsqueeze(-1), x_sing, x_reg)
    y = torch.linalg.cross(z, x, dim=-1)
    return x, y, z


def _rot_z_cs(c: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Rotations about z from cosines and sines, (B,), (B,) -> (B, 3, 3)."""
    zero = torch.zeros_like(c)
    one = torch.ones_like(c)
    rows = (
        torch.stack((c, -s, zero), dim=-1),
        torch.stack((s, c, zero), dim=-1),
        torch.stack((zero, zero, one), dim=-1),
    )
    return torch.stack(rows, dim=-2)


def rotation_from_p_cs(p: torch.Tensor, cs: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Rotations ``R_O_C'`` from positions and (cos, sin) of the roll.

    Args:
        p: Positions of C' in O [m], shape (B, 3).
        cs: Unnormalised (cos theta, sin theta), shape (B, 2); normalised here.
        eps: Added under the square root of the (cos, sin) norm to keep it differentiable.

    Returns:
        R_O_C' (B, 3, 3) = ``[x y z] @ Rz(theta)``.
    """
    b = check_batch_shape(p, (3,), "p")
    if check_batch_shape(cs, (2,), "cs") != b:
        raise InvalidArgumentError(f"cs has batch {cs.shape[0]} but p has batch {b}")
    n = torch.sqrt((cs * cs).sum(dim=-1) + eps)
    x, y, z = axes_from_p(p)
    base = torch.stack((x, y, z), dim=-1)
    return base @ _rot_z_cs(cs[:, 0] / n, cs[:, 1] / n)


def rotation_from_p_theta(p: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """Rotations ``R_O_C'`` from positions and roll angles (docs/DESIGN.md §5).

    Args:
        p: Positions of C' in O [m], shape (B, 3).
        theta: Roll of C' about its optical axis [rad], shape (B,).

    Returns:
        R_O_C' (B, 3, 3).
    """
    b = check_batch_shape(p, (3,), "p")
    if check_batch_shape(theta, (), "theta") != b:
        raise InvalidArgumentError(f"theta has batch {theta.shape[0]} but p has batch {b}")
    x, y, z = axes_from_p(p)
    base = torch.stack((x, y, z), dim=-1)
    return base @ _rot_z_cs(torch.cos(theta), torch.sin(theta))


def geodesic_distance(R1: torch.Tensor, R2: torch.Tensor, eps: float = ARCCOS_EPS) -> torch.Tensor:
    """Angle of the relative rotation, ``arccos((trace(R1^T R2) - 1) / 2)`` (paper eq. 6).

    The arccos argument is clamped to [-1 + eps, 1 - eps], so the gradient is finite; the
    price is a floor of about sqrt(2 eps) [rad] on the returned angle.

    Args:
        R1: Rotations (B, 3, 3).
        R2: Rotations (B, 3, 3).
        eps: Clamp margin.

    Returns:
        Angles [rad], shape (B,), in [0, pi].
    """
    b = check_batch_shape(R1, (3, 3), "R1")
    if check_batch_shape(R2, (3, 3), "R2") != b:
        raise InvalidArgumentError(f"R2 has batch {R2.shape[0]} but R1 has batch {b}")
    trace = (R1 * R2).sum(dim=(-2, -1))  # trace(R1^T R2)
    cos = torch.clamp((trace - 1.0) / 2.0, -1.0 + eps, 1.0 - eps)
    return torch.arccos(cos)


def rotation_from_p_angle(
    p: torch.Tensor, angle: torch.Tensor, name: str = "theta"
) -> torch.Tensor:
    """``R_O_C'`` from p and a roll given as (B,) angles or (B, 2) (cos, sin)."""
    if angle.ndim == 1:
        return rotation_from_p_theta(p, angle)
    if angle.ndim == 2 and angle.shape[1] == 2:
        return rotation_from_p_cs(p, angle)
    raise InvalidArgumentError(
        f"{name} must have shape (B,) (theta) or (B, 2) (cos, sin), got {angle.shape}"
    )


def r_corr(uv: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Batched ``R_C_C'`` (see :func:`perception.geometry.r_corr`).

    Args:
        uv: Origin pixels [px], (B, 2).
        K: Intrinsics (3, 3) shared by the batch, or (B, 3, 3).

    Returns:
        R_C_C' (B, 3, 3).
    """
    b = check_batch_shape(uv, (2,), "uv")
    if K.shape == (3, 3):
        K = K.expand(b, 3, 3)
    elif check_batch_shape(K, (3, 3), "K") != b:
        raise InvalidArgumentError(f"K has batch {K.shape[0]} but uv has batch {b}")
    fx, fy, cx, cy, skew = K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 0, 1]
    y_n = (uv[:, 1] - cy) / fy
    x_n = (uv[:, 0] - cx - skew * y_n) / fx
    alpha = torch.atan(x_n)
    beta = -torch.asin(y_n / torch.sqrt(x_n * x_n + y_n * y_n + 1.0))
    ca, sa, cb, sb = torch.cos(alpha), torch.sin(alpha), torch.cos(beta), torch.sin(beta)
    zero = torch.zeros_like(ca)
    # Ry(alpha) @ Rx(beta), written out.
    rows = (
        torch.stack((ca, sa * sb, sa * cb), dim=-1),
        torch.stack((zero, cb, -sb), dim=-1),
        torch.stack((-sa, ca * sb, ca * cb), dim=-1),
    )
    return torch.stack(rows, dim=-2)


def decode_torch(
    p: torch.Tensor, theta: torch.Tensor, uv: torch.Tensor, K: torch.Tensor
) -> torch.Tensor:
    """Batched :func:`perception.geometry.decode`.

    Args:
        p: Positions of C' in O [m], (B, 3).
        theta: Roll [rad] (B,), or unnormalised (cos, sin) (B, 2).
        uv: Origin pixels [px], (B, 2).
        K: Intrinsics (3, 3) or (B, 3, 3).

    Returns:
        T_C_O (B, 4, 4).
    """
    R_O_Cv = rotation_from_p_angle(p, theta, "theta")
    R_C_Cv = r_corr(uv, K)
    # T_C'_O = [[R_O_C'^T, -R_O_C'^T p]], so T_C_O = [[R_corr R_O_C'^T, -R_corr R_O_C'^T p]].
    R_C_O = R_C_Cv @ R_O_Cv.transpose(-1, -2)
    t_C_O = -(R_C_O @ p.unsqueeze(-1)).squeeze(-1)
    top = torch.cat((R_C_O, t_C_O.unsqueeze(-1)), dim=-1)
    bottom = torch.zeros(p.shape[0], 1, 4, dtype=p.dtype, device=p.device)
    bottom[:, 0, 3] = 1.0
    return torch.cat((top, bottom), dim=-2)
