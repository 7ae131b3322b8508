"""posegrasp: score 6D pose estimators by simulated robot grasps.

This package is the bottom layer: the shared basics (`posegrasp.core`) and the simulated world
(`posegrasp.world`). Importing it registers the gymnasium env `GraspEval-v0` by a string entry
point (`sim.env:GraspEvalEnv`), which imports nothing of the layers above until the env is made,
so `gymnasium.make("posegrasp:GraspEval-v0")` works without any other import.
"""

import gymnasium

ENV_ID = "GraspEval-v0"
#: Where gymnasium finds the env class when it is made.
ENV_ENTRY_POINT = "sim.env:GraspEvalEnv"


def register_envs() -> None:
    """Register `GraspEval-v0` with gymnasium (idempotent).

    `gymnasium.make` does not wrap it in gymnasium's `PassiveEnvChecker`: the env's tests run the
    full `gymnasium.utils.env_checker.check_env` on it, and the passive checker (gymnasium 1.4)
    marks its first reset checked before calling it, so after a refused first reset (a bad seed)
    its first step failed with a TypeError however valid the next reset was.
    """
    if ENV_ID not in gymnasium.envs.registry:
        gymnasium.register(id=ENV_ID, entry_point=ENV_ENTRY_POINT, disable_env_checker=True)


register_envs()

__all__ = ["ENV_ENTRY_POINT", "ENV_ID", "register_envs"]
