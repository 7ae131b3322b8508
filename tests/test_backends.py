"""The parallel backends (`posegrasp.core.backends`): Ray gives the local pool's answers.

Same seeds, same per-episode results and the same data bytes on both backends; a Ray worker
killed mid-run has its chunk retried and the report stays complete and identical; an
unreachable cluster is one line within 30 s; a two-node cluster on this machine runs an
evaluation on both nodes and reports what the local backend reports.
"""

from __future__ import annotations

import functools
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import ray
from ray import cloudpickle
from ray.cluster_utils import Cluster

from perception.peers import extra
from perception.training.data.writer import WALL_TIME_FILE
from perception.training.datagen import main as datagen_main
from posegrasp.core.backends import default_chunk, run_map
from sim.evaluation import EpisodeJob, Protocol, evaluate_protocol, run_job

REPO = Path(__file__).resolve().parent.parent
OBJECTS = ["phone", "car"]
EPISODES = 2  # per object
SEED = 1_000_000_000
#: Small Ray start-ups: no dashboard, a small object store, explicit CPUs.
RAY_ARGS = {"include_dashboard": False, "object_store_memory": 100 * 2**20}

# Ray workers cannot import this file: its functions (the killing job) travel by value.
cloudpickle.register_pickle_by_value(sys.modules[__name__])


def _outcome(episode: dict) -> dict:
    """What both backends must agree on: everything but wall times and the node."""
    return {k: v for k, v in episode.items() if k not in ("wall_ms", "timings_ms", "node")}


def _stats(report: dict) -> dict:
    """The per-object and overall figures but the timings."""
    groups = {**report["per_object"], "overall": report["overall"]}
    return {
        n: {k: v for k, v in g.items() if not k.endswith("_ms_median")} for n, g in groups.items()
    }


def _evaluate(**kwargs) -> dict:
    return evaluate_protocol(Protocol(OBJECTS, EPISODES, SEED, "isolated"), "oracle", **kwargs)


@pytest.fixture(scope="module")
def local_report() -> dict:
    return _evaluate(workers=1)


def _files(root: Path) -> dict[str, bytes]:
    # Every file but the measured wall times.
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != WALL_TIME_FILE
    }


def _die_once(marker: str, job):
    """Kill this worker process the first time a job runs (the marker says it happened)."""
    if not os.path.exists(marker):
        Path(marker).touch()
        os.kill(os.getpid(), signal.SIGKILL)
    return run_job(job)


# --- without Ray -----------------------------------------------------------------------------


def test_results_come_in_job_order_locally() -> None:
    assert list(run_map(abs, [-3, 1, -2], workers=1)) == [3, 1, 2]
    assert list(run_map(abs, [-3, 1, -2], workers=1, with_node=True)) == [
        (3, None),
        (1, None),
        (2, None),
    ]
    assert default_chunk(1000, 2) == 16 and default_chunk(10, 2) == 1


def test_a_pool_of_two_workers_gives_the_same_episodes(local_report) -> None:
    pooled = _evaluate(workers=2)
    assert [_outcome(e) for e in pooled["episodes"]] == [
        _outcome(e) for e in local_report["episodes"]
    ]


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--backend", "spark"], "valid backends: local, ray"),
        (["--address", "127.0.0.1:6379"], "--address needs --backend ray"),
        (["--backend", "ray", "--address", "nohost"], "valid: host:port"),
    ],
)
def test_bad_backend_arguments_are_one_line(args: list[str], needle: str, capsys) -> None:
    from sim.evaluate import main

    assert main(["--objects", "phone", "--episodes", "1", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1


@pytest.mark.slow
def test_an_unreachable_cluster_is_one_line_within_30_s() -> None:
    cmd = [
        sys.executable,
        "-m",
        "sim.evaluate",
        "--objects",
        "phone",
        "--episodes",
        "1",
        "--estimator",
        "oracle",
        "--backend",
        "ray",
        "--address",
        "127.0.0.1:1",
    ]
    t = time.monotonic()
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=60)
    assert time.monotonic() - t < 30
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        "error: cannot reach a Ray cluster at 127.0.0.1:1 (Connection refused); start one with "
        "`ray start --head` and pass the address it prints"
    ]


