"""The mask net: its window is cut and drawn back where it came from, its training input degrades
a true mask as the detector does, and the shipped net gives back the outline a coarse mask lost."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from perception.mask_net import (
    MaskNet,
    MaskNetConfig,
    MaskRefiner,
    cut,
    paste,
    window_of,
)
from perception.training.trainers.mask_windows import degrade
from posegrasp.core.errors import InvalidArgumentError


def _disc(shape=(480, 640), centre=(300, 200), radius=40) -> np.ndarray:
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    return (xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 <= radius**2


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return np.count_nonzero(a & b) / max(1, np.count_nonzero(a | b))


def test_a_window_cut_and_drawn_back_gives_the_mask_back() -> None:
    """Cut at the net's size and pasted back, a mask comes back within a pixel's blur, also
    when its window reaches beyond the image."""
    for centre in ((300, 200), (20, 15)):
        mask = _disc(centre=centre)
        win = window_of(mask, 0.25)
        assert win is not None
        _x0, _y0, side = win
        assert side == round((mask.any(0).sum()) * 1.5)
        prob = cut(mask.astype(np.float32), win, 96)
        assert prob.shape == (96, 96)
        back = paste(prob, win, mask.shape) >= 0.5
        assert _iou(back, mask) > 0.95
    assert window_of(np.zeros((10, 10), bool), 0.25) is None


def test_the_coarse_training_masks_are_binary_and_lose_thin_parts() -> None:
    """The degraded masks are 0/1 and of the input's shape; a 2 px line, a thin part, is mostly
    gone from them while a disc survives; the same generator seed gives the same masks."""
    S = 96
    t = torch.zeros(16, S, S)
    yy, xx = torch.meshgrid(torch.arange(S), torch.arange(S), indexing="ij")
    t[:, (xx - 48) ** 2 + (yy - 48) ** 2 <= 20**2] = 1.0
    t[:, 10:12, 5:90] = 1.0  # a thin part
    a = degrade(t, torch.Generator().manual_seed(3))
    b = degrade(t, torch.Generator().manual_seed(3))
    assert a.shape == t.shape and torch.equal(a, b)
    assert set(torch.unique(a).tolist()) <= {0.0, 1.0}
    disc = ((xx - 48) ** 2 + (yy - 48) ** 2 <= 16**2).expand_as(t)
    assert a[disc].mean() > 0.95
    assert a[:, 10:12, 5:90].mean() < 0.5


def test_the_heavy_coarse_masks_also_lose_and_gain_whole_parts() -> None:
    """With `heavy` (as both protocols train), a disc's coarse masks are still 0/1 and
    seeded, but some lose a part of the disc far beyond the light masks' thin-part losses and
    some gain background well outside it."""
    S = 96
    t = torch.zeros(64, S, S)
    yy, xx = torch.meshgrid(torch.arange(S), torch.arange(S), indexing="ij")
    t[:, (xx - 48) ** 2 + (yy - 48) ** 2 <= 20**2] = 1.0
    light = degrade(t, torch.Generator().manual_seed(5))
    heavy = degrade(t, torch.Generator().manual_seed(5), heavy=True)
    assert torch.equal(heavy, degrade(t, torch.Generator().manual_seed(5), heavy=True))
    assert set(torch.unique(heavy).tolist()) <= {0.0, 1.0}
    inner = ((xx - 48) ** 2 + (yy - 48) ** 2 <= 14**2).expand_as(t)
    outer = ((xx - 48) ** 2 + (yy - 48) ** 2 > 26**2).expand_as(t)
    lost = ((1 - heavy) * inner).flatten(1).sum(1) / inner[0].sum()
    gained = (heavy * outer).flatten(1).sum(1)
    assert ((1 - light) * inner).sum() == 0 and (light * outer).sum() == 0
    assert (lost > 0.1).float().mean() > 0.2 and (gained > 50).float().mean() > 0.2
    assert (lost < 0.01).float().mean() > 0.2  # others keep the object whole


def test_the_net_keeps_its_window_size() -> None:
    net = MaskNet(MaskNetConfig(size=32, widths=(4, 8, 16)))
    assert net(torch.zeros(2, 4, 32, 32)).shape == (2, 1, 32, 32)
    with pytest.raises(InvalidArgumentError, match="divisible"):
        MaskNetConfig(size=30, widths=(4, 8, 16))


def test_the_shipped_net_gives_back_the_outline_a_coarse_mask_lost() -> None:
    """A coloured box with a thin leg on a textured table: the detector-like coarse mask (drawn
    on a 14-cell grid, most of the leg lost) is redrawn closer to the truth with nearly all of
    the leg, and of the coarse mask's blur beside the leg no more than a fifth of the object's
    area (the shipped net keeps about 14 %, its first stage alone kept 8 %)."""
    rng = np.random.default_rng(0)
    rgb = np.clip(rng.normal(150, 12, (480, 640, 3)), 0, 255).astype(np.uint8)
    truth = np.zeros((480, 640), bool)
    truth[200:240, 280:340] = True  # the body
    truth[240:275, 284:292] = True  # an 8 px leg
    rgb[truth] = (40, 70, 160)
    win = window_of(truth, 0.25)
    assert win is not None
    t = torch.as_tensor(cut(truth.astype(np.float32), win, 96))[None]
    coarse_small = torch.nn.functional.adaptive_avg_pool2d(t[None], 14)
    coarse_win = torch.nn.functional.interpolate(coarse_small, size=(96, 96), mode="bilinear")
    coarse = paste(coarse_win[0, 0].numpy(), win, truth.shape) >= 0.6
    refiner = MaskRefiner.from_weights()
    sharp = refiner.refine(rgb, coarse)
    assert _iou(sharp, truth) > _iou(coarse, truth) + 0.04
    assert _iou(sharp, truth) > 0.85
    assert np.count_nonzero(sharp & ~truth) < 0.2 * np.count_nonzero(truth)
    assert np.count_nonzero(truth & ~sharp) < 0.02 * np.count_nonzero(truth)
    leg = np.zeros_like(truth)
    leg[245:275, 284:292] = True
    assert np.count_nonzero(sharp & leg) > 2 * np.count_nonzero(coarse & leg)
    assert np.count_nonzero(sharp & leg) > 0.9 * np.count_nonzero(leg)
    with pytest.raises(InvalidArgumentError, match="bool mask"):
        refiner.refine(rgb, coarse.astype(np.uint8))


def test_the_paper_protocols_net_gives_back_a_part_its_detector_lost() -> None:
    """A coloured box on a random background, 256x256 as the paper's images: its coarse mask
    lost a third of the box and took in background beside it; the paper protocol's net redraws
    it close to the truth."""
    from perception.mask_net import PAPER_MASKNET

    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (256, 256, 3)).astype(np.uint8)
    truth = np.zeros((256, 256), bool)
    truth[80:170, 70:190] = True
    rgb[truth] = (150, 40, 40)
    coarse = truth.copy()
    coarse[80:170, 150:190] = False  # a third lost
    coarse[60:80, 70:130] = True  # background taken in
    sharp = MaskRefiner.from_weights(PAPER_MASKNET).refine(rgb, coarse)
    assert _iou(coarse, truth) < 0.65
    assert _iou(sharp, truth) > 0.9


def _render(tmp_path, monkeypatch, dist: str, folder: str, counts: dict[str, int]) -> Path:
    """Scenes of `dist` rendered into ``<data>/<folder>`` under a data root of the test's own."""
    from perception.training.datagen import main as datagen

    monkeypatch.setenv("POSEGRASP_DATA", str(tmp_path / "data"))
    out = tmp_path / "data" / folder
    for split, count in counts.items():
        argv = ["--dist", dist, "--split", split, "--count", str(count), "--out", str(out)]
        assert datagen([*argv, "--quiet"]) == 0
    return out


