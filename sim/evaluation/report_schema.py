"""The evaluation report's JSON Schema: what ``python -m sim.evaluate --json`` writes, versioned
and shipped in the package (`SCHEMA_FILE`), and the reader that `sim.compare` and the gate use.

Every report names its schema in its ``schema`` field (`REPORT_SCHEMA`). A reader validates a
report against the schema before it trusts any field, and refuses one that does not conform in
one line naming the field. A field added to the schema without raising its number is optional
(the groups' ``risk_coverage``, the episodes' ``confidence``, ``vsd`` and ``sensor``), so reports
written before it still read.
"""

from __future__ import annotations

import functools
import json
import shlex
from pathlib import Path
from typing import Any

from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.journal import interrupted

#: The id of the schema reports are written in; its number rises when a field changes meaning or
#: a required field is added.
REPORT_SCHEMA = "posegrasp-evaluate-report-1"
#: The schema file, shipped in the package.
SCHEMA_FILE = Path(__file__).with_name("schemas") / f"{REPORT_SCHEMA}.schema.json"


@functools.cache
def report_schema() -> dict[str, Any]:
    """The schema, as a dict."""
    return json.loads(SCHEMA_FILE.read_text())


@functools.cache
def _validator():
    import jsonschema

    return jsonschema.Draft202012Validator(report_schema())


def _where(path: Any) -> str:
    """A JSON path as ``episodes[3].pose_error``."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "the top level"


def validate_report(report: Any, source: str = "the report") -> dict[str, Any]:
    """`report` when it conforms to the schema it names (only `REPORT_SCHEMA` is known).

    Raises:
        InvalidArgumentError: one line naming `source`, the field and what is wrong with it (a
            missing field is named as such).
    """
    if not isinstance(report, dict):
        raise InvalidArgumentError(f"{source} is not a report of python -m sim.evaluate --json")
    named = report.get("schema")
    if named != REPORT_SCHEMA:
        got = "names no schema" if named is None else f"names schema {named!r}"
        raise InvalidArgumentError(
            f"{source} {got}; this version reads {REPORT_SCHEMA} (rerun python -m sim.evaluate "
            "--json)"
        )
    errors = sorted(_validator().iter_errors(report), key=lambda e: list(map(str, e.path)))
    if not errors:
        return check_played(report, source)
    err = errors[0]
    where = _where(err.absolute_path)
    if err.validator == "required":
        missing = next((k for k in err.validator_value if k not in err.instance), "?")
        field = f"{where}.{missing}" if err.absolute_path else missing
        raise InvalidArgumentError(f"{source} lacks the field {field} ({REPORT_SCHEMA})")
    raise InvalidArgumentError(f"{source}: {where}: {err.message} ({REPORT_SCHEMA})")


def check_played(report: dict[str, Any], source: str = "the report") -> dict[str, Any]:
    """`report` when every episode in it was played to its outcome; runs before an interruption
    passed the episode's error handling recorded a stopped episode as a failed grasp
    (`posegrasp.core.journal.interrupted`), and such a report is no result.

    Raises:
        InvalidArgumentError: one line naming the first stopped episode and the command that
            redoes the run.
    """
    stopped = [e for e in report.get("episodes", []) if interrupted(e)]
    if not stopped:
        return report
    first = stopped[0]
    raise InvalidArgumentError(
        f"{source} holds {len(stopped)} episodes stopped by an interruption, not played "
        f"({first.get('object')} seed {first.get('seed')}: {(first.get('notes') or ['?'])[0]}); "
        f"redo the run: {redo_command(report, source if source.endswith('.json') else 'OUT.json')}"
    )


def redo_command(report: dict[str, Any], path: str = "REPORT.json") -> str:
    """The ``python -m sim.evaluate`` command that plays a report's episodes again, from what
    the report records (a BOP route's report: the same ``--poses`` and ``--from``)."""
    estimator = str(report.get("estimator"))
    if estimator.startswith("bop:"):
        args = ["--poses", "CSV", "--from", "EXPORT"]
    else:
        args = [
            "--estimator",
            estimator,
            "--objects",
            ",".join(report.get("per_object") or {}),
            "--episodes",
            str(report.get("episodes_per_object")),
            "--seed-start",
            str(report.get("seed_start")),
            "--tier",
            str(report.get("tier")),
        ]
        if report.get("noise") is not None:
            args += ["--noise", str(report["noise"])]
        if report.get("distractor_pool"):
            args += ["--pool", ",".join(report["distractor_pool"])]
        if report.get("candidates", "designed") != "designed":
            args += ["--candidates", str(report["candidates"])]
        if any(e.get("friction_margin") is not None for e in report.get("episodes", [])):
            args.append("--margin")
    if report.get("obs_mode", "rgb") != "rgb":
        args += ["--obs-mode", str(report["obs_mode"])]
    if report.get("sensor", "ideal") != "ideal":
        args += ["--sensor", str(report["sensor"])]
    return shlex.join(["python", "-m", "sim.evaluate", *args, "--json", path])


def read_report(path: Path | str) -> dict[str, Any]:
    """The report in file `path`, validated (`validate_report`).

    Raises:
        InvalidArgumentError: unreadable, not JSON, or not conforming, naming the file.
    """
    try:
        report = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise InvalidArgumentError(
            f"{path} is not a report of python -m sim.evaluate --json ({exc})"
        ) from None
    return validate_report(report, str(path))
