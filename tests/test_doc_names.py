"""Docs that match the code: every config field (``SomeConfig.field.sub``) and every module path
(``sim.evaluation.harness.evaluate_protocol``, ``perception/peers/extra.py``) named in the docs,
the README, the guides and the code's own docstrings and comments exists in the code today.

The code is read as text (`ast`), nothing is imported: a name counts as existing when the module
defines it at its top level (a function, a class, an assignment or an import), and a config field
when its dataclass declares it (or a method or property of that name); a field whose type is
another config resolves on through it.
"""

from __future__ import annotations

import ast
import re
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("sim", "perception", "grasping", "posegrasp")
#: Where names are read: the prose, and the code whose docstrings and comments name things.
PROSE = ("README.md", "CONTRIBUTING.md", "docs/*.md", "studies/README.md", "bench/README.md")
CODE = ("sim", "perception", "grasping", "posegrasp", "studies", "bench", "examples")
#: History names what was, not what is.
LEFT_OUT = {"CHANGELOG.md"}

CONFIG_REF = re.compile(r"\b([A-Z][A-Za-z0-9]*Config)\.([a-z_][a-z0-9_]*(?:\.[a-z_][a-z0-9_]*)*)")
MODULE_REF = re.compile(
    r"`((?:sim|perception|grasping|posegrasp)(?:\.[A-Za-z_][A-Za-z0-9_]*)+)(?:\(\))?`"
)
FILE_REF = re.compile(r"`((?:sim|perception|grasping|posegrasp|studies|bench|examples)/[\w./-]+)`")


def _sources() -> list[Path]:
    out = [p for pattern in PROSE for p in sorted(REPO.glob(pattern))]
    for top in CODE:
        out += sorted((REPO / top).rglob("*.py"))
    return [p for p in out if p.name not in LEFT_OUT]


@cache
def _configs() -> dict[str, dict[str, set[str]]]:
    """Config class name -> attribute -> the config class names its annotation names (empty
    for a plain field, method or property); classes of one name are merged."""
    out: dict[str, dict[str, set[str]]] = {}
    for top in PACKAGES:
        for path in (REPO / top).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if not (isinstance(node, ast.ClassDef) and node.name.endswith("Config")):
                    continue
                attrs = out.setdefault(node.name, {})
                for item in node.body:
                    if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                        kinds = set(re.findall(r"\b[A-Z]\w*Config\b", ast.unparse(item.annotation)))
                        attrs.setdefault(item.target.id, set()).update(kinds)
                    elif isinstance(item, ast.FunctionDef | ast.AsyncFunctionDef):
                        attrs.setdefault(item.name, set())
    return out


def config_problem(cls: str, path: str) -> str | None:
    """Why ``cls.path`` names nothing the code has; None when it resolves."""
    configs = _configs()
    if cls not in configs:
        return None  # a class of another library, or named in passing
    owners = {cls}
    for part in path.split("."):
        found = [configs[o][part] for o in owners if o in configs and part in configs[o]]
        if not found:
            return f"{'/'.join(sorted(owners))} has no field {part!r}"
        owners = set().union(*found)
        if not owners:
            return None  # a plain value: what follows is its own attribute
    return None


@cache
def _top_names(module: Path) -> frozenset[str]:
    tree = ast.parse(module.read_text(encoding="utf-8"))
    names: set[str] = set()
    for node in tree.body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.add(node.name)
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name))
        elif isinstance(node, ast.Import | ast.ImportFrom):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
    return frozenset(names)


@cache
def _code_strings() -> frozenset[str]:
    """The string constants of the packages' code (an entry-point group's name, say)."""
    out: set[str] = set()
    for top in PACKAGES:
        for path in (REPO / top).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Constant) and isinstance(node.value, str):
                    out.add(node.value)
    return frozenset(out)


def module_problem(dotted: str) -> str | None:
    """Why a dotted path names no module, no top-level name of its module and no string the
    code holds; None when it does."""
    if dotted in _code_strings():
        return None
    parts = dotted.split(".")
    for k in range(len(parts), 0, -1):
        base = REPO.joinpath(*parts[:k])
        module = base.with_suffix(".py") if base.with_suffix(".py").is_file() else None
        if module is None and (base / "__init__.py").is_file():
            module = base / "__init__.py"
        if module is None:
            continue
        rest = parts[k:]
        if not rest:
            return None
        if rest[0] in _top_names(module) or (base.is_dir() and (base / rest[0]).exists()):
            return None
        return f"{'.'.join(parts[:k])} has no {rest[0]!r}"
    return f"no module {parts[0]}"


def _references(text: str) -> list[tuple[str, str]]:
    out = [("config", f"{c}.{p}") for c, p in CONFIG_REF.findall(text)]
    out += [("module", m) for m in MODULE_REF.findall(text)]
    out += [("file", f) for f in FILE_REF.findall(text)]
    return out


def _problem(kind: str, name: str) -> str | None:
    if kind == "config":
        cls, _, path = name.partition(".")
        return config_problem(cls, path)
    if kind == "module":
        return module_problem(name)
    path = name.rstrip("/.")
    if "*" in path or (REPO / path).exists():
        return None
    return "no such file"


def stale_names() -> list[str]:
    """Every name in `PROSE` and `CODE` that the code does not have, as ``file: name (why)``."""
    out = []
    for source in _sources():
        for kind, name in _references(source.read_text(encoding="utf-8")):
            if (why := _problem(kind, name)) is not None:
                out.append(f"{source.relative_to(REPO)}: {name} ({why})")
    return sorted(set(out))


def test_every_documented_name_exists_in_the_code() -> None:
    assert stale_names() == []


@pytest.mark.parametrize(
    "text",
    [
        "`GlobalConfig.min_score`",  # a flat field the config no longer has
        "GlobalConfig.detection.no_such_threshold",
        "`sim.evaluation.harness.evaluate`",  # a function that is gone
        "`sim.no_such_module`",
        "`perception/no_such_file.py`",
    ],
)
def test_a_planted_stale_name_is_found(text: str) -> None:
    assert [_problem(kind, name) for kind, name in _references(text)] != [None]
    assert all(_references(text))


def test_names_the_code_has_pass() -> None:
    text = (
        "`GlobalConfig.detection`, GlobalConfig.second_look, `sim.evaluation.evaluate_protocol`, "
        "`posegrasp.core.journal`, `perception/peers/extra.py`"
    )
    assert [_problem(kind, name) for kind, name in _references(text)] == [None] * 5
