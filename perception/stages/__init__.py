"""The stages `perception.global_pose.GlobalPoseEstimator` is composed of (docs/DESIGN.md §7).

Every stage has one interface (`Stage`): it takes one image's `Work` and returns it with its
own part filled in, says whether it has anything to do (`Stage.wanted`), and is built from its
part of `perception.global_pose.GlobalConfig` and the loaded pieces (`Kit`) by its ``build``
class method. In order:

- detection (`TargetDetection`): the requested object's best detection among the others;
- mask (`RedrawnMask`): the target's mask redrawn by the mask net;
- hypotheses (`Hypotheses`): the target's priors, and its first poses from the nets
  (`NetsPose`), the viewpoint codebook (`CodebookHypotheses`) and, with gravity, the
  codebook's templates that could rest (`RestingHypotheses`);
- verify (`Verify`): each hypothesis refined, scored and ranked (`perception.verification`);
- second look (`SecondLook`): when the best is unsure, more hypotheses verified;
- table (`TablePrior`) or support (`NeighbourSupport`): the winner placed where it rests.
"""

from perception.stages.config import (
    CodebookConfig,
    DetectionConfig,
    GlobalConfig,
    SecondLookConfig,
    SupportConfig,
    TableConfig,
)
from perception.stages.detection import RedrawnMask, TargetDetection
from perception.stages.hypotheses import (
    CodebookHypotheses,
    Hypotheses,
    NetsPose,
    RestingHypotheses,
)
from perception.stages.placement import NeighbourSupport, TablePrior
from perception.stages.verify import SecondLook, Verify
from perception.stages.work import (
    AnyDetection,
    CodebookMatch,
    Detections,
    Kit,
    Placed,
    Stage,
    StageKind,
    Work,
    run_stages,
)

__all__ = [
    "AnyDetection",
    "CodebookConfig",
    "CodebookHypotheses",
    "CodebookMatch",
    "DetectionConfig",
    "Detections",
    "GlobalConfig",
    "Hypotheses",
    "Kit",
    "NeighbourSupport",
    "NetsPose",
    "Placed",
    "RedrawnMask",
    "RestingHypotheses",
    "SecondLook",
    "SecondLookConfig",
    "Stage",
    "StageKind",
    "SupportConfig",
    "TableConfig",
    "TablePrior",
    "TargetDetection",
    "Verify",
    "Work",
    "run_stages",
]
