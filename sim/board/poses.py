"""The board's rows of methods run elsewhere: the poses of a BOP results CSV on an export of the
board's episodes (``--poses CSV EXPORT``), checked against the board (`poses_rows`), and what a
cell of one records as its settings (`poses_settings`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.files import sha256_file
from posegrasp.world.constants import EVAL_SEED_BASE


@dataclass(frozen=True)
class PosesRow:
    """A row of the board from a BOP results CSV: the poses of a method run elsewhere, on the
    episodes of the export the CSV answers.

    Attributes:
        name: the row's name, ``bop:<method>`` (the CSV's name up to its first underscore, as
            BOP names results files ``METHOD_DATASET-SPLIT.csv``).
        csv: the results CSV.
        export: the export folder of `sim.export_bop` that the CSV answers.
        tier, sensor: the export's tier and the sensor its images were rendered through.
    """

    name: str
    csv: str
    export: str
    tier: str
    sensor: str


def poses_rows(
    pairs: Sequence[Sequence[str]], objects: Sequence[str], episodes: int
) -> list[PosesRow]:
    """The CSV rows ``--poses CSV EXPORT`` gives, each checked against the board's episodes.

    Raises:
        InvalidArgumentError: an export that cannot be read, holds other episodes than the
            board's (objects, episodes per object, first seed), or two CSVs of one method for the
            same tier and sensor.
    """
    from sim.evaluation.bop_results import BopPosesEstimator

    rows: list[PosesRow] = []
    for csv, folder in pairs:
        export = BopPosesEstimator(csv, folder).export  # reads and checks both
        theirs = (list(export.objects), export.episodes, export.seed_start)
        ours = (list(objects), episodes, EVAL_SEED_BASE)
        if theirs != ours:
            raise InvalidArgumentError(
                f"the export {folder} holds {theirs[1]} episodes of {','.join(theirs[0])} from "
                f"seed {theirs[2]}, the board {ours[1]} of {','.join(ours[0])} from {ours[2]}; "
                f"export the board's: python -m sim.export_bop --tier {export.tier} --sensor "
                f"{export.sensor} --objects {','.join(ours[0])} --episodes {ours[1]} --out DIR"
            )
        name = "bop:" + Path(csv).stem.split("_")[0]
        row = PosesRow(name, str(csv), str(folder), export.tier, export.sensor)
        if any((r.name, r.tier, r.sensor) == (name, row.tier, row.sensor) for r in rows):
            raise InvalidArgumentError(
                f"two CSVs of {name} answer tier {row.tier} under sensor {row.sensor}; give one"
            )
        rows.append(row)
    return rows


def poses_settings(csv: str, export: str) -> dict:
    """What shapes a CSV row's results, as a cell records it: the CSV's and the export's map
    file's hashes."""
    from sim.evaluation.bop_results import MAP_FILE

    return {
        "weights": None,
        "settings": {
            "csv_sha256": sha256_file(Path(csv)),
            "export_map_sha256": sha256_file(Path(export) / MAP_FILE),
        },
    }
