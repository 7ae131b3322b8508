"""Textured meshes: `add_object` keeps a mesh's texture (an OBJ with its MTL and image, a GLB
with its image embedded), scenes draw it, and the BOP export writes it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from PIL import Image

from perception.training.data.bop import obj_id
from posegrasp.world import constants as C
from posegrasp.world.camera import CameraRenderer, body_mask
from posegrasp.world.objects import load_object
from posegrasp.world.scene import build_scene
from posegrasp.world.user_objects import DESCRIPTION_FILE, OBJECTS_ENV, TEXTURE_FILES
from sim.add_object import main as add_object

pytestmark = pytest.mark.slow
SIZE = np.array([0.06, 0.04, 0.03])


def _textured_box() -> trimesh.Trimesh:
    """A box whose six faces each show the whole texture: red on its left half, blue on its
    right (24 vertices, four a face, so that each face has its own coordinates)."""
    box = trimesh.creation.box(extents=SIZE)
    vertices, faces, uv = [], [], []
    for normal in np.eye(3).tolist() + (-np.eye(3)).tolist():
        n = np.asarray(normal)
        a = np.roll(n, 1) if n.sum() > 0 else -np.roll(n, 1)
        b = np.cross(n, a)
        centre = n * SIZE / 2
        k = len(vertices)
        for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
            vertices.append(centre + su * a * SIZE / 2 + sv * b * SIZE / 2)
            uv.append([(su + 1) / 2, (sv + 1) / 2])
        faces += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
    mesh = trimesh.Trimesh(np.array(vertices), np.array(faces), process=False)
    mesh.fix_normals()
    assert mesh.volume == pytest.approx(box.volume)
    image = np.zeros((32, 32, 3), np.uint8)
    image[:, :16, 0], image[:, 16:, 2] = 230, 230
    material = trimesh.visual.material.SimpleMaterial(image=Image.fromarray(image))
    mesh.visual = trimesh.visual.TextureVisuals(uv=np.array(uv), material=material)
    return mesh


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """The textured box as an OBJ (with its MTL and PNG) and as a GLB, each made a user object."""
    root = tmp_path_factory.mktemp("textured")
    mesh = _textured_box()
    obj_text, files = trimesh.exchange.obj.export_obj(
        mesh, include_texture=True, return_texture=True, mtl_name="box.mtl"
    )
    (root / "box.obj").write_text(obj_text)
    for name, data in files.items():
        (root / name).write_bytes(data)
    mesh.export(root / "box.glb")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(OBJECTS_ENV, str(root / "objects"))
        for name, suffix in (("tbox", "obj"), ("gbox", "glb")):
            assert add_object([str(root / f"box.{suffix}"), "--name", name, "--units", "m"]) == 0
        yield root


@pytest.mark.parametrize("name", ["tbox", "gbox"])
def test_the_texture_is_kept_and_drawn_in_the_scene(made, monkeypatch, name) -> None:
    monkeypatch.setenv(OBJECTS_ENV, str(made / "objects"))
    folder = made / "objects" / name
    assert json.loads((folder / DESCRIPTION_FILE).read_text())["texture"] == TEXTURE_FILES
    texture = load_object(name).geometry.texture
    assert texture is not None and texture.image.shape == (32, 32, 3)
    assert sorted(np.ptp(texture.vertices, axis=0)) == pytest.approx(sorted(SIZE), abs=1e-6)
    rgba = load_object(name).geometry.rgba  # the texture's mean colour, for the appearance score
    assert rgba[0] == pytest.approx(rgba[2], abs=0.05) and rgba[1] < 0.05
    scene = build_scene(name, 3)
    with CameraRenderer(scene.model, 640, 480) as r:
        rgb = r.rgb(scene.data, C.HEAD_CAMERA).astype(int)
        seen = body_mask(scene.model, r.segmentation(scene.data, C.HEAD_CAMERA), f"{name}_0")
    assert seen.sum() > 200
    px = rgb[seen]
    red = (px[:, 0] > px[:, 2] + 40).mean()
    blue = (px[:, 2] > px[:, 0] + 40).mean()
    assert red > 0.2 and blue > 0.2, (red, blue)  # both halves, not the texture's mean colour


def test_the_bop_export_writes_the_texture_beside_the_model(made, monkeypatch, tmp_path) -> None:
    from sim.export_bop import export_bop

    monkeypatch.setenv(OBJECTS_ENV, str(made / "objects"))
    export_bop(tmp_path / "bop", ["tbox"], 1, progress=False)
    for models in ("models", "models_eval"):
        ply = tmp_path / "bop" / models / f"obj_{obj_id('tbox'):06d}.ply"
        header = ply.read_bytes().split(b"end_header")[0].decode()
        png = ply.with_suffix(".png")
        assert f"comment TextureFile {png.name}" in header
        assert "property float texture_u" in header and "property float texture_v" in header
        assert np.asarray(Image.open(png)).shape == (32, 32, 3)
