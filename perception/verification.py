"""One detection's pose hypotheses refined and scored, on this process or shared with a helper.

`perception.global_pose` refines a dozen or more starts per detection, each independently of
the others: render-and-compare refinement (`perception.refine`), then the verification scores
(`perception.codebook.verification_scores`). Those steps are many small array operations that
hold the interpreter, so threads do not share them; a second process does. A `VerifyJob` holds
everything one detection's starts are refined and scored against, `VerifyJob.run` does one
start, and a `VerifyHelper` runs every other start of a batch in a helper process while this
one runs the rest; it also matches the later half of a codebook's templates
(`perception.codebook.Codebook.match`). Each result is the same to the bit on either process,
so the estimate does not depend on how the work was shared.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from perception.codebook import Codebook, verification_scores
from perception.geometry import axes_from_p, ray_correction
from perception.refine import PoseRefiner, RefineConfig, RefineTarget
from perception.support import snap_to_resting
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.world.objects import ObjectModel

#: Compute threads of the helper's libraries: one each (this process runs on the other core).
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

#: Within this angle [deg] of the object's z axis the view's in-plane angle is not defined
#: (`inplane_deg`): a degree of viewpoint there turns it by many.
POLE_DEG = 10.0


@dataclass(frozen=True)
class Verified:
    """One refined, scored hypothesis.

    Attributes:
        T_C_O: the refined pose (4, 4).
        score: the verification score.
        iou: silhouette IoU with the visible mask.
        appearance: the colour correlation.
        edges: the share of the parts' outlines on image edges.
        source: ``codebook`` or ``nets``.
        rank: where the start came from: 0 the nets, i >= 1 the codebook's i-th hypothesis.
        tilt: rotation to the nearest resting pose [deg] (0 when the camera pose is unknown).
        plausible: within the job's priors (`VerifyJob.max_tilt` with the camera's pose,
            `VerifyJob.max_inplane_deg`); plausible poses rank first.
    """

    T_C_O: np.ndarray
    score: float
    iou: float
    appearance: float
    edges: float
    source: str
    rank: int
    tilt: float = 0.0
    plausible: bool = True


def rank_verified(verified: list[Verified]) -> list[Verified]:
    """Best first: the plausible ones (`Verified.plausible`) before the others, each group by
    decreasing score (ties keep their order)."""
    return sorted(verified, key=lambda v: (v.plausible, v.score), reverse=True)


def inplane_deg(T_C_O: np.ndarray) -> float | None:
    """|theta| of the pose's 4D representation (`perception.geometry.encode`) [deg], or None
    when the camera looks within `POLE_DEG` of the object's z axis (theta is not defined there)
    or the object is behind the camera. The virtual camera C' looks along the ray to the
    object's origin, so no K is needed (`perception.geometry.ray_correction`)."""
    t = T_C_O[:3, 3]
    if t[2] <= 0:
        return None
    R_Cv_O = ray_correction(t[0] / t[2], t[1] / t[2]).T @ T_C_O[:3, :3]
    if abs(R_Cv_O[2, 2]) >= math.cos(math.radians(POLE_DEG)):  # C''s axis in O
        return None
    x, y, _ = axes_from_p(-R_Cv_O[2])  # C' at -z in O, up to the scale axes_from_p drops
    return abs(math.degrees(math.atan2(float(R_Cv_O[0] @ y), float(R_Cv_O[0] @ x))))


class Start(NamedTuple):
    """One start to refine and score (`VerifyJob.run`).

    Attributes:
        T_C_O: the starting pose (4, 4).
        source: ``codebook`` or ``nets``, as the result carries it.
        rank: where the start came from (`Verified.rank`).
        passes: refiner runs.
        iterations: refiner steps per run (0: the job's full refiner).
        axis: turn only about this unit axis in the camera frame (None: any rotation).
    """

    T_C_O: np.ndarray
    source: str
    rank: int
    passes: int
    iterations: int = 0
    axis: np.ndarray | None = None


class _Parts:
    """The refiner's vertex source for a job: the object's parts as the job carries them."""

    def __init__(self, name: str, parts: list[np.ndarray]) -> None:
        self._name, self._parts = name, parts

    def pieces(self, name: str) -> list[np.ndarray]:
        if name != self._name:
            raise InvalidArgumentError(f"this job refines {self._name!r}, not {name!r}")
        return self._parts


