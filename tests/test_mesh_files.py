"""Reading a mesh file: an OBJ's texture is found where its MTL says, also up the tree, as
packaged object sets lay theirs out (``meshes/x.obj`` naming ``../textures/x.png``)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image

from posegrasp.world.meshes import (
    DECOMPOSE_MAX_FACES,
    decompose,
    mesh_texture,
    read_mesh,
    simplified,
)


def _textured(tmp_path, image_path: str):
    """A textured box written as an OBJ in ``meshes/`` whose MTL names `image_path`."""
    mesh = trimesh.creation.box(extents=[0.05, 0.04, 0.03])
    uv = np.random.default_rng(0).uniform(size=(len(mesh.vertices), 2))
    pixels = np.zeros((8, 8, 3), np.uint8)
    pixels[:, :, 0] = 200
    material = trimesh.visual.material.SimpleMaterial(image=Image.fromarray(pixels))
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
    text, files = trimesh.exchange.obj.export_obj(
        mesh, include_texture=True, return_texture=True, mtl_name="box.mtl"
    )
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "box.obj").write_text(text)
    png = next(n for n in files if n.endswith(".png"))
    mtl = files["box.mtl"].decode().replace(png, image_path)
    (tmp_path / "meshes" / "box.mtl").write_text(mtl)
    target = tmp_path / "meshes" / image_path
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_bytes(files[png])
    return tmp_path / "meshes" / "box.obj"


def test_an_objs_texture_up_the_tree_is_read(tmp_path) -> None:
    texture = mesh_texture(read_mesh(_textured(tmp_path, "../textures/box.png")), 1.0)
    assert texture is not None and texture.image.shape == (8, 8, 3)
    assert (texture.image[..., 0] == 200).all()


def test_an_objs_texture_beside_it_is_read(tmp_path) -> None:
    texture = mesh_texture(read_mesh(_textured(tmp_path, "box_tex.png")), 1.0)
    assert texture is not None and (texture.image[..., 0] == 200).all()


def test_a_dense_mesh_is_simplified_before_its_decomposition() -> None:
    """CoACD cuts a simplification of a mesh over `DECOMPOSE_MAX_FACES` triangles, and says so;
    a mesh within it is cut as it is."""
    dense = trimesh.creation.icosphere(subdivisions=6, radius=0.03)  # 81,920 triangles
    assert len(dense.faces) > DECOMPOSE_MAX_FACES
    small = simplified(dense, DECOMPOSE_MAX_FACES)
    assert len(small.faces) <= DECOMPOSE_MAX_FACES
    assert small.volume == pytest.approx(dense.volume, rel=0.01)
    coarse = trimesh.creation.icosphere(subdivisions=2, radius=0.03)
    assert simplified(coarse, DECOMPOSE_MAX_FACES) is coarse

    quick = {"max_convex_hull": 1, "mcts_iterations": 10, "mcts_nodes": 5, "resolution": 200}
    dec = decompose(dense, **quick)
    assert dec.simplified_from == len(dense.faces) and dec.faces == len(small.faces)
    # One hull of at most 64 vertices (`max_ch_vertex`) inside the sphere.
    assert 0.75 * dense.volume < sum(h.volume for h in dec.hulls) <= 1.01 * dense.volume
    assert decompose(coarse, **quick).simplified_from is None
