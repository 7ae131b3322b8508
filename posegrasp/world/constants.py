"""Names of the Fetch robot as posegrasp converts it (see `posegrasp.world.robot`), in a fixed
order."""

from __future__ import annotations

PREFIX = "robot0:"

#: Holonomic base joints added at load time: x and y slides, yaw hinge (world frame axes).
BASE_JOINTS: tuple[str, ...] = ("base_x", "base_y", "base_yaw")
TORSO_JOINT = PREFIX + "torso_lift_joint"
HEAD_JOINTS: tuple[str, ...] = (PREFIX + "head_pan_joint", PREFIX + "head_tilt_joint")
ARM_JOINTS: tuple[str, ...] = tuple(
    PREFIX + n
    for n in (
        "shoulder_pan_joint",
        "shoulder_lift_joint",
        "upperarm_roll_joint",
        "elbow_flex_joint",
        "forearm_roll_joint",
        "wrist_flex_joint",
        "wrist_roll_joint",
    )
)
FINGER_JOINTS: tuple[str, ...] = (
    PREFIX + "r_gripper_finger_joint",
    PREFIX + "l_gripper_finger_joint",
)
#: Every actuated joint, in actuator order.
ACTUATED_JOINTS: tuple[str, ...] = (
    *BASE_JOINTS,
    TORSO_JOINT,
    *HEAD_JOINTS,
    *ARM_JOINTS,
    *FINGER_JOINTS,
)
#: Actuator names: "act_" + the joint name without prefix.
ACTUATORS: tuple[str, ...] = tuple("act_" + j.removeprefix(PREFIX) for j in ACTUATED_JOINTS)

BASE_BODY = PREFIX + "base_link"
GRIPPER_BODY = PREFIX + "gripper_link"
FINGER_BODIES: tuple[str, ...] = (
    PREFIX + "r_gripper_finger_link",
    PREFIX + "l_gripper_finger_link",
)
HEAD_CAMERA = "head_camera_rgb"
#: The scene's fixed third-person camera, and the size it is shown at (GIFs, env.render) [px].
EXTERNAL_CAMERA = "external"
EXTERNAL_SIZE = (480, 360)
#: Site between the finger pads, 13.5 mm behind the fingertips. Its x axis is the approach
#: direction (out of the gripper), y the closing direction, z completes the frame.
GRASP_SITE = "grasp_site"
GRASP_SITE_OFFSET = (0.025, 0.0, 0.0)  # in the gripper_link frame [m]
#: Finger travel of one finger [m]; the opening between the pads is twice this.
FINGER_TRAVEL = 0.05

#: Arm tucked to the side, torso part way up, head level, gripper open.
HOME_POSTURE: dict[str, float] = {
    "base_x": 0.0,
    "base_y": 0.0,
    "base_yaw": 0.0,
    TORSO_JOINT: 0.2,
    HEAD_JOINTS[0]: 0.0,
    HEAD_JOINTS[1]: 0.6,
    ARM_JOINTS[0]: 1.32,
    ARM_JOINTS[1]: 1.40,
    ARM_JOINTS[2]: -0.2,
    ARM_JOINTS[3]: 1.72,
    ARM_JOINTS[4]: 0.0,
    ARM_JOINTS[5]: 1.66,
    ARM_JOINTS[6]: 0.0,
    FINGER_JOINTS[0]: FINGER_TRAVEL,
    FINGER_JOINTS[1]: FINGER_TRAVEL,
}

#: The data generator (`perception.training.data.render_split.SEED_BASES`) draws its scenes from
#: seeds below this.
DATA_SEED_LIMIT = 300_000_000
#: Development episodes, for choosing between candidate weights or settings, start at this seed:
#: above every data seed and below every scoring seed, so that nothing is chosen on the scores.
DEV_SEED_BASE = 500_000_000
#: Episodes that score a learned estimator start at this seed, so that no evaluated scene was a
#: training, validation or test image of the networks.
EVAL_SEED_BASE = 1_000_000_000
