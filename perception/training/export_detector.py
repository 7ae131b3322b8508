"""Ship the detector: a training checkpoint -> ``perception/weights/detector.pt`` (float16 state
dict, model config, no optimiser state) and the ``detector`` entry of the weights' manifest.

Run by ``python -m perception.training.train_detector --export``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from perception.detector_net import (
    DetectorConfig,
    build_detector,
    count_parameters,
    state_dict_fp16,
)
from perception.training.checkpoints import read_checkpoint, save_atomically
from perception.training.manifest import (
    MANIFEST_NAME,
    read_manifest,
    stage_record,
    weights_entry,
    write_manifest,
)
from posegrasp.core.errors import AssetError
from posegrasp.core.paths import WEIGHTS_DIR

WEIGHTS_NAME = "detector.pt"
TRAIN_COMMAND = "python -m perception.training.train_detector"


def _command(tc: dict[str, Any]) -> str:
    """The training command of a run's train config (the options it changed)."""
    parts = [TRAIN_COMMAND]
    if tc.get("data"):
        parts.append(f"--data {tc['data']}")
    if tc.get("also"):
        parts.append(f"--also {','.join(tc['also'])}")
    if tc.get("init"):
        parts.append(f"--init {tc['init']}")
    if tc.get("limit"):
        parts.append(f"--limit {tc['limit']}")
    parts.append(f"--epochs {tc['epochs']}")
    if tc.get("batch") not in (None, 4):
        parts.append(f"--batch {tc['batch']}")
    if tc.get("lr") not in (None, 1e-3):
        parts.append(f"--lr {tc['lr']:g}")
    if tc.get("precision", "fp32") != "fp32":
        parts.append(f"--precision {tc['precision']}")
    if tc.get("channels_last"):
        parts.append("--channels-last")
    return " ".join([*parts, "--export"])


def _init_entry(init: str | None) -> dict[str, Any] | None:
    """The manifest entry of the shipped detector a run started from (`init`: a
    ``detector.pt`` whose folder's manifest records it), or None."""
    if not init or Path(init).name != WEIGHTS_NAME:
        return None
    manifest_path = Path(init).parent / MANIFEST_NAME
    if not manifest_path.is_file():
        return None
    entry = read_manifest(manifest_path).get("detector")
    return entry if isinstance(entry, dict) and entry.get("file") == WEIGHTS_NAME else None


def export_detector(checkpoint: Path, out_dir: Path = WEIGHTS_DIR) -> dict[str, Any]:
    """Write the shipped weights (float16 state dict, model config) and their manifest entry.

    Writes ``<out_dir>/detector.pt`` and updates the ``detector`` key of
    ``<out_dir>/manifest.json``, keeping every other key.

    Returns:
        The manifest entry.

    Raises:
        AssetError: missing or corrupt checkpoint, or a manifest that is not valid JSON.
    """
    if not checkpoint.is_file():
        raise AssetError(f"no detector checkpoint {checkpoint}; run {TRAIN_COMMAND} first")
    try:
        state = read_checkpoint(checkpoint)
        cfg = DetectorConfig.from_dict(state["model_config"])
        model = build_detector(cfg)
        model.load_state_dict(state["model"])
    except Exception as exc:
        raise AssetError(f"detector checkpoint {checkpoint} is corrupt ({exc})") from exc
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / WEIGHTS_NAME
    validation = state["history"][-1] if state["history"] else None
    shipped = {
        "kind": "detector",
        "model": state_dict_fp16(model),
        "model_config": cfg.to_dict(),
        "step": state["step"],
        "epoch": state["epoch"],
        "validation": validation,
        "commit": state["commit"],
    }
    save_atomically(shipped, path)
    tc = state["train_config"]
    entry = {
        **weights_entry(path),
        "parameters": count_parameters(model),
        "command": _command(tc),
        "train_config": tc,
        "data_seeds": state["data_seeds"],
        "epochs_done": state["epoch"],
        "wall_s": state.get("wall_s"),
        "validation": validation,
        "trained_at_commit": state["commit"],
    }
    previous = _init_entry(tc.get("init"))
    if previous is not None:  # fine-tuned from shipped weights: keep the stages that made them
        entry["stages"] = [
            *(previous.get("stages") or [stage_record(previous)]),
            stage_record(entry),
        ]
    manifest_path = out_dir / MANIFEST_NAME
    manifest = read_manifest(manifest_path)
    manifest["detector"] = entry
    write_manifest(manifest_path, manifest)
    return entry
