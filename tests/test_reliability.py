"""What guards the numbers cannot be fooled: recorded figures, weights hashes, atomic writes."""

from __future__ import annotations

import importlib
import importlib.util
import itertools
import json
import shutil
import sys
from pathlib import Path

import pytest
import torch

from perception import integrity
from perception.detector import Detector
from perception.hybrid import HybridPoseEstimator
from perception.nets import load_posenet
from perception.training import tables
from perception.training.shipping import record
from perception.training.trainers.checkpoints import save_atomically
from perception.training.trainers.manifest import write_manifest
from posegrasp.core import files
from posegrasp.core.backends import run_map
from posegrasp.core.cli import command, summary_stream, write_json
from posegrasp.core.errors import AssetError, InvalidArgumentError, UnknownNameError
from posegrasp.core.files import sha256_file
from posegrasp.core.paths import REPO_ROOT, WEIGHTS_DIR
from posegrasp.core.validate import (
    STDOUT,
    check_float,
    check_float_list,
    check_json_output,
    check_names,
    check_output_file,
    check_plot_path,
    check_seed,
    check_tolerance_curves,
    effective_workers,
    parse_intrinsics,
)
from posegrasp.world.objects import OBJECT_NAMES

MANIFEST = WEIGHTS_DIR / "manifest.json"


@pytest.fixture
def manifest_bytes() -> bytes:
    """The shipped manifest's bytes, to check that a refused command leaves them alone."""
    return MANIFEST.read_bytes()


