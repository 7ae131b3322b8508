"""Every command says what it does: each module of sim/ and perception/ with a ``__main__``
block (``python -m ...``), and each such script of studies/, bench/ and examples/
(``python path.py``), answers ``--help`` with exit status 0, a description whose first paragraph
is whole sentences, and help text on every option.

The modules are found, not listed, so a new command is checked as soon as it exists. Each runs
in a subprocess under a probe that records the parser as argparse parses ``--help``, so the
check reads the options themselves rather than the layout of the printed help.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
#: Packages whose commands run as ``python -m package.module``.
MODULE_ROOTS = ("sim", "perception")
#: Folders whose commands run as scripts, ``python folder/name.py``.
SCRIPT_ROOTS = ("studies", "bench", "examples")
MAIN_BLOCK = re.compile(r"^if __name__ == ['\"]__main__['\"]:", re.M)
#: Commands run at once (the machine's two cores).
PARALLEL = 2

#: Runs a command with ``--help`` and appends each parser it parses with (description and
#: every action's names and help, subcommands' parsers included) to a JSON-lines file.
PROBE = r"""
import argparse, json, os, runpy, sys

target, record = sys.argv[1], sys.argv[2]
original = argparse.ArgumentParser.parse_known_args


def actions(parser):
    out = []
    for action in parser._actions:
        names = list(action.option_strings) or [action.dest]
        out.append({"names": names, "help": action.help})
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                out.append({"names": [choice.dest], "help": choice.help})
            for sub in action.choices.values():
                out.extend(actions(sub))
    return out


def parse_known_args(self, args=None, namespace=None):
    entry = {"prog": self.prog, "description": self.description, "actions": actions(self)}
    with open(record, "a") as f:
        f.write(json.dumps(entry) + "\n")
    return original(self, args, namespace)


argparse.ArgumentParser.parse_known_args = parse_known_args
sys.argv = [target, "--help"]
if target.endswith(".py"):
    sys.path[0] = os.path.dirname(os.path.abspath(target))
    runpy.run_path(target, run_name="__main__")
else:
    runpy.run_module(target, run_name="__main__", alter_sys=True)
"""


def commands() -> list[str]:
    """Every command: dotted module names of `MODULE_ROOTS`, script paths of `SCRIPT_ROOTS`
    (relative to the repository), each a file with a ``__main__`` block."""
    found = []
    for root in (*MODULE_ROOTS, *SCRIPT_ROOTS):
        for path in sorted((REPO / root).rglob("*.py")):
            rel = path.relative_to(REPO)
            if "__pycache__" in rel.parts or not MAIN_BLOCK.search(path.read_text()):
                continue
            if root in SCRIPT_ROOTS:
                found.append(rel.as_posix())
            elif path.name == "__main__.py":
                found.append(".".join(rel.parent.parts))
            else:
                found.append(".".join(rel.with_suffix("").parts))
    return found


def problems(command: str, tmp: Path) -> list[str]:
    """What is wrong with `command`'s ``--help``: a status other than 0, no usage printed, no
    parser, a parser without a description or with one cut mid-sentence, options without help
    text; [] when nothing."""
    record = tmp / (re.sub(r"[^\w.-]", "_", command) + ".jsonl")
    env = {**os.environ, "MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl"}
    proc = subprocess.run(
        [sys.executable, "-c", PROBE, command, str(record)],
        capture_output=True,
        text=True,
        cwd=REPO,
        env=env,
        timeout=300,
    )
    out = []
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-1:] or ["no output"]
        out.append(f"exit status {proc.returncode} ({tail[0]})")
    if not proc.stdout.startswith("usage:"):
        out.append("prints no usage")
    if not record.exists():
        return [*out, "parses no command line with argparse"]
    first = json.loads(record.read_text().splitlines()[0])
    lead = (first["description"] or "").strip().split("\n\n")[0].rstrip("`'\"")
    if not lead:
        out.append("no description")
    elif lead[-1] not in ".?!":
        out.append(f"a description cut mid-sentence (...{lead[-30:]!r})")
    bare = [
        "/".join(a["names"])
        for a in first["actions"]
        if a["help"] != argparse.SUPPRESS and not (a["help"] or "").strip()
    ]
    if bare:
        out.append("options without help: " + ", ".join(bare))
    return out


def test_the_commands_are_found() -> None:
    found = commands()
    for expected in (
        "sim.run_episode",
        "sim.grasp_vs_bop",
        "studies/sensor_check.py",
        "bench/sim_speed.py",
    ):
        assert expected in found
    assert "sim.episodes.registry" not in found  # a library module, no __main__ block


@pytest.mark.slow
def test_every_command_answers_help_with_a_description_and_help_on_every_option(
    tmp_path: Path,
) -> None:
    found = commands()
    with ThreadPoolExecutor(PARALLEL) as pool:
        results = list(pool.map(lambda c: problems(c, tmp_path), found))
    bad = [f"{c}: {'; '.join(p)}" for c, p in zip(found, results, strict=True) if p]
    assert not bad, "commands whose --help falls short:\n" + "\n".join(bad)
