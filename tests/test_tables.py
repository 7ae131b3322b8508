"""The offline evaluation's figures (`perception.training.tables`) on synthetic inputs with known
answers: centre error in three frames, ADD or ADD-S by symmetry, both IoU readings, both outlier
readings, the printed comparison and the dataset folders it accepts."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from perception import metrics
from perception.training import tables
from perception.training.evals import paper_tables
from perception.training.evals.posenet_eval import pose_metrics
from posegrasp.core.transforms import intrinsics, rot_z
from posegrasp.world.objects import OBJECT_NAMES, load_object
from posegrasp.world.tiers import TIERS


def _pose(t: tuple[float, float, float], R: np.ndarray | None = None) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.eye(3) if R is None else R
    T[:3, 3] = t
    return T


def _crops(uv_gt: np.ndarray, side: float) -> dict[str, np.ndarray]:
    n = len(uv_gt)
    T = np.stack([_pose((0.0, 0.0, 1.0))] * n)
    return {"uv": uv_gt, "T_C_O": T, "box": np.tile([0.0, 0.0, side], (n, 1))}


def test_centre_error_as_rendered_rescaled_to_256_and_in_crop_pixels() -> None:
    data = _crops(np.array([[320.0, 240.0], [100.0, 50.0]]), side=128.0)
    offset = np.array([[10.0, 6.0], [0.0, -15.0]])
    dec = {"uv": data["uv"] + offset, "T_C_O": data["T_C_O"].copy()}
    m = pose_metrics(dec, data, (640, 480))
    np.testing.assert_allclose(m["center_px"], [math.hypot(10, 6), 15.0])
    # x scales by 256/640 = 0.4, y by 256/480: (4, 3.2) and (0, -8).
    np.testing.assert_allclose(m["center_256_px"], [math.hypot(4.0, 3.2), 8.0])
    # A 128 px box is cut to a 64 px crop: half the full-image pixels.
    np.testing.assert_allclose(m["center_crop_px"], [math.hypot(10, 6) / 2, 7.5])
    # The paper's own 256x256 images need no rescaling; without a size there is no such key.
    np.testing.assert_allclose(pose_metrics(dec, data, (256, 256))["center_256_px"], m["center_px"])
    assert "center_256_px" not in pose_metrics(dec, data)


def _errors(**over: list[float]) -> dict[str, np.ndarray]:
    base = {
        "center_px": [1.0] * 4,
        "center_crop_px": [0.5] * 4,
        "distance_pct": [2.0] * 4,
        "rotation_deg": [1.0, 16.0, 15.0, 90.0],
        "iou": [1.0, 0.6, 0.5, 0.2],
        "add_rel": [0.05, 0.2, 0.09, 0.5],
        "adi_rel": [0.01, 0.05, 0.09, 0.1],
        "trans_m": [0.01, 0.01, 0.2, 0.01],
    }
    return {k: np.asarray(v, float) for k, v in (base | over).items()}


def test_both_iou_readings_both_outlier_readings_and_add_recall() -> None:
    s = paper_tables.summarise(_errors(), "ADD")
    assert s["count"] == 4
    assert s["iou_mean"] == pytest.approx(0.575) and s["iou_acc"] == s["iou_mean"]
    assert s["iou_acc_50"] == pytest.approx(0.5)  # 1.0 and 0.6; 0.5 itself fails
    assert s["invalid_rate"] == pytest.approx(0.5)  # 0.5 and 0.2
    assert s["outlier_rate"] == pytest.approx(0.5)  # 16 and 90 deg; 15 itself is no outlier
    assert s["add_metric"] == "ADD"
    assert s["add_recall"] == pytest.approx(0.5)  # ADD/d 0.05 and 0.09 are below 0.1
    assert s["add_s_recall"] == pytest.approx(0.75)  # ADD-S/d 0.1 is not below 0.1
    assert s["recall_5cm5deg"] == pytest.approx(0.25)
    assert s["center_crop_px_mean"] == 0.5 and "center_256_px_mean" not in s


def test_average_over_objects_names_the_add_metric() -> None:
    a = paper_tables.summarise(_errors(), "ADD")
    b = paper_tables.summarise(_errors(iou=[0.0] * 4), "ADD-S")
    avg = paper_tables.average({"car": a, "faucet": b}, 8)
    assert avg["count"] == 8 and avg["add_metric"] == "ADD(-S)"
    assert avg["iou_acc_50"] == pytest.approx(0.25) and avg["invalid_rate"] == pytest.approx(0.75)
    assert paper_tables.average({"car": a}, 4)["add_metric"] == "ADD"


def test_shipped_objects_have_no_symmetry_so_add_is_used() -> None:
    for name in OBJECT_NAMES:
        assert load_object(name).symmetries == ()
        assert metrics.add_metric_name(tables._symmetry_set(name)) == "ADD"


def _fake_split(monkeypatch, symmetric: str) -> tuple[dict, list[np.ndarray], np.ndarray]:
    """Four car and faucet crops of a 640x480 camera whose decoded poses are given; `symmetric`
    gets a half-turn symmetry about its z axis (only its presence matters)."""
    K = intrinsics(math.radians(50.0), 640, 480)
    gt = [_pose((0.0, 0.0, 0.8))] * 4
    turned = _pose((0.0, 0.0, 0.8), rot_z(math.radians(25.0)))
    est = [gt[0], _pose((0.35, 0.0, 0.8)), gt[0], turned]
    cls = np.array([OBJECT_NAMES.index(o) for o in ("car", "car", "faucet", "faucet")])
    uv = np.tile([K[0, 2], K[1, 2]], (4, 1))
    data = {
        "crops": np.zeros((4, 64, 64, 3), np.uint8),
        "cls": cls,
        "scale": np.ones(4),
        "K": np.stack([K] * 4),
        "T_C_O": np.stack(gt),
        "uv": uv,
        "box": np.tile([0.0, 0.0, 128.0], (4, 1)),
    }
    offset = np.array([[3.0, 4.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    dec = {"uv": uv + offset, "T_C_O": np.stack(est)}
    half_turn = {"R": rot_z(math.pi), "t": np.zeros((3, 1))}
    real = tables._symmetry_set
    monkeypatch.setattr(tables, "predict", lambda *a: None)
    monkeypatch.setattr(tables, "decode_predictions", lambda pred, d: dec)
    monkeypatch.setattr(tables, "load_info", lambda root: {"width": 640, "height": 480})
    monkeypatch.setattr(
        tables, "_symmetry_set", lambda o: real(o) + ([half_turn] if o == symmetric else [])
    )
    return data, est, cls


def test_evaluate_split_uses_add_s_only_for_objects_with_symmetries(monkeypatch) -> None:
    data, est, _ = _fake_split(monkeypatch, symmetric="faucet")
    res = tables.evaluate_split(None, Path("unused"), data=data)
    car, faucet = res["per_object"]["car"], res["per_object"]["faucet"]
    assert car["add_metric"] == "ADD" and faucet["add_metric"] == "ADD-S"
    assert res["average"]["add_metric"] == "ADD(-S)"
    # The car: one exact pose and one 35 cm aside (disjoint silhouettes, no rotation error).
    assert car["iou_mean"] == pytest.approx(0.5) and car["iou_acc_50"] == 0.5
    assert car["invalid_rate"] == 0.5 and car["outlier_rate"] == 0.0
    assert car["add_recall"] == 0.5
    # The faucet: one exact pose and one turned 25 deg about z, which ADD fails and ADD-S
    # passes; its recall is ADD-S's.
    pts = np.asarray(load_object("faucet").mesh.vertices)
    d = load_object("faucet").diameter
    R, t = est[3][:3, :3], est[3][:3, 3]
    assert metrics.add(R, t, np.eye(3), t, pts) / d >= 0.1
    assert metrics.adi(R, t, np.eye(3), t, pts) / d < 0.1
    assert faucet["add_recall"] == faucet["add_s_recall"] == 1.0
    assert faucet["outlier_rate"] == 0.5
    # Centre: (3, 4) px in the 640x480 image; (1.2, 2.133) px at 256x256; 2.5 crop px.
    assert car["center_px_mean"] == pytest.approx(2.5)
    assert car["center_256_px_mean"] == pytest.approx(math.hypot(1.2, 4 * 256 / 480) / 2)
    assert car["center_crop_px_mean"] == pytest.approx(1.25)
    assert res["image_size"] == [640, 480]
    assert res["center_256_scale"] == pytest.approx([0.4, 256 / 480])
    assert res["paper_readings"]["Table 1 e_distance [px]"] == "center_crop_px_mean"


def test_printed_tables_put_the_paper_beside_the_comparable_columns(monkeypatch) -> None:
    data, _, _ = _fake_split(monkeypatch, symmetric="")
    res = tables.evaluate_split(None, Path("u"), data=data)
    # Without a symmetry the faucet's turned pose fails ADD, though ADD-S passes it.
    assert res["per_object"]["faucet"]["add_metric"] == "ADD"
    assert res["per_object"]["faucet"]["add_recall"] == 0.5
    assert res["per_object"]["faucet"]["add_s_recall"] == 1.0
    text = paper_tables.format_tables("x", res)
    line = {ln.split("  ")[0].strip(): ln for ln in text.splitlines()}
    assert "(1.72)" in line["* e_centre [64x64 crop px]"]
    assert "(96.40)" in line["* acc_IoU: IoU > 0.5 [%]"]
    assert "(8.00)" in line["* invalid: IoU <= 0.5 [%]"]
    assert "(" not in line["mean IoU [%]"] and "(" not in line["e_centre [image px, 640x480]"]
    assert "sqrt((du * 256/640)^2 + (dv * 256/480)^2)" in text
    assert "ADD-S for: none" in text
    # Images already 256x256 (the paper protocol) print no rescaled row.
    monkeypatch.setattr(tables, "load_info", lambda root: {"width": 256, "height": 256})
    text = paper_tables.format_tables("x", tables.evaluate_split(None, Path("u"), data=data))
    assert "to 256x256]" not in text and "no rescaling" in text


def test_the_manifest_record_reads_the_report(monkeypatch, tmp_path) -> None:
    data, _, _ = _fake_split(monkeypatch, symmetric="")
    weights = tmp_path / "posenet_ours.pt"
    weights.write_bytes(b"weights")
    manifest = tmp_path / "manifest.json"
    manifest.write_text(json.dumps({"pose_nets": {"ours": {"file": weights.name}}}))
    report = {"headcam": tables.evaluate_split(None, Path("u"), data=data)}
    assert tables.record_in_manifest(report, weights, "gt", "cmd", manifest) == "ours"
    test = json.loads(manifest.read_text())["pose_nets"]["ours"]["test"]
    for key in ("iou_mean", "iou_acc_50", "invalid_rate", "center_256_px_mean", "add_recall"):
        assert test["headcam"][key] == report["headcam"]["average"][key], key
    assert test["headcam"]["add_s_recall"] == report["headcam"]["average"]["add_s_recall"]


@pytest.mark.parametrize("tier", sorted(TIERS))
def test_a_missing_tier_folder_is_a_one_line_error(tier, tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setenv("POSEGRASP_DATA", str(tmp_path))
    assert tables.main(["--dists", f"headcam_{tier}", "--limit", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert (
        f"python -m perception.training.datagen --dist headcam --tier {tier} --split test "
        "--count N" in err[0]
    )


def test_unknown_dataset_lists_the_tier_folders(capsys) -> None:
    assert tables.main(["--dists", "headcam_nope"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "headcam_hard" in err[0] and "headcam_far" in err[0]
    assert tables.datagen_command("paper").endswith("--dist paper --split test --count N")


@pytest.mark.parametrize("split, tag", [("headcam", ""), ("paper", "paper_")])
def test_a_split_with_detector_boxes_adds_detection_and_the_ratio_to_true_boxes(
    split, tag, monkeypatch
) -> None:
    import argparse
    import io
    import types

    def fake_split(model, root, limit, data=None, success=None):
        error = 2.0 if data is not None else 1.0  # detector boxes err twice as much
        return {"average": {k: error for k in tables.RATIO_KEYS}}

    monkeypatch.setattr(tables, "evaluate_split", fake_split)
    monkeypatch.setattr(tables.Detector, "from_weights", staticmethod(lambda *a, **k: None))
    detection = {"detection": {"AP": 0.9}, "images": 3}
    monkeypatch.setattr(tables, "detector_crops", lambda *a, **k: ("crops", detection))
    monkeypatch.setattr(tables, "format_detection", lambda det: "the detection")
    monkeypatch.setattr(tables, "format_tables", lambda title, res: f"tables of {title}")
    args = argparse.Namespace(boxes="detector", detector=Path("d.pt"), limit=3)
    model = types.SimpleNamespace(cfg=types.SimpleNamespace(crop=64))
    log = io.StringIO()
    report = tables._split_tables(split, Path("r"), model, {}, args, log)  # type: ignore[arg-type]
    assert list(report) == [
        f"{tag}detection",
        f"{tag}detection_summary",
        split,
        f"{split}_gt_boxes",
        f"{tag}detector_to_gt_ratio",
    ]
    assert report[f"{tag}detection_summary"] == {"images": 3}
    assert report[split]["boxes"] == "detector"
    assert report[f"{tag}detector_to_gt_ratio"] == dict.fromkeys(tables.RATIO_KEYS, 2.0)
    printed = log.getvalue().splitlines()
    assert printed[:2] == ["the detection", f"tables of {split} (detector boxes)"]
    assert printed[2].startswith(
        "detector boxes / ground-truth boxes (average): center_px_mean 2.00x"
    )
    args.boxes = "gt"
    assert list(tables._split_tables(split, Path("r"), model, {}, args, log)) == [split]  # type: ignore[arg-type]
