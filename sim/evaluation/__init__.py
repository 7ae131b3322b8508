"""Evaluation as a library: success over many seeded episodes of one `Protocol`.

One job per module, top to bottom:

- `harness`: `evaluate_protocol` runs a `Protocol`'s episodes on a backend, journaled, and hands
  them to the report: the one way into an evaluation, for the commands, the gate, the
  leaderboard, the studies, the benches and a user's own code;
- `aggregate`: `make_report`, the aggregates per object and overall (`group_summary`,
  `bop_scores`);
- `summary`: `format_report`, the report as text, with `failure_notes`;
- `plots`: `plot_success_vs_error`;
- `bop_route`: grasping on the poses of a BOP results CSV (`poses_estimator`,
  `export_protocol`, `poses_record`);
- `protocol`: `Protocol`, what defines the results, and `run_protocol`, its journal record.

``python -m sim.evaluate`` is the command line over it. Importing this package runs nothing and
loads neither matplotlib nor the estimators' nets.
"""

from __future__ import annotations

from sim.evaluation.aggregate import IMAGE_WIDTH, bop_scores, group_summary, make_report
from sim.evaluation.bop_route import (
    export_protocol,
    format_poses_record,
    poses_estimator,
    poses_record,
)
from sim.evaluation.harness import (
    EpisodeJob,
    EstimatorRef,
    cached_estimator,
    estimator_label,
    evaluate_protocol,
    run_job,
)
from sim.evaluation.plots import COMPONENTS, plot_success_vs_error
from sim.evaluation.protocol import Protocol, run_protocol
from sim.evaluation.summary import NOTE_CHARS, NOTES_SHOWN, failure_notes, format_report

__all__ = [
    "COMPONENTS",
    "IMAGE_WIDTH",
    "NOTES_SHOWN",
    "NOTE_CHARS",
    "EpisodeJob",
    "EstimatorRef",
    "Protocol",
    "bop_scores",
    "cached_estimator",
    "estimator_label",
    "evaluate_protocol",
    "export_protocol",
    "failure_notes",
    "format_poses_record",
    "format_report",
    "group_summary",
    "make_report",
    "plot_success_vs_error",
    "poses_estimator",
    "poses_record",
    "run_job",
    "run_protocol",
]
