"""Where things live: the repository, its assets and shipped weights, and the data folder.

The data folder (datasets, training checkpoints) is outside git: ``$POSEGRASP_DATA`` when set,
else ``data/`` in the repository.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
SCENES_DIR = REPO_ROOT / "scenes"
WEIGHTS_DIR = REPO_ROOT / "perception" / "weights"
DOCS_DIR = REPO_ROOT / "docs"
#: The environment variable naming the data folder.
DATA_ENV = "POSEGRASP_DATA"


def data_root() -> Path:
    """Folder holding one dataset per distribution: $POSEGRASP_DATA, else data/ in the repo."""
    env = os.environ.get(DATA_ENV)
    return Path(env) if env else REPO_ROOT / "data"


def in_repo(path: Path | str) -> Path:
    """`path` relative to the repository when it lies inside it (as manifests record paths),
    else as it is, resolved."""
    p = Path(path).resolve()
    return p.relative_to(REPO_ROOT) if p.is_relative_to(REPO_ROOT) else p


def checkpoint_dir() -> Path:
    """Where training checkpoints live by default: <data root>/checkpoints."""
    return data_root() / "checkpoints"


def git_commit() -> str:
    """The repository's HEAD commit, or "unknown"."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True, timeout=5
        )
        return out.stdout.strip() or "unknown"
    except OSError:
        return "unknown"
