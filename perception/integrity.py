"""Weights checked against the SHA-256 hashes of their manifest before they are loaded.

A weights file whose folder holds a ``manifest.json`` that lists the file's name (``"file"`` of an
entry, as the exporters write it) must have the entry's ``sha256``: a shipped file replaced by
another (``posenet_paper.pt`` copied over ``posenet_ours.pt``) is refused instead of loading
silently and grasping worse. Files that no manifest lists (training checkpoints, weights in
another folder) are loaded as they are.

Weights the user trained and put in place by hand are accepted with ``verify=False`` on the
loaders or with the environment variable ``POSEGRASP_UNVERIFIED_WEIGHTS=1``. Each file is hashed
once per process (`posegrasp.core.files.sha256_file`), so loading again costs nothing extra.

A shipped file that is missing or damaged is restored from git (the message names the command);
retraining (``make weights``) is the way only to new weights. `recording_loads` lists the files
loaded within a block: how a built-in estimator reports the weights it loads
(`perception.estimators.weights_files`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any

from posegrasp.core.errors import AssetError
from posegrasp.core.files import sha256_file
from posegrasp.core.paths import REPO_ROOT, WEIGHTS_DIR

MANIFEST_NAME = "manifest.json"
#: Set to 1 to load weights whose hash differs from their manifest's.
UNVERIFIED_ENV = "POSEGRASP_UNVERIFIED_WEIGHTS"

#: The list `recording_loads` fills, while one is active in this context.
_RECORDING: ContextVar[list[Path] | None] = ContextVar("posegrasp_weights_loads", default=None)


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


@contextmanager
def recording_loads() -> Iterator[list[Path]]:
    """Collect the weights files `load_checked` loads within the block.

    Yields:
        A list that gains each file's resolved path as it is loaded, once, in load order.
    """
    files: list[Path] = []
    token = _RECORDING.set(files)
    try:
        yield files
    finally:
        _RECORDING.reset(token)


def restore_hint(path: Path) -> str:
    """How to get a shipped weights file back from git ("" for a file outside the shipped
    weights folder), as the start of a message's advice."""
    path = Path(path).resolve()
    if not path.is_relative_to(WEIGHTS_DIR.resolve()):
        return ""
    rel = path.relative_to(REPO_ROOT.resolve()).as_posix()
    return f"restore the shipped file with `git checkout -- {rel}` (or `git restore {rel}`); "


def _override_hint(path: Path) -> str:
    return (
        f"{restore_hint(path) or 'restore the shipped file, '}retrain it (make weights), or, "
        f"for weights you trained, pass verify=False or set {UNVERIFIED_ENV}=1"
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
            f"{manifest_path} lists {Path(path).name} without a sha256; {_override_hint(path)}"
        )
    actual = sha256_file(path)
    if actual != expected:
        raise WeightsMismatchError(
            f"weights {path} do not match {manifest_path} (sha256 {actual[:12]}..., "
            f"recorded {expected[:12]}...); {_override_hint(path)}"
        )


def load_checked(path: Path, verify: bool, build: Callable[[dict], Any], what: str, hint: str):
    """Load a weights file the way every loader does: present, its hash checked
    (`verify_weights`), unpickled on the CPU and turned into a model by `build(state)`.

    Args:
        path: the weights file.
        verify: check the hash its folder's manifest records.
        build: makes the model from the file's dict; anything it raises means a bad file.
        what: what the file holds, for messages (e.g. "detector weights").
        hint: how to retrain the file, for messages (after the advice to restore a shipped
            file from git, `restore_hint`).

    Raises:
        AssetError: the file is missing or corrupt; the message says how to restore a shipped
            file, and how to retrain it.
        WeightsMismatchError: the manifest next to it records another hash.
    """
    import torch

    path = Path(path)
    restore = restore_hint(path)
    advice = f"{restore}to retrain it instead, {hint}" if restore else hint
    if not path.is_file():
        raise AssetError(f"{what} file {path} is missing; {advice}")
    verify_weights(path, verify)
    try:
        model = build(torch.load(path, map_location="cpu", weights_only=False))
    except Exception as exc:  # unpickling, missing keys or shape mismatches: a bad file
        raise AssetError(f"{what} file {path} is corrupt ({exc}); {advice}") from exc
    files = _RECORDING.get()
    if files is not None and path.resolve() not in files:
        files.append(path.resolve())
    return model
