"""Refining and scoring a detection's starts: on a worker process every start gets the result
this process gives it, to the bit; a worker that fails or is not up yet changes nothing but the
time, and an error a start raises there is raised here. The ranking refines further and snaps
each start once, however often it is made again."""

from __future__ import annotations

import os
import time
from collections import Counter
from dataclasses import replace

import numpy as np
import pytest

from perception.codebook import Codebook, TemplateMatch
from perception.parallel import HELD, OneProcess, TwoProcesses
from perception.parts import ConvexParts, Parts
from perception.priors import Gravity, GravityConfig, Plausibility
from perception.refine import PoseRefiner, RefineConfig
from perception.scoring import Scorer, ScoringConfig, id_map, image_edges
from perception.verification import (
    Hypothesis,
    RefinementConfig,
    Start,
    Verification,
    Verified,
    VerifyJob,
)
from posegrasp.core.transforms import intrinsics, quat_to_mat, rot_x, rot_y, rot_z
from posegrasp.world.objects import load_object

K = intrinsics(np.deg2rad(50), 640, 480)
NAME = "pistol"


def _pose() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rot_x(np.deg2rad(-70)) @ rot_y(np.deg2rad(40)) @ rot_z(np.deg2rad(10))
    T[:3, 3] = [0.04, -0.02, 0.75]
    return T


def _job(T: np.ndarray | None = None) -> VerifyJob:
    """The pistol drawn at T (default `_pose`) in its parts' colours on a grey image, as a job."""
    parts = ConvexParts().parts(NAME)
    ids = id_map(parts, _pose() if T is None else T, K, (0, 0, 640, 480))
    assert ids is not None
    mask = ids != 0
    rgb = np.full((480, 640, 3), 90, np.uint8)
    rgb[mask] = (255 * parts.colours[ids[mask].astype(int) - 1]).astype(np.uint8)
    box = (200, 120, 460, 380)
    refiner = PoseRefiner(RefineConfig())
    scorer = Scorer(parts, K, rgb, mask, image_edges(rgb, box), box, ScoringConfig())
    return VerifyJob(parts, refiner.prepare(K, mask, rgb, None), refiner.config, scorer)


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


def _up(workers: TwoProcesses, timeout_s: float = 60.0) -> None:
    end = time.monotonic() + timeout_s
    while not workers.available():
        assert time.monotonic() < end, "the worker process never came up"
        time.sleep(0.05)


@pytest.fixture
def workers():
    w = TwoProcesses()
    yield w
    w.close()


def _kill(workers: TwoProcesses) -> None:
    """Kill the worker process, as a crash would."""
    for process in list(workers._pool._processes.values()):
        process.kill()
        process.join()


def test_the_worker_gives_every_start_the_result_this_process_gives(workers) -> None:
    job, starts = _job(), _starts()
    here = OneProcess.map(job, starts)
    assert here[-1] is None and all(v is not None for v in here[:-1])
    assert max(v.score for v in here if v is not None) > 1.0  # the refined starts fit
    assert _same(workers.map(job, starts), here)  # up or not, the same results
    _up(workers)
    assert _same(workers.map(job, starts), here)  # the job sent along
    assert _same(workers.map(job, starts[:3]), here[:3])  # the job it holds
    other = replace(job, scorer=replace(job.scorer, config=ScoringConfig(edge_weight=0.0)))
    assert _same(workers.map(other, starts), OneProcess.map(other, starts))  # a new job


def test_an_error_on_the_worker_is_raised_here_and_a_dead_worker_is_done_without(
    workers,
) -> None:
    job, starts = _job(), _starts()
    _up(workers)
    few = replace(job.parts, colours=job.parts.colours[:1])  # too few colours for the pieces
    broken = replace(job, scorer=replace(job.scorer, parts=few))
    with pytest.raises(IndexError):  # the worker's start fails, this one's (behind) does not
        workers.map(broken, [starts[-1], starts[0]])
    with pytest.raises(IndexError):  # this one's fails; the worker's result is dropped
        workers.map(broken, starts[:2])
    assert _same(workers.map(job, starts), OneProcess.map(job, starts))  # it goes on serving
    _kill(workers)
    assert _same(workers.map(job, starts), OneProcess.map(job, starts))
    assert not workers.available()


