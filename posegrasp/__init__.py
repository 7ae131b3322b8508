"""posegrasp: score 6D pose estimators by simulated robot grasps.

Importing this package registers the gymnasium env `GraspEval-v0`, so
`gymnasium.make("posegrasp:GraspEval-v0")` works without any other import.
"""

from sim.env import ENV_ID, GraspEvalEnv, pose_action, register_envs

__all__ = ["ENV_ID", "GraspEvalEnv", "pose_action", "register_envs"]
