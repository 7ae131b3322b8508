"""Several head-camera views per generated scene (`--views`), and the writer's shortcuts."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from perception.training.data import bop
from perception.training.data import dataset as ds
from perception.training.data.distributions import HeadcamGenerator, _disjoint_batches
from perception.training.datagen import main

W, H = 160, 120


def _args(out: Path, count: int, views: int, *extra: str) -> list[str]:
    size = ["--width", str(W), "--height", str(H)]
    split = ["--dist", "headcam", "--split", "val", "--count", str(count), "--views", str(views)]
    return [*split, *size, "--out", str(out), "--quiet", *extra]


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "wall_time.json"
    }


@pytest.fixture(scope="module")
def gen():
    g = HeadcamGenerator(W, H)
    yield g
    g.close()


def test_a_view_does_not_depend_on_the_views_rendered_before_it(gen) -> None:
    together = gen.render_views("chair", 11, [0, 1, 2, 3])
    alone = gen.render_views("chair", 11, [2])[0]
    np.testing.assert_array_equal(alone.rgb, together[2].rgb)
    bodies = lambda im: [o.extra["body"] for o in im.objects]  # noqa: E731
    assert bodies(alone) == bodies(together[2])
    # View 0 is the image of `render`; the others look elsewhere, at another object.
    np.testing.assert_array_equal(gen.render("chair", 11).rgb, together[0].rgb)
    assert not np.array_equal(together[1].rgb, together[0].rgb)
    targets = [im.extra["target"] for im in together]
    assert targets[0] == "chair" and len(set(targets)) >= 2
    for im in together:
        flagged = [o.name for o in im.objects if o.extra["target"]]
        assert flagged in ([], [im.extra["target"]])


def test_views_split_same_bytes_with_any_workers_resume_and_seeds(tmp_path: Path) -> None:
    one, two = tmp_path / "one", tmp_path / "two"
    assert main(_args(one, 6, 3)) == 0
    assert main(_args(two, 6, 3, "--workers", "2")) == 0
    assert _files(one) == _files(two)
    info = ds.load_info(one)["splits"]["val"]
    assert info["views"] == 3 and info["seed_range"] == [100_000_000, 100_000_002]
    # Images 0-2 show the first scene, 3-5 the second, each from its own view.
    seeds = [ds.load_sample(one, "val", i).seed for i in range(6)]
    assert seeds == [100_000_000] * 3 + [100_000_001] * 3
    # Resuming re-renders a lost view of a scene alone, to the same bytes.
    sdir = one / "val" / "000000"
    for p in [bop.record_path(sdir, 4), bop.rgb_path(sdir, 4)]:
        p.unlink()
    assert main(_args(one, 6, 3)) == 0
    assert _files(one) == _files(two)
    # A split of other views per scene is refused; --views is for head-camera scenes only.
    assert main(_args(one, 6, 2)) != 0
    paper = ["--dist", "paper", "--split", "val", "--count", "2", "--views", "2"]
    assert main([*paper, "--out", str(tmp_path / "p"), "--quiet"]) != 0


def test_an_unoccluded_visible_mask_is_the_full_mask_file(tmp_path: Path) -> None:
    out = tmp_path / "d"
    assert main(_args(out, 2, 1)) == 0
    same = 0
    for i in range(2):
        sample = ds.load_sample(out, "val", i)
        sdir = out / "val" / "000000"
        for k, obj in enumerate(sample.objects):
            full, visib = bop.mask_path(sdir, i, k, False), bop.mask_path(sdir, i, k, True)
            if np.array_equal(obj.mask, obj.mask_visib):
                assert visib.read_bytes() == full.read_bytes()
                same += int(os.path.samefile(full, visib))
    probe = tmp_path / "probe"
    probe.write_bytes(b"")
    try:
        os.link(probe, tmp_path / "probe_link")
    except OSError:  # a file system without hard links: the visible masks are copies
        return
    assert same >= 1


def test_write_same_replaces_and_copies_without_links(tmp_path: Path, monkeypatch) -> None:
    src, dst = tmp_path / "a.png", tmp_path / "b.png"
    bop.write_bytes(src, b"payload")
    dst.write_bytes(b"stale")
    bop.write_same(dst, src, b"payload")
    assert dst.read_bytes() == b"payload" and os.path.samefile(src, dst)

    def no_links(*_args):
        raise OSError("hard links not supported")

    monkeypatch.setattr(os, "link", no_links)
    other = tmp_path / "c.png"
    bop.write_same(other, src, b"payload")
    assert other.read_bytes() == b"payload" and not os.path.samefile(src, other)


def test_disjoint_batches() -> None:
    windows = [(0, 0, 10, 10), (10, 0, 20, 10), (5, 5, 15, 15), (0, 10, 10, 20), (9, 9, 11, 11)]
    batches = _disjoint_batches(windows)
    assert sorted(k for b in batches for k in b) == list(range(5))
    assert batches[0] == [0, 1, 3]  # boxes that only touch at their edges do not overlap
    for b in batches:
        for i in b:
            for j in b:
                wi, wj = windows[i], windows[j]
                overlap = wi[0] < wj[2] and wj[0] < wi[2] and wi[1] < wj[3] and wj[1] < wi[3]
                assert i == j or not overlap


@pytest.mark.parametrize("views", ["0", "17", "x"])
def test_bad_views_give_one_line(views: str, tmp_path: Path, capsys) -> None:
    args = _args(tmp_path / "x", 2, 1)
    args[args.index("--views") + 1] = views
    assert main(args) != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and "--views" in err
