"""The 2D prior of ``ppf-det`` and ``fpfh-icp-det``: the project's Mask R-CNN (the detector
`hybrid-global` uses, `perception.detector.TIERS_DETECTOR`) finds the requested object, and its
mask crops the scene's points."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from perception.detector import TIERS_DETECTOR, Detector
from posegrasp.core.contract import Observation
from posegrasp.core.errors import InvalidArgumentError


@dataclass(frozen=True)
class PriorConfig:
    """The detection prior.

    Attributes:
        target_score: the detector score a detection of the requested object needs
            (`hybrid-global`'s own, `perception.global_pose.GlobalConfig.detection.target_score`).
        detector: the detector's weights.
    """

    target_score: float = 0.3
    detector: Path = TIERS_DETECTOR

    def __post_init__(self) -> None:
        if not 0 <= self.target_score <= 1:
            raise InvalidArgumentError(
                f"PriorConfig.target_score must be in [0, 1], got {self.target_score}"
            )


class DetectionPrior:
    """The requested object's detection mask (its highest-scoring detection). The detector is
    loaded when the prior is made, and again on first use in a process it is unpickled in (it
    is not pickled).

    Args:
        config: the settings.
    """

    def __init__(self, config: PriorConfig | None = None) -> None:
        self.config = config or PriorConfig()
        self._detector: Detector | None = None
        _ = self.detector

    def __getstate__(self) -> dict:
        return {"config": self.config}

    def __setstate__(self, state: dict) -> None:
        self.config = state["config"]
        self._detector = None

    @property
    def detector(self) -> Detector:
        """The detector (loaded now if not yet)."""
        if self._detector is None:
            self._detector = Detector.from_weights(
                self.config.detector, score_threshold=self.config.target_score
            )
        return self._detector

    def mask(self, obs: Observation) -> tuple[np.ndarray | None, dict[str, Any]]:
        """The mask of obs.object's best detection, shape (H, W) bool, or None; and the
        detection's class, score, box and the count of detections of the class."""
        found = [d for d in self.detector.detect(obs.rgb) if d.name == obs.object]
        if not found:
            return None, {"detected": False}
        best = max(found, key=lambda d: d.score)
        return best.mask, {
            "detected": True,
            "score": float(best.score),
            "box_xyxy": [float(v) for v in best.box_xyxy],
            "detections": len(found),
        }