def _tiny_run(tmp_path, heavy: bool = True):
    """A run of two epochs of a tiny net on the scenes of `_render` (``tiny``, 6 train, 2 val)."""
    from perception.training.trainers.masknet_trainer import MaskTrainConfig

    return MaskTrainConfig(
        sources=(("tiny", 6),),
        val=("tiny", 2),
        heavy=heavy,
        epochs=2,
        batch=4,
        net=MaskNetConfig(size=32, widths=(4, 8, 16)),
        out=tmp_path / "whole",
    )


@pytest.mark.slow
@pytest.mark.parametrize("heavy", [False, True])
def test_the_trainer_resumes_exactly(tmp_path, monkeypatch, heavy) -> None:
    """On a few rendered scenes: the windows are cut once and cached; a run stopped in the middle
    of an epoch and resumed ends with the very weights of a run never stopped; a run of other
    epochs does not resume it."""
    from perception.training.trainers.masknet_trainer import train

    _render(tmp_path, monkeypatch, "headcam", "tiny", {"train": 6, "val": 2})
    cfg = _tiny_run(tmp_path, heavy)
    whole = train(cfg)
    assert whole["epoch"] == 2 and [h["epoch"] for h in whole["history"]] == [1, 2]
    assert 0 <= whole["history"][-1]["iou"] <= 1
    assert len(list((tmp_path / "data" / "masknet").glob("tiny_*.npz"))) == 2  # train, val
    per_epoch = whole["step"] // 2
    stopped = replace(cfg, out=tmp_path / "stopped")
    cut_short = train(stopped, max_steps=per_epoch + 1)
    assert (cut_short["epoch"], cut_short["step"]) == (1, per_epoch + 1)
    with pytest.raises(InvalidArgumentError, match="--epochs 2"):
        train(replace(stopped, epochs=3))
    resumed = train(stopped)
    assert resumed["step"] == whole["step"] and resumed["history"] == whole["history"]
    for key, value in whole["model"].items():
        assert torch.equal(value, resumed["model"][key]), key


