"""The BOP route of an evaluation: grasp on the poses of a BOP results CSV in exactly the episodes
of the export it answers (``python -m sim.evaluate --poses CSV --from DIR``), and say where the
poses came from and whether they belong to these episodes at all."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from posegrasp.core.files import sha256_file
from sim.evaluation.bop_results import BopPosesEstimator, time_summary, truth_match
from sim.evaluation.protocol import Protocol


def poses_estimator(csv_path: Path, export: Path) -> BopPosesEstimator:
    """The estimator that answers each episode of the export at `export` with its rows of the
    CSV at `csv_path` (`sim.evaluation.bop_results.BopPosesEstimator`), named ``bop:<csv
    name>@<first 12 hex digits of its SHA-256>``.

    Raises:
        InvalidArgumentError, AssetError: an export or a CSV that cannot be read, or a CSV that
            answers another export (`sim.evaluation.bop_results`).
    """
    estimator = BopPosesEstimator(csv_path, export)
    estimator.name = f"bop:{Path(csv_path).name}@{sha256_file(csv_path)[:12]}"
    return estimator


def export_protocol(estimator: BopPosesEstimator, **settings: Any) -> Protocol:
    """The protocol of the export's episodes (its objects, episodes, seed start, tier and the
    scene shifts its images were rendered under), with the episode `settings` given
    (`Protocol`'s ``margin``, ``obs_mode``, ``task``, ...)."""
    export = estimator.export
    return Protocol(
        objects=tuple(export.objects),
        episodes=export.episodes,
        seed_start=export.seed_start,
        tier=export.tier,
        **{"shifts": export.shifts, **settings},
    )


def poses_record(estimator: BopPosesEstimator, csv_path: Path, report: dict) -> dict[str, Any]:
    """Where the poses of a ``--poses`` run came from (the CSV and its hash, the export), how many
    of the export's targets the CSV had a row for, the method's time per image from the CSV's
    ``time`` column (`sim.evaluation.bop_results.time_summary`), and whether the poses belong to
    these episodes at all (``truth_match``, `sim.evaluation.bop_results.truth_match`)."""
    eps = report["episodes"]
    times = [(e.get("estimate_info") or {}).get("time") for e in eps]
    return {
        "csv": str(csv_path),
        "csv_sha256": sha256_file(csv_path),
        "export": str(estimator.export.root),
        "targets": len(eps),
        "targets_with_a_row": sum(e.get("T_C_O_est") is not None for e in eps),
        **time_summary([t for t in times if isinstance(t, (int, float))]),
        "truth_match": truth_match(eps),
    }


def format_poses_record(record: dict[str, Any]) -> str:
    """A `poses_record` as text: the targets with a row and the time per image, then a warning
    when the poses look made for other scenes."""
    timed = (
        f"time per image median {record['time_s_median']:.3g} s, 90th percentile "
        f"{record['time_s_p90']:.3g} s ({record['images_timed']} images timed)"
        if record["images_timed"]
        else "no time given"
    )
    rows = [
        f"BOP route: {record['targets_with_a_row']} of {record['targets']} targets had a row in "
        f"{record['csv']}; {timed}"
    ]
    match = record["truth_match"]
    if match["unrelated"]:
        rows.append(
            f"warning: only {match['nearest_own']} of {match['estimates']} estimates lie "
            f"nearest their own episode's target ({match['chance']:.1f} expected of poses "
            f"made for other scenes, chance {match['p_value']:.2g}): does {record['csv']} "
            f"answer another export than {record['export']}, or are its poses far off?"
        )
    return "\n".join(rows)
