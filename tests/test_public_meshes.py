"""studies/public_meshes.py: the dense version of a mesh that onboarding is timed on."""

from __future__ import annotations

import importlib.util
import sys

import pytest
import trimesh

from posegrasp.core.paths import REPO_ROOT

_spec = importlib.util.spec_from_file_location(
    "public_meshes", REPO_ROOT / "studies" / "public_meshes.py"
)
study = importlib.util.module_from_spec(_spec)
sys.modules["public_meshes"] = study  # its dataclasses look their module up
_spec.loader.exec_module(study)


def test_a_dense_mesh_is_the_mesh_with_the_faces_asked(tmp_path) -> None:
    source = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=2, radius=0.03).export(source)  # 320 triangles
    mesh = study.PublicMesh("ball", "pkg", "1.0", "ball.obj", units="m", extras=("ball.mtl",))
    dense, path = study.dense_mesh(mesh, source, 3000, tmp_path)
    assert dense.name == "ball_dense" and dense.extras == () and dense.units == "m"
    assert "3000 triangles" in dense.member
    made = trimesh.load(path)
    assert 2900 <= len(made.faces) <= 3000
    assert made.volume == pytest.approx(trimesh.load(source).volume, rel=0.02)
    stamp = path.stat().st_mtime_ns
    assert study.dense_mesh(mesh, source, 3000, tmp_path)[1].stat().st_mtime_ns == stamp  # reused


def test_dense_takes_a_face_count_in_range(capsys) -> None:
    assert study.main(["--dense", "10", "--episodes", "0"]) == 2
    assert "--dense" in capsys.readouterr().err