@pytest.mark.slow
def test_the_export_writes_the_net_and_the_stages_behind_it(tmp_path, monkeypatch) -> None:
    """An unfinished run is not exported; the export writes the net and its manifest entry; a
    further stage from the shipped net, on windows of another seed, starts with that net's
    validation, will not resume as a run of another seed, and its entry lists both stages."""
    import json

    from perception.training.shipping.ship import export_masknet
    from perception.training.trainers.masknet_trainer import train
    from posegrasp.core.errors import AssetError

    _render(tmp_path, monkeypatch, "headcam", "tiny", {"train": 6, "val": 2})
    cfg = _tiny_run(tmp_path)
    whole = train(cfg)
    stopped = train(replace(cfg, out=tmp_path / "stopped"), max_steps=1)
    with pytest.raises(AssetError, match="0/2 epochs"):
        export_masknet(tmp_path / "stopped" / "last.pt", "cmd", tmp_path / "w" / "masknet.pt")
    assert stopped["step"] == 1
    entry = export_masknet(cfg.out / "last.pt", "cmd", tmp_path / "w" / "masknet.pt")
    manifest = json.loads((tmp_path / "w" / "manifest.json").read_text())
    assert manifest["mask_net"] == entry
    assert entry["wall_s"] == round(whole["wall_s"], 1) and entry["epochs_done"] == 2
    assert MaskRefiner.from_weights(tmp_path / "w" / "masknet.pt").cfg == cfg.net
    further = replace(
        cfg, out=tmp_path / "further", epochs=1, seed=1, init=tmp_path / "w" / "masknet.pt"
    )
    run = train(further)
    assert run["history"][0]["epoch"] == 0
    assert run["history"][0]["iou"] == pytest.approx(whole["history"][-1]["iou"], abs=0.02)
    assert run["data_seeds"]["init_sha256"] == entry["sha256"]
    assert len(list((tmp_path / "data" / "masknet").glob("tiny_train_*.npz"))) == 2
    with pytest.raises(InvalidArgumentError, match="--seed 1"):
        train(replace(further, seed=2))
    with pytest.raises(AssetError, match="mask net of"):
        train(replace(further, out=tmp_path / "other", net=MaskNetConfig(size=32, widths=(4, 8))))
    second = export_masknet(further.out / "last.pt", "cmd2", tmp_path / "w" / "masknet.pt")
    assert [s["command"] for s in second["stages"]] == ["cmd", "cmd2"]
    assert second["stages"][0]["wall_s"] == entry["wall_s"] and second["epochs_done"] == 1
    _export_an_expert(tmp_path / "w", further.out / "last.pt", second)


