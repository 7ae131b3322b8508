"""The peers as estimators of the contract: a short list of stages from the observation to the
`Estimate`.

`PeerEstimator` (``ppf``, ``fpfh-icp`` and, with a `DetectionPrior`, ``ppf-det`` and
``fpfh-icp-det``): [the detection mask of the requested object] -> the objects' points on the
table (`object_points`) -> a registration stage (`Registration`: the model found among them
and refined) -> the estimate. `DepthRefinedEstimator` (``hybrid-global-icp``): another
estimator's pose -> the scene's points around it -> point-to-plane ICP.

Each sees only what a robot has: the depth image, K, the camera's pose and the table's height.
Without depth or table height there is no estimate, and the note says what is missing. An
estimate's ``info`` holds its ``score`` (the registration's confidence), ``timings_ms`` per
stage and the stages' own figures.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from perception.peers.points import CropConfig, object_points
from posegrasp.core.contract import Estimate, Observation, PoseEstimator
from posegrasp.world.objects import ObjectModel, load_object

#: Fewest scene points a registration is tried on.
MIN_SCENE_POINTS = 30


@dataclass(frozen=True)
class Registered:
    """What a registration stage found.

    Attributes:
        T_C_O: the object's pose in the camera frame, shape (4, 4) [m]; None when none was
            found (``info["note"]`` says why).
        score: its confidence (the method's own: PPF votes, ICP fitness).
        info: the stage's figures, JSON-serialisable.
        timings_ms: wall time per step [ms].
    """

    T_C_O: np.ndarray | None
    score: float
    info: dict[str, Any]
    timings_ms: dict[str, float]


class Registration(Protocol):
    """A registration stage: the pose of a model among the scene's points."""

    def register(self, model: ObjectModel, points_C: np.ndarray, seed: int) -> Registered:
        """The pose of `model` among `points_C` (N, 3), camera frame [m]; `seed` seeds it."""
        ...


class MaskPrior(Protocol):
    """A 2D prior: where in the image the requested object is."""

    def mask(self, obs: Observation) -> tuple[np.ndarray | None, dict[str, Any]]:
        """The object's mask (H, W) bool, or None when not found, and what was found."""
        ...


def depth_note(name: str, obs: Observation) -> str | None:
    """Why `name` cannot estimate from obs (no depth, no table height), or None."""
    if obs.depth is None:
        return f"{name} needs the depth image: run with --obs-mode rgbd"
    if obs.table_top_z is None:
        return f"{name} needs the table's height (Observation.table_top_z)"
    return None


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000


class PeerEstimator:
    """A classical peer (module docstring).

    Args:
        name: the name results carry.
        registration: the registration stage.
        crop: how the objects' points are cut out.
        prior: the 2D prior that crops them to the requested object's detection (None: none).
    """

    def __init__(
        self,
        name: str,
        registration: Registration,
        crop: CropConfig | None = None,
        prior: MaskPrior | None = None,
    ) -> None:
        self.name = name
        self.registration = registration
        self.crop = crop or CropConfig()
        self.prior = prior

    def estimate(self, obs: Observation) -> Estimate:
        """The requested object's pose from the depth image (None, with a note, when it cannot
        be found)."""
        note = depth_note(self.name, obs)
        if note is not None:
            return Estimate(None, info={"note": note})
        assert obs.depth is not None and obs.table_top_z is not None
        timings: dict[str, float] = {}
        info: dict[str, Any] = {"timings_ms": timings}
        mask = None
        if self.prior is not None:
            t0 = time.perf_counter()
            mask, info["detection"] = self.prior.mask(obs)
            timings["detect"] = _ms(t0)
            if mask is None:
                return Estimate(None, info=info | {"note": f"no detection of {obs.object}"})
        model = load_object(obs.object)
        t0 = time.perf_counter()
        points = object_points(
            obs.depth, obs.K, obs.T_world_cam, obs.table_top_z, model.diameter, self.crop, mask
        )
        timings["points"] = _ms(t0)
        info["points"] = len(points)
        if len(points) < MIN_SCENE_POINTS:
            note = f"{len(points)} points above the table, fewer than {MIN_SCENE_POINTS}"
            return Estimate(None, info=info | {"note": note})
        found = self.registration.register(model, points, obs.seed)
        timings |= found.timings_ms
        info = info | found.info | {"score": found.score}
        return Estimate(found.T_C_O, (), info, confidence=float(found.score))


class Refinement(Protocol):
    """A refinement stage on depth (`perception.peers.icp.PointToPlaneIcp`)."""

    def refine(self, model: ObjectModel, points_C: np.ndarray, T_C_O: np.ndarray) -> Any:
        """The refined pose (``T_C_O``, ``fitness``, ``rmse``, ``ms``)."""
        ...


class DepthRefinedEstimator:
    """Another estimator's pose refined on the depth image (``hybrid-global-icp``).

    The points kept are the objects' points on the table (`object_points`) within
    `radius_factor` times the object's diameter of the estimated origin; the refined pose
    replaces the estimate when its fitness is at least `min_fitness`. Without depth there is
    no estimate (the note says why), as for every peer.

    Args:
        name: the name results carry.
        inner: the estimator whose pose is refined.
        refinement: the refinement stage.
        crop: how the objects' points are cut out.
        radius_factor: the points kept lie within this many diameters of the estimated origin.
        min_fitness: the least fitness at which the refined pose replaces the estimate.
    """

    def __init__(
        self,
        name: str,
        inner: PoseEstimator,
        refinement: Refinement,
        crop: CropConfig | None = None,
        radius_factor: float = 0.75,
        min_fitness: float = 0.3,
    ) -> None:
        self.name = name
        self.inner = inner
        self.refinement = refinement
        self.crop = crop or CropConfig()
        self.radius_factor = radius_factor
        self.min_fitness = min_fitness

    def estimate(self, obs: Observation) -> Estimate:
        """The inner estimate, its pose refined on depth."""
        note = depth_note(self.name, obs)
        if note is not None:
            return Estimate(None, info={"note": note})
        est = self.inner.estimate(obs)
        if est.T_C_O is None:
            return est
        assert obs.depth is not None and obs.table_top_z is not None
        info = dict(est.info)
        timings = dict(info.get("timings_ms", {}))
        model = load_object(obs.object)
        t0 = time.perf_counter()
        points = object_points(
            obs.depth, obs.K, obs.T_world_cam, obs.table_top_z, model.diameter, self.crop
        )
        near = np.linalg.norm(points - est.T_C_O[:3, 3], axis=1) < (
            self.radius_factor * model.diameter
        )
        points = points[near]
        timings["points"] = _ms(t0)
        icp: dict[str, Any] = {"points": len(points), "applied": False}
        T = est.T_C_O
        if len(points) >= MIN_SCENE_POINTS:
            refined = self.refinement.refine(model, points, est.T_C_O)
            timings["icp"] = refined.ms
            icp |= {"fitness": refined.fitness, "rmse_m": refined.rmse}
            if refined.fitness >= self.min_fitness:
                T, icp["applied"] = refined.T_C_O, True
        info |= {"timings_ms": timings, "icp": icp, "score": icp.get("fitness", 0.0)}
        return Estimate(T, est.neighbours, info, confidence=float(info["score"]))
