"""A minimal external pose estimator for posegrasp (a plug-in, not part of posegrasp).

It implements the estimator contract (`posegrasp.core.contract`, version 2): a ``name`` and
``estimate(obs) -> Estimate``. The head camera looks at the requested object, so the estimator
puts the object where the optical axis meets the table top, standing in its canonical resting
pose and turned to face the camera. It uses only what the observation holds: K, the camera pose
and the table height (RGB is not even looked at), and the object's size from posegrasp's models.

Score it with any posegrasp command::

    python -m sim.evaluate --estimator posegrasp_crude:CrudeTableEstimator --objects phone
    python -m sim.evaluate --estimator crude --objects phone      # once this package is installed
"""

from __future__ import annotations

import numpy as np

from posegrasp.core.contract import Estimate, Observation
from posegrasp.core.transforms import quat_to_mat
from posegrasp.world.objects import load_object


class CrudeTableEstimator:
    """The object on the table where the camera's optical axis meets it, upright, facing the
    camera."""

    name = "crude"

    def estimate(self, obs: Observation) -> Estimate:
        if obs.table_top_z is None:
            return Estimate(None, info={"note": "needs the table height"})
        model = load_object(obs.object)
        quat = next(iter(model.resting_poses.values()))
        z = obs.table_top_z + model.resting_height(quat)
        origin = obs.T_world_cam[:3, 3]
        axis = obs.T_world_cam[:3, 2]  # the optical axis in the world
        if axis[2] > -1e-6:
            return Estimate(None, info={"note": "the camera does not look down at the table"})
        p = origin + axis * (z - origin[2]) / axis[2]
        yaw = np.arctan2(origin[1] - p[1], origin[0] - p[0])  # the object's x towards the camera
        c, s = np.cos(yaw), np.sin(yaw)
        T_world_O = np.eye(4)
        T_world_O[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ quat_to_mat(
            quat
        )
        T_world_O[:3, 3] = p
        T_C_O = np.linalg.inv(obs.T_world_cam) @ T_world_O
        return Estimate(T_C_O, info={"ray_hit_world": p.tolist()})
