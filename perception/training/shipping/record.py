"""Recording test figures in the weights' manifest (``perception.training.tables --record``).

The manifest holds the figures the project claims, so a record is refused unless it measures the
shipped weights (their hashes as the manifest records them) on the full shipped test splits in
the default data folder: no ``--limit``, no subset of ``--dists``, no ``$POSEGRASP_DATA``
elsewhere, no weights override. Each record carries its provenance: the command, the weights'
SHA-256, the commit and the image counts.
"""

from __future__ import annotations

from argparse import Namespace
from pathlib import Path

from perception.detector import DEFAULT_WEIGHTS
from perception.integrity import UNVERIFIED_ENV, verification_overridden
from perception.nets import VARIANTS
from perception.training.data.dataset import DISTS, PoseDataset
from perception.training.trainers.manifest import MANIFEST_NAME, read_manifest, write_manifest
from posegrasp.core.errors import AssetError, InvalidArgumentError
from posegrasp.core.files import sha256_file
from posegrasp.core.paths import DATA_ENV, REPO_ROOT, WEIGHTS_DIR, data_root, git_commit, in_repo

#: Averages the manifest keeps of each test split.
RECORD_KEYS = (
    "count",
    "center_px_mean",
    "center_256_px_mean",
    "center_crop_px_mean",
    "distance_pct_mean",
    "rotation_deg_mean",
    "rotation_deg_median",
    "outlier_rate",
    "invalid_rate",
    "iou_mean",
    "iou_acc_50",
    "add_recall",
    "add_s_recall",
)
#: Images of each shipped test split (`make data`).
SHIPPED_TEST_IMAGES = {"paper": 1000, "headcam": 500}
#: The splits a record covers, by kind of crop box.
RECORD_DISTS = {"gt": tuple(DISTS), "detector": tuple(DISTS)}


def _same(a: Path, b: Path) -> bool:
    return Path(a).resolve() == Path(b).resolve()


def check_record_request(args: Namespace, dists: list[str]) -> None:
    """Refuse a ``--record`` that is not the shipped weights on the full shipped test splits.

    Args:
        args: the parsed command line of ``perception.training.tables``.
        dists: the distributions it would evaluate.

    Raises:
        InvalidArgumentError: the first reason the figures would not be the shipped ones.
    """
    why = None
    shipped = [WEIGHTS_DIR / f"posenet_{v}.pt" for v in VARIANTS]
    full = RECORD_DISTS[args.boxes]
    if args.limit is not None:
        why = "--limit measures part of a split"
    elif sorted(dists) != sorted(full):
        why = f"--dists {','.join(dists)} is not every split; valid: {','.join(full)}"
    elif not _same(data_root(), REPO_ROOT / "data"):
        why = f"${DATA_ENV} points to {data_root()}, not the default data/"
    elif not any(_same(args.weights, w) for w in shipped):
        why = f"--weights {args.weights} is not shipped; valid: {', '.join(map(str, shipped))}"
    elif args.boxes == "detector" and not _same(args.detector, DEFAULT_WEIGHTS):
        why = f"--detector {args.detector} is not the shipped {DEFAULT_WEIGHTS}"
    elif verification_overridden():
        why = f"${UNVERIFIED_ENV} is set; the weights must match the manifest's hashes"
    if why is not None:
        raise InvalidArgumentError(f"--record refused: {why}")


def check_full_splits(dists: list[str]) -> None:
    """Raise AssetError unless each test split on disk has all its shipped images."""
    for d in dists:
        n = len(PoseDataset(data_root() / d, "test"))
        if n != SHIPPED_TEST_IMAGES[d]:
            raise AssetError(
                f"--record refused: the {d} test split has {n} images, the shipped one "
                f"{SHIPPED_TEST_IMAGES[d]}; regenerate it with `make data`"
            )


def record_command(args: Namespace) -> str:
    """The evaluation command, as the manifest records it."""
    parts = ["python -m perception.training.tables", f"--weights {in_repo(args.weights)}"]
    parts += [f"--boxes {args.boxes}"] if args.boxes != "gt" else []
    return " ".join(parts)


def record_in_manifest(
    report: dict, weights: Path, boxes: str, command: str, manifest_path: Path | None = None
) -> str:
    """Store a report's test averages in the manifest entry of the shipped `weights` (and, with
    detector boxes, the detection AP in the detector's entry). Returns the variant's name.

    Raises:
        AssetError: no manifest, or `weights` is not a shipped file it lists.
    """
    manifest_path = manifest_path or weights.parent / MANIFEST_NAME
    if not manifest_path.is_file():
        raise AssetError(
            f"no {manifest_path}; write it with `python -m perception.training.recipe --ship`"
        )
    manifest = read_manifest(manifest_path)
    nets = manifest.get("pose_nets", {})
    variant = next((v for v, e in nets.items() if e.get("file") == weights.name), None)
    if variant is None:
        raise AssetError(
            f"{weights.name} is not listed in {manifest_path}; --record works on shipped weights: "
            + ", ".join(e.get("file", "?") for e in nets.values())
        )
    splits = {d: {k: report[d]["average"][k] for k in RECORD_KEYS} for d in DISTS if d in report}
    provenance = {
        "command": command,
        "weights_sha256": sha256_file(weights),
        "commit": git_commit(),
    }
    if boxes == "gt":
        nets[variant]["test"] = {**provenance, **splits}
    else:
        nets[variant]["test_detector_boxes"] = {
            **provenance,
            **splits,
            "ratio_to_gt_boxes": report["detector_to_gt_ratio"],
        }
        summary = report["detection_summary"]
        detector_sha = sha256_file(weights.parent / DEFAULT_WEIGHTS.name)
        manifest.setdefault("detector", {})["test"] = {
            **provenance,
            "weights_sha256": detector_sha,
            "images": summary["images"],
            "overall": summary["overall"],
            "per_class": report["detection"],
            "missed": summary["missed"],
            **{
                d: {
                    "images": report[f"{d}_detection_summary"]["images"],
                    "overall": report[f"{d}_detection_summary"]["overall"],
                    "per_class": report[f"{d}_detection"],
                }
                for d in DISTS
                if f"{d}_detection_summary" in report
            },
        }
    write_manifest(manifest_path, manifest)
    return variant
