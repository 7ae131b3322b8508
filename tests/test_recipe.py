"""The training recipe: each stage is what the shipped manifests record (command, data, seeds),
each stage's command line reruns it, a stage starts from a checkpoint and never from a shipped
file, and the smoke recipe trains every trainer, resumes and ships into a folder of its own while
the shipped weights stay as they are."""

from __future__ import annotations

import json
import shlex
from dataclasses import replace
from pathlib import Path

import pytest

from perception import integrity
from perception.detector import Detector
from perception.mask_net import MaskRefiner
from perception.nets import load_posenet
from perception.training import recipe as recipe_mod
from perception.training import train_detector, train_masknet, train_posenet
from perception.training.data.dataset import DISTS
from perception.training.data.rooms import folder_suffix
from perception.training.recipe import RECIPE, SMOKE
from perception.training.shipping.recipe_stages import (
    STAGE_FILE,
    TRAINERS,
    Artefact,
    Recipe,
    Stage,
    artefact_records,
    checkpoint_path,
    is_done,
    manifest_entry,
    run_stage,
    ship_all,
    stage_command,
    stage_config,
)
from posegrasp.core.errors import AssetError, InvalidArgumentError, UnknownNameError
from posegrasp.core.files import sha256_file
from posegrasp.core.paths import WEIGHTS_DIR

#: The modules of the recorded commands and the trainer each names (the first pose-net stages
#: were run when the trainer was ``perception.train``).
MODULES = {
    "perception.train": "posenet",
    "perception.training.train_posenet": "posenet",
    "perception.training.train_detector": "detector",
    "perception.training.train_masknet": "masknet",
}
#: Each trainer's command line.
COMMANDS = {"posenet": train_posenet, "detector": train_detector, "masknet": train_masknet}
#: What a run computes on, which no stage sets.
COMPUTE = {"workers", "threads", "device", "loss_log"}


def _parsed(command: str, trainer: str):
    """The config a recorded command line asks for, parsed by its trainer's own parser."""
    words = shlex.split(command)
    assert words[:2] == ["python", "-m"] and MODULES[words[2]] == trainer, command
    return COMMANDS[trainer].parse_config(words[3:])[0]


def _recorded_data(trainer: str, seeds: dict) -> dict[str, int]:
    """The training images of each folder, as a stage's record gives them."""
    if trainer == "posenet":
        assert all(s["train"][0] == 0 for s in seeds.values())  # the first images of each
        return {d: s["train"][1] - s["train"][0] for d, s in seeds.items()}
    if trainer == "detector":
        first = seeds["train_images"] - sum(seeds["also"].values())
        return {Path(seeds["dataset"]).name: first, **seeds["also"]}
    return dict(seeds["sources"])


def _check_stage(stage: Stage, record: dict, tmp_path: Path) -> None:
    """One recipe stage against its recorded stage."""
    got = _parsed(record["command"], stage.trainer)
    want = stage_config(stage, tmp_path)
    keys = {"epochs", "lr", "batch", "seed", "precision", "channels_last"}
    keys |= {"posenet": {"variant"}, "detector": set(), "masknet": {"val", "detected"}}[
        stage.trainer
    ]
    assert {k: getattr(got, k) for k in keys} == {k: getattr(want, k) for k in keys}, stage.name
    assert (got.init is None) == (stage.init is None), stage.name
    assert record.get("epochs_done", record.get("epochs")) == stage.epochs, stage.name
    seeds = record["data_seeds"]
    assert _recorded_data(stage.trainer, seeds) == dict(stage.data), stage.name
    if stage.trainer == "posenet":
        assert got.dists == tuple(name for name, _ in stage.data), stage.name  # their order
    else:
        assert seeds["seed"] == stage.seed, stage.name
    if stage.trainer == "masknet":
        assert seeds["val"] == dict([want.val]), stage.name
        assert seeds.get("detected") == (list(want.detected) if want.detected else None)


def test_every_stage_is_what_the_manifests_record(tmp_path) -> None:
    checked = set()
    for artefact in RECIPE.artefacts:
        pairs = artefact_records(RECIPE, artefact, WEIGHTS_DIR)
        chain = RECIPE.chain(artefact)
        # Every recorded stage is matched; the unrecorded ones are the first of the chain.
        assert len(pairs) == len(chain) - artefact.unrecorded > 0, artefact.file
        entry = manifest_entry(WEIGHTS_DIR, artefact)
        assert entry is not None and entry["sha256"] == sha256_file(WEIGHTS_DIR / artefact.file)
        for stage, record in pairs:
            _check_stage(stage, record, tmp_path)
            checked.add(stage.name)
    # The stages no manifest records: the head camera's detector from scratch, which every
    # detector's recorded history starts after.
    assert set(RECIPE.names()) - checked == {"detector-scratch-headcam"}
    # The paper protocol's mask-net stages cut their windows with the paper detector the recipe
    # names: its shipped hash is the one their records name.
    paper = next(a for a in RECIPE.artefacts if a.file == "paper_protocol/detector.pt")
    for artefact in RECIPE.artefacts:
        for stage, record in artefact_records(RECIPE, artefact, WEIGHTS_DIR):
            if stage.detector_stage() is not None:
                assert stage.detector_stage() == paper.stage
                assert record["data_seeds"]["detector_sha256"] == sha256_file(
                    WEIGHTS_DIR / paper.file
                )


