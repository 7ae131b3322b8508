"""The manifest of the shipped weights (``perception/weights/manifest.json``): one JSON object
whose keys (``pose_nets``, ``detector``, ...) each exporter and ``tables --record`` update."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from sim.core.errors import AssetError

MANIFEST_NAME = "manifest.json"


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


def write_manifest(path: Path, manifest: dict[str, Any]) -> None:
    """Write the manifest (sorted keys, one-space indent) through a temporary file."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")
    tmp.replace(path)
