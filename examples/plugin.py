"""A plug-in estimator, scored by the same episodes as the built-in ones."""

import numpy as np

from posegrasp.core.cli import ArgumentParser
from posegrasp.core.contract import Estimate, Observation
from sim.evaluation import Protocol, evaluate_protocol


class MyEstimator:
    name = "mine"

    def estimate(self, obs: Observation) -> Estimate:
        T_C_O = np.eye(4)  # (4, 4) pose of obs.object in the camera frame [m], or None
        T_C_O[2, 3] = 0.8  # here a guess: 0.8 m straight ahead, axes along the camera's
        return Estimate(T_C_O, neighbours=(), info={"score": 0.9})


if __name__ == "__main__":
    ArgumentParser(description=__doc__).parse_args()  # --help says what this is
    report = evaluate_protocol(Protocol(["phone"], episodes=1), MyEstimator())
    episode = report["episodes"][0]
    print(f"{report['estimator']}: success {episode['success']}, {episode['failure_reason']}")
    print(f"position error {episode['pose_error']['translation_m'] * 1000:.1f} mm")