def test_every_shipped_file_is_an_artefact_of_the_recipe() -> None:
    files = sorted(p.relative_to(WEIGHTS_DIR).as_posix() for p in WEIGHTS_DIR.rglob("*.pt"))
    assert sorted(a.file for a in RECIPE.artefacts) == files
    listed = []
    for manifest in WEIGHTS_DIR.rglob("manifest.json"):
        folder = manifest.parent.relative_to(WEIGHTS_DIR)
        entries = integrity.manifest_entries(json.loads(manifest.read_text()))
        listed += [(folder / name).as_posix() for name in entries]
    assert sorted(listed) == files


def test_a_stage_starts_from_a_checkpoint_never_a_shipped_file(tmp_path) -> None:
    for recipe, stage in [(r, s) for r in (RECIPE, SMOKE) for s in r.stages]:
        cfg = stage_config(stage, tmp_path)
        assert Path(cfg.out) == tmp_path / stage.name
        starts = [cfg.init] + ([cfg.detector] if stage.trainer == "masknet" else [])
        for path in (Path(p) for p in starts if p is not None):
            assert path.is_relative_to(tmp_path) and not path.is_relative_to(WEIGHTS_DIR)
        if stage.init is not None:
            assert Path(cfg.init) == checkpoint_path(recipe.stage(stage.init), tmp_path)
    masks = stage_config(RECIPE.stage("masknet-paper-detector-masks-10k"), tmp_path)
    assert masks.detector == tmp_path / "detector-tune-paper" / "detector.pt"
    assert masks.detected == ("paper", 30000, 10000)


def test_each_stages_command_line_reruns_it(tmp_path) -> None:
    """A stage's command (what the manifest records once the recipe ships it), parsed by its
    trainer, is the stage's very config: the trainers share one spelling of it."""
    for stage in RECIPE.stages:
        line = stage_command(stage, tmp_path)
        assert "--data " in line and "--dists" not in line and "--also" not in line
        want = stage_config(stage, tmp_path)
        got = _parsed(line, stage.trainer)
        assert replace(got, **{k: getattr(want, k) for k in COMPUTE if hasattr(want, k)}) == want
    # One vocabulary: every trainer takes these options.
    for trainer, module in COMMANDS.items():
        argv = ["--data", "headcam=3", "--epochs", "2", "--batch", "4", "--lr", "0.01"]
        argv += ["--seed", "7", "--precision", "bf16", "--channels-last"]
        argv += ["--init", "start.pt", "--out", str(tmp_path / trainer)]
        cfg = module.parse_config(argv)[0]
        assert (cfg.epochs, cfg.batch, cfg.lr, cfg.seed) == (2, 4, 0.01, 7), trainer
        assert (cfg.precision, cfg.channels_last, cfg.out) == ("bf16", True, tmp_path / trainer)
        assert Path(cfg.init).name == "start.pt"


def test_the_older_spellings_read_as_the_new() -> None:
    pose = COMMANDS["posenet"].parse_config
    assert (
        pose(["--dists", "headcam,paper", "--limit", "headcam=5"])[0]
        == pose(["--data", "headcam=5,paper"])[0]
    )
    assert pose([])[0].dists == DISTS
    detector = COMMANDS["detector"].parse_config
    old = detector(["--data", "x/headcam_hard", "--also", "headcam", "--limit", "7"])[0]
    assert old.limit == 7 and old.also == ("headcam",)
    new = detector(["--data", "headcam_hard=7,headcam=7"])[0]
    parts = TRAINERS["detector"].part_limits
    assert parts(old) == parts(new) == (7, 7)


@pytest.mark.parametrize(
    ("module", "argv", "words"),
    [
        ("posenet", ["--data", "headcam", "--dists", "paper"], "drop --dists and --limit"),
        ("posenet", ["--data", "studio=3"], "valid: paper, headcam"),
        ("posenet", ["--data", "headcam=0"], "NAME=N with N >= 1"),
        ("posenet", ["--data", "headcam,headcam"], "headcam twice"),
        ("posenet", ["--seed", "-1"], "invalid --seed -1"),
        ("detector", ["--data", "headcam,paper", "--also", "paper"], "drop --also"),
        ("masknet", ["--data", "paper"], "a count of every folder"),
        ("masknet", ["--val", "paper=3,headcam=2"], "--val wants one NAME=N"),
    ],
)
def test_the_trainers_refuse_bad_data_in_one_line(module, argv, words, capsys) -> None:
    assert COMMANDS[module].main(argv) == 2
    err = capsys.readouterr().err
    assert words in err and err.startswith("error: ") and len(err.strip().splitlines()) == 1