@dataclass(frozen=True, eq=False)
class VerifyJob:
    """Everything one detection's starts are refined and scored against; it pickles, so a
    helper process runs its starts as this one would.

    Attributes:
        name: the object.
        parts: the refiner's vertices of each convex part in O [m]
            (`perception.refine.PoseRefiner.part_vertices`).
        pieces: the verification's pieces (the codebook source's).
        colours: RGB of each piece, (pieces, 3) in [0, 1].
        K: the intrinsics (3, 3) [px].
        rgb: the image (H, W, 3) uint8.
        mask: the detection's mask (H, W) bool.
        edge_distance: `perception.codebook.image_edges` of `box`.
        box: the window (x0, y0, x1, y1) [px] the verification draws in.
        target: the refiner's prepared target (`perception.refine.PoseRefiner.prepare`).
        refine: the full refiner's settings (a start's `iterations` shortens its runs).
        appearance_weight: weight of the colour correlation in the score.
        edge_weight: weight of the edge agreement in it.
        max_tilt: with the camera's rotation `R_W_C` and the object's resting poses, the
            largest tilt from resting [deg] a plausible pose may have (None: no such prior).
        R_W_C: the camera's rotation in the world (3, 3); needed with `max_tilt`.
        model: the object's model (its resting poses); needed with `max_tilt`.
        max_inplane_deg: the largest in-plane angle [deg] of a plausible pose (None: any).
    """

    name: str
    parts: list[np.ndarray]
    pieces: list[np.ndarray]
    colours: np.ndarray
    K: np.ndarray
    rgb: np.ndarray
    mask: np.ndarray
    edge_distance: np.ndarray
    box: tuple[int, int, int, int]
    target: RefineTarget
    refine: RefineConfig
    appearance_weight: float
    edge_weight: float
    max_tilt: float | None = None
    R_W_C: np.ndarray | None = None
    model: ObjectModel | None = None
    max_inplane_deg: float | None = None
    _refiners: dict[int, PoseRefiner] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_refiners"] = {}  # built again where the job runs
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)

    def steps(self, iterations: int) -> int:
        """Refiner steps per run of a start of `iterations` (0, or more than the full
        refiner's: the full refiner's)."""
        full = self.refine.iterations
        return full if iterations <= 0 or iterations >= full else iterations

    def _refiner(self, iterations: int) -> PoseRefiner:
        """The refiner of `steps(iterations)` steps per run, reading this job's parts."""
        steps = self.steps(iterations)
        if steps not in self._refiners:
            cfg = (
                self.refine
                if steps == self.refine.iterations
                else replace(self.refine, iterations=steps)
            )
            self._refiners[steps] = PoseRefiner(cfg, _Parts(self.name, self.parts))
        return self._refiners[steps]

    def run(self, start: Start) -> Verified | None:
        """`start` refined (`Start.passes` runs) and scored; None when a run finds it behind the
        camera (not a pose to verify)."""
        refiner = self._refiner(start.iterations)
        T, info = start.T_C_O, {"iou_after": 0.0}
        try:
            for _ in range(start.passes):
                T, info = refiner.refine_prepared(self.name, T, self.target, start.axis)
        except InvalidArgumentError:
            return None
        app, edges = verification_scores(
            self.pieces, self.colours, T, self.K, self.rgb, self.mask, self.edge_distance, self.box
        )
        iou = float(info["iou_after"])
        score = iou + self.appearance_weight * app + self.edge_weight * edges
        tilt, plausible = 0.0, True
        if self.max_tilt is not None:
            assert self.R_W_C is not None and self.model is not None
            tilt = snap_to_resting(self.R_W_C @ T[:3, :3], self.model)[2]
            plausible = tilt <= self.max_tilt
        if self.max_inplane_deg is not None:
            roll = inplane_deg(T)
            plausible = plausible and (roll is None or roll <= self.max_inplane_deg)
        return Verified(T, score, iou, app, edges, start.source, start.rank, tilt, plausible)


def run_here(job: VerifyJob, starts: Sequence[Start]) -> list[Verified | None]:
    """Every start of `job` run on this process, in order."""
    return [job.run(s) for s in starts]


#: A framing of a detected mask as the codebook matches it: packed mask bits, packed hidden
#: pixels or None (`perception.codebook.MaskView`).
Framing = tuple[np.ndarray, np.ndarray | None]


def match_here(
    book: Codebook, framings: Sequence[Framing], templates: slice = slice(None)
) -> list[np.ndarray]:
    """Each framing's IoUs with the `templates` of `book` (`Codebook.match`), on this process."""
    return [book.match(bits, hidden, templates) for bits, hidden in framings]


class OnThisProcess:
    """`VerifyHelper`'s work, all of it on this process: what runs where no helper does."""

    @staticmethod
    def map(job: VerifyJob, starts: Sequence[Start]) -> list[Verified | None]:
        """Every start of `job` refined and scored, in order."""
        return run_here(job, starts)

    @staticmethod
    def match(book: Codebook, framings: Sequence[Framing]) -> np.ndarray:
        """Each framing's IoUs with every template of `book`, the framings' arrays joined."""
        return np.concatenate(match_here(book, framings))


#: What the helper does, by the name a request gives: with the object it holds and the
#: request's payload.
_OPERATIONS: dict[str, Callable[[Any, Any], Any]] = {
    "starts": run_here,
    "match": lambda book, payload: match_here(book, *payload),
}


def _serve(conn: Connection) -> None:
    """The helper process: answers each request (an operation, the slot of the object it
    works on, that object when it is new, the payload) with its result or the error it
    raised, until told to stop or its parent is gone."""
    import cv2
    import threadpoolctl

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    cv2.setNumThreads(1)
    threadpoolctl.threadpool_limits(limits=1)
    conn.send("ready")
    held: dict[str, Any] = {}
    while True:
        try:
            message = conn.recv()
        except EOFError:  # the parent has gone
            return
        if message is None:
            return
        op, slot, sent, payload = message
        if sent is not None:
            held[slot] = sent
        try:
            conn.send(("ok", _OPERATIONS[op](held[slot], payload)))
        except Exception as e:  # handed back, to be raised where the request was made
            conn.send(("error", e))


