"""Refining and scoring a detection's starts on a helper process gives every start the result
this process gives it, to the bit; a helper that fails or is not ready yet changes nothing but
the time, and an error a start raises there is raised here."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from perception.codebook import Codebook, ConvexParts, id_map, image_edges
from perception.refine import PoseRefiner, RefineConfig
from perception.verification import Start, Verified, VerifyHelper, VerifyJob, _stop, run_here
from posegrasp.core.transforms import intrinsics, rot_x, rot_y, rot_z
from posegrasp.world.objects import load_object

K = intrinsics(np.deg2rad(50), 640, 480)
NAME = "pistol"


def _pose() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_x(np.deg2rad(-70)) @ rot_y(np.deg2rad(40)) @ rot_z(np.deg2rad(10))
    T[:3, 3] = [0.04, -0.02, 0.75]
    return T


def _job() -> VerifyJob:
    """The pistol drawn in its parts' colours on a grey image, as a job."""
    pieces = ConvexParts().pieces(NAME)
    colours = np.array([p.rgba[:3] for p in load_object(NAME).parts])
    ids = id_map(pieces, _pose(), K, (0, 0, 640, 480))
    assert ids is not None
    mask = ids != 0
    rgb = np.full((480, 640, 3), 90, np.uint8)
    rgb[mask] = (255 * colours[ids[mask].astype(int) - 1]).astype(np.uint8)
    box = (200, 120, 460, 380)
    refiner = PoseRefiner(RefineConfig())
    return VerifyJob(
        name=NAME,
        parts=refiner.part_vertices(NAME),
        pieces=pieces,
        colours=colours,
        K=K,
        rgb=rgb,
        mask=mask,
        edge_distance=image_edges(rgb, box),
        box=box,
        target=refiner.prepare(K, mask, rgb, None),
        refine=refiner.config,
        appearance_weight=0.05,
        edge_weight=0.3,
    )


def _starts() -> list[Start]:
    """Starts turned 3-12 deg off about several axes, short and full runs, one behind the
    camera (no pose to verify)."""
    out = []
    for i, deg in enumerate((3, 5, 8, 12, 6, 9, 4)):
        T = _pose()
        T[:3, :3] = rot_x(np.deg2rad(deg)) @ rot_z(np.deg2rad(deg / 2 * (-1) ** i)) @ T[:3, :3]
        out.append(Start(T, "codebook", i + 1, 1 + i % 2, 2 if i % 3 else 0))
    behind = _pose()
    behind[2, 3] = -0.5
    return [*out, Start(behind, "nets", 0, 1)]


def _same(a: list[Verified | None], b: list[Verified | None]) -> bool:
    def key(v: Verified | None):
        return None if v is None else (v.T_C_O.tobytes(), v.score, v.iou, v.source, v.rank)

    return [key(v) for v in a] == [key(v) for v in b]


def _ready(helper: VerifyHelper, timeout_s: float = 60.0) -> None:
    end = time.monotonic() + timeout_s
    while not helper.available():
        assert time.monotonic() < end, "the helper process never came up"
        time.sleep(0.05)


def test_the_helper_gives_every_start_the_result_this_process_gives() -> None:
    job, starts = _job(), _starts()
    here = run_here(job, starts)
    assert here[-1] is None and all(v is not None for v in here[:-1])
    assert max(v.score for v in here if v is not None) > 1.0  # the refined starts fit
    helper = VerifyHelper()
    try:
        assert _same(helper.map(job, starts), here)  # ready or not, the same results
        _ready(helper)
        assert _same(helper.map(job, starts), here)  # the job sent along
        assert _same(helper.map(job, starts[:3]), here[:3])  # the job it holds
        other = replace(job, edge_weight=0.0)
        assert _same(helper.map(other, starts), run_here(other, starts))  # a new job
    finally:
        helper.close()


def test_an_error_in_the_helper_is_raised_here_and_a_dead_helper_is_done_without() -> None:
    job, starts = _job(), _starts()
    helper = VerifyHelper()
    try:
        _ready(helper)
        broken = replace(job, colours=job.colours[:1])  # too few colours for the pieces
        with pytest.raises(IndexError):  # the helper's start fails, this one's (behind) does not
            helper.map(broken, [starts[-1], starts[0]])
        with pytest.raises(IndexError):  # this one's fails; the helper's reply is read anyway
            helper.map(broken, starts[:2])
        assert _same(helper.map(job, starts), run_here(job, starts))  # it goes on serving
        helper._process.kill()
        helper._process.wait()
        assert _same(helper.map(job, starts), run_here(job, starts))
        assert not helper.available()
    finally:
        helper.close()


def test_the_helper_matches_half_the_templates_as_this_process_would() -> None:
    """`VerifyHelper.match`: every framing's IoUs with every template, the later half matched
    by the helper, equal to `Codebook.match` here; a codebook is sent once and then held."""
    book = Codebook.build("car", 60, 6)
    rng = np.random.default_rng(3)
    views = [(book.bits[i].copy(), None) for i in (5, 200)]
    views.append((book.bits[17].copy(), rng.integers(0, 2**63, book.bits.shape[1], np.uint64)))
    here = np.concatenate([book.match(bits, hidden) for bits, hidden in views])
    assert here.shape == (3 * len(book.rotations),) and here[5] == 1.0
    helper = VerifyHelper()
    try:
        _ready(helper)
        assert np.array_equal(helper.match(book, views), here)
        assert np.array_equal(helper.match(book, views[:1]), here[: len(book.rotations)])
        helper._process.kill()
        helper._process.wait()
        assert np.array_equal(helper.match(book, views), here)  # done here without it
    finally:
        helper.close()


def test_a_reply_left_unread_or_a_forked_child_retires_the_helper(monkeypatch) -> None:
    """A request whose reply was never read (Ctrl-C while waiting for it) would put every later
    reply one behind; a forked child shares its parent's socket. Either way the helper is no
    longer used, and the results, made here, are the same."""
    import os

    job, starts = _job(), _starts()
    here = run_here(job, starts)
    helper = VerifyHelper()
    try:
        _ready(helper)
        real_recv = helper._conn.recv

        def interrupted():
            raise KeyboardInterrupt

        monkeypatch.setattr(helper._conn, "recv", interrupted)
        with pytest.raises(KeyboardInterrupt):
            helper.map(job, starts)
        monkeypatch.setattr(helper._conn, "recv", real_recv)
        assert not helper.available()
        assert _same(helper.map(job, starts), here)
    finally:
        helper.close()
    forked = VerifyHelper()
    _ready(forked)
    with monkeypatch.context() as m:
        m.setattr(os, "getpid", lambda: -1)  # as in a child forked from this process
        assert not forked.available()
        assert _same(forked.map(job, starts), here)
        forked.close()  # a child leaves its parent's helper running
    assert forked._process.poll() is None
    _stop(forked._process, forked._conn, os.getpid())  # the parent stops it
    assert forked._process.poll() is not None
