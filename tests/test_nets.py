"""2D/4D pose nets: shapes, input checks, learning, training smoke run, resume, evaluation."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from perception.geometry_torch import rotation_from_p_cs
from perception.nets import NetConfig, PoseNet, _from_6d, load_posenet, normalise
from perception.training import datagen, train_posenet
from perception.training.data.crop_sets import CropConfig, build_crops
from perception.training.data.dataset import parse_limit
from perception.training.shipping import ship as export_weights
from perception.training.tables import evaluate_split
from perception.training.trainers import posenet_trainer as train_mod
from perception.training.trainers.ddp import ONE_PROCESS
from perception.training.trainers.losses import posenet_loss
from perception.training.trainers.posenet_trainer import SMOKE, train
from perception.training.trainers.schedule import learning_rate
from posegrasp.core.errors import AssetError
from posegrasp.core.paths import WEIGHTS_DIR
from posegrasp.core.transforms import quat_to_mat
from posegrasp.world.objects import OBJECT_NAMES


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    for split, n_paper, n_head in (("train", 12, 4), ("val", 6, 2), ("test", 6, 2)):
        for dist, n in (("paper", n_paper), ("headcam", n_head)):
            argv = [
                "--dist",
                dist,
                "--split",
                split,
                "--count",
                str(n),
                "--quiet",
                "--out",
                str(root / dist),
            ]
            assert datagen.main(argv) == 0
    return root


@pytest.mark.parametrize("variant", ["paper", "ours"])
def test_output_shapes_and_ranges(variant: str) -> None:
    net = PoseNet(NetConfig(variant=variant, width=4))
    x = normalise(torch.randint(0, 256, (5, 64, 64, 3), dtype=torch.uint8))
    out = net(x, torch.tensor([0, 1, 2, 3, 5]), torch.full((5,), 0.15))
    assert out.uv_unit.shape == (5, 2) and out.p.shape == (5, 3) and out.cs.shape == (5, 2)
    assert torch.all(out.uv_unit > -0.25) and torch.all(out.uv_unit < 1.25)
    assert out.theta.shape == (5,)


def test_normalise_rejects_wrong_input() -> None:
    with pytest.raises(ValueError, match="uint8"):
        normalise(torch.zeros((2, 64, 64, 3)))
    with pytest.raises(ValueError, match="shape"):
        normalise(torch.zeros((2, 32, 48, 3), dtype=torch.uint8))
    net = PoseNet(NetConfig(width=4))  # 64x64 crops
    x = normalise(torch.zeros((2, 32, 32, 3), dtype=torch.uint8))
    with pytest.raises(ValueError, match="takes 64x64 crops, got"):
        net(x, torch.tensor([0, 1]), torch.full((2,), 0.15))
    with pytest.raises(ValueError, match="multiple of 8"):
        NetConfig(crop=60)
    with pytest.raises(ValueError, match="view-roll"):
        NetConfig(variant="paper", rotation="6d")


@pytest.mark.parametrize(("crop", "rotation"), [(48, "view-roll"), (96, "6d")])
def test_other_crop_sizes_and_the_6d_rotation(crop: int, rotation: str) -> None:
    net = PoseNet(NetConfig(width=4, crop=crop, rotation=rotation)).eval()
    x = normalise(torch.randint(0, 256, (3, crop, crop, 3), dtype=torch.uint8))
    out = net(x, torch.tensor([0, 2, 5]), torch.full((3,), 0.15))
    assert out.p.shape == (3, 3) and out.cs.shape == (3, 2)
    # At initialisation the 6D head starts near a level view from -y, |p| = 0.2 / scale.
    if rotation == "6d":
        assert torch.allclose(out.p, torch.tensor([0.0, -0.2 / 0.15, 0.0]), atol=0.15)


def test_6d_rotation_decodes_to_the_rotation_it_encodes() -> None:
    g = torch.Generator().manual_seed(3)
    q = torch.randn(64, 4, generator=g).numpy()
    R = torch.tensor(np.stack([quat_to_mat(v / np.linalg.norm(v)) for v in q]), dtype=torch.float32)
    six = torch.cat([R[:, :, 0], R[:, :, 1]], dim=1) * 2.5  # the scale of a column is free
    dist = torch.rand(64, generator=g) + 0.5
    p, cs = _from_6d(six, dist)
    assert torch.allclose(torch.linalg.norm(p, dim=1), dist, atol=1e-5)
    assert torch.allclose(rotation_from_p_cs(p, cs), R, atol=1e-4)


def test_unknown_variant() -> None:
    with pytest.raises(ValueError, match="valid variants: paper, ours"):
        NetConfig(variant="fancy")


@pytest.mark.parametrize("variant", ["paper", "ours"])
def test_fits_a_small_batch(variant: str) -> None:
    torch.manual_seed(0)
    net = PoseNet(NetConfig(variant=variant, width=8, dropout=0.0))
    x = normalise(torch.randint(0, 256, (8, 64, 64, 3), dtype=torch.uint8))
    cls = torch.arange(8) % 6
    scale = torch.full((8,), 0.2)
    uv = torch.rand(8, 2)
    p = torch.nn.functional.normalize(torch.randn(8, 3), dim=1) * 0.7
    theta = torch.rand(8) - 0.5
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    first = None
    for _ in range(200):
        loss, _ = posenet_loss(net(x, cls, scale), uv, p, theta, variant)
        first = float(loss.detach()) if first is None else first
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.1 * first


def test_smoke_training_checkpoints_and_resumes(tiny_data, tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("POSEGRASP_DATA", str(tiny_data))
    cfg = replace(SMOKE, out=tmp_path)
    result = train(cfg)
    ckpt = torch.load(result["checkpoint"], weights_only=False)
    for key in (
        "model",
        "model_config",
        "optimizer",
        "step",
        "epoch",
        "rng",
        "data_seeds",
        "commit",
    ):
        assert key in ckpt
    assert ckpt["epoch"] == 1 and len(result["history"]) == 1
    assert ckpt["data_seeds"]["paper"]["train"] == [0, 12]
    assert ckpt["data_seeds"]["headcam"]["test"] == [200_000_000, 200_000_002]
    # A longer run resumes from the checkpoint instead of starting over.
    more = train(replace(cfg, epochs=2))
    assert [h["epoch"] for h in more["history"]] == [1, 2]
    model = load_posenet(tmp_path / "posenet_ours.pt")
    report = evaluate_split(model, tiny_data / "paper")
    assert {
        "center_px_mean",
        "distance_pct_mean",
        "rotation_deg_mean",
        "iou_acc",
        "outlier_rate",
        "add_s_recall",
    } <= set(report["average"])
    assert np.isfinite(report["average"]["distance_pct_mean"])


def test_fine_tune_records_its_lineage_and_exports_stages(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setenv("POSEGRASP_DATA", str(tiny_data))
    base = replace(SMOKE, out=tmp_path, name="posenet_ours_mixed")
    first = train(base, command="stage one")
    parent = torch.load(first["checkpoint"], weights_only=False)
    ft = replace(
        SMOKE,
        out=tmp_path,
        dists=("headcam",),
        dist_limits=(("headcam", 3),),
        init="posenet_ours_mixed",
        epochs=2,
    )
    result = train(ft)
    ckpt = torch.load(result["checkpoint"], weights_only=False)
    assert result["checkpoint"].endswith("posenet_ours.pt")
    assert ckpt["init_from"]["checkpoint"] == "posenet_ours_mixed.pt"
    assert ckpt["init_from"]["command"] == "stage one"
    assert ckpt["init_from"]["data_seeds"] == parent["data_seeds"]
    assert ckpt["command"] == (
        "python -m perception.training.train_posenet --variant ours --data headcam=3 --epochs 2 "
        f"--batch 16 --width 4 --lam 1 --init posenet_ours_mixed --out {tmp_path}"
    )
    assert ckpt["data_seeds"] == {
        "headcam": {
            "train": [0, 3],
            "val": [100_000_000, 100_000_002],
            "test": [200_000_000, 200_000_002],
        },
    }
    # The fine-tune starts from the parent's weights, not from a fresh initialisation.
    fresh = train(replace(ft, init=None, name="fresh", epochs=1))
    tuned = train(replace(ft, name="tuned", epochs=1))
    assert tuned["history"][0]["rotation_deg"] != fresh["history"][0]["rotation_deg"]
    out = tmp_path / "weights"
    manifest = export_weights.export(tmp_path, out)
    stages = manifest["pose_nets"]["ours"]["stages"]
    assert [s["command"] for s in stages] == ["stage one", ckpt["command"]]
    assert [s["epochs_done"] for s in stages] == [1, 2]
    assert manifest["pose_nets"]["ours"]["command"] == ckpt["command"]
    # Test figures survive a re-export of the same weights (compared by value, the file is not
    # rewritten) and are dropped when the weights change.
    shipped = out / "posenet_ours.pt"
    manifest["pose_nets"]["ours"]["test"] = {"rotation_deg": 1.0}
    export_weights.write_manifest(out / "manifest.json", manifest)
    mtime = shipped.stat().st_mtime_ns
    again = export_weights.export(tmp_path, out)
    assert again["pose_nets"]["ours"]["test"] == {"rotation_deg": 1.0}
    assert shipped.stat().st_mtime_ns == mtime
    train(replace(ft, epochs=3))
    changed = export_weights.export(tmp_path, out)
    assert "test" not in changed["pose_nets"]["ours"]
    assert shipped.stat().st_mtime_ns != mtime
    curves = export_weights.training_curves(tmp_path)
    assert [[h["epoch"] for h in st] for st in curves["ours"]] == [[1], [1, 2, 3]]
    export_weights.plot_curves(curves, tmp_path / "curves.png")
    assert (tmp_path / "curves.png").stat().st_size > 1000


def test_a_fine_tune_of_shipped_weights_keeps_their_recorded_stages(
    tiny_data, tmp_path, monkeypatch
):
    monkeypatch.setenv("POSEGRASP_DATA", str(tiny_data))
    first = train(replace(SMOKE, out=tmp_path / "ckpt", name="posenet_ours"), command="stage one")
    weights = tmp_path / "weights"
    shipped = export_weights.export(Path(first["checkpoint"]).parent, weights)
    recorded = shipped["pose_nets"]["ours"]["stages"]
    assert [s["command"] for s in recorded] == ["stage one"]
    # A fine-tune started from the shipped file (not a checkpoint) continues its history.
    ft = replace(SMOKE, out=tmp_path / "ft", init=str(weights / "posenet_ours.pt"), epochs=2)
    result = train(ft)
    ckpt = torch.load(result["checkpoint"], weights_only=False)
    assert ckpt["init_from"]["stages"] == recorded
    stages = export_weights.export(tmp_path / "ft", weights)["pose_nets"]["ours"]["stages"]
    assert [s["command"] for s in stages] == ["stage one", ckpt["command"]]
    # Exporting the same fine-tune again does not repeat the shipped stages, and the curves
    # continue with the shipped file's recorded stages instead of following its name back to
    # the checkpoint itself: stage one's final validation alone, as its checkpoint is elsewhere.
    again = export_weights.export(tmp_path / "ft", weights)["pose_nets"]["ours"]["stages"]
    assert again == stages
    curves = export_weights.training_curves(tmp_path / "ft")["ours"]
    assert [[h["epoch"] for h in st] for st in curves] == [[1], [1, 2]]
    assert curves[0] == [recorded[0]["validation"]]
    # With the stage's checkpoint beside it (named by its --name), its whole history is drawn.
    base = train(replace(SMOKE, out=tmp_path / "base", epochs=2), command="x --name ours_base")
    export_weights.export(Path(base["checkpoint"]).parent, weights)
    named = tmp_path / "named"
    named.mkdir()
    shutil.copy(base["checkpoint"], named / "ours_base.pt")
    train(replace(ft, out=named, epochs=1))
    curves = export_weights.training_curves(named)["ours"]
    assert [[h["epoch"] for h in st] for st in curves] == [[1, 2], [1]]
    # Weights that are not the recorded bytes carry no stages.
    other = tmp_path / "weights" / "posenet_ours.pt"
    other.write_bytes(other.read_bytes() + b"x")
    assert train_mod.shipped_stages(other) is None


def test_distillation_adds_the_teachers_outputs_as_a_target(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setenv("POSEGRASP_DATA", str(tiny_data))
    teacher = train(replace(SMOKE, out=tmp_path, name="teacher", seed=5))["checkpoint"]
    plain = train(replace(SMOKE, out=tmp_path, name="plain"))
    again = train(replace(SMOKE, out=tmp_path, name="again"))
    taught = train(replace(SMOKE, out=tmp_path, name="taught", teacher=Path(teacher)))
    a = torch.load(plain["checkpoint"], weights_only=False)["model"]
    b = torch.load(taught["checkpoint"], weights_only=False)["model"]
    c = torch.load(again["checkpoint"], weights_only=False)["model"]
    assert all(torch.equal(a[k], c[k]) for k in a)  # a run is repeatable to the bit
    # Same seed, same data and labels: only the teacher's term can make the weights differ.
    assert any(not torch.equal(a[k], b[k]) for k in a)
    assert np.isfinite(taught["history"][-1]["rotation_deg"])


def test_bf16_and_channels_last_follow_fp32_and_are_recorded(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setenv("POSEGRASP_DATA", str(tiny_data))
    first = {}
    for precision, channels_last in (("fp32", False), ("fp32", True), ("bf16", True)):
        name = f"{precision}_{channels_last}"
        log = tmp_path / f"{name}.jsonl"
        cfg = replace(SMOKE, out=tmp_path, name=name, loss_log=log)
        cfg = replace(cfg, precision=precision, channels_last=channels_last)
        result = train(cfg)
        ckpt = torch.load(result["checkpoint"], weights_only=False)
        assert ckpt["train_config"]["precision"] == precision
        assert ckpt["train_config"]["channels_last"] is channels_last
        assert ("--precision bf16" in ckpt["command"]) is (precision == "bf16")
        assert ("--channels-last" in ckpt["command"]) is channels_last
        assert all(v.dtype != torch.bfloat16 for v in ckpt["model"].values())
        first[name] = json.loads(log.read_text().splitlines()[0])["loss"]
    # Same initialisation and batch: the layout changes only the order of sums, bf16 the
    # rounding of the forward pass (8 bits of mantissa).
    assert first["fp32_True"] == pytest.approx(first["fp32_False"], rel=1e-5)
    assert first["bf16_True"] == pytest.approx(first["fp32_False"], rel=2e-2)


def test_the_bf16_loss_and_gradients_are_fp32() -> None:
    cfg = replace(SMOKE, precision="bf16", channels_last=True)
    net = PoseNet(cfg.net_config()).to(memory_format=torch.channels_last)
    crops = torch.randint(0, 256, (4, 64, 64, 3), dtype=torch.uint8)
    batch = {
        "crops": crops,
        "cls": torch.tensor([0, 1, 2, 3]),
        "scale": torch.full((4,), 0.15),
        "uv_unit": torch.rand(4, 2),
        "p": torch.tensor([[0.0, -0.7, 0.1]]).repeat(4, 1),
        "theta": torch.zeros(4),
    }
    x = train_mod.training_inputs(cfg, batch, torch.Generator().manual_seed(0), ONE_PROCESS)
    assert x.is_contiguous(memory_format=torch.channels_last)
    loss, parts = train_mod.training_loss(cfg, net, None, x, batch)
    assert loss.dtype == torch.float32 and np.isfinite(parts["total"])
    loss.backward()
    assert all(p.grad is not None and p.grad.dtype == torch.float32 for p in net.parameters())


def test_fine_tune_from_a_missing_checkpoint_is_a_clear_error(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setenv("POSEGRASP_DATA", str(tiny_data))
    with pytest.raises(AssetError, match="no checkpoint 'nope'"):
        train(replace(SMOKE, out=tmp_path, init="nope"))


def test_a_crop_cache_is_extended_to_the_crops_a_fresh_build_cuts(tiny_data, tmp_path) -> None:
    fresh, grown = tmp_path / "fresh", tmp_path / "grown"
    for d in (fresh, grown):
        shutil.copytree(tiny_data / "paper", d)
    cfg = CropConfig(seed=7)
    first = build_crops(grown, "train", cfg, limit=5)
    assert (grown / "crops_train_2_7_5.npz").is_file()
    (grown / "train" / "000000" / "rgb" / "000001.png").unlink()  # a re-cut would fail on it
    extended = build_crops(grown, "train", cfg, limit=12)
    scratch = build_crops(fresh, "train", cfg, limit=12)
    assert len(first["cls"]) < len(scratch["cls"])
    assert extended.keys() == scratch.keys()
    for k in scratch:
        np.testing.assert_array_equal(extended[k], scratch[k], err_msg=k)


def test_parse_limit() -> None:
    assert parse_limit(None) == (None, ())
    assert parse_limit("50") == (50, ())
    assert parse_limit("headcam=5000") == (None, (("headcam", 5000),))
    assert parse_limit("headcam=5,paper=7,9") == (9, (("headcam", 5), ("paper", 7)))
    with pytest.raises(ValueError, match="valid: paper, headcam"):
        parse_limit("studio=5")
    with pytest.raises(ValueError, match="N >= 1"):
        parse_limit("headcam=0")


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--limit", "lots"], "--limit wants N or dist=N"),
        (["--limit", "studio=3"], "valid: paper, headcam"),
        (["--name", "a/b"], "--name must be a plain name"),
        (["--objects", "car,boat"], "valid: car, faucet, chair"),
        (["--width", "0"], "--width must be at least 1"),
        (["--variant", "big"], "valid variants: paper, ours"),
        (["--epochs", "0"], "invalid --epochs 0; valid: integers 1..10000"),
        (["--batch", "x"], "invalid --batch 'x'; valid: integers 1..65536"),
        (["--lr", "0"], "invalid --lr 0.0; valid: numbers in (0, 1]"),
        (["--lr", "nan"], "invalid --lr nan"),
        (["--threads", "0"], "invalid --threads 0; valid: integers 1..256"),
        (["--device", "tpu"], "valid devices: auto, cpu, cuda"),
        (["--precision", "fp16"], "valid precisions: fp32, bf16"),
        (["--out", __file__], "a file, not a folder"),
    ],
)
def test_train_cli_bad_input(argv, needle, capsys) -> None:
    assert train_posenet.main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and err.startswith("error: ")


def test_one_net_per_object_sees_only_its_object(tiny_data, tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("POSEGRASP_DATA", str(tiny_data))
    seen = {"train": set(), "val": set()}

    class Recording(PoseNet):
        def forward(self, crops, cls, scale):
            seen["train" if self.training else "val"].update(cls.tolist())
            return super().forward(crops, cls, scale)

    monkeypatch.setattr(train_mod, "PoseNet", Recording)
    cfg = replace(SMOKE, out=tmp_path, objects=("chair",), augment=False, decay=False, limit=None)
    train(cfg)
    assert seen["train"] == seen["val"] == {OBJECT_NAMES.index("chair")}
    ckpt = torch.load(tmp_path / "posenet_ours.pt", weights_only=False)
    assert "--width 4 --lam 1 --objects chair --no-augment --constant-lr --out" in ckpt["command"]


def test_learning_rate_schedules() -> None:
    lrs = [learning_rate(s, 100, 1e-3) for s in range(100)]
    flat = [learning_rate(s, 100, 1e-3, decay=False) for s in range(100)]
    assert lrs[:5] == flat[:5] and lrs[4] == pytest.approx(1e-3)  # the same warm-up
    assert lrs[-1] == pytest.approx(1e-5, rel=0.05) and flat[5:] == [1e-3] * 95


def test_missing_and_corrupt_weights(tmp_path) -> None:
    with pytest.raises(AssetError, match="make weights"):
        load_posenet(tmp_path / "nope.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(AssetError, match="corrupt"):
        load_posenet(bad)


def test_detector_boxes_evaluation(tiny_data) -> None:
    """End-to-end crops from the shipped detector: matched objects, COCO AP per class."""
    from perception.detector import DEFAULT_WEIGHTS, Detector
    from perception.training.tables import detector_crops, format_detection

    detector = Detector.from_weights(DEFAULT_WEIGHTS, score_threshold=0.05)
    data, det = detector_crops(tiny_data / "headcam", detector)
    n_obj = sum(det["objects"].values())
    assert n_obj >= 2 and len(data["crops"]) == n_obj - sum(det["missed"].values())
    # Each tiny head-camera image names its target; the targets missed are among the missed.
    assert 1 <= det["targets"] <= det["images"]
    assert 0 <= det["targets_missed"] <= min(det["targets"], sum(det["missed"].values()))
    assert "episode targets found" in format_detection(det)
    assert data["crops"].shape[1:] == (64, 64, 3) and data["crops"].dtype == np.uint8
    assert set(det["detection"]) == set(OBJECT_NAMES)
    for a in det["detection"].values():
        assert {"box_ap", "mask_ap50"} <= set(a)
    if len(data["crops"]):
        report = evaluate_split(
            load_posenet(WEIGHTS_DIR / "posenet_ours.pt"), tiny_data / "headcam", data=data
        )
        assert np.isfinite(report["average"]["center_px_mean"])


def test_evaluate_records_test_figures_in_the_manifest(tiny_data, tmp_path, monkeypatch):
    import json
    import shutil

    from perception.training import tables as evaluate
    from posegrasp.core.files import sha256_file

    monkeypatch.setenv("POSEGRASP_DATA", str(tiny_data))
    weights = tmp_path / "posenet_ours.pt"
    shutil.copy(WEIGHTS_DIR / "posenet_ours.pt", weights)
    entry = {"file": "posenet_ours.pt", "sha256": sha256_file(weights)}
    (tmp_path / "manifest.json").write_text(json.dumps({"pose_nets": {"ours": entry}}))
    argv = ["--weights", str(weights), "--dists", "headcam", "--json", str(tmp_path / "r.json")]
    # The tiny data, a copy of the weights and one split are refused (tests/test_reliability.py);
    # with those guards lifted, the figures reach the manifest of the weights measured.
    assert evaluate.main([*argv, "--record"]) == 2
    monkeypatch.setattr(evaluate, "check_record_request", lambda args, dists: None)
    monkeypatch.setattr(evaluate, "check_full_splits", lambda dists: None)
    assert evaluate.main([*argv, "--record"]) == 0
    test = json.loads((tmp_path / "manifest.json").read_text())["pose_nets"]["ours"]["test"]
    report = json.loads((tmp_path / "r.json").read_text())
    assert test["headcam"]["rotation_deg_mean"] == report["headcam"]["average"]["rotation_deg_mean"]
    assert test["command"].startswith("python -m perception.training.tables --weights")
    assert "paper" not in test and test["weights_sha256"] == entry["sha256"]
    # Weights the manifest does not list cannot be recorded.
    other = tmp_path / "posenet_other.pt"
    shutil.copy(weights, other)
    assert evaluate.main(["--weights", str(other), "--dists", "headcam", "--record"]) == 2


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--boxes", "magic"], "valid box sources: gt, detector"),
        (["--boxes", "detector", "--dists", "mars"], "valid distributions: paper, headcam"),
        (["--dists", "mars"], "valid distributions: paper, headcam"),
    ],
)
def test_evaluate_cli_bad_input(argv, needle, capsys) -> None:
    from perception.training import tables as evaluate

    assert evaluate.main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err and len(err.strip().splitlines()) == 1