def _export_an_expert(weights: Path, last: Path, shipped_entry: dict) -> None:
    """The same stage shipped as the net of one object alone: its own file and entry, the
    protocol's net and entry untouched, and its hash checked when it is loaded."""
    import json

    from perception.training.shipping.ship import export_masknet
    from posegrasp.core.errors import AssetError

    shipped = (weights / "masknet.pt").read_bytes()
    alone = export_masknet(last, "cmd3", weights / "masknet.pt", expert="faucet")
    manifest = json.loads((weights / "manifest.json").read_text())
    assert manifest["mask_net"] == shipped_entry and manifest["mask_net_experts"]["faucet"] == alone
    assert alone["file"] == "masknet_faucet.pt" and alone["stages"][-1]["command"] == "cmd3"
    assert (weights / "masknet.pt").read_bytes() == shipped
    both = MaskRefiner.from_weights(weights / "masknet.pt", experts=("faucet",))
    assert list(both.experts) == ["faucet"]
    (weights / "masknet_faucet.pt").write_bytes(shipped + b"\0")  # other bytes
    with pytest.raises(AssetError, match=r"masknet_faucet\.pt do not match"):
        MaskRefiner.from_weights(weights / "masknet.pt", experts=("faucet",))


def test_an_objects_own_net_redraws_that_objects_masks_alone() -> None:
    """A refiner with a net of its own for one object hands that object's masks to it, every
    other object's (and a mask of no named object) to the protocol's net."""
    torch.manual_seed(0)
    cfg = MaskNetConfig(size=32, widths=(4, 8, 16))
    own_net, shared = MaskNet(cfg), MaskNet(cfg)
    with torch.no_grad():  # one net sees the object everywhere, the other nowhere
        own_net.head.bias.fill_(-20.0)
        shared.head.bias.fill_(20.0)
    own = MaskRefiner(own_net)
    refiner = MaskRefiner(shared, experts={"faucet": own})
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (64, 64, 3)).astype(np.uint8)
    mask = np.zeros((64, 64), bool)
    mask[20:44, 16:40] = True
    by_own = own.refine(rgb, mask)
    by_shared = MaskRefiner(shared).refine(rgb, mask)
    assert not np.array_equal(by_own, by_shared)
    assert np.array_equal(refiner.refine(rgb, mask, "faucet"), by_own)
    for name in ("car", None):
        assert np.array_equal(refiner.refine(rgb, mask, name), by_shared)


def test_the_examples_are_drawn_into_a_picture(tmp_path) -> None:
    """One row per example, the three masks' outlines on its window: a PNG is written."""
    from perception.training.evals.masknet_eval import plot_examples

    rgb = np.full((64, 64, 3), 120, np.uint8)
    truth = _disc((64, 64), (32, 32), 20)
    coarse = _disc((64, 64), (33, 31), 17)
    plot_examples([("car", rgb, coarse, truth, truth, 0.7, 1.0)], tmp_path / "m.png")
    assert (tmp_path / "m.png").stat().st_size > 1000


class _StandIn:
    """The detector of `_stand_in_detector`: its answers by image, and how often it ran."""

    def __init__(self, answers: dict) -> None:
        self.answers, self.calls = answers, 0

    def detect(self, rgb, score_threshold=None):
        self.calls += 1
        return self.answers[rgb.tobytes()]


