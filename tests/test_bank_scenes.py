"""Scenes of the training bank's meshes alone (``datagen --bank``), annotated for a detector of
any object (``train_detector --any-object``)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from perception.detector_net import ANY_OBJECT, DetectorConfig, class_label
from perception.training.data import bop
from perception.training.data.annotations import object_diameter, object_mesh
from perception.training.data.dataset import PoseDataset
from perception.training.data.render_split import (
    BANK_SEED_OFFSETS,
    ROOM_SEED_OFFSETS,
    SEED_BASES,
    GenConfig,
)
from perception.training.datagen import main
from perception.training.trainers.detection_data import DetectionSet
from posegrasp.core.errors import AssetError, InvalidArgumentError, UnknownNameError
from posegrasp.world.distractor_bank import (
    BANK_OBJ_ID_BASE,
    DISTRACTOR_IDS,
    SHAPE_IDS,
    SHAPE_KINDS,
    SHAPE_SIZE,
    TRAINING_IDS,
    bank_id,
    bank_mesh,
    bank_name,
    shape_mesh,
)
from posegrasp.world.objects import OBJECT_NAMES

pytest.importorskip("pybullet")
W, H = 320, 240


@pytest.fixture(scope="module")
def bank_folder(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bank")
    args = ["--dist", "headcam", "--bank", "--rooms", "--split", "val", "--count", "4"]
    assert main([*args, "--width", str(W), "--height", str(H), "--quiet", "--out", str(out)]) == 0
    return out


def test_a_bank_name_is_its_mesh_and_its_bop_id_is_above_every_other_object() -> None:
    assert bank_name(7) == "bank-007" and bank_id("bank-007") == 7
    for other in ("phone", "bank-7", "bank-0070", "bank-abc", "banks-007"):
        assert bank_id(other) is None
    assert bop.obj_id("bank-042") == BANK_OBJ_ID_BASE + 42
    assert bop.obj_name(BANK_OBJ_ID_BASE + 42) == "bank-042"
    assert bop.obj_name(bop.obj_id("phone")) == "phone"
    with pytest.raises(UnknownNameError):
        bop.obj_name(BANK_OBJ_ID_BASE + 2000)
    mesh = object_mesh("bank-042")
    assert len(mesh.faces) > 0
    assert 0.0 < object_diameter("bank-042") >= np.ptp(mesh.vertices, axis=0).max()


def test_bank_scenes_show_bank_meshes_only_each_annotated_where_it_is_drawn(
    bank_folder: Path, tmp_path: Path
) -> None:
    info = json.loads((bank_folder / "info.json").read_text())
    assert info["bank"] == "training" and info["rooms"] == "wide"
    base = SEED_BASES["val"] + ROOM_SEED_OFFSETS["wide"] + BANK_SEED_OFFSETS["training"]
    assert info["splits"]["val"]["seed_range"][0] == base
    assert "--bank" in info["splits"]["val"]["command"]
    data = PoseDataset(bank_folder, "val")
    seen = 0
    for i in range(len(data)):
        s = data[i]
        for o in s.objects:
            mesh_id = bank_id(o.name)
            assert mesh_id in TRAINING_IDS and mesh_id not in DISTRACTOR_IDS
            assert o.name not in OBJECT_NAMES and o.mask_visib.any()
            # The pose is the mesh's: its projected vertices span the drawn silhouette.
            v = object_mesh(o.name).vertices @ o.T_C_O[:3, :3].T + o.T_C_O[:3, 3]
            uv = v[:, :2] / v[:, 2:3] * [s.K[0, 0], s.K[1, 1]] + s.K[:2, 2]
            ys, xs = np.nonzero(o.mask)
            assert uv[:, 0].min() - 2 <= xs.min() and xs.max() <= uv[:, 0].max() + 2
            assert uv[:, 1].min() - 2 <= ys.min() and ys.max() <= uv[:, 1].max() + 2
            seen += 1
        assert sum(o.extra["target"] for o in s.objects) <= 1
    assert seen >= 4
    # The same command renders the same bytes.
    again = tmp_path / "again"
    args = ["--dist", "headcam", "--bank", "--rooms", "--split", "val", "--count", "4"]
    assert main([*args, "--width", str(W), "--height", str(H), "--quiet", "--out", str(again)]) == 0
    for png in (bank_folder / "val").rglob("*.png"):
        assert png.read_bytes() == (again / png.relative_to(bank_folder)).read_bytes()


def test_a_detector_of_any_object_learns_every_annotated_object_as_one_class(
    bank_folder: Path,
) -> None:
    assert class_label((ANY_OBJECT,), "bank-003") == 1 == class_label((ANY_OBJECT,), "phone")
    assert class_label(OBJECT_NAMES, "phone") == OBJECT_NAMES.index("phone") + 1
    assert class_label(OBJECT_NAMES, "bank-003") is None
    cfg = DetectorConfig(classes=(ANY_OBJECT,), n_classes=2)
    items = [DetectionSet(bank_folder, "val", 1, cfg)[i][1] for i in range(4)]
    assert sum(len(t["labels"]) for t in items) >= 4
    assert all(set(t["labels"].tolist()) <= {1} for t in items)
    # The six-class detector finds nothing to learn in these images.
    plain = [DetectionSet(bank_folder, "val", 1, DetectorConfig())[i][1] for i in range(4)]
    assert all(len(t["labels"]) == 0 for t in plain)


def test_bank_scenes_refuse_what_they_are_not(capsys) -> None:
    for argv, words in (
        (["--dist", "paper", "--bank"], "--bank applies to --dist headcam"),
        (["--dist", "headcam", "--tier", "hard", "--bank"], "without --tier"),
    ):
        assert main([*argv, "--split", "val", "--count", "1"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err
    with pytest.raises(InvalidArgumentError, match="one view"):
        GenConfig("headcam", "val", 2, Path("x"), views=2, bank="training")
    assert main(["--dist", "headcam", "--bank", "mine", "--split", "val", "--count", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "training" in err[0] and "held-out" in err[0]


def test_generated_shapes_are_closed_seeded_household_sized_and_of_every_kind() -> None:
    assert not set(SHAPE_IDS) & (set(TRAINING_IDS) | set(DISTRACTOR_IDS))
    assert bank_name(1234) == "bank-1234" and bank_id("bank-1234") == 1234
    assert bop.obj_name(bop.obj_id("bank-1234")) == "bank-1234"
    extents = []
    for mesh_id in SHAPE_IDS[:60]:
        m = bank_mesh(mesh_id)
        assert m is shape_mesh(mesh_id) or np.array_equal(m.vertices, shape_mesh(mesh_id).vertices)
        assert abs(m.vertices[:, 2].min()) < 1e-9  # standing on its lowest point
        e = np.ptp(m.vertices, axis=0)
        assert SHAPE_SIZE[0] - 1e-9 <= e.max() <= SHAPE_SIZE[1] + 1e-9 and e.min() > 0.2 * e.max()
        assert trimesh.Trimesh(m.vertices, m.faces).is_watertight
        extents.append(e.max())
    assert np.ptp(extents) > 0.1  # sizes differ, from small to large
    kinds = {
        SHAPE_KINDS[int(np.random.default_rng(i).integers(len(SHAPE_KINDS)))]
        for i in SHAPE_IDS[:60]
    }
    assert kinds == set(SHAPE_KINDS)
    with pytest.raises(AssetError, match="1000-1999"):
        shape_mesh(5)


@pytest.mark.parametrize(("bank", "ids"), [("held-out", DISTRACTOR_IDS), ("shapes", SHAPE_IDS)])
def test_a_banks_scenes_show_its_meshes_only(tmp_path: Path, bank: str, ids) -> None:
    out = tmp_path / bank
    args = ["--dist", "headcam", "--bank", bank, "--split", "val", "--count", "2"]
    assert main([*args, "--width", str(W), "--height", str(H), "--quiet", "--out", str(out)]) == 0
    data = PoseDataset(out, "val")
    names = [o.name for i in range(len(data)) for o in data[i].objects]
    assert names and all(bank_id(n) in ids for n in names)
    info = json.loads((out / "info.json").read_text())
    split = info["splits"]["val"]
    assert info["bank"] == bank and f"--bank {bank}" in split["command"]
    assert split["seed_range"][0] == SEED_BASES["val"] + BANK_SEED_OFFSETS[bank]


def test_a_detector_of_any_object_starts_from_a_named_one_but_its_class_layers() -> None:
    from perception.detector import TIERS_DETECTOR, load_detector_model
    from perception.detector_net import build_detector
    from perception.training.trainers.detection_data import start_from

    parent, parent_cfg, _ = load_detector_model(TIERS_DETECTOR, verify=False)
    cfg = replace(parent_cfg, classes=(ANY_OBJECT,), n_classes=2)
    model = build_detector(cfg)
    fresh = {k: v.clone() for k, v in model.state_dict().items()}
    start_from(model, TIERS_DETECTOR, cfg)
    got, theirs = model.state_dict(), parent.state_dict()
    kept = [k for k in got if got[k].shape == theirs[k].shape]
    anew = [k for k in got if got[k].shape != theirs[k].shape]
    assert all(torch.equal(got[k], theirs[k].float()) for k in kept)
    assert anew and all("predictor" in k for k in anew)
    assert all(torch.equal(got[k], fresh[k]) for k in anew)
    with pytest.raises(AssetError, match="another detector architecture"):
        start_from(model, TIERS_DETECTOR, replace(cfg, fpn_channels=32))
