"""Every reason an episode can fail with, each with its meaning: the one list that the executor,
the planner, the env, `sim.evaluate` and the docs use."""

from __future__ import annotations

#: Failure reason -> what it means. An episode's ``failure_reason`` is one of these keys, or None
#: on success.
FAILURE_REASONS: dict[str, str] = {
    "no_estimate": "the estimator returned no pose (e.g. the object was not detected)",
    "unreachable": "the object is farther than 1.3 m from the base after the drive, or the drive "
    "would exceed 2 m",
    "no_grasp": "no grasp candidate approaches from above at the estimated pose",
    "ik_infeasible": "no tried candidate's inverse kinematics converged at some stage",
    "collision": "before closing, the robot touched the table or knocked the object by over 2 cm",
    "missed": "after closing, not both fingers touch the object",
    "slipped": "after lift and hold, the object is below 0.10 m or no longer between the fingers",
    "disturbed": "the object was held, but another object moved over 3 cm or tilted over 30 deg",
    "invalid_action": "the estimate or the env's action was not a valid pose: non-finite, a "
    "rotation off orthonormal by more than 1e-6 or a reflection, a position beyond 10 m of the "
    "camera (metres, not millimetres), or a non-unit quaternion (the cause is the episode's first "
    "note and, in the env, info['error'])",
    "place_infeasible": "place task: the inverse kinematics of the set-down at the goal did not "
    "converge",
    "dropped": "place task: the object left the hand on the way to the goal",
    "tipped": "place task: the object came to rest with its up axis over 20 deg from the goal's",
    "off_target": "place task: the object rests over 2 cm or 10 deg (symmetry-aware) from its goal",
    "error": "the episode raised an error, recorded in its notes (sim.evaluate keeps going)",
}


def check_failure_reason(reason: str | None) -> str | None:
    """reason itself when it is None or one of `FAILURE_REASONS`.

    Raises:
        UnknownNameError: any other reason.
    """
    if reason is not None and reason not in FAILURE_REASONS:
        from posegrasp.core.errors import UnknownNameError

        raise UnknownNameError("failure reason", reason, FAILURE_REASONS)
    return reason
