"""Point-to-plane ICP on depth (Open3D): the refinement stage of ``fpfh-icp`` and
``hybrid-global-icp``.

The scene's points (source, camera frame C) are registered onto points sampled over the whole
model surface with their face normals (target, object frame O), so every scene point has its
true counterpart on the target, however little of the object the camera sees. The result maps
C to O (``T_O_C``); the estimate is its inverse. The distance within which a scene point and a
model point correspond shrinks stage by stage (`IcpConfig.distances_m`), coarse to fine. It runs
on `IcpConfig.threads` of Open3D's threads: over several, its sums add in a varying order, and a
fit whose rotation the points barely fix (a near-sphere) ends somewhere else each time.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from perception.peers.points import model_surface, nearest_rigid
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.transforms import invert_transform
from posegrasp.world.objects import ObjectModel

_REG = o3d.pipelines.registration


@dataclass(frozen=True)
class IcpConfig:
    """Point-to-plane ICP (Open3D's ``registration_icp``; its tutorial's choices, scaled to
    tabletop objects and tuned on training scenes, ``studies/peer_tuning.py``).

    Attributes:
        voxel_m: the scene's points are thinned to one per voxel of this size first [m].
        distances_m: the correspondence distance of each stage, coarse to fine [m].
        iterations: at most this many iterations per stage.
        model_points: samples of the model surface the scene is registered onto.
        seed: the model sampling's seed.
        threads: Open3D's threads during ICP (1: the same pose for the same start).
    """

    voxel_m: float = 0.003
    distances_m: tuple[float, ...] = (0.02, 0.008, 0.003)
    iterations: int = 30
    model_points: int = 20000
    seed: int = 0
    threads: int = 1

    def __post_init__(self) -> None:
        if self.voxel_m <= 0 or not self.distances_m or min(self.distances_m) <= 0:
            raise InvalidArgumentError("IcpConfig: voxel_m and every distance must be > 0")
        if self.iterations < 1 or self.model_points < 100 or self.threads < 1:
            raise InvalidArgumentError(
                "IcpConfig: iterations >= 1, model_points >= 100 and threads >= 1"
            )


@dataclass(frozen=True)
class Refined:
    """An ICP result.

    Attributes:
        T_C_O: the refined pose, shape (4, 4) [m].
        fitness: share of the scene's points within the last stage's distance of the model.
        rmse: their RMS distance to it [m].
        ms: wall time [ms].
    """

    T_C_O: np.ndarray
    fitness: float
    rmse: float
    ms: float


@contextmanager
def open3d_threads(n: int) -> Iterator[None]:
    """Open3D runs on `n` threads within the block, and on as many as before it after."""
    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(n)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(before)


def cloud(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    """An Open3D point cloud of (N, 3) points [m] and, when given, (N, 3) normals."""
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    return pc


class PointToPlaneIcp:
    """The refinement stage: `refine` a pose of an object on the scene's points.

    The model clouds are made on first use per object and process (not pickled).

    Args:
        config: the settings.
    """

    def __init__(self, config: IcpConfig | None = None) -> None:
        self.config = config or IcpConfig()
        self._targets: dict[tuple[str, str], o3d.geometry.PointCloud] = {}

    def __getstate__(self) -> dict:
        return {"config": self.config}

    def __setstate__(self, state: dict) -> None:
        type(self).__init__(self, state["config"])

    def target(self, model: ObjectModel) -> o3d.geometry.PointCloud:
        """The model's surface samples with normals, in O."""
        key = (model.name, model.revision)
        if key not in self._targets:
            pts, normals = model_surface(model, self.config.model_points, self.config.seed)
            self._targets[key] = cloud(pts, normals)
        return self._targets[key]

    def refine(self, model: ObjectModel, points_C: np.ndarray, T_C_O: np.ndarray) -> Refined:
        """Refine a pose of `model` on the scene's points.

        Args:
            model: the object.
            points_C: the scene's points of (or around) the object, shape (N, 3), C [m].
            T_C_O: the starting pose, shape (4, 4) [m].

        Returns:
            The refined pose and how well it fits.
        """
        cfg = self.config
        t0 = time.perf_counter()
        source = cloud(points_C).voxel_down_sample(cfg.voxel_m)
        T_O_C = invert_transform(T_C_O)
        result = None
        criteria = _REG.ICPConvergenceCriteria(max_iteration=cfg.iterations)
        with open3d_threads(cfg.threads):
            for distance in cfg.distances_m:
                result = _REG.registration_icp(
                    source,
                    self.target(model),
                    distance,
                    T_O_C,
                    _REG.TransformationEstimationPointToPlane(),
                    criteria,
                )
                T_O_C = np.asarray(result.transformation)
        assert result is not None
        return Refined(
            invert_transform(nearest_rigid(T_O_C)),
            float(result.fitness),
            float(result.inlier_rmse),
            (time.perf_counter() - t0) * 1000,
        )
