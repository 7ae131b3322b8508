"""Reading a mesh file: an OBJ's texture is found where its MTL says, also up the tree, as
packaged object sets lay theirs out (``meshes/x.obj`` naming ``../textures/x.png``)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image

from posegrasp.world.meshes import (
    COACD_DEFAULTS,
    DECOMPOSE_MAX_FACES,
    decompose,
    is_convex,
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

    # A ring is not convex, so CoACD cuts it (here told to stop at its first hull).
    ring = trimesh.creation.torus(0.03, 0.012, major_sections=128, minor_sections=64)
    assert len(ring.faces) > DECOMPOSE_MAX_FACES
    quick = {"threshold": 1.0, "max_convex_hull": 1, "resolution": 200}
    dec = decompose(ring, **quick)
    assert not dec.convex
    assert dec.simplified_from == len(ring.faces) and dec.faces == DECOMPOSE_MAX_FACES
    few = trimesh.creation.torus(0.03, 0.012, major_sections=32, minor_sections=16)
    assert decompose(few, **quick).simplified_from is None


def test_a_convex_mesh_is_its_own_hull() -> None:
    """A mesh convex within `CONVEX_TOL` is one hull, its own, of at most ``max_ch_vertex``
    vertices, and CoACD is not run; a mesh with a dent deeper than that is cut."""
    box = trimesh.creation.box(extents=[0.05, 0.04, 0.03])
    dec = decompose(box)
    assert dec.convex and len(dec.hulls) == 1
    assert np.allclose(np.sort(dec.hulls[0].vertices, axis=0), np.sort(box.vertices, axis=0))

    sphere = trimesh.creation.icosphere(subdivisions=6, radius=0.03)
    dec = decompose(sphere)
    (hull,) = dec.hulls
    assert dec.convex and len(hull.vertices) <= COACD_DEFAULTS["max_ch_vertex"]
    # Inside the sphere, touching it at each vertex, and closed.
    assert hull.is_watertight and 0.85 * sphere.volume < hull.volume <= sphere.volume
    assert np.allclose(np.linalg.norm(hull.vertices, axis=1), 0.03)
    assert len(decompose(sphere, max_ch_vertex=20).hulls[0].vertices) <= 20

    assert is_convex(trimesh.creation.capsule(height=0.08, radius=0.02))
    # A block with a groove 10 mm wide and 6 mm deep along its top is not convex.
    slab = trimesh.creation.box(extents=[0.05, 0.04, 0.018])
    tops = [trimesh.creation.box(extents=[0.02, 0.04, 0.006]) for _ in range(2)]
    for top, x in zip(tops, (-0.015, 0.015), strict=True):
        top.apply_translation([x, 0.0, 0.012])
    grooved = trimesh.util.concatenate([slab, *tops])
    assert not is_convex(grooved)
    assert is_convex(
        trimesh.util.concatenate(
            [
                slab,
                trimesh.creation.box(extents=[0.05, 0.04, 0.006]).apply_translation(
                    [0.0, 0.0, 0.012]
                ),
            ]
        )
    )
