"""The stages on the winner: the known table, or, when the winner is unsure, the surface its
neighbours rest on, each slides the pose onto where the object rests (`Placed`)."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy import ndimage

from perception.detector_net import ANY_OBJECT
from perception.stages.config import GlobalConfig, SupportConfig, TableConfig
from perception.stages.work import AnyDetection, Kit, Placed, Work
from perception.support import refine_on_support, resting_surface_z
from perception.verification import Verified
from posegrasp.core.contract import Observation
from posegrasp.world.objects import ObjectModel, load_object

#: Neighbours are verified until this many give a confident resting pose
#: (`SupportConfig.neighbours`).
SUPPORT_ENOUGH = 2

#: A neighbour whose mask comes this close to the target's [px] touches it.
NEIGHBOUR_TOUCH_PX = 6


class TablePrior:
    """The table prior: when the observation carries the table's height
    (`Observation.table_top_z`, a prior of the scene, not of the image), the pose's rotation is
    snapped to the nearest resting pose and its origin slid along its camera ray until the
    object rests on the table (`perception.support.refine_on_support`, as `hybrid-table`); the
    silhouette does not fix the distance of a half-hidden object, the table does.

    Args:
        config: the prior's settings.
    """

    name = "table"

    def __init__(self, config: TableConfig) -> None:
        self.config = config

    @classmethod
    def build(cls, config: GlobalConfig, kit: Kit) -> TablePrior | None:
        """The stage of `config.table` (None: left out)."""
        return None if config.table is None else cls(config.table)

    @staticmethod
    def wanted(work: Work) -> bool:
        """Whether there is a winner and the observation gives the table's height."""
        return (
            work.winner is not None
            and work.target is not None
            and work.obs is not None
            and work.obs.table_top_z is not None
        )

    def __call__(self, work: Work) -> Work:
        """`work` with its winner placed on the table (or not, for an object that does not
        rest)."""
        assert work.winner is not None and work.target is not None and work.obs is not None
        model = load_object(work.target.name)
        return work.given(placed=self.place(work.winner.T_C_O.copy(), work.obs, model))

    def place(self, T_C_O: np.ndarray, obs: Observation, model: ObjectModel) -> Placed | None:
        """T_C_O (4, 4) on the table; None without the table's height or resting poses."""
        if obs.table_top_z is None or not model.resting_poses:
            return None
        ref = refine_on_support(
            T_C_O, obs.T_world_cam, model, obs.table_top_z, self.config.max_tilt_deg
        )
        return Placed(ref.T_C_O, ref.description())


class NeighbourSupport:
    """The support of the neighbours: the visible part of a half-hidden object does not fix its
    distance along the viewing ray; the objects around it, which rest on the same table, do.
    When the target's winner scores below `SupportConfig.below` and is within the gravity
    prior's tilt of resting, the neighbouring detections are verified, and the median height
    of the surface the confident ones rest on is the target's support: when the target's own
    pose puts it more than `SupportConfig.tolerance_m` above or below it, the pose is slid along
    its camera ray onto it (`perception.support.refine_on_support`).

    Args:
        config: the prior's settings.
        tilt_deg: the gravity prior's tilt [deg] (`perception.priors.GravityConfig.tilt_deg`).
    """

    name = "support"

    def __init__(
        self,
        config: SupportConfig,
        tilt_deg: float,
        as_target: Callable[[AnyDetection, Work], Work],
    ) -> None:
        self.config, self.tilt_deg, self.as_target = config, tilt_deg, as_target

    @classmethod
    def build(cls, config: GlobalConfig, kit: Kit) -> NeighbourSupport | None:
        """The stage of `config.support` with the gravity prior's tilt (None: left out)."""
        if config.support is None or config.gravity is None:
            return None
        return cls(config.support, config.gravity.tilt_deg, kit.as_target)

    def wanted(self, work: Work) -> bool:
        """Whether no earlier prior placed the winner, and it asks for support: unsure, yet
        near resting."""
        win, det = work.winner, work.target
        if win is None or det is None or work.obs is None or work.found is None:
            return False
        return work.placed is None and self.unsure(win, load_object(det.name))

    def unsure(self, win: Verified, model: ObjectModel) -> bool:
        """Whether the target's winner asks for support: unsure, yet near resting."""
        return bool(
            model.resting_poses and win.score < self.config.below and win.tilt <= self.tilt_deg
        )

    def __call__(self, work: Work) -> Work:
        """`work` with its winner placed on its neighbours' surface."""
        win, det, found, obs = work.winner, work.target, work.found, work.obs
        assert win is not None and det is not None and found is not None and obs is not None

        def neighbour(d: AnyDetection) -> Verified | None:
            return self.as_target(d, work).winner

        return work.given(placed=self.place(win.T_C_O.copy(), det, found.every, obs, neighbour))

    def place(
        self,
        T_C_O: np.ndarray,
        target: AnyDetection,
        every: list[AnyDetection],
        obs: Observation,
        verify: Callable[[AnyDetection], Verified | None],
    ) -> Placed:
        """T_C_O (4, 4) of `target` slid onto its neighbours' surface when they give one it is
        off from; `verify` gives a neighbour's best verified pose (None: none)."""
        model = load_object(target.name)
        support_z, seen = self.surface(target, every, obs, verify)
        own_z = resting_surface_z(T_C_O, obs.T_world_cam, model)
        described: dict = {"source": "neighbours", "neighbours": seen, "own_z": own_z}
        T = T_C_O
        if support_z is not None and abs(own_z - support_z) > self.config.tolerance_m:
            ref = refine_on_support(T, obs.T_world_cam, model, support_z, self.tilt_deg)
            T, described = ref.T_C_O, described | ref.description()
        return Placed(T, described | {"surface_z": support_z})

    def surface(
        self,
        target: AnyDetection,
        every: list[AnyDetection],
        obs: Observation,
        verify: Callable[[AnyDetection], Verified | None],
    ) -> tuple[float | None, list[dict]]:
        """The height of the surface the target's neighbours rest on, or None when none gives
        a confident resting pose, and what each verified neighbour gave (``class``, ``score``,
        ``tilt_deg``, ``surface_z``, ``counted``); only detections of known objects are
        neighbours."""
        grown = ndimage.binary_dilation(target.mask, iterations=NEIGHBOUR_TOUCH_PX)
        centre = np.argwhere(target.mask).mean(0)

        def order(d: AnyDetection) -> tuple[int, float]:
            pixels = np.argwhere(d.mask)
            far = float(np.hypot(*(pixels.mean(0) - centre))) if len(pixels) else math.inf
            return -int((grown & d.mask).sum()), far

        # A detection of a detector of any object names no object: its mesh is unknown, so it
        # cannot say where it rests.
        candidates = [
            d
            for d in every
            if d.name not in (target.name, ANY_OBJECT) and load_object(d.name).resting_poses
        ]
        heights: list[float] = []
        seen: list[dict] = []
        for found in sorted(candidates, key=order)[: self.config.neighbours]:
            win = verify(found)
            if win is None:
                continue
            z = resting_surface_z(win.T_C_O, obs.T_world_cam, load_object(found.name))
            score, tilt = float(win.score), win.tilt
            counted = bool(score >= self.config.score and tilt <= self.tilt_deg)
            seen.append(
                {
                    "class": found.name,
                    "score": score,
                    "tilt_deg": tilt,
                    "surface_z": z,
                    "counted": counted,
                }
            )
            if counted:
                heights.append(z)
                if len(heights) >= SUPPORT_ENOUGH:
                    break
        return (float(np.median(heights)) if heights else None), seen
