"""``fpfh-icp``: FPFH features, RANSAC global registration, point-to-plane ICP (Open3D;
Rusu et al., "Fast Point Feature Histograms (FPFH) for 3D registration", ICRA 2009).

The pipeline of Open3D's global registration tutorial and its ``registration_ransac.py``
example: both clouds thinned to one point per voxel, normals from their neighbourhoods (the
model's from its faces), FPFH features, RANSAC over feature correspondences with the edge
length and distance checkers, then ICP. The scene is the source and the model the target, so
the fitness is the share of the scene the model explains.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from perception.peers.estimator import Registered
from perception.peers.icp import IcpConfig, PointToPlaneIcp, cloud, open3d_threads
from perception.peers.points import model_surface, nearest_rigid
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.transforms import invert_transform
from posegrasp.world.objects import ObjectModel

_REG = o3d.pipelines.registration


@dataclass(frozen=True)
class FpfhConfig:
    """FPFH + RANSAC + ICP (Open3D's tutorial values relative to the voxel; the voxel and the
    RANSAC budget and restarts tuned on training scenes, ``studies/peer_tuning.py``).

    Attributes:
        voxel_m: both clouds are thinned to one point per voxel of this size [m].
        normal_radius: the scene's normals from neighbours within this many voxels.
        normal_max_nn: ... and at most this many of them.
        feature_radius: FPFH from neighbours within this many voxels.
        feature_max_nn: ... and at most this many of them.
        distance: RANSAC's inlier distance, in voxels.
        mutual_filter: keep only correspondences that are each other's nearest feature.
        edge_length: RANSAC's edge length checker: corresponding edges agree to this ratio.
        max_iterations: RANSAC's iterations at most.
        confidence: RANSAC stops once this sure of its best model.
        restarts: RANSAC runs from this many seeds (the seed, the seed + 1, ...), each refined
            by ICP; the pose of the highest ICP fitness is kept.
        model_points: samples of the model surface before thinning.
        threads: Open3D's threads during RANSAC (1: the same answer for the same seed).
        icp: the refinement.
    """

    voxel_m: float = 0.005
    normal_radius: float = 2.0
    normal_max_nn: int = 30
    feature_radius: float = 5.0
    feature_max_nn: int = 100
    distance: float = 1.5
    mutual_filter: bool = False
    edge_length: float = 0.9
    max_iterations: int = 100000
    confidence: float = 0.999
    restarts: int = 3
    model_points: int = 20000
    threads: int = 1
    icp: IcpConfig = field(default_factory=IcpConfig)

    def __post_init__(self) -> None:
        if min(self.voxel_m, self.normal_radius, self.feature_radius, self.distance) <= 0:
            raise InvalidArgumentError("FpfhConfig: the voxel and the radii must be > 0")
        if not 0 < self.edge_length < 1 or not 0 < self.confidence < 1:
            raise InvalidArgumentError("FpfhConfig: edge_length and confidence in (0, 1)")
        if self.restarts < 1:
            raise InvalidArgumentError(f"FpfhConfig: restarts must be >= 1, not {self.restarts}")


class FpfhRegistration:
    """The registration stage of ``fpfh-icp``: `register` finds the object among the scene's
    points. Model features are made on first use per object and process (not pickled).

    Args:
        config: the settings.
    """

    def __init__(self, config: FpfhConfig | None = None) -> None:
        self.config = config or FpfhConfig()
        self.icp = PointToPlaneIcp(self.config.icp)
        self._models: dict[tuple[str, str], tuple] = {}

    def __getstate__(self) -> dict:
        return {"config": self.config}

    def __setstate__(self, state: dict) -> None:
        type(self).__init__(self, state["config"])

    def _features(self, pc: o3d.geometry.PointCloud) -> o3d.pipelines.registration.Feature:
        cfg = self.config
        radius = cfg.feature_radius * cfg.voxel_m
        search = o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=cfg.feature_max_nn)
        # Open3D's stub drops the default of `indices` (all points), which the binding has.
        return _REG.compute_fpfh_feature(pc, search)  # type: ignore[call-arg]

    def model(self, model: ObjectModel) -> tuple[o3d.geometry.PointCloud, object, float]:
        """The model's thinned cloud (face normals), its features and the time they took [ms]."""
        key = (model.name, model.revision)
        if key not in self._models:
            t0 = time.perf_counter()
            pts, normals = model_surface(model, self.config.model_points, self.config.icp.seed)
            pc = cloud(pts, normals).voxel_down_sample(self.config.voxel_m)
            pc.normalize_normals()
            self._models[key] = (pc, self._features(pc), (time.perf_counter() - t0) * 1000)
        return self._models[key]

    def _ransac(self, scene, target, features, target_features, distance: float, seed: int):
        """Open3D's RANSAC over feature correspondences, seeded, on `FpfhConfig.threads`
        threads, its warnings (too few mutual correspondences) silenced."""
        cfg = self.config
        o3d.utility.random.seed(int(seed) % 2**31)
        with (
            open3d_threads(cfg.threads),
            o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error),
        ):
            return _REG.registration_ransac_based_on_feature_matching(
                scene,
                target,
                features,
                target_features,
                cfg.mutual_filter,
                distance,
                _REG.TransformationEstimationPointToPoint(False),
                3,
                [
                    _REG.CorrespondenceCheckerBasedOnEdgeLength(cfg.edge_length),
                    _REG.CorrespondenceCheckerBasedOnDistance(distance),
                ],
                _REG.RANSACConvergenceCriteria(cfg.max_iterations, cfg.confidence),
            )

    def register(self, model: ObjectModel, points_C: np.ndarray, seed: int) -> Registered:
        """The pose of `model` among the scene's points.

        Args:
            model: the object.
            points_C: the scene's points, shape (N, 3), camera frame [m].
            seed: RANSAC's first seed.

        Returns:
            The ICP-refined pose of the highest fitness over the restarts; its score is that
            fitness.
        """
        cfg = self.config
        timings: dict[str, float] = {}
        trained = (model.name, model.revision) not in self._models
        target, target_features, model_ms = self.model(model)
        if trained:
            timings["model"] = model_ms
        t0 = time.perf_counter()
        scene = cloud(points_C).voxel_down_sample(cfg.voxel_m)
        radius = cfg.normal_radius * cfg.voxel_m
        scene.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=cfg.normal_max_nn)
        )
        scene.orient_normals_towards_camera_location(np.zeros(3))
        features = self._features(scene)
        timings["features"] = (time.perf_counter() - t0) * 1000
        distance = cfg.distance * cfg.voxel_m
        timings["ransac"], timings["icp"] = 0.0, 0.0
        tries = []
        for restart in range(cfg.restarts):
            t0 = time.perf_counter()
            found = self._ransac(scene, target, features, target_features, distance, seed + restart)
            timings["ransac"] += (time.perf_counter() - t0) * 1000
            T_C_O = invert_transform(nearest_rigid(np.asarray(found.transformation)))
            tries.append((found, self.icp.refine(model, points_C, T_C_O)))
            timings["icp"] += tries[-1][1].ms
        # The first of the best fits: the highest fitness, then the lowest error.
        ransac, refined = max(tries, key=lambda t: (t[1].fitness, -t[1].rmse))
        info = {
            "ransac_fitness": float(ransac.fitness),
            "icp_fitness": refined.fitness,
            "icp_rmse_m": refined.rmse,
            "scene_points": len(scene.points),
        }
        return Registered(refined.T_C_O, refined.fitness, info, timings)