@pytest.mark.parametrize(
    "argv, env, words",
    [
        (["--limit", "2"], {}, "--limit"),
        (["--dists", "headcam"], {}, "not every split"),
        (["--dists", "paper"], {}, "not every split"),
        (["--boxes", "detector", "--limit", "5"], {}, "--limit"),
        ([], {"POSEGRASP_DATA": "{tmp}"}, "POSEGRASP_DATA"),
        (["--weights", "{tmp}/posenet_ours.pt"], {}, "not shipped"),
        (["--boxes", "detector", "--detector", "{tmp}/detector.pt"], {}, "not the shipped"),
        ([], {"POSEGRASP_UNVERIFIED_WEIGHTS": "1"}, "POSEGRASP_UNVERIFIED_WEIGHTS"),
    ],
)
def test_record_refuses_anything_but_the_shipped_weights_on_full_splits(
    argv, env, words, tmp_path, monkeypatch, capsys, manifest_bytes
) -> None:
    shutil.copy(WEIGHTS_DIR / "posenet_ours.pt", tmp_path / "posenet_ours.pt")
    # The tests' own data folder is itself a refusal; each case names the one it tests.
    monkeypatch.delenv("POSEGRASP_DATA")
    for k, v in env.items():
        monkeypatch.setenv(k, v.format(tmp=tmp_path))
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert tables.main([*argv, "--record"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--record refused" in err[0] and words in err[0]
    assert MANIFEST.read_bytes() == manifest_bytes


def test_record_refuses_a_partial_test_split(monkeypatch) -> None:
    class Partial:
        def __init__(self, root, split) -> None:
            pass

        def __len__(self) -> int:
            return 6

    monkeypatch.setattr(record, "PoseDataset", Partial)
    with pytest.raises(AssetError, match="headcam test split has 6 images"):
        record.check_full_splits(["headcam"])


def test_record_command_names_only_the_weights_and_boxes() -> None:
    args = tables.ArgumentParser().parse_args([])
    args.weights, args.boxes = WEIGHTS_DIR / "posenet_paper.pt", "detector"
    assert record.record_command(args) == (
        "python -m perception.training.tables --weights perception/weights/posenet_paper.pt "
        "--boxes detector"
    )


@pytest.fixture
def weights_copy(tmp_path: Path) -> Path:
    """A copy of the shipped weights folder (weights and manifest)."""
    out = tmp_path / "weights"
    shutil.copytree(WEIGHTS_DIR, out)
    return out


def test_a_shipped_file_replaced_by_another_is_refused(weights_copy, monkeypatch) -> None:
    monkeypatch.delenv(integrity.UNVERIFIED_ENV, raising=False)
    load_posenet(weights_copy / "posenet_ours.pt")  # the copy matches its manifest
    shutil.copy(weights_copy / "posenet_paper.pt", weights_copy / "posenet_ours.pt")
    with pytest.raises(integrity.WeightsMismatchError) as exc:
        load_posenet(weights_copy / "posenet_ours.pt")
    msg = str(exc.value)
    assert "posenet_ours.pt" in msg and "\n" not in msg
    assert "verify=False" in msg and integrity.UNVERIFIED_ENV in msg
    with pytest.raises(integrity.WeightsMismatchError):
        HybridPoseEstimator.from_weights(
            weights_copy / "detector.pt", weights_copy / "posenet_ours.pt"
        )
    # Weights the user trained: the explicit overrides.
    assert load_posenet(weights_copy / "posenet_ours.pt", verify=False).cfg.variant == "paper"
    monkeypatch.setenv(integrity.UNVERIFIED_ENV, "1")
    assert load_posenet(weights_copy / "posenet_ours.pt").cfg.variant == "paper"


def test_detector_weights_are_checked_too(weights_copy, monkeypatch) -> None:
    monkeypatch.delenv(integrity.UNVERIFIED_ENV, raising=False)
    shutil.copy(weights_copy / "posenet_ours.pt", weights_copy / "detector.pt")
    with pytest.raises(integrity.WeightsMismatchError, match=r"detector\.pt"):
        Detector.from_weights(weights_copy / "detector.pt")


def test_unlisted_files_load_and_an_entry_without_hash_fails_closed(weights_copy) -> None:
    shutil.copy(weights_copy / "posenet_ours.pt", weights_copy / "mine.pt")
    assert load_posenet(weights_copy / "mine.pt").cfg.variant == "ours"
    manifest = json.loads((weights_copy / "manifest.json").read_text())
    del manifest["pose_nets"]["ours"]["sha256"]
    (weights_copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(integrity.WeightsMismatchError, match="without a sha256"):
        load_posenet(weights_copy / "posenet_ours.pt")
    (weights_copy / "manifest.json").write_text("{not json")
    with pytest.raises(AssetError, match="cannot read"):
        load_posenet(weights_copy / "posenet_ours.pt")


def test_shipped_manifest_hashes_match_and_each_file_is_hashed_once(tmp_path) -> None:
    from perception.training.trainers.masknet_trainer import PROTOCOLS

    manifest = json.loads(MANIFEST.read_text())
    entries = integrity.manifest_entries(manifest)
    # Every shipped file is listed, and nothing else.
    assert sorted(entries) == sorted(p.name for p in WEIGHTS_DIR.glob("*.pt"))
    assert sorted(entries) == [
        "detector.pt",
        "posenet_ours.pt",
        "posenet_ours_hard.pt",
        "posenet_paper.pt",
    ]
    for name, e in entries.items():
        assert sha256_file(WEIGHTS_DIR / name) == e["sha256"]
    # The paper protocol's detector and mask nets (the faucet has one of its own) have a folder
    # and a manifest of their own; the detector records its two stages (with the head camera's
    # images, then on its own).
    paper = WEIGHTS_DIR / "paper_protocol"
    entries = integrity.manifest_entries(json.loads((paper / "manifest.json").read_text()))
    names = sorted(p.name for p in paper.glob("*.pt"))
    assert sorted(entries) == names == ["detector.pt", "masknet.pt", "masknet_faucet.pt"]
    for name in names:
        assert sha256_file(paper / name) == entries[name]["sha256"]
        integrity.verify_weights(paper / name)
    stages = entries["detector.pt"]["stages"]
    assert "--also paper" in stages[0]["command"] and "--data data/paper" in stages[-1]["command"]
    assert "--protocol paper" in entries["masknet.pt"]["command"]
    assert entries["masknet.pt"]["data_seeds"]["sources"] == dict(PROTOCOLS["paper"].sources)
    assert "--expert faucet" in entries["masknet_faucet.pt"]["command"]
    assert PROTOCOLS["paper"].experts == ("faucet",)
    # So has hybrid-global's detector, fine-tuned on the tiers' scenes from the shipped one,
    # whose stages it records.
    tiers = WEIGHTS_DIR / "tiers"
    entries = integrity.manifest_entries(json.loads((tiers / "manifest.json").read_text()))
    # and its mask net, trained on the tiers' scenes.
    names = sorted(p.name for p in tiers.glob("*.pt"))
    assert sorted(entries) == names == ["detector.pt", "masknet.pt"]
    for name in names:
        integrity.verify_weights(tiers / name)
    stages = entries["detector.pt"]["stages"]
    assert "--also headcam_any-pose,headcam" in stages[-1]["command"]
    assert all(s["wall_s"] > 0 for s in stages)
    mask_net = entries["masknet.pt"]
    assert mask_net["command"].startswith("python -m perception.training.train_masknet")
    assert mask_net["wall_s"] > 0 and mask_net["validation"]["iou"] > 0.9
    # trained on what the trainer's tiers protocol names (the command `make weights` runs)
    assert mask_net["data_seeds"]["sources"] == dict(PROTOCOLS["tiers"].sources)
    # A budget on the weights in the repository: an estimator that ships nets of its own raises
    # it on purpose (hybrid-global-rooms and hybrid-global-unseen did), nothing else does.
    total = sum(p.stat().st_size for p in WEIGHTS_DIR.rglob("*.pt"))
    assert total <= 40e6, f"the shipped weights total {total / 1e6:.1f} MB, over 40 MB"
    f = tmp_path / "w.bin"
    f.write_bytes(b"abc")
    before = files._sha256.cache_info().misses
    first = sha256_file(f)
    assert sha256_file(f) == first and files._sha256.cache_info().misses == before + 1
    f.write_bytes(b"abcd")  # rewritten: hashed again
    assert sha256_file(f) != first


class _Boom:
    """Pickles into an error, half way through a save."""

    def __reduce__(self):
        raise AssetError("disk full")


def _no_temporaries(folder: Path) -> bool:
    return not [p for p in folder.iterdir() if p.name.endswith(".tmp")]


def test_a_failed_write_leaves_the_old_record_intact(tmp_path: Path) -> None:
    path = tmp_path / "report.json"
    write_json(path, {"successes": 60})
    old = path.read_bytes()

    def half(f) -> None:
        f.write(b'{"successes": 6')
        raise AssetError("disk full")

    with pytest.raises(AssetError):
        files.atomic_write(path, half)
    with pytest.raises(TypeError):
        write_json(path, {"successes": object()})
    assert path.read_bytes() == old and json.loads(old) == {"successes": 60}
    assert _no_temporaries(tmp_path)


def test_a_failed_checkpoint_save_leaves_the_old_checkpoint_intact(tmp_path: Path) -> None:
    path = tmp_path / "ckpt.pt"
    save_atomically({"step": 1, "w": torch.ones(3)}, path)
    old = path.read_bytes()
    with pytest.raises(AssetError):
        save_atomically({"step": 2, "w": torch.zeros(100_000), "bad": _Boom()}, path)
    assert path.read_bytes() == old and torch.load(path)["step"] == 1
    assert _no_temporaries(tmp_path)


def test_the_manifest_writer_is_atomic(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "manifest.json"
    write_manifest(path, {"pose_nets": {}})
    old = path.read_bytes()

    def no_rename(*args) -> None:
        raise OSError("rename failed")

    monkeypatch.setattr(files.os, "replace", no_rename)
    with pytest.raises(OSError):
        write_manifest(path, {"pose_nets": {"ours": {}}})
    assert path.read_bytes() == old and _no_temporaries(tmp_path)


# --- bounded inputs, one validator per concept --------------------------------------------------


def test_jobs_stream_lazily_into_the_pool() -> None:
    """An endless job stream: the pool takes windows of it, so the first results come back."""
    jobs = (-i for i in itertools.count())
    out = run_map(abs, jobs, workers=2, total=10**12)
    assert list(itertools.islice(out, 5)) == [0, 1, 2, 3, 4]
    out.close()


def test_workers_are_capped_by_jobs_and_cores_with_a_note() -> None:
    n, note = effective_workers(1000, 1)
    assert n == 1 and "using 1 worker(s), not 1000" in note
    assert effective_workers(1, 50) == (1, None)


@pytest.mark.parametrize(
    "check, args, words",
    [
        (check_seed, (-1,), "0..4294967295"),
        (check_seed, (2**32,), "0..4294967295"),
        (check_seed, (True,), "integers"),
        (check_seed, (2**32 - 5, "--seed-start", 10), "valid: 0..4294967286"),
        (check_names, ("phone,phone", OBJECT_NAMES, "object", "--objects"), "phone twice"),
        (check_names, ("", OBJECT_NAMES, "object", "--objects"), "comma list"),
        (check_names, ("teapot", OBJECT_NAMES, "object", "--objects"), "valid objects"),
        (check_output_file, ("out/", "--out"), "it is a folder"),
        (check_json_output, ("out/",), "invalid --json 'out/': it is a folder"),
        (check_float, (float("nan"), 0.0, 1.0, "--x"), "numbers 0..1"),
        (check_float, (True, 0.0, 1.0, "--x"), "numbers 0..1"),
        (check_float_list, ("0.5,x", 0.0, 1.0, "--x"), "invalid --x 'x'; valid: numbers 0..1"),
        (check_float_list, ("0.5,2", 0.0, 1.0, "--x"), "invalid --x 2.0; valid: numbers 0..1"),
        (check_plot_path, ("p.xyz",), ".png, .pdf, .svg"),
        (parse_intrinsics, ("1e30,1e30,320,240",), "within +-100000"),
        (parse_intrinsics, ("500,-500,320,240",), "positive focal lengths"),
        (parse_intrinsics, ("500,500,320",), "four numbers"),
        (
            check_tolerance_curves,
            ({"phone": {"ray_mm": {"levels": [0], "success_rate": [2]}}},),
            "python -m sim.tolerance",
        ),
    ],
)
def test_shared_validators_name_the_valid_range(check, args, words) -> None:
    with pytest.raises((InvalidArgumentError, UnknownNameError)) as exc:
        check(*args)
    assert words in str(exc.value) and "\n" not in str(exc.value)


CLI_REJECTIONS = [
    ("sim.run_episode", ["--seed", "-1"], "0..4294967295"),
    ("sim.run_episode", ["--out", "{file}/sub"], "is a file, not a folder"),
    ("sim.run_episode", ["--save", "{file}/sub"], "is a file, not a folder"),
    ("sim.run_episode", ["--tier", "nope"], "valid tiers: isolated"),
    ("sim.run_episode", ["--json", "out/"], "it is a folder"),
    ("sim.evaluate", ["--episodes", "99999999999"], "1..100000"),
    ("sim.evaluate", ["--seed-start", "-5"], "0..4294967295"),
    ("sim.evaluate", ["--objects", "phone,phone"], "phone twice"),
    ("sim.evaluate", ["--plot", "p.xyz"], ".png, .pdf, .svg"),
    ("sim.evaluate", ["--json", "out/"], "it is a folder"),
    ("sim.evaluate", ["--tolerance", "{file}"], "not a JSON file"),
    ("sim.evaluate", ["--workers", "1000"], "1..64"),
    ("sim.evaluate", ["--workers", "0"], "1..64"),
    ("sim.evaluate", ["--tier", "nope"], "valid tiers: isolated"),
    ("sim.evaluate", ["--noise", "1,1,1,1"], "noisy-oracle only"),
    ("sim.tolerance", ["--object", "car", "--objects", "phone"], "not allowed with"),
    ("sim.tolerance", ["--json", "dir/"], "it is a folder"),
    ("sim.tolerance", ["--plot", "p.xyz"], ".png, .pdf, .svg"),
    ("sim.tolerance", ["--seed-start", "-1"], "0..4294967295"),
    ("sim.tolerance", ["--workers", "0"], "1..64"),
    ("sim.tolerance", ["--tier", "nope"], "valid tiers: isolated"),
    ("sim.render_scene", ["--seed", "-2"], "0..4294967295"),
    ("sim.render_scene", ["--tier", "nope"], "valid tiers: isolated"),
    ("sim.gate", ["--workers", "0"], "1..64"),
    ("sim.gate", ["--write", "--baseline", "{file}/b.json"], "is a file, not a folder"),
    ("sim.compare", ["a.json", "b.json", "--boot", "5"], "100..100000"),
    ("sim.fit_success", ["--objects", "car,car"], "car twice"),
    ("sim.fit_success", ["--workers", "0"], "1..64"),
    ("sim.fit_success", ["--tier", "nope"], "valid tiers: isolated"),
    (
        "perception.training.datagen",
        ["--dist", "paper", "--split", "val", "--count", "1", "--preview", "sheet.xyz"],
        "valid suffixes: .png",
    ),
    (
        "perception.training.datagen",
        ["--dist", "paper", "--split", "val", "--count", "1", "--objects", "car,car"],
        "car twice",
    ),
    (
        "perception.training.datagen",
        ["--dist", "paper", "--split", "val", "--count", "1", "--workers", "0"],
        "1..64",
    ),
    (
        "perception.training.datagen",
        ["--dist", "headcam", "--split", "val", "--count", "1", "--tier", "nope"],
        "valid tiers: isolated",
    ),
    ("perception.training.overlays", ["--out", "o", "--images", "0"], "1..1000"),
    (
        "perception.training.overlays",
        ["--out", "o", "--image", "x.png", "--K", "1e30,1,1,1"],
        "within +-100000",
    ),
    ("perception.training.overlays", ["--images", "2"], "one of the arguments --out is required"),
    ("perception.training.tables", ["--dists", "paper,paper"], "paper twice"),
    ("perception.training.tables", ["--limit", "0"], "1..100000000"),
    ("perception.training.tables", ["--boxes", "magic"], "valid box sources: gt, detector"),
    ("perception.training.tables", ["--json", "out/"], "it is a folder"),
    ("perception.training.export", ["--plot", "curves.xyz"], ".png, .pdf, .svg"),
    ("posegrasp.world.resting", ["--seed", "-1"], "0..4294967295"),
]


@pytest.mark.parametrize("module, argv, words", CLI_REJECTIONS)
def test_every_cli_refuses_bad_input_in_one_line_before_any_work(
    module, argv, words, tmp_path, monkeypatch, capsys
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "file").write_text("not json")
    before = sorted(tmp_path.rglob("*"))
    main = importlib.import_module(module).main
    argv = [a.format(file=tmp_path / "file") for a in argv]
    try:
        status = main(argv)
    except SystemExit as exc:
        status = exc.code
    err = capsys.readouterr().err
    assert status == 2
    assert err.count("\n") == 1 and err.startswith("error: ") and words in err, err
    assert sorted(tmp_path.rglob("*")) == before  # nothing written


def _bench(name: str, monkeypatch):
    """A script of bench/ or studies/ as a module (neither is a package), registered while the
    test runs."""
    paths = [REPO_ROOT / folder / f"{name}.py" for folder in ("bench", "studies")]
    path = next(p for p in paths if p.exists())
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, name, module)  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


BENCH_REJECTIONS = [
    ("estimate_latency", ["--stages", "--tier", "hard"], "valid there: --seed"),
    ("estimate_latency", ["--random-weights"], "valid there: --estimator, --tier"),
    ("gate_power", ["--workers", "65"], "1..64"),
    ("noise_curves", ["--workers", "0"], "1..64"),
    ("noise_curves", ["--out", "{file}"], "a file, not a folder"),
    ("episode_speed", ["--tier", "nope"], "valid tiers: isolated"),
    ("sim_speed", ["--sim-seconds", "nan"], "numbers 0.01..3600"),
    ("datagen_speed", ["--workers", "0"], "1..64"),
    ("evaluate_speed", ["--estimator", "magic"], "valid estimators: oracle"),
    ("mask_choice", ["--estimator", "hybrid"], "valid estimators: hybrid-global,"),
    ("mask_choice", ["--images", "0"], "1..100000"),
    ("flip_ambiguity", ["--turns", "2,0"], "numbers 0.1..90"),
    ("flip_ambiguity", ["--plot", "f.txt"], "valid"),
]


@pytest.mark.parametrize("name, argv, words", BENCH_REJECTIONS)
def test_every_bench_refuses_bad_input_in_one_line(
    name, argv, words, tmp_path, monkeypatch, capsys
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "file").write_text("")
    main = _bench(name, monkeypatch).main
    assert main([a.format(file=tmp_path / "file") for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and words in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]  # nothing written


def test_a_command_returns_its_status_and_a_posegrasp_error_is_one_line(capsys) -> None:
    @command
    def refuses(argv: list[str] | None = None) -> int:
        raise AssetError("no weights in w/; run make weights")

    @command
    def parses(argv: list[str] | None = None) -> int:
        from posegrasp.core.cli import ArgumentParser

        p = ArgumentParser(prog="x")
        p.add_argument("--n", type=int, default=0)
        return p.parse_args(argv).n

    @command
    def breaks(argv: list[str] | None = None) -> int:
        raise KeyError("a bug")

    assert refuses([]) == 2
    assert capsys.readouterr().err == "error: no weights in w/; run make weights\n"
    assert parses(["--n", "3"]) == 3 and parses(["--help"]) == 0
    capsys.readouterr()
    assert parses(["--n", "x"]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    with pytest.raises(KeyError):  # a bug is not turned into a user error
        breaks([])
    assert refuses.__name__ == "refuses"


def test_json_to_standard_output_is_the_json_alone(tmp_path, capsys) -> None:
    assert check_json_output("-") == STDOUT and check_json_output(tmp_path / "r.json").name
    write_json(STDOUT, {"b": 1, "a": [0.5]})
    captured = capsys.readouterr()
    assert json.loads(captured.out) == {"a": [0.5], "b": 1} and captured.err == ""
    assert not list(tmp_path.iterdir())
    assert summary_stream(STDOUT) is sys.stderr
    assert summary_stream(tmp_path / "r.json") is sys.stdout and summary_stream(None) is sys.stdout
    write_json(tmp_path / "r.json", {"a": 1})
    assert capsys.readouterr().out == f"wrote {tmp_path / 'r.json'}\n"
    assert json.loads((tmp_path / "r.json").read_text()) == {"a": 1}


def test_evaluation_computes_a_learned_estimator_on_one_thread(monkeypatch) -> None:
    # The nets' sums depend on the thread count; one thread in every worker and in-process keeps
    # an episode's pose independent of the number of workers and the backend.
    import torch

    from sim.evaluation import harness

    before = torch.get_num_threads()
    monkeypatch.setattr(harness, "make_estimator", lambda name, noise=None: (name, noise))
    harness.cached_estimator.cache_clear()
    try:
        torch.set_num_threads(2)
        assert harness.cached_estimator("hybrid") == ("hybrid", None)
        assert torch.get_num_threads() == 1
    finally:
        harness.cached_estimator.cache_clear()
        torch.set_num_threads(before)


@pytest.mark.slow
def test_hybrid_episodes_are_bit_identical_with_one_or_two_workers() -> None:
    # The whole chain with the shipped nets: same seeds, same poses to the last bit, however the
    # evaluation is spread over processes.
    from sim.evaluation import Protocol, evaluate_protocol

    protocol = Protocol(["phone", "chair"], 2, 1_200_000_000)
    runs = [evaluate_protocol(protocol, "hybrid", workers=w) for w in (1, 2)]
    keep = ("object", "seed", "success", "failure_reason", "pose_error", "T_C_O_est")
    one, two = ([{k: e.get(k) for k in keep} for e in r["episodes"]] for r in runs)
    assert len(one) == 4 and one == two
