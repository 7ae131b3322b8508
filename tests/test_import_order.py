"""Rendering first and loading torch afterwards must not crash (docs/DESIGN.md §11)."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def test_render_then_import_torchvision_in_a_fresh_process() -> None:
    code = textwrap.dedent(
        """
        import sys
        import sim
        from sim.world.camera import CameraRenderer
        from sim.world.scene import build_scene
        from sim.world import constants as C
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
