"""The layer rule and the house rules of the code (docs/DESIGN.md §2), checked."""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import grimp
import pytest

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("sim", "perception", "grasping", "posegrasp")
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")
#: Training, data generation and evaluation: never loaded by a user who only estimates poses.
OFFLINE_MODULES = re.compile(
    r"^(perception\.training(\..*)?|sim\.(evaluate|gate|tolerance|run_episode)|pycocotools(\..*)?)$"
)
#: Built-in exceptions a deliberate error must not be raised as (PosegraspError subclasses).
BUILTIN_ERRORS = {
    "Exception",
    "ValueError",
    "TypeError",
    "RuntimeError",
    "KeyError",
    "IndexError",
    "OSError",
    "IOError",
    "FileNotFoundError",
    "AssertionError",
}


def _source_files() -> list[Path]:
    out = []
    for pkg in (*PACKAGES, "bench", "studies"):
        out.extend(p for p in (REPO / pkg).rglob("*.py") if "__pycache__" not in p.parts)
    return sorted(out)


def _lint_imports(cwd: Path, pythonpath: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    return subprocess.run(
        [str(LINT_IMPORTS), "--no-cache"],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_import_contracts_hold() -> None:
    res = _lint_imports(REPO)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert "0 broken" in res.stdout


@pytest.mark.slow
@pytest.mark.parametrize(
    "module, bad_import",
    [
        ("posegrasp/world/constants.py", "import sim.episodes.episode"),  # the bottom reaching up
        ("posegrasp/core/errors.py", "import posegrasp.world.scene"),  # core reaching into world
        ("grasping/candidates.py", "import perception.geometry"),  # siblings meeting
        ("perception/hybrid.py", "import perception.training.data.dataset"),  # run time -> training
        ("perception/training/data/bop.py", "import perception.training.trainers.ddp"),  # data up
    ],
)
def test_import_contracts_catch_a_back_edge(tmp_path: Path, module: str, bad_import: str) -> None:
    """The same contracts fail on a copy of the tree with one forbidden import added."""
    for pkg in PACKAGES:
        shutil.copytree(REPO / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("*.pt"))
    shutil.copy(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    target = tmp_path / module
    target.write_text(target.read_text() + f"\n{bad_import}  # noqa\n")
    res = _lint_imports(tmp_path, pythonpath=tmp_path)
    assert res.returncode != 0
    assert "BROKEN" in res.stdout


def _strongly_connected(graph: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components of a directed graph."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            out.append(comp)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles_between_files() -> None:
    g = grimp.build_graph(*PACKAGES)
    graph = {m: set(g.find_modules_directly_imported_by(m)) & g.modules for m in g.modules}
    # A package's __init__ importing its own children is not a cycle between files.
    for m, deps in graph.items():
        graph[m] = {d for d in deps if not d.startswith(m + ".")}
    cycles = [sorted(c) for c in _strongly_connected(graph) if len(c) > 1]
    assert cycles == []


def _modules_loaded_by(code: str) -> set[str]:
    prog = textwrap.dedent(code) + "\nimport sys\nprint('\\n'.join(sorted(sys.modules)))\n"
    res = subprocess.run(
        [sys.executable, "-c", prog], capture_output=True, text=True, cwd=REPO, timeout=300
    )
    assert res.returncode == 0, res.stderr[-2000:]
    return set(res.stdout.split())


def test_the_runtime_estimator_loads_no_training_or_evaluation_code() -> None:
    loaded = _modules_loaded_by(
        """
        from perception import HybridPoseEstimator
        est = HybridPoseEstimator.from_weights()
        """
    )
    assert "perception.hybrid" in loaded and "perception.nets" in loaded
    assert sorted(m for m in loaded if OFFLINE_MODULES.match(m)) == []


def test_making_the_env_loads_no_training_or_evaluation_code() -> None:
    loaded = _modules_loaded_by(
        """
        import gymnasium
        import posegrasp
        env = gymnasium.make("posegrasp:GraspEval-v0", object="phone", width=64, height=48)
        env.reset(seed=0)
        env.close()
        """
    )
    assert "sim.episodes.episode" in loaded
    assert sorted(m for m in loaded if OFFLINE_MODULES.match(m)) == []


def _raised_builtins(path: Path, root: Path = REPO) -> list[str]:
    tree = ast.parse(path.read_text())
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Raise) and node.exc is not None:
            exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
            if isinstance(exc, ast.Name) and exc.id in BUILTIN_ERRORS:
                out.append(f"{path.relative_to(root)}:{node.lineno} raises {exc.id}")
    return out


def test_every_deliberate_error_is_a_posegrasp_error() -> None:
    hits = [h for p in _source_files() for h in _raised_builtins(p)]
    assert hits == []


def test_perception_all_is_honest() -> None:
    import perception

    missing = [name for name in perception.__all__ if not hasattr(perception, name)]
    assert missing == []
