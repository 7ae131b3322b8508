"""One episode through the gymnasium env, as `sim.evaluate` plays it."""

import gymnasium as gym

from posegrasp.core.contract import Observation
from sim.env import pose_action
from sim.episodes.registry import DEFAULT_ESTIMATOR, make_estimator

estimator = make_estimator(DEFAULT_ESTIMATOR)  # hybrid-global, or "pkg.module:factory" for yours
env = gym.make("posegrasp:GraspEval-v0", object="phone", tier="isolated", obs_mode="rgb")
obs, info = env.reset(seed=1_000_000_000)  # sim.evaluate's episode 0 of the phone
# obs: rgb (480, 640, 3) uint8, K (3, 3), T_world_cam (4, 4), object (class index), table_top_z
# (1,) [m]; info: object (its name), episode_seed. from_env keeps all an estimator may see.
est = estimator.estimate(Observation.from_env(obs, info))
obs, reward, terminated, truncated, info = env.step(pose_action(est.T_C_O, est.neighbours))
print(f"reward {reward}, failure reason {info['failure_reason']}, correct {info['pose_correct']}")
if info["pose_error"] is not None:  # None without a valid estimate
    print(f"position error {info['pose_error']['translation_m'] * 1000:.1f} mm")
env.close()