def test_a_recipe_refuses_what_it_cannot_run() -> None:
    a = Stage("a", "posenet", (("headcam", 3),), 1, 1e-3)
    with pytest.raises(UnknownNameError, match="valid trainers: posenet, detector, masknet"):
        Stage("a", "gan", (("headcam", 3),), 1, 1e-3)
    with pytest.raises(InvalidArgumentError, match=r"unknown settings.*valid: .*variant"):
        Stage("a", "posenet", (("headcam", 3),), 1, 1e-3, settings=(("colour", 1),))
    with pytest.raises(InvalidArgumentError, match="needs \\['b'\\], not before it"):
        Recipe((Stage("c", "posenet", (("headcam", 3),), 1, 1e-3, "b"),), ())
    with pytest.raises(InvalidArgumentError, match="twice"):
        Recipe((a, a), ())
    with pytest.raises(InvalidArgumentError, match="of its own trainer"):
        Recipe((a, Stage("d", "detector", (("headcam", 3),), 1, 1e-3, "a")), ())
    with pytest.raises(UnknownNameError, match="valid stages: a"):
        Recipe((a,), (Artefact("x.pt", ("x",), "b"),))


def test_the_dry_run_shows_each_stage_with_its_recorded_wall_time(tmp_path, capsys) -> None:
    assert recipe_mod.main(["--dry-run", "--checkpoints", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == len(RECIPE.stages) + 1
    for line, stage in zip(lines, RECIPE.stages, strict=False):
        assert stage.name in line and line.rstrip().split()[-1] != "done"
    final = next(line for line in lines if "ours-tune-headcam-160k-far-20k" in line)
    assert " 1.66 h " in final and "to do" in final  # 5990 s, as the manifest records
    assert lines[-1].startswith(f"0/{len(RECIPE.stages)} stages done")


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--only", "ours-ft40k"], "unknown stage 'ours-ft40k'; valid stages: ours-scratch"),
        (["--smoke", "--ship"], "needs --weights DIR"),
        (["--smoke", "--weights", str(WEIGHTS_DIR)], "never writes or reads"),
        (["--plot", "curves.txt"], ".png, .pdf, .svg"),
    ],
)
def test_the_recipe_command_refuses_in_one_line(argv, words, capsys) -> None:
    assert recipe_mod.main([*argv, "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert words in err and err.startswith("error: ") and len(err.strip().splitlines()) == 1


def _tree(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): sha256_file(p) for p in folder.rglob("*.*")}


@pytest.mark.slow
def test_the_smoke_recipe_trains_resumes_and_ships_into_its_own_folder(
    tmp_path, monkeypatch, capsys
) -> None:
    shipped = _tree(WEIGHTS_DIR)
    monkeypatch.setenv("POSEGRASP_DATA", str(tmp_path / "data"))
    checkpoints, weights = tmp_path / "data" / "checkpoints" / "smoke", tmp_path / "w"
    assert recipe_mod.main(["--smoke"]) == 0  # renders its data, trains every stage
    assert all(is_done(s, checkpoints) for s in SMOKE.stages) and not weights.exists()
    # A second run trains nothing: every stage is done.
    capsys.readouterr()
    assert recipe_mod.main(["--smoke", "--only", "pose-scratch"]) == 0
    assert capsys.readouterr().out.startswith("pose-scratch: done")
    # A stage changed in the recipe neither counts as done nor resumes another's checkpoint.
    changed = replace(SMOKE.stage("mask-scratch"), epochs=2)
    assert not is_done(changed, checkpoints)
    other = Recipe((changed,), ())
    with pytest.raises(AssetError, match="another version of stage mask-scratch"):
        run_stage(other, changed, checkpoints)
    # A stage that takes more images of a folder than are rendered is refused, naming it.
    folder = SMOKE.stage("mask-scratch").data[0][0]
    greedy = replace(SMOKE.stage("mask-scratch"), name="mask-greedy", data=((folder, 10**6),))
    with pytest.raises(AssetError, match=rf"more images than are rendered \({folder}: \d+ of"):
        run_stage(Recipe((greedy,), ()), greedy, checkpoints)
    assert not (checkpoints / "mask-greedy").exists()
    # Shipping is refused, and writes nothing, while a stage is not done.
    with pytest.raises(AssetError, match="not trained yet: pose-scratch, pose-tune-headcam"):
        ship_all(SMOKE, tmp_path / "empty", weights)
    assert not weights.exists()
    assert recipe_mod.main(["--smoke", "--ship", "--weights", str(weights)]) == 0
    for artefact in SMOKE.artefacts:
        entry = manifest_entry(weights, artefact)
        assert entry is not None and entry["stage"] == artefact.stage
        assert entry["sha256"] == sha256_file(weights / artefact.file)
        chain = [s.name for s in SMOKE.chain(artefact)]
        assert [s["stage"] for s in entry["stages"]] == chain
        assert entry["stages"][-1]["command"] == entry["command"]
        assert all(str(checkpoints) in s["command"] for s in entry["stages"][1:])  # --init
        integrity.verify_weights(weights / artefact.file)
    assert len(artefact_records(SMOKE, SMOKE.artefacts[0], weights)) == 2
    load_posenet(weights / "posenet_ours.pt")
    Detector.from_weights(weights / "detector.pt")
    MaskRefiner.from_weights(weights / "tiers" / "masknet.pt")
    # Shipping again leaves equal weights as they are, with the test figures recorded of them.
    manifest = json.loads((weights / "manifest.json").read_text())
    manifest["detector"]["test"] = {"box_ap": 0.5}
    (weights / "manifest.json").write_text(json.dumps(manifest))
    mtime = (weights / "detector.pt").stat().st_mtime_ns
    ship_all(SMOKE, checkpoints, weights)
    assert manifest_entry(weights, SMOKE.artefacts[1])["test"] == {"box_ap": 0.5}
    assert (weights / "detector.pt").stat().st_mtime_ns == mtime
    assert recipe_mod.main(["--smoke", "--plot", str(tmp_path / "curves.png")]) == 0
    assert (tmp_path / "curves.png").stat().st_size > 1000
    # The dry run reads the smoke manifests' wall times and finds every stage done.
    capsys.readouterr()
    assert recipe_mod.main(["--smoke", "--dry-run", "--weights", str(weights)]) == 0
    out = capsys.readouterr().out
    assert out.strip().splitlines()[-1].startswith(f"{len(SMOKE.stages)}/{len(SMOKE.stages)}")
    assert json.loads((checkpoints / "pose-scratch" / STAGE_FILE).read_text())["name"] == (
        "pose-scratch"
    )
    assert _tree(WEIGHTS_DIR) == shipped  # the shipped weights are untouched


def test_the_mask_net_trainer_records_its_own_argv(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("POSEGRASP_DATA", str(tmp_path / "data"))
    recipe_mod.render_smoke_data()
    weights = tmp_path / "w" / "masknet.pt"
    proto = replace(train_masknet.PROTOCOLS["tiers"], weights=weights)
    monkeypatch.setitem(train_masknet.PROTOCOLS, "tiers", proto)
    monkeypatch.setattr("sys.argv", ["pytest", "--something", "else"])
    argv = ["--data", "headcam=4", "--val", "headcam=2", "--epochs", "1", "--batch", "8"]
    argv += ["--out", str(tmp_path / "run"), "--export"]
    assert train_masknet.main(argv) == 0
    entry = json.loads((weights.parent / "manifest.json").read_text())["mask_net"]
    assert entry["command"] == f"python -m perception.training.train_masknet {shlex.join(argv)}"
    assert entry["data_seeds"]["sources"] == {"headcam": 4}
    assert entry["data_seeds"]["val"] == {"headcam": 2}


def test_make_data_renders_every_image_the_recipe_trains_on() -> None:
    text = (Path(__file__).resolve().parent.parent / "Makefile").read_text().replace("\\\n", " ")
    rendered: dict[tuple[str, str], int] = {}
    counts = (("DATA_COUNTS", ""), ("TIER_COUNTS", "headcam_"), ("ROOM_COUNTS", ""))
    for var, prefix in (*counts, ("BANK_COUNTS", "")):
        line = next(x for x in text.splitlines() if x.startswith(f"{var} :="))
        for spec in line.split(":=")[1].split():
            folder, split, count, *family = spec.split(":")
            if var == "ROOM_COUNTS":  # a tier's rooms, or the mixed scenes' ("-")
                folder = "headcam" if folder == "-" else f"headcam_{folder}"
                folder += folder_suffix(family[0])
            if var == "BANK_COUNTS":  # a bank's scenes in rooms (the training bank's: no name)
                folder = "headcam_bank" + ("" if folder == "training" else f"_{folder}")
                folder += folder_suffix(family[0])
            rendered[(prefix + folder, split)] = int(count)
    for stage in RECIPE.stages:
        needs = [((name, "train"), n) for name, n in stage.data]
        if detected := stage.setting("detected"):
            needs.append(((detected[0], "train"), detected[1] + detected[2]))
        if val := stage.setting("val"):
            needs.append(((val[0], "val"), val[1]))
        for key, n in needs:
            assert rendered.get(key, 0) >= n, (stage.name, key, n)
