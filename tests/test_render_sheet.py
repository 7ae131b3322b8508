"""`python -m sim.render_scene --sheet`: the true pose and the estimate drawn on each tier's head
image, the estimate's errors (or a missed detection) in the label, one-line errors for a bad
`--estimator`."""

from __future__ import annotations

import subprocess
import sys
from importlib.util import find_spec
from pathlib import Path

import cv2
import numpy as np
import pytest

from perception.overlay import silhouette
from posegrasp.core.contract import Estimate, Observation
from posegrasp.world.scene import SceneConfig
from posegrasp.world.shifts import parse_shifts
from posegrasp.world.tiers import TIERS
from sim import render_scene
from sim.episodes.episode import Episode, EpisodeConfig
from sim.episodes.registry import ESTIMATORS
from sim.render_scene import main

REPO = Path(__file__).resolve().parent.parent
W, H, SEED, TIER = 160, 120, 4, "isolated"
LABEL = 4 + 18 * 3  # tier name, summary, estimate


@pytest.fixture
def one_tier(monkeypatch: pytest.MonkeyPatch) -> None:
    """A sheet of the isolated tier only (fast)."""
    monkeypatch.setattr(render_scene, "TIERS", {TIER: TIERS[TIER]})


@pytest.fixture
def label_lines(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every text cv2.putText draws, in order."""
    texts: list[str] = []
    put_text = cv2.putText

    def spy(img, text, *args, **kwargs):
        texts.append(text)
        return put_text(img, text, *args, **kwargs)

    monkeypatch.setattr(cv2, "putText", spy)
    return texts


def _sheet(tmp_path: Path, estimator: str) -> np.ndarray:
    out = tmp_path / f"{estimator}.png"
    argv = ["--sheet", str(out), "--width", str(W), "--height", str(H), "--seed", str(SEED)]
    assert main([*argv, "--no-shadows", "--estimator", estimator]) == 0
    bgr = cv2.imread(str(out))
    assert bgr is not None
    return bgr[..., ::-1]


def _true_outline() -> np.ndarray:
    """(N, 2) pixels (x, y) on the outline of the target's true pose in the head image."""
    ep = Episode("phone", SEED, EpisodeConfig(width=W, height=H, shadows=False, tier=TIER))
    try:
        mesh = ep.scene.target.model.mesh
        mask = silhouette(ep.T_C_O_true, ep.K, mesh.vertices, mesh.faces, (H, W))
    finally:
        ep.close()
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    return np.concatenate([c[:, 0] for c in contours])


def _share(head: np.ndarray, pixels: np.ndarray, colour: tuple[int, int, int]) -> float:
    values = head[pixels[:, 1], pixels[:, 0]].astype(int)
    return float(np.mean(np.abs(values - colour).max(axis=1) < 60))


def test_oracle_estimate_is_drawn_on_the_true_outline(
    tmp_path: Path, one_tier: None, label_lines: list[str]
) -> None:
    img = _sheet(tmp_path, "oracle")
    assert img.shape == (LABEL + 2 * H, W, 3)
    head = img[LABEL : LABEL + H]
    outline = _true_outline()
    assert len(outline) > 20
    # The green estimate is drawn over the white true pose, exactly where it is.
    assert _share(head, outline, (0, 255, 0)) > 0.9
    assert "oracle estimate: 0 mm, 0.0 deg off" in label_lines
    assert {"true", "estimate"} <= set(label_lines)
    # Without an estimator, the same head image carries no poses and the label two lines.
    plain = _sheet(tmp_path, "none")
    assert plain.shape == (40 + 2 * H, W, 3)
    assert _share(plain[40 : 40 + H], outline, (0, 255, 0)) < 0.1
    assert np.array_equal(plain[40 + H :], img[LABEL + H :])  # the external view is untouched


@pytest.mark.skipif(find_spec("pybullet_data") is None, reason="all:1 stands distractors")
def test_the_sheet_is_drawn_under_the_shifts_and_names_them(
    tmp_path: Path, one_tier: None, label_lines: list[str]
) -> None:
    out = tmp_path / "shifted.png"
    argv = ["--sheet", str(out), "--width", str(W), "--height", str(H), "--seed", str(SEED)]
    assert main([*argv, "--no-shadows", "--estimator", "none", "--shift", "all:1"]) == 0
    assert f"{TIER}, shifts all:1" in label_lines
    cfg = EpisodeConfig(
        width=W, height=H, shadows=False, tier=TIER, scene=SceneConfig(shifts=parse_shifts("all:1"))
    )
    ep = Episode("phone", SEED, cfg)
    try:
        want = ep.observe().rgb
    finally:
        ep.close()
    head = cv2.imread(str(out))[..., ::-1][40 : 40 + H]
    np.testing.assert_array_equal(head, want)
    assert render_scene.shifts_text(parse_shifts("camera:3,walls")) == "walls:2,camera:3"


class _Blind:
    """An estimator that never finds its target; keeps what it was shown in `seen`."""

    name = "blind"

    def __init__(self, seen: list[Observation]) -> None:
        self.seen = seen

    def estimate(self, obs: Observation) -> Estimate:
        self.seen.append(obs)
        return Estimate(None)


def test_a_missed_detection_is_shown_not_raised(
    tmp_path: Path, one_tier: None, label_lines: list[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    seen: list[Observation] = []
    monkeypatch.setitem(ESTIMATORS, "blind", lambda: _Blind(seen))
    img = _sheet(tmp_path, "blind")
    assert "blind: phone not detected" in label_lines
    assert "estimate" not in label_lines
    # The estimator was shown the very head image of the sheet, and the true pose is drawn.
    (obs,) = seen
    plain = _sheet(tmp_path, "none")
    assert np.array_equal(obs.rgb, plain[40 : 40 + H])
    assert _share(img[LABEL : LABEL + H], _true_outline(), (255, 255, 255)) > 0.9


class _Shifted:
    """An oracle 3 cm off along the camera's x axis."""

    name = "shifted"

    def estimate_from_truth(
        self, obs: Observation, T_C_O_true: np.ndarray, neighbours: tuple
    ) -> Estimate:
        T = np.array(T_C_O_true, dtype=float)
        T[0, 3] += 0.03
        return Estimate(T, tuple(neighbours))


def test_a_wrong_estimate_is_drawn_off_the_true_outline(
    tmp_path: Path, one_tier: None, label_lines: list[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(ESTIMATORS, "shifted", _Shifted)
    head = _sheet(tmp_path, "shifted")[LABEL : LABEL + H]
    assert "shifted estimate: 30 mm, 0.0 deg off" in label_lines
    outline = _true_outline()
    assert _share(head, outline, (255, 255, 255)) > 0.5
    assert _share(head, outline, (0, 255, 0)) < 0.3


def test_bad_estimator_name_is_one_line_exit_2(tmp_path: Path) -> None:
    out = tmp_path / "sheet.png"
    proc = subprocess.run(
        [sys.executable, "-m", "sim.render_scene", "--sheet", str(out), "--estimator", "teapot"],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: ") and lines[0].endswith("(see --help)")
    assert "unknown estimator 'teapot'; valid estimators: " in lines[0]
    for name in [*ESTIMATORS, "none"]:
        assert name in lines[0]
    assert proc.stdout == "" and not out.exists()


def test_estimator_without_sheet_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "head.png"
    assert main(["--png", str(out), "--estimator", "oracle"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == ["error: --estimator applies to --sheet only"]
    assert not out.exists()