def test_the_worker_matches_half_the_templates_as_this_process_would(workers) -> None:
    """`TemplateMatch.scores`: every framing's IoUs with every template, the later half matched
    by the worker, equal to `Codebook.match` here; a codebook is sent once and then held."""
    book = Codebook.build("car", 60, 6)
    rng = np.random.default_rng(3)
    views = [(book.bits[i].copy(), None) for i in (5, 200)]
    views.append((book.bits[17].copy(), rng.integers(0, 2**63, book.bits.shape[1], np.uint64)))
    here = np.concatenate([book.match(bits, hidden) for bits, hidden in views])
    assert here.shape == (3 * len(book.rotations),) and here[5] == 1.0
    match = TemplateMatch(book)
    assert np.array_equal(match.scores(views, OneProcess()), here)
    _up(workers)
    assert np.array_equal(match.scores(views, workers), here)
    assert np.array_equal(match.scores(views[:1], workers), here[: len(book.rotations)])
    _kill(workers)
    assert np.array_equal(match.scores(views, workers), here)  # done here without it


def test_codebooks_that_take_turns_travel_to_the_worker_once_each(workers, monkeypatch) -> None:
    """An evaluation's episodes take the objects in turn, and each detection's verification job
    passes between them: each object's codebook is sent to the worker once and held, while no
    more than `HELD` jobs of a kind are held; one let go is sent again."""
    books = [Codebook.build(name, 60, 6) for name in ("car", "phone")]
    sent: Counter[str] = Counter()

    def counted(book: Codebook) -> dict:
        sent[book.name] += 1
        return dict(book.__dict__)

    monkeypatch.setattr(Codebook, "__getstate__", counted, raising=False)
    matches = [TemplateMatch(book) for book in books]
    views = {b.name: [(b.bits[i].copy(), None) for i in (3, 40)] for b in books}
    here = {m.book.name: m.scores(views[m.book.name], OneProcess()) for m in matches}
    job, starts = _job(), _starts()
    _up(workers)
    for _ in range(3):
        for m in matches:
            assert np.array_equal(m.scores(views[m.book.name], workers), here[m.book.name])
            for _ in range(HELD):
                workers.map(replace(job), starts[:2])  # a new verification job each time
    assert sent == {"car": 1, "phone": 1}
    others = [TemplateMatch(books[0]) for _ in range(HELD)]  # as many new jobs as it holds
    for m in others:
        m.scores(views["car"], workers)
    assert sent["car"] == 1 + HELD
    assert np.array_equal(matches[1].scores(views["phone"], workers), here["phone"])
    assert sent["phone"] == 2  # let go, so sent again


def test_an_interrupted_batch_or_a_forked_child_leaves_the_results_in_order(
    workers, monkeypatch
) -> None:
    """Ctrl-C during this process's share leaves the worker's result unread; the next batch
    still gets its own results in order. A forked child shares its parent's pool: it does its
    work alone, and the parent's worker goes on."""
    job, starts = _job(), _starts()
    here = OneProcess.map(job, starts)
    _up(workers)
    with monkeypatch.context() as m:

        def interrupted(job, items):
            raise KeyboardInterrupt

        m.setattr(OneProcess, "map", staticmethod(interrupted))
        with pytest.raises(KeyboardInterrupt):
            workers.map(job, starts)
    assert workers.available()
    assert _same(workers.map(job, starts), here)
    pid = os.getpid()
    with monkeypatch.context() as m:
        m.setattr(os, "getpid", lambda: pid + 1)  # as in a child forked from this process
        assert not workers.available()
        assert _same(workers.map(job, starts), here)
    assert workers.available()


class Counting:
    """An executor that runs every item here and counts the starts it runs."""

    def __init__(self) -> None:
        self.runs: list[tuple[int, int, int]] = []  # (rank, passes, iterations) per start

    def map(self, job, items):
        self.runs += [(s.rank, s.passes, s.iterations) for s in items]
        return OneProcess.map(job, items)


