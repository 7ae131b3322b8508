"""`python -m sim.render_scene`: images of the right size, one-line errors naming the choices."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.scene import SceneConfig
from posegrasp.world.sensors import SENSOR_NAMES
from posegrasp.world.shifts import parse_shifts
from posegrasp.world.tiers import TIERS
from sim.episodes.episode import Episode, EpisodeConfig
from sim.render_scene import depth_to_mm, far_plane, main

REPO = Path(__file__).resolve().parent.parent


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "sim.render_scene", *args],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )


def test_writes_head_and_external_png(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "sub" / "head.png"
    argv = ["--object", "chair", "--seed", "1", "--png", str(out), "--external"]
    assert main([*argv, "--width", "200", "--height", "150", "--no-shadows"]) == 0
    external = tmp_path / "sub" / "head_external.png"
    images = []
    for path in (out, external):
        img = cv2.imread(str(path))
        assert img is not None and img.shape == (150, 200, 3)
        assert img.std() > 5  # a rendered scene, not a blank image
        images.append(img.astype(int))
    assert np.abs(images[0] - images[1]).mean() > 5  # two different views
    assert capsys.readouterr().out.split() == [str(out), str(external)]


def test_default_size_without_external(tmp_path: Path) -> None:
    out = tmp_path / "h.png"
    assert main(["--object", "phone", "--png", str(out), "--no-shadows"]) == 0
    img = cv2.imread(str(out))
    assert img is not None and img.shape == (480, 640, 3)
    assert not (tmp_path / "h_external.png").exists()


def test_help(capsys: pytest.CaptureFixture) -> None:
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    options = (
        "--object",
        "--seed",
        "--png",
        "--sheet",
        "--external",
        "--width",
        "--distractors",
        "--sensor",
        "--depth",
        "--shift",
    )
    for option in options:
        assert option in text
    assert ", ".join(OBJECT_NAMES) in " ".join(text.split())


BAD_INPUTS = [
    (
        ["--object", "teapot"],
        ["unknown object 'teapot'", "valid objects: " + ", ".join(OBJECT_NAMES)],
    ),
    (["--width", "-640"], ["-640x480", "1..4096"]),
    (["--height", "0"], ["640x0", "1..4096"]),
    (["--png", "{file}/head.png"], ["is a file, not a folder"]),
    (["--png", "{tmp}/dir.png"], ["is a folder"]),
    (["--png", "{tmp}/head.jpg"], [".png"]),
    (["--sheet", "{tmp}/tiers.jpg"], ["--sheet", ".png"]),
    (["--png", "{tmp}/a.png", "--sheet", "{tmp}/b.png"], ["not allowed with argument --png"]),
    (["--tier", "nope"], ["unknown tier 'nope'", "valid tiers: " + ", ".join(TIERS)]),
    (["--out", "{tmp}/head.png"], ["unrecognized arguments: --out"]),
    (["--distractors", "9"], ["0..5"]),
    (["--seed", "-1"], ["0..4294967295"]),
    (["--seed", str(2**32)], ["0..4294967295"]),
    (["--width", "wide"], ["--width", "invalid int value", "--help"]),
    (["--colour", "red"], ["unrecognized arguments: --colour", "--help"]),
    (
        ["--sensor", "lidar"],
        ["unknown sensor 'lidar'", "valid sensors: " + ", ".join(SENSOR_NAMES)],
    ),
    (["--sheet", "{tmp}/s.png", "--depth"], ["--depth applies to --png only"]),
    (["--shift", "fog"], ["unknown scene shift 'fog'", "valid scene shifts: light_colour, "]),
    (["--shift", "camera:9"], ["invalid level '9' of scene shift 'camera'", "3 strong"]),
    (["--png", "{tmp}/h.png", "--depth"], ["--depth", "is a folder"]),
]


def _fill(args: list[str], tmp_path: Path) -> list[str]:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    (tmp_path / "dir.png").mkdir()
    (tmp_path / "h_depth_view.png").mkdir()  # where --png h.png --depth would write its view
    args = [a.format(file=blocker, tmp=tmp_path) for a in args]
    named = "--png" in args or "--sheet" in args
    return args if named else [*args, "--png", str(tmp_path / "x.png")]


def _assert_one_line_error(stderr: str, expected: list[str]) -> None:
    lines = stderr.splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: ")
    assert "Traceback" not in stderr
    for text in expected:
        assert text in lines[0]


@pytest.mark.parametrize(("args", "expected"), BAD_INPUTS)
def test_bad_input_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture, args: list[str], expected: list[str]
) -> None:
    assert main(_fill(args, tmp_path)) == 2
    captured = capsys.readouterr()
    _assert_one_line_error(captured.err, expected)
    assert captured.out == ""
    # Checked before anything was built or written.
    assert [p for p in tmp_path.glob("**/*.png") if p.is_file()] == []


@pytest.mark.parametrize(("args", "expected"), [BAD_INPUTS[0], BAD_INPUTS[3]])
def test_bad_input_as_a_process(tmp_path: Path, args: list[str], expected: list[str]) -> None:
    proc = _run(*_fill(args, tmp_path))
    assert proc.returncode == 2
    _assert_one_line_error(proc.stderr, expected)
    assert proc.stdout == ""


def test_sheet_shows_every_tier(tmp_path) -> None:
    out = tmp_path / "tiers.png"
    argv = ["--sheet", str(out), "--width", "64", "--height", "48", "--no-shadows"]
    assert main([*argv, "--estimator", "none"]) == 0  # poses: tests/test_render_sheet.py
    img = cv2.imread(str(out))
    assert img.shape == (40 + 2 * 48, 64 * len(TIERS), 3)
    # Every column holds two real renders (not blank).
    for k in range(len(TIERS)):
        assert img[40:, 64 * k : 64 * (k + 1)].std() > 5


def test_depth_through_a_sensor_is_the_depth_an_episode_of_the_seed_observes(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    out = tmp_path / "head.png"
    argv = ["--object", "phone", "--seed", "3", "--png", str(out), "--no-shadows"]
    assert main([*argv, "--sensor", "kinect-v1", "--depth"]) == 0
    metric, view = tmp_path / "head_depth.png", tmp_path / "head_depth_view.png"
    captured = capsys.readouterr()
    assert captured.out.split() == [str(out), str(metric), str(view)]
    assert "note:" not in captured.err  # the depth is written: nothing goes unused
    written = cv2.imread(str(metric), cv2.IMREAD_UNCHANGED)
    assert written is not None and written.dtype == np.uint16
    ep = Episode("phone", 3, EpisodeConfig(shadows=False, obs_mode="rgbd", sensor="kinect-v1"))
    try:
        depth = ep.observe().depth
        far = far_plane(ep.scene.model)
    finally:
        ep.close()
    assert depth is not None and (depth == 0).any()  # the sensor's holes
    np.testing.assert_array_equal(written, depth_to_mm(depth, far))
    coloured = cv2.imread(str(view))
    assert coloured is not None and coloured.shape[0] > written.shape[0]


def test_a_colour_model_changes_the_head_image_and_a_depth_model_says_its_depth_is_unseen(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    argv = ["--object", "phone", "--seed", "3", "--no-shadows", "--width", "200", "--height", "150"]
    images = {}
    for sensor in ("ideal", "ideal+camera", "azure-tof"):
        out = tmp_path / f"{sensor}.png"
        assert main([*argv, "--png", str(out), "--sensor", sensor]) == 0
        images[sensor] = cv2.imread(str(out)).astype(int)
        notes = [x for x in capsys.readouterr().err.splitlines() if x.startswith("note:")]
        assert len(notes) == (sensor == "azure-tof")
    assert np.abs(images["ideal+camera"] - images["ideal"]).mean() > 0.5
    np.testing.assert_array_equal(images["azure-tof"], images["ideal"])  # a depth model alone
    assert not list(tmp_path.glob("*_depth*.png"))  # no --depth: no depth images


def test_a_shifted_head_image_is_what_an_episode_under_the_shifts_observes(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    spec = "light_colour:3,camera:3"
    argv = ["--object", "phone", "--seed", "3", "--no-shadows", "--width", "200", "--height", "150"]
    assert main([*argv, "--png", str(tmp_path / "plain.png")]) == 0
    assert main([*argv, "--png", str(tmp_path / "shifted.png"), "--shift", spec]) == 0
    cfg = EpisodeConfig(
        width=200, height=150, shadows=False, scene=SceneConfig(shifts=parse_shifts(spec))
    )
    ep = Episode("phone", 3, cfg)
    try:
        want = ep.observe().rgb
    finally:
        ep.close()
    shifted = cv2.imread(str(tmp_path / "shifted.png"))[..., ::-1]
    np.testing.assert_array_equal(shifted, want)
    plain = cv2.imread(str(tmp_path / "plain.png"))[..., ::-1]
    assert np.abs(shifted.astype(int) - plain).mean() > 5