# --- a Ray started by the command, then one started by the tests ------------------------------


@pytest.mark.slow
def test_datagen_writes_the_same_bytes_on_ray(tmp_path: Path) -> None:
    args = [
        "--dist",
        "paper",
        "--split",
        "val",
        "--count",
        "5",
        "--width",
        "96",
        "--height",
        "96",
        "--quiet",
    ]
    assert datagen_main([*args, "--out", str(tmp_path / "local")]) == 0
    assert (
        datagen_main([*args, "--out", str(tmp_path / "ray"), "--backend", "ray", "--workers", "2"])
        == 0
    )
    assert not ray.is_initialized()  # the Ray the command started is stopped
    local, on_ray = _files(tmp_path / "local"), _files(tmp_path / "ray")
    assert len(local) > 10 and on_ray == local


@pytest.fixture(scope="class")
def ray_session():
    ray.init(num_cpus=2, logging_level="ERROR", **RAY_ARGS)
    yield
    ray.shutdown()


@pytest.mark.slow
@pytest.mark.usefixtures("ray_session")
class TestOnALocalRay:
    """Two tests on one Ray session of 2 CPUs (`run_map` uses a session it finds)."""

    def test_same_episodes_as_the_local_backend(self, local_report: dict) -> None:
        report = _evaluate(workers=2, backend="ray")
        assert [_outcome(e) for e in report["episodes"]] == [
            _outcome(e) for e in local_report["episodes"]
        ]
        assert _stats(report) == _stats(local_report)
        assert all(isinstance(e["node"], str) for e in report["episodes"])
        assert all("node" not in e for e in local_report["episodes"])

    def test_a_killed_worker_is_retried(self, local_report: dict, tmp_path: Path) -> None:
        marker = tmp_path / "killed"
        protocol = Protocol(OBJECTS, EPISODES, SEED, "isolated")
        jobs = [EpisodeJob(o, seed, "oracle", protocol) for o, seed in protocol.seeds()]
        results = list(
            run_map(functools.partial(_die_once, str(marker)), jobs, backend="ray", chunk=2)
        )
        assert marker.exists()  # a worker died mid-run ...
        assert [_outcome(r) for r in results] == [  # ... and the report is complete and the same
            _outcome(e) for e in local_report["episodes"]
        ]

    @pytest.mark.skipif(
        not (extra.has_ppf() and extra.has_open3d()), reason="the extra peers is not installed"
    )
    def test_the_classical_peers_run_on_ray_as_in_the_local_pool(self) -> None:
        """Each library's peer (OpenCV's PPF, Open3D's FPFH) on Ray's workers: the same
        episodes as the local pool's (its detectors are trained again on each worker), the
        poses equal but for the last bits of Open3D's sums."""
        for name in ("ppf", "fpfh-icp"):
            local, on_ray = (
                evaluate_protocol(
                    Protocol(["phone", "pistol"], 1, SEED, obs_mode="rgbd"), name, workers=2, **kw
                )["episodes"]
                for kw in ({}, {"backend": "ray"})
            )
            for a, b in zip(local, on_ray, strict=True):
                keys = ("object", "seed", "estimator", "success", "failure_reason")
                assert [a[k] for k in keys] == [b[k] for k in keys]
                assert b["estimator"] == name and b["T_C_O_est"] is not None, b["notes"]
                np.testing.assert_allclose(b["T_C_O_est"], a["T_C_O_est"], rtol=0, atol=1e-9)


@pytest.mark.slow
def test_two_nodes_share_an_evaluation(local_report: dict) -> None:
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, **RAY_ARGS})
    try:
        cluster.add_node(num_cpus=1, object_store_memory=RAY_ARGS["object_store_memory"])
        cluster.wait_for_nodes()
        report = _evaluate(workers=1, backend="ray", address=cluster.address)
    finally:
        cluster.shutdown()
    assert len({e["node"] for e in report["episodes"]}) == 2  # each episode names its node
    assert [_outcome(e) for e in report["episodes"]] == [
        _outcome(e) for e in local_report["episodes"]
    ]
    assert _stats(report) == _stats(local_report)
