"""Object extractor: the Mask R-CNN, its inference wrapper, weights, training, export and AP."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from torchvision.models.detection import MaskRCNN

from perception.detector import (
    Detection,
    Detector,
    from_model_box,
    image_tensor,
    paste_mask,
    to_model_box,
)
from perception.detector_net import (
    DetectorConfig,
    build_detector,
    count_parameters,
    state_dict_fp16,
)
from perception.training import datagen
from perception.training.data.bop import box_xyxy
from perception.training.evals.detection_eval import coco_ap
from perception.training.shipping.ship import export_detector
from perception.training.train_detector import main
from perception.training.trainers.detector_trainer import SMOKE, train
from posegrasp.core.errors import AssetError, InvalidArgumentError
from posegrasp.world.objects import OBJECT_NAMES

H, W = 480, 640


pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def detector() -> Detector:
    return Detector.random(score_threshold=0.0)


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)


@pytest.fixture(scope="module")
def tiny_headcam(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("headcam")
    for split, n in (("train", 4), ("val", 2)):
        argv = [
            "--dist",
            "headcam",
            "--split",
            split,
            "--count",
            str(n),
            "--quiet",
            "--out",
            str(root),
        ]
        assert datagen.main(argv) == 0
    return root


def test_model_is_torchvision_mask_rcnn_and_small() -> None:
    model = build_detector()
    assert isinstance(model, MaskRCNN)
    assert model.roi_heads.box_predictor.cls_score.out_features == 1 + len(OBJECT_NAMES)
    assert model.roi_heads.mask_predictor.mask_fcn_logits.out_channels == 1 + len(OBJECT_NAMES)
    n = count_parameters(model)
    assert 0.5e6 < n < 5e6, n  # a few MB as float16
    assert model.transform.min_size == (240,) and model.transform.max_size == 320


def test_detects_on_a_640x480_image(detector: Detector, image: np.ndarray) -> None:
    dets = detector.detect(image)
    assert 0 < len(dets) <= detector.cfg.box_detections_per_img  # random weights: some boxes
    scores = [d.score for d in dets]
    assert scores == sorted(scores, reverse=True)
    for d in dets:
        assert isinstance(d, Detection) and d.name in OBJECT_NAMES
        assert d.name in OBJECT_NAMES and 0.0 <= d.score <= 1.0
        assert d.box_xyxy.shape == (4,) and d.box_xyxy.dtype == np.float64
        x0, y0, x1, y1 = d.box_xyxy
        assert -0.5 <= x0 < x1 <= W - 0.5 and -0.5 <= y0 < y1 <= H - 0.5
        assert d.mask.shape == (H, W) and d.mask.dtype == bool


def test_fast_path_equals_the_plain_forward(detector: Detector, image: np.ndarray) -> None:
    """`Detector._forward` resizes before normalising; the model's forward does the opposite."""
    with torch.inference_mode():
        ref = detector.model([image_tensor(image)])[0]
        fast = detector._forward(image)
    assert torch.equal(ref["labels"], fast["labels"])
    torch.testing.assert_close(ref["boxes"], fast["boxes"], atol=1e-3, rtol=0)
    torch.testing.assert_close(ref["scores"], fast["scores"], atol=1e-5, rtol=0)
    torch.testing.assert_close(ref["masks"], fast["masks"], atol=1e-4, rtol=0)


def test_masks_pasted_per_detection_equal_torchvision_s(
    detector: Detector, image: np.ndarray
) -> None:
    """`detect` pastes each kept mask alone (`paste_mask`); torchvision pastes every one into
    a full-size float image. The probabilities agree exactly."""
    with torch.inference_mode():
        full = detector._forward(image)
        raw = detector._forward(image, paste=False)
    assert len(raw["scores"]) > 0 and torch.equal(full["boxes"], raw["boxes"])
    for i in range(len(raw["scores"])):
        pasted = paste_mask(raw["masks"][i, 0], raw["boxes"][i], image.shape[:2])
        np.testing.assert_array_equal(pasted, full["masks"][i, 0].numpy())


