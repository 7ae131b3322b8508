"""What a pose should look like before the image is consulted: gravity and the in-plane range.

- **Gravity** (docs/DESIGN.md §7, "Gravity"): objects rest on something. With the camera's
  rotation in the world, a pose's tilt is its rotation to the nearest resting pose of the object,
  any turn about the vertical (`perception.support.snap_to_resting`); poses within
  `GravityConfig.tilt_deg` of resting are plausible, and the best few within
  `GravityConfig.snap_tilt_deg` are snapped onto their resting pose and refined again, turning
  about the vertical only.
- **In-plane range** (`max_inplane_deg`): the paper's protocol draws every view with its in-plane
  angle (`perception.geometry.encode`'s theta) in -60..60 deg; a pose outside the range is not
  plausible. Within `POLE_DEG` of the object's z axis the angle is not defined and every pose is.

`Plausibility` holds one detection's priors and judges a pose by them; the verification ranks
plausible poses first (`perception.verification.rank_verified`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from perception.geometry import axes_from_p, ray_correction
from perception.support import snap_to_resting
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world.objects import ObjectModel

#: Within this angle [deg] of the object's z axis the view's in-plane angle is not defined
#: (`inplane_deg`): a degree of viewpoint there turns it by many.
POLE_DEG = 10.0

#: A start snapped onto its resting pose is kept unless its verification score drops by more
#: (the score, not the IoU alone: the detector's mask is often fitted a little better by a tilt
#: that the image's edges refute); the snapped starts win only if the best of them scores
#: within this much of the best pose of all.
SNAP_SCORE_DROP = 0.05


@dataclass(frozen=True)
class GravityConfig:
    """The gravity prior.

    Attributes:
        tilt_deg: refined poses within this rotation [deg] of one of the object's resting poses
            (any turn about the vertical) are plausible and rank above the others; in (0, 180).
        snap_candidates: this many of the best refined poses within `snap_tilt_deg` of a
            resting pose are each turned onto it (heading kept) and refined again, one run,
            turning about the vertical only; the best of these wins unless all of them score
            more than `SNAP_SCORE_DROP` below the best pose of all (the object is not resting).
            A pose off by a few degrees is often mostly tilted, so it is snapped, not passed
            over (0: none).
        snap_tilt_deg: the largest tilt from a resting pose [deg] a pose may have to be
            snapped; in (0, 180).
        snap_iterations: refiner steps of a snapped pose's run (turning about the vertical
            only, it has four unknowns, not six); >= 1.
    """

    tilt_deg: float = 10.0
    snap_candidates: int = 5
    snap_tilt_deg: float = 25.0
    snap_iterations: int = 6

    def __post_init__(self) -> None:
        for key in ("tilt_deg", "snap_tilt_deg"):
            value = getattr(self, key)
            if not 0 < value < 180:
                raise InvalidArgumentError(f"GravityConfig.{key} must be in (0, 180), got {value}")
        if self.snap_candidates < 0:
            raise InvalidArgumentError(
                f"GravityConfig.snap_candidates must be >= 0, got {self.snap_candidates}"
            )
        if self.snap_iterations < 1:
            raise InvalidArgumentError(
                f"GravityConfig.snap_iterations must be >= 1, got {self.snap_iterations}"
            )


@dataclass(frozen=True)
class Gravity:
    """The world's vertical as one detection sees it.

    Attributes:
        R_W_C: the camera's rotation in the world (3, 3).
        model: the object (its resting poses; at least one).
        config: the prior's settings.
    """

    R_W_C: np.ndarray
    model: ObjectModel
    config: GravityConfig

    @property
    def up(self) -> np.ndarray:
        """The world's vertical in the camera frame (3,), unit."""
        return self.R_W_C[2].copy()

    def tilt(self, T_C_O: np.ndarray) -> float:
        """The rotation [deg] of pose T_C_O (4, 4) to the nearest resting pose."""
        return snap_to_resting(self.R_W_C @ T_C_O[:3, :3], self.model)[2]

    def snapped(self, T_C_O: np.ndarray) -> np.ndarray:
        """Pose T_C_O (4, 4) turned onto its nearest resting pose, heading and origin kept."""
        T = T_C_O.copy()
        T[:3, :3] = self.R_W_C.T @ snap_to_resting(self.R_W_C @ T[:3, :3], self.model)[0]
        return T


@dataclass(frozen=True)
class InplaneConfig:
    """The in-plane prior.

    Attributes:
        max_deg: a refined pose whose in-plane angle (the roll of the virtual camera C',
            `perception.geometry.encode`'s theta) lies within this many degrees of zero ranks
            above one that does not: a prior of the paper's protocol, whose views are drawn with
            the in-plane angle in -60..60 deg, as gravity is the tiers'. A silhouette turned half
            way round about the viewing ray is the same silhouette; the protocol never shows
            it. Views within `POLE_DEG` of the object's z axis, where the angle is not defined,
            always count as within; in (0, 180).
    """

    max_deg: float = 65.0

    def __post_init__(self) -> None:
        if not 0 < self.max_deg < 180:
            raise InvalidArgumentError(
                f"InplaneConfig.max_deg must be in (0, 180), got {self.max_deg}"
            )


def inplane_deg(T_C_O: np.ndarray) -> float | None:
    """|theta| of the pose's 4D representation (`perception.geometry.encode`) [deg], or None
    when the camera looks within `POLE_DEG` of the object's z axis (theta is not defined there)
    or the object is behind the camera. The virtual camera C' looks along the ray to the
    object's origin, so no K is needed (`perception.geometry.ray_correction`)."""
    t = T_C_O[:3, 3]
    if t[2] <= 0:
        return None
    R_Cv_O = ray_correction(t[0] / t[2], t[1] / t[2]).T @ T_C_O[:3, :3]
    if abs(R_Cv_O[2, 2]) >= math.cos(math.radians(POLE_DEG)):  # C''s axis in O
        return None
    x, y, _ = axes_from_p(-R_Cv_O[2])  # C' at -z in O, up to the scale axes_from_p drops
    return abs(math.degrees(math.atan2(float(R_Cv_O[0] @ y), float(R_Cv_O[0] @ x))))


@dataclass(frozen=True)
class Plausibility:
    """One detection's priors.

    Attributes:
        gravity: the gravity prior, or None (no camera pose, an object without resting poses,
            or images without gravity).
        max_inplane_deg: the largest in-plane angle [deg] of a plausible pose (None: any).
    """

    gravity: Gravity | None = None
    max_inplane_deg: float | None = None

    def judge(self, T_C_O: np.ndarray) -> tuple[float, bool]:
        """(tilt from resting [deg], 0 without gravity; whether the pose is plausible)."""
        tilt, plausible = 0.0, True
        if self.gravity is not None:
            tilt = self.gravity.tilt(T_C_O)
            plausible = tilt <= self.gravity.config.tilt_deg
        if self.max_inplane_deg is not None:
            roll = inplane_deg(T_C_O)
            plausible = plausible and (roll is None or roll <= self.max_inplane_deg)
        return tilt, plausible
