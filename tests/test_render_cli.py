"""`python -m sim.render_scene`: images of the right size, one-line errors naming the choices."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from posegrasp.world.objects import OBJECT_NAMES
from posegrasp.world.tiers import TIERS
from sim.render_scene import main

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
    options = ("--object", "--seed", "--png", "--sheet", "--external", "--width", "--distractors")
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
]


def _fill(args: list[str], tmp_path: Path) -> list[str]:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    (tmp_path / "dir.png").mkdir()
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