def test_thresholds_and_max_detections(image: np.ndarray) -> None:
    assert Detector.random(score_threshold=1.01).detect(image) == []
    dets = Detector.random(score_threshold=0.0, max_detections=2).detect(image)
    assert len(dets) == 2
    with pytest.raises(InvalidArgumentError):
        Detector.random(max_detections=0)


def test_a_call_may_use_its_own_threshold(image: np.ndarray) -> None:
    strict = Detector.random(score_threshold=1.01)
    loose = Detector.random(score_threshold=0.0)
    got = strict.detect(image, 0.0)
    assert got and [d.score for d in got] == [d.score for d in loose.detect(image)]
    assert strict.detect(image) == []  # the detector's own threshold is back
    with pytest.raises(InvalidArgumentError, match="finite"):
        strict.detect(image, float("nan"))


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (np.zeros((H, W, 3), np.float32), "uint8"),
        (np.zeros((H, W), np.uint8), r"\(H, W, 3\)"),
        (np.zeros((H, W, 4), np.uint8), r"\(H, W, 3\)"),
        (np.zeros((0, 0, 3), np.uint8), "empty"),
        ([[0, 0, 0]], "numpy uint8 array"),
    ],
)
def test_bad_images_are_rejected(detector: Detector, bad: object, match: str) -> None:
    with pytest.raises(InvalidArgumentError, match=match):
        detector.detect(bad)  # type: ignore[arg-type]


def test_missing_and_corrupt_weights(tmp_path: Path) -> None:
    with pytest.raises(AssetError, match=r"missing.*make weights.*train_detector"):
        Detector.from_weights(tmp_path / "nope.pt")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a torch file")
    with pytest.raises(AssetError, match=r"corrupt.*make weights"):
        Detector.from_weights(garbage)
    wrong = tmp_path / "wrong.pt"  # a valid file whose shapes do not match its config
    state = state_dict_fp16(build_detector(DetectorConfig(fpn_channels=32)))
    torch.save({"model": state, "model_config": DetectorConfig().to_dict()}, wrong)
    with pytest.raises(AssetError, match="corrupt"):
        Detector.from_weights(wrong)


def test_fp16_weights_round_trip(tmp_path: Path, image: np.ndarray) -> None:
    cfg = DetectorConfig()
    torch.manual_seed(3)
    model = build_detector(cfg)
    path = tmp_path / "detector.pt"
    torch.save({"model": state_dict_fp16(model), "model_config": cfg.to_dict()}, path)
    loaded = Detector.from_weights(path, score_threshold=0.0)
    assert all(p.dtype == torch.float32 for p in loaded.model.parameters())
    ref = Detector(model.half().float(), cfg, score_threshold=0.0).detect(image)
    got = loaded.detect(image)
    assert [d.name for d in got] == [d.name for d in ref]
    np.testing.assert_allclose([d.score for d in got], [d.score for d in ref], atol=1e-5)


def test_box_conventions() -> None:
    mask = np.zeros((10, 12), bool)
    mask[2:5, 3:9] = True  # rows 2..4, columns 3..8
    np.testing.assert_array_equal(box_xyxy(mask), [2.5, 1.5, 8.5, 4.5])
    np.testing.assert_array_equal(to_model_box(box_xyxy(mask)), [3, 2, 9, 5])
    np.testing.assert_array_equal(from_model_box(to_model_box(box_xyxy(mask))), box_xyxy(mask))


def _det(oid: int, mask: np.ndarray, score: float) -> Detection:
    return Detection(OBJECT_NAMES[oid - 1], score, box_xyxy(mask), mask)


