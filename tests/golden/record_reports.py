"""Record the golden reports: `python -m sim.evaluate` on held-out episodes, as a user runs it.

Each case (`CASES`) is one command line of ``python -m sim.evaluate`` on two objects x two
episodes from the default seed start (`posegrasp.world.constants.EVAL_SEED_BASE`): the default
estimator (``hybrid-global``) on every scene tier, ``oracle`` (with a distractor pool and depth),
``noisy-oracle`` with ``--noise``, a run with ``--margin``, and the BOP route (``python -m
sim.export_bop``, a results CSV of the export's ground truth, then ``--poses CSV --from DIR``).
Each command runs in a fresh process from the root of the ``sim`` package this script imports,
with the tests' data folder (``.test-data/``, where codebooks are cached) and an empty user
objects folder, as the tests run. For each case two files are written:

- ``<case>.json``: the ``--json`` report, `normalise`\\ d (wall times and paths left out);
- ``<case>.txt``: the summary the command printed, `mask`\\ ed (timing columns and the run's
  folder replaced by placeholders).

`tests/test_golden_reports.py` reruns the same commands and compares to the bit, so a
refactoring of the evaluation that changes no result is shown to change none. Run from the
commit whose reports are golden, e.g. in a separate worktree::

    git worktree add /tmp/golden HEAD
    cd /tmp/golden && PYTHONPATH=/tmp/golden python /path/to/tests/golden/record_reports.py

The estimates are those of this machine's CPU kernels, which differ from another processor's
in the last bits: the files go to this CPU kind's set (`golden_cpu.py`), with the kind noted.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

if str(Path(__file__).resolve().parent) not in sys.path:  # run as a script or loaded by a test
    sys.path.insert(0, str(Path(__file__).resolve().parent))
import golden_cpu as CPU

#: Where the golden files live.
GOLDEN_DIR = Path(__file__).resolve().parent / "reports"
#: The tests' own data folder (as ``tests/conftest.py``): the codebooks are cached there.
TEST_DATA = Path(__file__).resolve().parents[2] / ".test-data"
#: Two objects per case, two episodes each.
EPISODES = "2"
#: The BOP case's export (``sim.export_bop``): its objects and tier.
BOP_OBJECTS, BOP_TIER = "phone,car", "isolated"
#: ``sim.evaluate``'s arguments per case (``--json`` is added); ``bop`` grasps on the CSV of
#: its export's ground truth.
CASES: dict[str, list[str]] = {
    "hybrid-isolated": ["--objects", "phone,car", "--tier", "isolated"],
    "hybrid-clutter": ["--objects", "chair,pistol", "--tier", "clutter"],
    "hybrid-any-pose": ["--objects", "faucet,screen", "--tier", "any-pose"],
    "hybrid-far": ["--objects", "pistol,car", "--tier", "far"],
    "hybrid-hard": ["--objects", "phone,chair", "--tier", "hard"],
    "oracle": [
        "--objects",
        "faucet,phone",
        "--estimator",
        "oracle",
        "--tier",
        "clutter",
        "--pool",
        "car,chair,screen",
        "--obs-mode",
        "rgbd",
    ],
    "noisy-oracle": [
        "--objects",
        "car,screen",
        "--estimator",
        "noisy-oracle",
        "--noise",
        "10,10,5,5",
    ],
    "margin": [
        "--objects",
        "phone,pistol",
        "--estimator",
        "noisy-oracle",
        "--noise",
        "5,5,2,2",
        "--margin",
    ],
    "bop": [],
}
#: Report entries that vary from run to run, left out at any depth: wall times and the timings
#: they are made of (the report's, each episode's and its estimate info's).
VARYING_KEYS = frozenset(
    {"wall_s", "wall_ms", "timings_ms", "episode_wall_ms_median", "planning_ms_median"}
)
#: Entries of the BOP route's ``poses`` record that name paths of the run's own folder.
PATH_KEYS = frozenset({"csv", "export"})


def normalise(report: dict[str, Any]) -> dict[str, Any]:
    """A report with what legitimately varies between two runs of the same command left out:
    every `VARYING_KEYS` entry at any depth and the paths (`PATH_KEYS`) of ``poses``; everything
    else, floats included, is kept exactly."""

    def strip(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: strip(v) for k, v in value.items() if k not in VARYING_KEYS}
        if isinstance(value, list):
            return [strip(v) for v in value]
        return value

    out = strip(report)
    if "poses" in out:
        out["poses"] = {k: v for k, v in out["poses"].items() if k not in PATH_KEYS}
    return out


#: The summary's first line ends with the run's wall time.
_WALL = re.compile(r", \d+(?:\.\d+)? s wall$")
#: Whitespace-separated fields of a table row before its plan and episode times.
_ROW_FIELDS = 10


def mask(text: str, folder: Path) -> str:
    """A printed summary with the run's `folder` written ``<dir>``, the first line's wall time
    ``<s>``, and each table row's ``plan ms`` and ``ep ms`` columns ``<ms>``."""
    lines = text.replace(str(folder), "<dir>").splitlines()
    if lines:
        lines[0] = _WALL.sub(", <s> s wall", lines[0])
    in_table = False
    for i, line in enumerate(lines):
        if line.startswith("object "):
            in_table = True
            continue
        if in_table and line.startswith("pose right"):
            break
        if in_table:
            fields = list(re.finditer(r"\S+", line))
            cut, end = fields[_ROW_FIELDS - 1].end(), fields[_ROW_FIELDS + 1].end()
            lines[i] = f"{line[:cut]} {'<ms>':>8} {'<ms>':>7}{line[end:]}"
    return "\n".join(lines) + "\n"


