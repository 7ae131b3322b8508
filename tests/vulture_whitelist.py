"""Names vulture reports as unused that are used, each with the reason (`make lint` runs vulture).

Run: vulture sim perception grasping posegrasp bench studies tests/vulture_whitelist.py
"""

from vulture.whitelist_utils import Whitelist

_ = Whitelist()

# Attributes set on MuJoCo specs and models, torchvision detectors and gymnasium envs: the
# libraries read them.
_.armature
_.castshadow
_.center
_.condim
_.conaffinity
_.contype
_.ctrllimited
_.detections_per_img
_.euler
_.extent
_.fixedcamid
_.forcelimited
_.forcerange
_.gravcomp
_.inertia
_.limited
_.markrgb
_.mocap
_.modelname
_.nchannel
_.rgb1
_.rgb2
_.score_thresh
_.stiffness
_.texuniform
_.trntype
_.zfar
_.znear
_.action_space
_.observation_space
_.dataset  # torch DataLoader worker info
_.readDepthMap  # MjrContext: depth read back as distance

# Protocols: torch modules' forward, the module-level __getattr__ of perception (lazy names).
_.forward
_.__getattr__

# Fields of result records, part of what a result reports.
_.T_world_G  # GraspPlan: the chosen gripper pose
_.crop_box  # PoseDetection: the square crop the nets saw
_.description  # ObjectModel: the definition's prose
_.ctrl_home  # Scene: the control vector that holds the home posture

# Public API used by the tests and by users, not by other modules.
_.decode_torch  # batched, differentiable decode, checked against perception.geometry.decode
_.pose_loss_4d  # the paper's eq. 7 as one function
_.load_sample  # one sample of a split without building a PoseDataset
_.symmetries_from_models_info  # BOP models_info.json symmetries as a metrics symmetry set

# Fields of a MuJoCo render context set from a model (read by MuJoCo, not by Python).
_.lineWidth
_.shadowClip
_.shadowScale
_.fogStart
_.fogEnd

# The env's public API: gymnasium makes GraspEvalEnv from its string entry point
# ("sim.env:GraspEvalEnv"), and users build actions with pose_action.
_.GraspEvalEnv
_.pose_action
_.from_env

# Fields of MuJoCo spec elements set from Python (read by MuJoCo when the model compiles).
_.meshname
_.explicitinertial
_.ipos
_.fullinertia
_.uservert
_.userface
_.usertexcoord
_.fromto
_.copy_during_attach

# Public API used by the tests and by users: a finished run's journal removed; the outcomes a
# checked grasp can have (documentation of grasping.grasp_check's results).
_.finish
_.OUTCOMES