def _resting_scene() -> tuple[VerifyJob, Gravity, np.ndarray]:
    """The pistol resting, seen from a camera looking down at its table: (job, gravity, pose)."""
    model = load_object(NAME)
    R_W_C = rot_x(np.deg2rad(-120))
    T = np.eye(4)
    T[:3, :3] = R_W_C.T @ rot_z(0.6) @ quat_to_mat(next(iter(model.resting_poses.values())))
    T[:3, 3] = [0.03, 0.01, 0.8]
    return _job(T), Gravity(R_W_C, model, GravityConfig()), T


def _off(T: np.ndarray, deg: float, axis) -> Hypothesis:
    S = T.copy()
    S[:3, :3] = axis(np.deg2rad(deg)) @ T[:3, :3]
    return Hypothesis(S, "codebook")


def test_the_ranking_refines_the_best_further_and_snaps_each_start_once() -> None:
    """Every start is screened; the best two get the further runs and up to five near resting
    are snapped (one run, about the vertical); a start joining later is screened, and no run
    already made is made again."""
    job, gravity, T = _resting_scene()
    runs = Counting()
    v = Verification(job, RefinementConfig(), Plausibility(gravity), runs)
    v.add([_off(T, d, rot_x) for d in (4, 7, 10)])
    ranked = v.ranked()
    assert [(r, p, i) for r, p, i in runs.runs[:3]] == [(0, 1, 2), (1, 1, 2), (2, 1, 2)]
    further = [r for r in runs.runs[3:] if r[1:] == (2, 0)]
    snapped = [r for r in runs.runs[3:] if r[1:] == (1, GravityConfig().snap_iterations)]
    assert len(further) == 2 and 1 <= len(snapped) <= 5
    assert len(runs.runs) == 3 + len(further) + len(snapped)
    assert ranked[0].tilt < 1e-6  # a snapped pose won
    assert len(ranked) == 3
    made = len(runs.runs)
    assert _same(v.ranked(), ranked) and len(runs.runs) == made  # nothing run again
    v.add([_off(T, 6, rot_y)])  # a second look's start: rank 3
    assert runs.runs[made] == (3, 1, 2)
    assert len(v.ranked()) == 4
    further = [r[0] for r in runs.runs if r[1:] == (2, 0)]
    assert len(further) == len(set(further))  # each start refined further once at most
    snapped = [r[0] for r in runs.runs if r[1:] == (1, GravityConfig().snap_iterations)]
    assert all(snapped.count(r) <= 2 for r in snapped)  # its first run's and its further one's


def test_without_keeping_the_best_every_start_gets_all_its_runs() -> None:
    job, _, T = _resting_scene()
    runs = Counting()
    v = Verification(job, RefinementConfig(keep_after_first=0), Plausibility(), runs)
    v.add([_off(T, d, rot_x) for d in (4, 7)])
    ranked = v.ranked()
    assert runs.runs == [(0, 2, 0), (1, 2, 0)]  # no gravity: nothing snapped
    assert ranked[0].score >= ranked[1].score and ranked[0].tilt == 0.0


def test_a_plausible_pose_ranks_first() -> None:
    """A refined start within the priors (resting, in the protocol's in-plane range) wins over a
    better-scoring one that is not; among equals the score decides."""
    from perception.verification import rank_verified

    def v(score: float, plausible: bool, rank: int) -> Verified:
        return Verified(np.eye(4), score, score, 0.0, 0.0, "codebook", rank, 0.0, plausible)

    flipped, resting, other = v(1.2, False, 1), v(1.1, True, 2), v(0.9, True, 3)
    assert [x.rank for x in rank_verified([flipped, other, resting])] == [2, 3, 1]
    assert [x.rank for x in rank_verified([flipped, v(1.0, False, 4)])] == [1, 4]


def test_parts_pickle_with_what_they_draw() -> None:
    """A job's parts travel to the worker as data: the pieces, colours and the planes that
    order them."""
    import pickle

    parts = ConvexParts().parts(NAME)
    back: Parts = pickle.loads(pickle.dumps(parts))
    assert back.name == NAME and len(back.pieces) == len(parts.pieces)
    assert np.array_equal(back.separations.normal, parts.separations.normal)
    assert np.array_equal(back.stacked[0], parts.stacked[0])
