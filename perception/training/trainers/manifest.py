"""The manifest of the shipped weights (``perception/weights/manifest.json``): one JSON object
whose keys (``pose_nets``, ``detector``, ...) each exporter and ``tables --record`` update."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from perception.integrity import MANIFEST_NAME, manifest_entries
from posegrasp.core.errors import AssetError
from posegrasp.core.files import atomic_write_json, sha256_file

__all__ = [
    "MANIFEST_NAME",
    "read_manifest",
    "shipped_entry",
    "shipped_stages",
    "stage_record",
    "weights_entry",
    "write_manifest",
]


def read_manifest(path: Path) -> dict[str, Any]:
    """The manifest at `path`; empty when there is none yet.

    Raises:
        AssetError: the file is not valid JSON.
    """
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text())
    except ValueError as exc:
        raise AssetError(f"{path} is not valid JSON ({exc}); fix or delete it") from exc


def weights_entry(path: Path) -> dict[str, Any]:
    """The identity of a shipped weights file as its manifest entry records it: ``file`` (name),
    ``bytes`` and ``sha256`` (which `perception.integrity.verify_weights` checks at load)."""
    return {"file": path.name, "bytes": path.stat().st_size, "sha256": sha256_file(path)}


def stage_record(entry: dict[str, Any]) -> dict[str, Any]:
    """What a manifest entry's ``stages`` keep of one training stage (its recipe stage's name,
    ``stage``, when the entry names one)."""
    keys = ("command", "data_seeds", "epochs_done", "wall_s", "validation", "trained_at_commit")
    named = {"stage": entry["stage"]} if "stage" in entry else {}
    return named | {k: entry.get(k) for k in keys}


def shipped_entry(path: Path) -> dict[str, Any] | None:
    """The manifest entry beside `path` that records it, when its bytes are the ones recorded;
    None for any other file."""
    entry = manifest_entries(read_manifest(path.parent / MANIFEST_NAME)).get(path.name)
    if entry is None or entry.get("sha256") != sha256_file(path):
        return None
    return entry


def shipped_stages(path: Path) -> list[dict[str, Any]] | None:
    """The training stages the manifest beside `path` records for it, when `path` is a shipped
    pose net whose bytes are the ones recorded (so a fine-tune from it keeps its history);
    None for any other file."""
    entry = shipped_entry(path)
    return None if entry is None else entry.get("stages")


def write_manifest(path: Path, manifest: dict[str, Any]) -> None:
    """Write the manifest (sorted keys, one-space indent) atomically (`posegrasp.core.files`)."""
    atomic_write_json(path, manifest)