def _stop(process: subprocess.Popen, conn: Connection, pid: int) -> None:
    """Tell the helper to stop and wait for it briefly (from the process that started it only:
    a forked child leaves its parent's helper alone)."""
    if os.getpid() != pid:
        return
    try:
        conn.send(None)
        process.wait(timeout=2.0)
    except (OSError, ValueError, subprocess.TimeoutExpired):
        process.kill()
        process.wait()
    conn.close()


class VerifyHelper:
    """A helper process that shares the global estimator's work with this one: it matches the
    later half of a codebook's templates (`match`) and takes every other start of a batch
    (`map`) while this process does the rest. It starts in the background (a fresh interpreter
    that imports this module alone, so a caller's script is never run again); until it is
    ready, or after it has failed, this process does all of it, with the same results. It
    holds each object it works on (a job, an object's codebook) once sent.

    Raises:
        OSError, ValueError: the process cannot be started (it is handed one end of a socket
            pair, which needs a POSIX system).
    """

    def __init__(self) -> None:
        ours, theirs = socket.socketpair()
        env = dict(os.environ) | {name: "1" for name in _THREAD_VARIABLES}
        root = str(Path(__file__).resolve().parents[1])  # where `perception` is importable
        env["PYTHONPATH"] = os.pathsep.join(filter(None, (root, env.get("PYTHONPATH"))))
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-m", "perception.verification", str(theirs.fileno())],
                pass_fds=(theirs.fileno(),),
                env=env,
                stdin=subprocess.DEVNULL,
            )
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        self._conn = Connection(ours.detach())
        self._ready = False
        self._broken = False
        self._held: dict[str, Any] = {}  # by slot: what the helper holds
        self._pid = os.getpid()
        self._waiting = False  # a request sent whose reply was not read
        self._finalizer = weakref.finalize(self, _stop, self._process, self._conn, self._pid)

    def available(self) -> bool:
        """Whether the helper takes work now: ready, alive, in step with this process (no reply
        left unread by an interruption) and this process the one that started it (not a forked
        child)."""
        if self._waiting or os.getpid() != self._pid:
            self._broken = True
        if not (self._ready or self._broken):
            try:
                self._ready = self._conn.poll() and self._conn.recv() == "ready"
            except (EOFError, OSError):
                self._broken = True
        return self._ready and not self._broken

    def _shared(
        self,
        op: str,
        slot: str,
        obj: Any,
        payload: Any,
        mine: Callable[[], Any],
        theirs: Callable[[], Any],
    ) -> tuple[Any, Any]:
        """(`mine()` here, the helper's `op` on `obj` and `payload`) at the same time; when
        the helper cannot take it or dies, `theirs()` here instead (the same result)."""
        try:
            fresh = self._held.get(slot) is not obj
            self._waiting = True  # from the first byte sent: an interrupted send counts too
            self._conn.send((op, slot, obj if fresh else None, payload))
            self._held[slot] = obj
        except Exception:  # an object that does not pickle, or a helper gone: all done here
            self._broken = True
            return mine(), theirs()
        try:
            here = mine()
        finally:  # the helper's reply is read even when this process's share failed
            try:
                status, result = self._conn.recv()
                self._waiting = False
            except (EOFError, OSError):
                self._broken = True
                status, result = "ok", theirs()
        if status == "error":
            raise result
        return here, result

    def map(self, job: VerifyJob, starts: Sequence[Start]) -> list[Verified | None]:
        """Every start of `job` refined and scored, in order: every other one by the helper."""
        if len(starts) < 2 or not self.available():
            return OnThisProcess.map(job, starts)
        odd = list(starts[1::2])
        even = list(starts[0::2])
        mine, result = self._shared(
            "starts", "job", job, odd, lambda: run_here(job, even), lambda: run_here(job, odd)
        )
        return [mine[i // 2] if i % 2 == 0 else result[i // 2] for i in range(len(starts))]

    def match(self, book: Codebook, framings: Sequence[Framing]) -> np.ndarray:
        """Each framing's IoUs with every template of `book` (`Codebook.match`), the framings'
        arrays joined: the later half of the templates matched by the helper."""
        if not self.available():
            return OnThisProcess.match(book, framings)
        first, later = slice(0, len(book.rotations) // 2), slice(len(book.rotations) // 2, None)
        mine, result = self._shared(
            "match",
            f"book:{book.name}",
            book,
            (framings, later),
            lambda: match_here(book, framings, first),
            lambda: match_here(book, framings, later),
        )
        return np.concatenate([np.concatenate(pair) for pair in zip(mine, result, strict=True)])

    def close(self) -> None:
        """Stop the helper process."""
        self._finalizer()


if __name__ == "__main__":  # the helper process (`VerifyHelper`), on the socket it was handed
    _serve(Connection(int(sys.argv[1])))