def test_coco_ap_with_pycocotools() -> None:
    a = np.zeros((H, W), bool)
    a[100:180, 200:260] = True
    b = np.zeros((H, W), bool)
    b[300:340, 400:500] = True
    tiny = np.zeros((H, W), bool)
    tiny[10:15, 10:15] = True  # 25 px: ignored (crowd), neither a miss nor a false positive
    gts = [[(1, a), (4, b), (2, tiny)], [(6, b)]]
    perfect = [[_det(1, a, 0.9), _det(4, b, 0.8), _det(2, tiny, 0.7)], [_det(6, b, 0.95)]]
    ap = coco_ap(gts, perfect, min_visible_px=100)
    assert ap == pytest.approx({"box_ap50": 1.0, "box_ap": 1.0, "mask_ap50": 1.0, "mask_ap": 1.0})
    wrong_class = [[_det(2, a, 0.9), _det(4, b, 0.8)], [_det(6, b, 0.95)]]
    ap = coco_ap(gts, wrong_class, min_visible_px=100)
    assert 0.0 < ap["box_ap50"] < 1.0 and ap["box_ap50"] == pytest.approx(ap["mask_ap50"])
    assert coco_ap(gts, [[], []], min_visible_px=100)["mask_ap50"] == 0.0


def test_coco_ap_per_class() -> None:
    a = np.zeros((H, W), bool)
    a[100:180, 200:260] = True
    b = np.zeros((H, W), bool)
    b[300:340, 400:500] = True
    gts = [[(1, a), (4, b)], [(6, b)]]
    # car found, phone labelled as pistol, pistol found in the second image.
    dets = [[_det(1, a, 0.9), _det(6, b, 0.8)], [_det(6, b, 0.95)]]
    per_class: dict = {}
    coco_ap(gts, dets, min_visible_px=100, per_class=per_class)
    assert per_class["car"]["box_ap"] == pytest.approx(1.0)
    assert per_class["car"]["mask_ap50"] == pytest.approx(1.0)
    assert per_class["phone"]["box_ap50"] == pytest.approx(0.0)
    assert 0.0 < per_class["pistol"]["box_ap50"] < 1.0  # one true and one false positive
    assert per_class["chair"]["box_ap"] == -1.0  # no ground truth


def test_training_smoke_checkpoint_resume_and_export(tiny_headcam: Path, tmp_path: Path) -> None:
    cfg = replace(SMOKE, data=tiny_headcam, out=tmp_path / "ckpt")
    first = train(cfg, max_steps=1)
    assert first["step"] == 1 and not first["finished"] and first["history"] == []
    state = torch.load(tmp_path / "ckpt" / "detector.pt", map_location="cpu", weights_only=False)
    for key in (
        "model",
        "model_config",
        "optimizer",
        "train_config",
        "step",
        "epoch",
        "history",
        "rng",
        "data_seeds",
        "commit",
    ):
        assert key in state, key
    assert state["step"] == 1 and state["epoch"] == 0
    assert DetectorConfig.from_dict(state["model_config"]) == cfg.detector
    assert state["data_seeds"]["train_images"] == 4
    resumed = train(cfg)
    assert resumed["step"] == 2 and resumed["finished"]
    val = resumed["history"][-1]
    assert val["epoch"] == 1 and val["images"] == 2
    for k in ("box_ap50", "mask_ap50", "box_ap", "mask_ap"):
        assert 0.0 <= val[k] <= 1.0
    with pytest.raises(AssetError, match="another architecture"):
        train(replace(cfg, detector=DetectorConfig(fpn_channels=32)))
    # Resuming gives the same weights as one uninterrupted run.
    straight = train(replace(cfg, out=tmp_path / "straight"))
    a = torch.load(resumed["checkpoint"], map_location="cpu", weights_only=False)["model"]
    b = torch.load(straight["checkpoint"], map_location="cpu", weights_only=False)["model"]
    for k in a:
        torch.testing.assert_close(a[k], b[k], atol=1e-5, rtol=1e-4, msg=k)
    # Export: fp16 weights loadable by the Detector; the manifest keeps other keys.
    out = tmp_path / "weights"
    out.mkdir()
    (out / "manifest.json").write_text(json.dumps({"pose_nets": {"ours": {"file": "x.pt"}}}))
    entry = export_detector(Path(resumed["checkpoint"]), out)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["pose_nets"] == {"ours": {"file": "x.pt"}}
    assert manifest["detector"] == json.loads(json.dumps(entry)) and entry["file"] == "detector.pt"
    assert entry["bytes"] < 2.2 * count_parameters(build_detector()) + 200_000  # float16
    shipped = torch.load(out / "detector.pt", map_location="cpu", weights_only=False)
    assert "optimizer" not in shipped
    assert all(v.dtype == torch.float16 for v in shipped["model"].values() if v.is_floating_point())
    loaded = Detector.from_weights(out / "detector.pt")
    assert isinstance(loaded.detect(np.zeros((48, 64, 3), np.uint8)), list)


