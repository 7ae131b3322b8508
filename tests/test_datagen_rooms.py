"""Rooms drawn for training (`perception.training.data.rooms`, ``datagen --rooms``)."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import mujoco
import numpy as np
import pytest

from perception.training.data.distributions import HeadcamGenerator
from perception.training.data.render_split import (
    MAX_COUNT,
    ROOM_SEED_OFFSETS,
    SEED_BASES,
    GenConfig,
)
from perception.training.data.rooms import FACTORS, FAMILIES, randomize_room, room_shifts
from perception.training.datagen import main
from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.world.constants import DATA_SEED_LIMIT
from posegrasp.world.distractor_bank import BODY, DISTRACTOR_IDS, TRAINING_IDS, bank_mesh
from posegrasp.world.scene import SceneConfig, build_scene

W, H = 160, 120


def test_a_room_is_drawn_from_its_seed_alone_and_each_factor_is_drawn() -> None:
    scenes = [build_scene("phone", 7, SceneConfig(randomize_appearance=True)) for _ in range(2)]
    draws = [randomize_room(s.model, s.data, [s.target.body], 41) for s in scenes]
    assert draws[0] == draws[1]
    assert np.array_equal(scenes[0].model.geom_rgba, scenes[1].model.geom_rgba)
    assert np.array_equal(scenes[0].model.tex_data, scenes[1].model.tex_data)
    seen: set[str] = set()
    for seed in range(40):  # the draws' keys only: the edits pile up on the one scene
        seen |= set(randomize_room(scenes[0].model, scenes[0].data, [], seed))
    assert seen == set(FACTORS)


def test_a_room_changes_what_is_drawn_and_no_physics() -> None:
    plain = build_scene("car", 3, SceneConfig(randomize_appearance=True))
    roomed = build_scene("car", 3, SceneConfig(randomize_appearance=True))
    seed = next(s for s in range(100) if {"surfaces", "objects"} <= set(_draw(roomed, s)))
    assert not np.array_equal(plain.model.tex_data, roomed.model.tex_data)
    assert not np.array_equal(plain.model.geom_rgba, roomed.model.geom_rgba)
    for field in ("body_mass", "geom_friction", "geom_size", "actuator_gainprm"):
        assert np.array_equal(getattr(plain.model, field), getattr(roomed.model, field)), seed
    plain.step(0.3)
    roomed.step(0.3)
    assert np.array_equal(plain.data.qpos, roomed.data.qpos)


def _draw(scene, seed: int, family: str = "wide") -> dict:
    return randomize_room(scene.model, scene.data, [o.body for o in scene.objects], seed, family)


def test_training_distractors_come_from_the_training_bank_only() -> None:
    pytest.importorskip("pybullet")
    seed = next(s for s in range(100) if room_shifts(s))
    cfg = SceneConfig(shifts=room_shifts(seed), distractor_bank="training")
    scene = build_scene("phone", seed, cfg)
    meshes = [
        scene.model.mesh(int(scene.model.geom_dataid[g])).name
        for g in np.flatnonzero(scene.model.geom_bodyid == scene.model.body(BODY).id)
    ]
    ids = {int(name.rsplit("/", 1)[-1]) for name in meshes}
    assert ids and ids <= set(TRAINING_IDS) and not ids & set(DISTRACTOR_IDS), meshes
    for mesh_id in TRAINING_IDS:  # every training mesh is read
        assert len(bank_mesh(mesh_id).faces) > 0
    with pytest.raises(UnknownNameError, match="held-out, training"):
        SceneConfig(distractor_bank="test")


def test_rooms_render_the_same_images_as_annotated_and_their_seeds_are_their_own(
    tmp_path: Path, capsys
) -> None:
    size = ["--width", str(W), "--height", str(H), "--quiet"]
    args = ["--dist", "headcam", "--split", "val", "--count", "3", "--rooms", *size]
    for out in ("a", "b"):
        assert main([*args, "--out", str(tmp_path / out)]) == 0
    files = {
        out: {
            p.relative_to(tmp_path / out): p.read_bytes() for p in (tmp_path / out).rglob("*.png")
        }
        for out in ("a", "b")
    }
    assert files["a"] == files["b"] and len(files["a"]) >= 6
    info = json.loads((tmp_path / "a" / "info.json").read_text())
    assert info["rooms"] == "wide"
    assert info["splits"]["val"]["seed_range"][0] == SEED_BASES["val"] + ROOM_SEED_OFFSETS["wide"]
    assert "--rooms" in info["splits"]["val"]["command"]
    record = json.loads(next((tmp_path / "a").rglob("records/*.json")).read_text())
    assert "room" in json.dumps(record)
    # The plain split of the same folder would mix two kinds of image: refused in one line.
    capsys.readouterr()
    plain = ["--dist", "headcam", "--split", "val", "--count", "1", *size]
    assert main([*plain, "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "rooms wide" in err[0] and "rooms None" in err[0]


def test_rooms_are_of_the_head_camera_only(capsys) -> None:
    assert main(["--dist", "paper", "--split", "val", "--count", "1", "--rooms"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--rooms applies to --dist headcam" in err[0]
    with pytest.raises(InvalidArgumentError, match="holds 1"):
        GenConfig("headcam", "train", MAX_COUNT + 1, Path("x"), rooms="wide")
    assert main(["--dist", "headcam", "--split", "val", "--count", "1", "--rooms", "dim"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "wide" in err[0] and "joint" in err[0]


def test_each_family_of_rooms_has_seeds_of_its_own_and_joint_rooms_draw_more_at_once() -> None:
    assert set(ROOM_SEED_OFFSETS) == set(FAMILIES)
    kinds = [
        GenConfig("headcam", split, MAX_COUNT, Path("x"), rooms=rooms, bank=bank)
        for split in SEED_BASES
        for rooms in (None, *FAMILIES)
        for bank in (None, "training", "held-out")
    ]
    ranges = sorted((c.seed(0), c.seed(MAX_COUNT - 1) + 1) for c in kinds)
    assert all(a[1] <= b[0] for a, b in itertools.pairwise(ranges))
    assert ranges[-1][1] <= DATA_SEED_LIMIT
    scene = build_scene("phone", 7, SceneConfig(randomize_appearance=True))
    per_image = {
        family: np.mean([len(_draw(scene, seed, family)) for seed in range(60)])
        for family in FAMILIES
    }
    assert per_image["joint"] > 1.5 * per_image["wide"], per_image
    shifted = {f: sum(bool(room_shifts(s, f)) for s in range(200)) for f in FAMILIES}
    assert shifted["joint"] > 1.5 * shifted["wide"], shifted


def test_a_room_view_is_the_view_of_its_scene(tmp_path: Path) -> None:
    gen = HeadcamGenerator(W, H, rooms="wide")
    try:
        seed = next(s for s in range(100) if "camera" in _camera_draw(s))
        image = gen.render("phone", seed)
    finally:
        gen.close()
    assert "camera" in image.extra["room"]
    # The annotation follows the moved camera: the target's origin projects onto its mask.
    target = next(o for o in image.objects if o.extra["target"])
    u, v, w = image.K @ target.T_C_O[:3, 3]
    ys, xs = np.nonzero(target.mask)
    assert xs.min() - 2 <= u / w <= xs.max() + 2 and ys.min() - 2 <= v / w <= ys.max() + 2


def _camera_draw(seed: int) -> dict:
    scene = build_scene("phone", seed, SceneConfig(randomize_appearance=True))
    mujoco.mj_forward(scene.model, scene.data)
    return _draw(scene, seed)
