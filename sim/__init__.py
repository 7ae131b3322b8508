"""posegrasp simulation: the Fetch robot, scenes, cameras, rendering and episodes.

Rendering defaults to Mesa's software EGL (`MUJOCO_GL=egl`): the variable must be set before
MuJoCo's renderer is first loaded, so it is defaulted here. No GL context is created on import.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
