"""``ppf``: point pair features (Drost et al., "Model globally, match locally: efficient and
robust 3D object recognition", CVPR 2010), as OpenCV's contrib module ``ppf_match_3d`` has
them, then its ICP.

The steps of OpenCV's ``ppf_load_match`` sample: the detector is trained on the model's points
with normals (here sampled over the mesh with the faces' normals), the scene's normals come
from `cv2.ppf_match_3d.computeNormalsPC3d` (turned towards the camera), `match` votes and
clusters poses, and the best `PpfConfig.hypotheses` are refined by OpenCV's ICP; the one with
the least ICP residual wins, its votes being the score.

OpenCV's training time grows steeply with the model points left after its sampling (the
relative sampling step): that step is the coarsest at which training takes seconds, not
minutes.

The clouds go to OpenCV in units of the object's diameter. Its pose clustering joins the poses
whose positions differ by less than the relative sampling step, compared with absolute
distances, and whose rotation angles differ by less than a threshold it computes as about 30
rad, so never; it returns the mean pose of each cluster, and its Python binding does not expose
``setSearchParams``, which sets both thresholds. In metres every pose within 7 cm would be one
cluster and its rotations averaged (``studies/peer_tuning.py`` records two copies of a model
at one place turned 90 deg apart coming back as one pose between them); in diameters the
clusters are the 7 % of the object that the relative step means. Every other parameter of
OpenCV's PPF is relative to the model's or the scene's extent and reads the same in either
unit; ICP's residual is then in diameters.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from perception.peers.estimator import Registered
from perception.peers.points import model_surface, nearest_rigid
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world.objects import ObjectModel

#: The residual at or above which OpenCV's ICP says it failed (it reports 1e10 and leaves the
#: pose wherever its iterations went).
ICP_FAILED = 1e9


@dataclass(frozen=True)
class PpfConfig:
    """OpenCV's PPF detector and ICP (the sample's values where they apply; the sampling
    tuned on training scenes, ``studies/peer_tuning.py``).

    Attributes:
        model_points: samples of the model surface handed to training (OpenCV thins them).
        sampling_step: ``relativeSamplingStep``: the model is thinned to this fraction of its
            diameter.
        distance_step: ``relativeDistanceStep``: pair distances are quantised to this fraction
            of the diameter.
        num_angles: ``numAngles``: the angles of a pair are quantised into this many bins.
        scene_sample_step: ``relativeSceneSampleStep``: this share of the thinned scene points
            are reference points.
        scene_distance: ``relativeSceneDistance``: the scene is thinned to this fraction of the
            diameter.
        normal_neighbours: the scene's normals are fitted to this many nearest points.
        hypotheses: the best this-many poses are refined by ICP.
        icp_iterations: ICP's iterations per level.
        icp_tolerance: ICP stops when its residual changes less than this.
        icp_rejection_scale: ICP rejects pairs farther than this many robust deviations.
        icp_levels: ICP's coarse-to-fine levels.
        seed: the model sampling's seed.
    """

    model_points: int = 5000
    sampling_step: float = 0.1
    distance_step: float = 0.05
    num_angles: int = 30
    scene_sample_step: float = 0.2
    scene_distance: float = 0.05
    normal_neighbours: int = 6
    hypotheses: int = 2
    icp_iterations: int = 100
    icp_tolerance: float = 0.005
    icp_rejection_scale: float = 2.5
    icp_levels: int = 8
    seed: int = 0

    def __post_init__(self) -> None:
        steps = (self.sampling_step, self.distance_step, self.scene_sample_step)
        if min(steps) <= 0 or max(steps) > 1 or not 0 < self.scene_distance <= 1:
            raise InvalidArgumentError("PpfConfig: the relative steps must be in (0, 1]")
        if min(self.num_angles, self.hypotheses, self.icp_levels, self.normal_neighbours) < 1:
            raise InvalidArgumentError(
                "PpfConfig: num_angles, hypotheses, icp_levels, normal_neighbours >= 1"
            )


class PpfRegistration:
    """The registration stage of ``ppf``: `register` finds the object among the scene's
    points. A detector is trained on first use per object and process (not pickled).

    Args:
        config: the settings.
    """

    def __init__(self, config: PpfConfig | None = None) -> None:
        self.config = config or PpfConfig()
        self._models: dict[tuple[str, str], tuple] = {}

    def __getstate__(self) -> dict:
        return {"config": self.config}

    def __setstate__(self, state: dict) -> None:
        type(self).__init__(self, state["config"])

    def trained(
        self, model: ObjectModel
    ) -> tuple[cv2.ppf_match_3d.PPF3DDetector, np.ndarray, float]:
        """The detector trained on `model`, its training cloud (N, 6) float32 (points in units
        of the object's diameter, normals; O) and the time training took [ms]."""
        key = (model.name, model.revision)
        if key not in self._models:
            cfg = self.config
            t0 = time.perf_counter()
            pts, normals = model_surface(model, cfg.model_points, cfg.seed)
            pc = np.hstack([pts / model.diameter, normals]).astype(np.float32)
            detector = cv2.ppf_match_3d.PPF3DDetector(
                cfg.sampling_step, cfg.distance_step, cfg.num_angles
            )
            detector.trainModel(pc)
            self._models[key] = (detector, pc, (time.perf_counter() - t0) * 1000)
        return self._models[key]

    def register(self, model: ObjectModel, points_C: np.ndarray, seed: int) -> Registered:
        """The pose of `model` among the scene's points.

        Args:
            model: the object.
            points_C: the scene's points, shape (N, 3), camera frame [m].
            seed: unused (OpenCV's matching draws nothing at random).

        Returns:
            The ICP-refined pose of least residual; its score is its PPF votes.
        """
        del seed
        cfg = self.config
        timings: dict[str, float] = {}
        first = (model.name, model.revision) not in self._models
        detector, pc, train_ms = self.trained(model)
        if first:
            timings["train"] = train_ms
        t0 = time.perf_counter()
        scene: np.ndarray = np.ascontiguousarray(points_C / model.diameter, np.float32)
        _, scene = cv2.ppf_match_3d.computeNormalsPC3d(
            scene, cfg.normal_neighbours, True, (0.0, 0.0, 0.0)
        )
        timings["normals"] = (time.perf_counter() - t0) * 1000
        t0 = time.perf_counter()
        results = list(detector.match(scene, cfg.scene_sample_step, cfg.scene_distance))
        timings["match"] = (time.perf_counter() - t0) * 1000
        if not results:
            info = {"votes": 0, "hypotheses": 0, "note": "no PPF pose hypothesis"}
            return Registered(None, 0.0, info, timings)
        votes = [int(r.numVotes) for r in results[: cfg.hypotheses]]
        t0 = time.perf_counter()
        icp = cv2.ppf_match_3d.ICP(
            cfg.icp_iterations, cfg.icp_tolerance, cfg.icp_rejection_scale, cfg.icp_levels
        )
        _, refined = icp.registerModelToScene(pc, scene, results[: cfg.hypotheses])
        timings["icp"] = (time.perf_counter() - t0) * 1000
        fitted = [i for i in range(len(refined)) if float(refined[i].residual) < ICP_FAILED]
        if not fitted:
            info = {"votes": max(votes), "hypotheses": len(results), "note": "ICP failed"}
            return Registered(None, 0.0, info, timings)
        best = min(fitted, key=lambda i: float(refined[i].residual))
        T = nearest_rigid(np.asarray(refined[best].pose, np.float64))
        T[:3, 3] *= model.diameter
        info = {
            "votes": votes[best],
            "icp_residual_diameters": float(refined[best].residual),
            "hypotheses": len(results),
        }
        return Registered(T, float(votes[best]), info, timings)
