"""The verification stages: every hypothesis refined against the mask and the image and scored
(`perception.verification`), and, when the best is unsure, a second look at more of them."""

from __future__ import annotations

from perception.parts import ConvexParts
from perception.refine import PoseRefiner
from perception.scoring import Scorer, ScoringConfig
from perception.stages.config import CodebookConfig, GlobalConfig, SecondLookConfig
from perception.stages.hypotheses import RestingHypotheses
from perception.stages.work import Kit, Work
from perception.verification import RefinementConfig, Verification, VerifyJob


class Verify:
    """The verification stage: the first hypotheses refined, scored and ranked.

    Args:
        parts: the objects' convex pieces.
        refinement: how each hypothesis is refined.
        scoring: the score's weights.
    """

    name = "verify"

    def __init__(
        self, parts: ConvexParts, refinement: RefinementConfig, scoring: ScoringConfig
    ) -> None:
        self.parts, self.refinement, self.scoring = parts, refinement, scoring
        self.refiner = PoseRefiner(refinement.refiner())

    @classmethod
    def build(cls, config: GlobalConfig, kit: Kit) -> Verify:
        """The stage of `config.refinement` and `config.scoring`."""
        return cls(kit.parts, config.refinement, config.scoring)

    @staticmethod
    def wanted(work: Work) -> bool:
        """Whether the target has its hypotheses, not verified yet."""
        return work.target is not None and work.executor is not None and work.verification is None

    def __call__(self, work: Work) -> Work:
        """`work` with its hypotheses' verification and ranking."""
        det, K, rgb = work.target, work.K, work.rgb
        assert det is not None and work.executor is not None
        parts = self.parts.parts(det.name)
        target = self.refiner.prepare(K, det.mask, rgb, work.occluder)
        scorer = Scorer.of(parts, K, rgb, det.mask, self.scoring)
        job = VerifyJob(parts, target, self.refiner.config, scorer)
        verification = Verification(job, self.refinement, work.priors, work.executor)
        verification.add(work.hypotheses)
        return work.given(verification=verification, ranked=tuple(verification.ranked()))


class SecondLook:
    """The second look: the next best codebook templates (and, with gravity, resting ones)
    verified with the first hypotheses, and the choice made again.

    Args:
        config: the second look's settings.
        codebook: the codebook's settings (the templates are ranked as the hypotheses stage
            ranks them, after its `CodebookConfig.hypotheses`).
    """

    name = "second_look"

    def __init__(self, config: SecondLookConfig, codebook: CodebookConfig) -> None:
        self.config, self.codebook = config, codebook
        self.resting = RestingHypotheses(codebook.min_angle_deg)

    @classmethod
    def build(cls, config: GlobalConfig, kit: Kit) -> SecondLook | None:
        """The stage of `config.second_look` (None: left out)."""
        if config.second_look is None:
            return None
        return cls(config.second_look, config.codebook)

    def wanted(self, work: Work) -> bool:
        """Whether the work allows it, the mask was matched and the best is unsure or none."""
        win = work.winner
        return (
            work.second_look
            and work.match is not None
            and work.verification is not None
            and (win is None or win.score < self.config.below)
        )

    def __call__(self, work: Work) -> Work:
        """`work` with more hypotheses verified and ranked again."""
        match, look, gravity = work.match, self.config, work.priors.gravity
        assert match is not None and work.verification is not None
        taken = list(work.taken)
        book = self.codebook
        later = match.best(book.hypotheses, look.hypotheses, taken, book.min_angle_deg)
        if gravity is not None and look.resting:
            later += self.resting.best(match, gravity, look.resting, taken + later)
        work.verification.add(match.hypotheses(later))
        ranked = tuple(work.verification.ranked())
        return work.given(taken=(*taken, *later), ranked=ranked, looked_again=True)