def _stand_in_detector(tmp_path, monkeypatch) -> tuple[Path, _StandIn]:
    """Paper scenes (5 train, 2 val) and a detector standing in for the shipped one: its mask of
    each object is the true one with its right third dropped."""
    import perception.detector as detector_module
    from perception.detector import Detection
    from perception.training.data.dataset import PoseDataset

    out = _render(tmp_path, monkeypatch, "paper", "paper", {"train": 5, "val": 2})
    answers: dict[bytes, list[Detection]] = {}
    for split in ("train", "val"):
        ds = PoseDataset(out, split)
        for i in range(len(ds)):
            s = ds[i]
            dets = []
            for obj in s.objects:
                cols = np.flatnonzero(obj.mask_visib.any(0))
                lost = obj.mask_visib.copy()
                if len(cols):
                    lost[:, cols[0] + 2 * len(cols) // 3 :] = False
                dets.append(Detection(obj.name, 0.9, np.zeros(4), lost))
            answers[s.rgb.tobytes()] = dets
    stand_in = _StandIn(answers)
    monkeypatch.setattr(detector_module.Detector, "from_weights", lambda path: stand_in)
    return out, stand_in


def test_the_detectors_windows_are_cut_around_its_masks_and_kept_in_blocks(tmp_path, monkeypatch):
    """Windows of the `detected` images are cut around the detector's own mask of each object,
    which is their coarse input as it is. They are cached in blocks: a longer run runs the
    detector only on the images past the blocks a shorter one finished, and a run again not at
    all."""
    from perception.metrics import mask_iou
    from perception.training.data.dataset import PoseDataset
    from perception.training.evals.masknet_eval import MIN_VISIBLE_PX
    from perception.training.trainers import mask_windows

    out, stand_in = _stand_in_detector(tmp_path, monkeypatch)
    net_cfg = MaskNetConfig(size=32, widths=(4, 8, 16))
    monkeypatch.setattr(mask_windows, "DETECTED_BLOCK", 2)
    shorter = mask_windows.detector_windows("paper", "train", 2, 2, net_cfg, None)
    assert stand_in.calls == 2
    windows = mask_windows.detector_windows("paper", "train", 2, 3, net_cfg, None)
    assert stand_in.calls == 3  # the finished block of the shorter run is reused
    assert np.array_equal(windows["coarse"][: len(shorter["coarse"])], shorter["coarse"])
    ds = PoseDataset(out, "train")
    expected = []
    for i in range(2, 5):
        for obj, det in zip(ds[i].objects, stand_in.answers[ds[i].rgb.tobytes()], strict=True):
            if obj.mask_visib.sum() >= MIN_VISIBLE_PX and mask_iou(det.mask, obj.mask_visib) >= 0.3:
                win = window_of(det.mask, net_cfg.margin)
                expected.append(cut(det.mask.astype(np.float32), win, 32) >= 0.5)
    assert len(expected) >= 2 and len(windows["coarse"]) == len(expected)
    for got, want in zip(windows["coarse"], expected, strict=True):
        assert np.array_equal(got.astype(bool), want)
    assert windows["target"].dtype == np.uint8 and windows["rgb"].shape[1:] == (32, 32, 3)
    again = mask_windows.detector_windows("paper", "train", 2, 3, net_cfg, None)
    assert stand_in.calls == 3 and np.array_equal(again["coarse"], windows["coarse"])


def test_a_run_trains_on_the_detectors_masks_as_they_are(tmp_path, monkeypatch):
    """A run with `detected` images trains on their windows beside the degraded true masks, its
    batches carrying the detector's masks unchanged, and validates on the detector's masks of
    the validation scenes too."""
    from perception.training.trainers import mask_windows
    from perception.training.trainers import masknet_trainer as tm

    _stand_in_detector(tmp_path, monkeypatch)
    net_cfg = MaskNetConfig(size=32, widths=(4, 8, 16))
    windows = mask_windows.detector_windows("paper", "train", 2, 3, net_cfg, None)
    seen: list[np.ndarray] = []
    real_input = tm.net_input

    def recording(rgb, coarse):
        seen.append(np.asarray(coarse).copy())
        return real_input(rgb, coarse)

    monkeypatch.setattr(tm, "net_input", recording)
    cfg = tm.MaskTrainConfig(
        sources=(("paper", 2),),
        val=("paper", 2),
        epochs=1,
        batch=1,  # every window in a batch of its own
        net=net_cfg,
        out=tmp_path / "run",
        detected=("paper", 2, 3),
    )
    run = tm.train(cfg)
    fed = np.concatenate(seen)
    for given in windows["coarse"]:
        assert any(np.array_equal(row, given) for row in fed)
    last = run["history"][-1]
    assert 0 <= last["detected_iou"] <= 1 and 0 < last["detector_iou"] < 1
    assert run["data_seeds"]["detected_windows"] == len(windows["coarse"])
