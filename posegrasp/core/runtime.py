"""Process set-up for rendering: an explicit call, never an import-time side effect.

Every command, the gymnasium env and the worker processes call `setup_rendering()` before they
render. It

- defaults ``MUJOCO_GL`` to ``egl`` (Mesa's software EGL on a machine with no screen); the GL
  context is opened with the backend that variable names when the first render needs it, so the
  order in which mujoco and this module are imported does not matter;
- loads torch, torch._dynamo and torchvision, when installed, before the first GL context exists:
  importing them once a MuJoCo GL context exists crashes the process (inside triton), so a user
  who renders first and loads a network afterwards would otherwise crash;
- optionally pins the compute threads (`threads`): torch's, OpenMP's and Mesa's rasteriser's;
- runs the OpenBLAS that numpy, SciPy and OpenCV bring on one thread. Their matrices here are
  small (the refiner's 6x6 solves and Jacobian products); a second OpenBLAS thread only spins
  for a while after each call, taking a core from the torch threads that run next (the detector
  then took twice as long right after a verification);
- lets OpenMP's idle threads spin only briefly (``GOMP_SPINCOUNT``, `OMP_SPIN_COUNT`, unless
  set already; it takes effect when torch loads, so before it). By default an idle thread
  spins 300,000 times after each parallel region of torch: that took the other core from the
  global estimator's worker process (`perception.parallel`) for several milliseconds after the
  detector and the mask net ran (its half of the codebook matching took twice as long as this
  process's half). A short spin keeps torch's own speed; none at all slowed the detector.

Rendering without it raises `StateError` naming this function.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import platform
import sys

from posegrasp.core.errors import StateError

#: GL backends MuJoCo can open a context with, by platform.
GL_BACKENDS = {"Linux": ("egl", "osmesa", "glfw"), "Darwin": ("cgl", "glfw"), "Windows": ("glfw",)}
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "LP_NUM_THREADS")
#: Spins of an idle OpenMP thread of torch before it sleeps (libgomp's default: 300,000).
OMP_SPIN_COUNT = 10_000
_DONE = False


def setup_rendering(threads: int | None = None, preload_torch: bool = True) -> None:
    """Prepare this process for rendering (idempotent; see the module docstring).

    Args:
        threads: when given, the number of compute threads of torch, OpenMP and Mesa's software
            rasteriser in this process (the evaluation workers use 1).
        preload_torch: import torch and torchvision now, when installed.
    """
    global _DONE
    if _DONE and threads is None:
        return
    default = "egl" if platform.system() == "Linux" else "glfw"
    os.environ.setdefault("MUJOCO_GL", default)
    os.environ.setdefault("GOMP_SPINCOUNT", str(OMP_SPIN_COUNT))
    if threads is not None:
        for name in _THREAD_VARIABLES:
            os.environ[name] = str(threads)
    if preload_torch and importlib.util.find_spec("torchvision") is not None:
        import torch
        import torch._dynamo  # noqa: F401
        import torchvision  # noqa: F401

    if threads is not None and "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(threads)
    import threadpoolctl

    threadpoolctl.threadpool_limits(limits=1, user_api="blas")
    _DONE = True


def gl_context_class() -> type:
    """The GLContext class of the backend ``MUJOCO_GL`` names (default set by
    `setup_rendering`).

    Raises:
        StateError: `setup_rendering` was not called in this process.
        InvalidArgumentError: ``MUJOCO_GL`` names no backend of this platform.
    """
    if not _DONE:
        raise StateError(
            "rendering is not set up in this process: call "
            "posegrasp.core.runtime.setup_rendering() before the first render"
        )
    from posegrasp.core.errors import InvalidArgumentError

    backend = os.environ["MUJOCO_GL"].lower().strip()
    choices = GL_BACKENDS.get(platform.system(), ("glfw",))
    if backend not in choices:
        raise InvalidArgumentError(
            f"MUJOCO_GL={backend!r} is not a GL backend of this platform; valid: "
            + ", ".join(choices)
        )
    return importlib.import_module(f"mujoco.{backend}").GLContext
