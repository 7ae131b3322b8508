"""Rendering first and loading torch afterwards must not crash (docs/DESIGN.md §11)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap


def test_render_then_import_torchvision_in_a_fresh_process() -> None:
    code = textwrap.dedent(
        """
        import sys
        from posegrasp.core.runtime import setup_rendering
        setup_rendering()
        from posegrasp.world.camera import CameraRenderer
        from posegrasp.world.scene import build_scene
        from posegrasp.world import constants as C
        scene = build_scene("phone", 0)
        with CameraRenderer(scene.model, 64, 48) as r:
            img = r.rgb(scene.data, C.HEAD_CAMERA)
            assert "torchvision" in sys.modules  # loaded before the GL context
            import torch
            import torchvision
            from torchvision.ops import nms
            boxes = torch.tensor([[0.0, 0, 10, 10], [1, 1, 10, 10]])
            keep = nms(boxes, torch.tensor([0.9, 0.8]), 0.5)
            img2 = r.rgb(scene.data, C.HEAD_CAMERA)
        print("ok", img.shape, int(keep.numel()), img2.shape)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("ok (48, 64, 3) 1")


def test_rendering_without_set_up_is_refused_in_one_line() -> None:
    code = textwrap.dedent(
        """
        from posegrasp.core.errors import StateError
        from posegrasp.world.camera import CameraRenderer
        from posegrasp.world.scene import build_scene
        from posegrasp.world import constants as C
        scene = build_scene("phone", 0)
        try:
            with CameraRenderer(scene.model, 64, 48) as r:
                r.rgb(scene.data, C.HEAD_CAMERA)
        except StateError as exc:
            print("refused:", exc)
        """
    )
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "refused:" in out.stdout and "setup_rendering()" in out.stdout
    assert "torch" not in out.stdout


def test_importing_the_packages_changes_no_environment_variable() -> None:
    code = "import os; before = dict(os.environ)\n" + textwrap.dedent(
        """
        import posegrasp, posegrasp.world.camera, sim.episodes.episode, sim.env
        import perception, grasping
        import sys
        print(sorted(k for k in os.environ if os.environ.get(k) != before.get(k)))
        print("torch" in sys.modules)
        """
    )
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split("\n")[:2] == ["[]", "False"]


def test_an_evaluation_job_sets_up_its_own_process() -> None:
    """A worker that never ran the evaluation's initializer (a Ray worker started afresh after
    another died) still renders: each job sets up rendering in the process that runs it."""
    code = textwrap.dedent(
        """
        from sim.evaluation import EpisodeJob, Protocol, run_job
        protocol = Protocol(["phone"], 1, 1_000_000_000, "isolated")
        d = run_job(EpisodeJob("phone", 1_000_000_000, "oracle", protocol))
        print(d["success"], d["failure_reason"])
        """
    )
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["True", "None"]


def test_set_up_lets_openmp_spin_briefly_unless_told_otherwise() -> None:
    """`setup_rendering` sets libgomp's spin count before torch loads (when it reads it), and
    leaves a count the user set alone."""
    code = textwrap.dedent(
        """
        import os, sys
        from posegrasp.core.runtime import OMP_SPIN_COUNT, setup_rendering
        assert "torch" not in sys.modules
        setup_rendering()
        print(os.environ["GOMP_SPINCOUNT"] == str(OMP_SPIN_COUNT), "torch" in sys.modules)
        """
    )
    for given, expected in ((None, "True True"), ("123", "False True")):
        env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
        if given is not None:
            env["GOMP_SPINCOUNT"] = given
        out = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env
        )
        assert out.returncode == 0, out.stderr[-2000:]
        assert out.stdout.strip() == expected