def test_cli_smoke_and_errors(
    tiny_headcam: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = [
        "--smoke",
        "--data",
        str(tiny_headcam),
        "--out",
        str(tmp_path / "c"),
        "--export",
        "--weights-out",
        str(tmp_path / "w"),
    ]
    assert main(argv) == 0
    assert (tmp_path / "w" / "detector.pt").is_file()
    assert "detector" in json.loads((tmp_path / "w" / "manifest.json").read_text())
    capsys.readouterr()
    assert main(["--epochs", "0"]) == 2
    assert main(["--data", str(tmp_path / "none"), "--out", str(tmp_path / "c2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("error: ") for line in err)
    assert "python -m perception.training.datagen" in err[1]
    for argv, needle in (
        (["--batch", "x"], "invalid --batch 'x'; valid: integers 1..65536"),
        (["--workers", "-1"], "invalid --workers -1; valid: integers 0..64"),
        (["--workers", "65"], "invalid --workers 65; valid: integers 0..64"),
        (["--threads", "0"], "invalid --threads 0; valid: integers 1..256"),
        (["--lr=-1e-3"], "invalid --lr -0.001; valid: numbers in (0, 1]"),
        (["--limit", "0"], "invalid --limit 0; valid: integers 1..100000000"),
        (["--max-steps", "0"], "invalid --max-steps 0"),
        (["--seed", "-1"], "invalid --seed -1"),
    ):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("error: ") and len(err.strip().splitlines()) == 1, argv
        assert needle in err, (argv, err)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "detector.pt").write_bytes(b"junk")
    bad = ["--smoke", "--data", str(tiny_headcam), "--out", str(tmp_path / "bad")]
    assert main(bad) == 2
    assert "corrupt" in capsys.readouterr().err


def test_mixed_data_and_fine_tuning_start(
    tiny_headcam: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from perception.training.trainers.detection_data import start_from, training_images

    monkeypatch.setenv("POSEGRASP_DATA", str(tmp_path / "data"))
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "headcam_hard").symlink_to(tiny_headcam)
    cfg = replace(SMOKE, data=tiny_headcam, out=tmp_path / "ckpt", also=("headcam_hard",))
    mix, parts = training_images(tiny_headcam, cfg.also, 100, cfg.detector, (None, None))
    assert len(parts) == 2 and len(mix) == 8
    for i in (0, 5):  # item 5 of the mix is item 1 of the second set
        a, b = mix[i], parts[i // 4][i % 4]
        torch.testing.assert_close(a[0], b[0])
    result = train(cfg, max_steps=1)
    state = torch.load(result["checkpoint"], map_location="cpu", weights_only=False)
    assert state["data_seeds"]["also"] == {"headcam_hard": 4}
    assert state["data_seeds"]["train_images"] == 8
    with pytest.raises(InvalidArgumentError, match="banana"):
        replace(SMOKE, also=("banana",))
    # A run started from weights begins from exactly those weights.
    model = build_detector(cfg.detector)
    start_from(model, Path(result["checkpoint"]), cfg.detector)
    for k, v in model.state_dict().items():
        torch.testing.assert_close(v, state["model"][k].to(v.dtype), msg=k)
    with pytest.raises(AssetError, match="another detector architecture"):
        start_from(
            build_detector(DetectorConfig(fpn_channels=32)),
            Path(result["checkpoint"]),
            DetectorConfig(fpn_channels=32),
        )


def test_bf16_and_channels_last_training_follows_fp32_and_is_recorded(
    tiny_headcam: Path, tmp_path: Path
) -> None:
    first = {}
    for precision, channels_last in (("fp32", False), ("bf16", True)):
        name = f"{precision}_{channels_last}"
        log = tmp_path / f"{name}.jsonl"
        cfg = replace(SMOKE, data=tiny_headcam, out=tmp_path / name, loss_log=log)
        result = train(replace(cfg, precision=precision, channels_last=channels_last))
        entry = export_detector(Path(result["checkpoint"]), tmp_path / f"w_{name}")
        assert entry["train_config"]["precision"] == precision
        assert ("--precision bf16" in entry["command"]) is (precision == "bf16")
        assert ("--channels-last" in entry["command"]) is channels_last
        ckpt = torch.load(result["checkpoint"], weights_only=False)
        assert all(
            v.dtype == torch.float32 for v in ckpt["model"].values() if v.is_floating_point()
        )
        first[name] = json.loads(log.read_text().splitlines()[0])["loss"]
    # Same weights and batch: bf16 rounds the forward pass (8 bits of mantissa) and no more.
    assert first["bf16_True"] == pytest.approx(first["fp32_False"], rel=5e-2)


def test_the_detector_loss_under_bf16_is_fp32_with_fp32_gradients(tiny_headcam: Path) -> None:
    from perception.training.trainers.detection_data import DetectionSet
    from perception.training.trainers.detector_trainer import detection_loss

    cfg = replace(SMOKE, precision="bf16", channels_last=True)
    model = build_detector(cfg.detector).to(memory_format=torch.channels_last).train()
    items = [DetectionSet(tiny_headcam, "train", 100, cfg.detector)[i] for i in range(2)]
    loss, parts = detection_loss(
        cfg, model, [x for x, _ in items], [t for _, t in items], torch.device("cpu")
    )
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
    assert set(parts) >= {"loss_classifier", "loss_box_reg", "loss_mask"}
    loss.backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad and p.grad is not None]
    assert grads and all(g.dtype == torch.float32 for g in grads)


def test_a_stage_fine_tuned_from_shipped_weights_keeps_their_stages(
    tiny_headcam: Path, tmp_path: Path
) -> None:
    out = tmp_path / "weights"
    base = train(replace(SMOKE, data=tiny_headcam, out=tmp_path / "base"))
    first = export_detector(Path(base["checkpoint"]), out)
    assert "stages" not in first  # trained from scratch: one stage, the entry itself
    tuned = train(
        replace(SMOKE, data=tiny_headcam, out=tmp_path / "tuned", init=out / "detector.pt")
    )
    second = export_detector(Path(tuned["checkpoint"]), out)
    assert [s["command"] for s in second["stages"]] == [first["command"], second["command"]]
    assert "--init" in second["command"] and second["stages"][0]["wall_s"] == first["wall_s"]
    again = train(
        replace(SMOKE, data=tiny_headcam, out=tmp_path / "again", init=out / "detector.pt")
    )
    # Exported into another folder (as the tiers' detector is), the stages come along.
    third = export_detector(Path(again["checkpoint"]), tmp_path / "elsewhere")
    assert len(third["stages"]) == 3 and third["stages"][:2] == second["stages"]
    # Started from a checkpoint, not from shipped weights: nothing to carry.
    fresh = train(
        replace(SMOKE, data=tiny_headcam, out=tmp_path / "fresh", init=Path(base["checkpoint"]))
    )
    assert "stages" not in export_detector(Path(fresh["checkpoint"]), tmp_path / "other")