def canonical(report: dict[str, Any]) -> str:
    """The JSON text two normalised reports are compared by (keys sorted, floats as Python
    writes them, which reads back to the same float)."""
    return json.dumps(report, indent=1, sort_keys=True, allow_nan=True) + "\n"


def source_root() -> Path:
    """The folder holding the ``sim`` package this interpreter imports: the commands run there."""
    spec = importlib.util.find_spec("sim")
    if spec is None or spec.origin is None:
        raise SystemExit("the sim package is not importable here")
    return Path(spec.origin).resolve().parent.parent


def _run(args: list[str], cwd: Path, env: dict[str, str]) -> str:
    """Run ``python -m <args>`` in `cwd`; its standard output, or an error with its stderr."""
    done = subprocess.run(
        [sys.executable, "-m", *args], cwd=cwd, env=env, capture_output=True, text=True
    )
    if done.returncode != 0:
        raise RuntimeError(f"python -m {' '.join(args)} failed:\n{done.stderr[-4000:]}")
    return done.stdout


def bop_csv(export: Path, path: Path) -> int:
    """A BOP 2019 results CSV of every object in every image of `export`, from its
    ``scene_gt.json`` (score 1, no time); returns the rows written."""
    rows = ["scene_id,im_id,obj_id,score,R,t,time"]
    for scene in sorted((export / "test").iterdir()):
        gt = json.loads((scene / "scene_gt.json").read_text())
        for im_id, objects in sorted(gt.items(), key=lambda kv: int(kv[0])):
            for o in objects:
                R = " ".join(f"{float(v):.9f}" for v in o["cam_R_m2c"])
                t = " ".join(f"{float(v):.6f}" for v in o["cam_t_m2c"])
                rows.append(f"{int(scene.name)},{int(im_id)},{o['obj_id']},1.0,{R},{t},-1")
    path.write_text("\n".join(rows) + "\n")
    return len(rows) - 1


def run_case(name: str, folder: Path) -> tuple[dict[str, Any], str]:
    """Run case `name` of `CASES` in `folder` (empty; the run's files go there).

    Returns:
        (the normalised report, the masked summary).
    """
    root = source_root()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(root), *filter(None, [env.get("PYTHONPATH")])])
    env["POSEGRASP_DATA"] = str(TEST_DATA)
    env["POSEGRASP_OBJECTS"] = str(folder / "user-objects")
    env["XDG_DATA_HOME"] = str(folder / "xdg")
    argv = list(CASES[name])
    if name == "bop":
        export, csv = folder / "export", folder / "truth.csv"
        _run(
            [
                "sim.export_bop",
                "--objects",
                BOP_OBJECTS,
                "--episodes",
                EPISODES,
                "--tier",
                BOP_TIER,
                "--out",
                str(export),
            ],
            root,
            env,
        )
        bop_csv(export, csv)
        argv = ["--poses", str(csv), "--from", str(export)]
    else:
        argv += ["--episodes", EPISODES]
    out = folder / "report.json"
    text = _run(["sim.evaluate", *argv, "--json", str(out)], root, env)
    return normalise(json.loads(out.read_text())), mask(text, folder)


def main(argv: list[str] | None = None) -> int:
    """Record the golden reports (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="folder of the files (default: this CPU kind's set in the golden folder)",
    )
    parser.add_argument(
        "--cases", default=",".join(CASES), help=f"comma list of: {', '.join(CASES)} (all)"
    )
    args = parser.parse_args(argv)
    names = args.cases.split(",")
    if unknown := [n for n in names if n not in CASES]:
        parser.error(f"unknown case {', '.join(unknown)}; cases: {', '.join(CASES)}")
    print(f"running sim.evaluate from {source_root()}", file=sys.stderr)
    out = args.out or CPU.default_out(GOLDEN_DIR)
    out.mkdir(parents=True, exist_ok=True)
    CPU.note_kind(out)
    for name in names:
        with tempfile.TemporaryDirectory(prefix="golden-report-") as tmp:
            report, text = run_case(name, Path(tmp))
        (out / f"{name}.json").write_text(canonical(report))
        (out / f"{name}.txt").write_text(text)
        print(f"{name}: {report['overall']['successes']}/{report['overall']['episodes']} grasped")
    print(f"{len(names)} case(s) written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
