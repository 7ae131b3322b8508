"""Weights checked against the SHA-256 hashes of their manifest before they are loaded.

A weights file whose folder holds a ``manifest.json`` that lists the file's name (``"file"`` of an
entry, as the exporters write it) must have the entry's ``sha256``: a shipped file replaced by
another (``posenet_paper.pt`` copied over ``posenet_ours.pt``) is refused instead of loading
silently and grasping worse. Files that no manifest lists (training checkpoints, weights in
another folder) are loaded as they are.

Weights the user trained and put in place by hand are accepted with ``verify=False`` on the
loaders or with the environment variable ``POSEGRASP_UNVERIFIED_WEIGHTS=1``. Each file is hashed
once per process (`posegrasp.core.files.sha256_file`), so loading again costs nothing extra.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from posegrasp.core.errors import AssetError
from posegrasp.core.files import sha256_file

MANIFEST_NAME = "manifest.json"
#: Set to 1 to load weights whose hash differs from their manifest's.
UNVERIFIED_ENV = "POSEGRASP_UNVERIFIED_WEIGHTS"


class WeightsMismatchError(AssetError):
    """A weights file whose SHA-256 is not the one its manifest records."""


def verification_overridden() -> bool:
    """True when ``$POSEGRASP_UNVERIFIED_WEIGHTS`` asks to skip the hash check."""
    return os.environ.get(UNVERIFIED_ENV, "").strip().lower() in ("1", "true", "yes")


def manifest_entries(manifest: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The manifest's weights entries by file name: top-level entries with a ``file`` (the
    detector) and those one level down (``pose_nets.<variant>``)."""
    out: dict[str, dict[str, Any]] = {}
    for value in manifest.values():
        if not isinstance(value, dict):
            continue
        children = [value] if "file" in value else list(value.values())
        for e in children:
            if isinstance(e, dict) and isinstance(e.get("file"), str):
                out[e["file"]] = e
    return out


def _override_hint() -> str:
    return (
        "restore the shipped file (git checkout perception/weights), re-export it "
        "(make weights), or, for weights you trained, pass verify=False or set "
        f"{UNVERIFIED_ENV}=1"
    )


def verify_weights(path: Path, verify: bool = True) -> None:
    """Check `path` against the hash its folder's manifest records for it.

    Args:
        path: a weights file (it must exist).
        verify: False skips the check (weights the user trained); so does `UNVERIFIED_ENV`.

    Raises:
        WeightsMismatchError: the manifest lists the file with another hash, or without one.
        AssetError: the manifest next to the file is not valid JSON.
    """
    if not verify or verification_overridden():
        return
    manifest_path = Path(path).parent / MANIFEST_NAME
    if not manifest_path.is_file():
        return
    try:
        manifest = json.loads(manifest_path.read_text())
    except (OSError, ValueError) as exc:
        raise AssetError(f"cannot read {manifest_path} ({exc}); fix or restore it") from None
    entry = manifest_entries(manifest if isinstance(manifest, dict) else {}).get(Path(path).name)
    if entry is None:
        return
    expected = entry.get("sha256")
    if not isinstance(expected, str):
        raise WeightsMismatchError(
            f"{manifest_path} lists {Path(path).name} without a sha256; {_override_hint()}"
        )
    actual = sha256_file(path)
    if actual != expected:
        raise WeightsMismatchError(
            f"weights {path} do not match {manifest_path} (sha256 {actual[:12]}..., "
            f"recorded {expected[:12]}...); {_override_hint()}"
        )


def load_checked(path: Path, verify: bool, build: Callable[[dict], Any], what: str, hint: str):
    """Load a weights file the way every loader does: present, its hash checked
    (`verify_weights`), unpickled on the CPU and turned into a model by `build(state)`.

    Args:
        path: the weights file.
        verify: check the hash its folder's manifest records.
        build: makes the model from the file's dict; anything it raises means a bad file.
        what: what the file holds, for messages (e.g. "detector weights").
        hint: how to rebuild the file, for messages.

    Raises:
        AssetError: the file is missing or corrupt; the message says how to rebuild it.
        WeightsMismatchError: the manifest next to it records another hash.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise AssetError(f"{what} file {path} is missing; {hint}")
    verify_weights(path, verify)
    try:
        return build(torch.load(path, map_location="cpu", weights_only=False))
    except Exception as exc:  # unpickling, missing keys or shape mismatches: a bad file
        raise AssetError(f"{what} file {path} is corrupt ({exc}); {hint}") from exc
