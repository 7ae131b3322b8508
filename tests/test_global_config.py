"""The composition of `hybrid-global` and its variants: one config per stage, every setting checked
under its own name in one line, and the registered estimators declared as compositions."""

from __future__ import annotations

import math

import pytest

from perception.global_pose import GlobalConfig
from perception.priors import GravityConfig, InplaneConfig
from perception.scoring import ScoringConfig
from perception.stages import (
    CodebookConfig,
    DetectionConfig,
    SecondLookConfig,
    SupportConfig,
    TableConfig,
)
from perception.verification import RefinementConfig
from posegrasp.core.errors import InvalidArgumentError

BAD = [
    (DetectionConfig, {"target_score": 1.5}, "DetectionConfig.target_score"),
    (DetectionConfig, {"target_score": math.nan}, "DetectionConfig.target_score"),
    (DetectionConfig, {"mask_net": "yes"}, "DetectionConfig.mask_net"),
    (DetectionConfig, {"shortlist": 0}, "DetectionConfig.shortlist"),
    (DetectionConfig, {"joined": 0}, "DetectionConfig.joined"),
    (DetectionConfig, {"joined": True}, "DetectionConfig.joined"),
    (DetectionConfig, {"sure": 0.0}, "DetectionConfig.sure"),
    (DetectionConfig, {"sure": math.nan}, "DetectionConfig.sure"),
    (DetectionConfig, {"sure": True}, "DetectionConfig.sure"),
    (DetectionConfig, {"table_tolerance_m": 0.0}, "DetectionConfig.table_tolerance_m"),
    (DetectionConfig, {"table_tolerance_m": math.nan}, "DetectionConfig.table_tolerance_m"),
    (CodebookConfig, {"views": 0}, "CodebookConfig.views"),
    (CodebookConfig, {"inplane": 0}, "CodebookConfig.inplane"),
    (CodebookConfig, {"hypotheses": 0}, "CodebookConfig.hypotheses"),
    (CodebookConfig, {"min_angle_deg": 180.0}, "CodebookConfig.min_angle_deg"),
    (CodebookConfig, {"min_angle_deg": math.nan}, "CodebookConfig.min_angle_deg"),
    (CodebookConfig, {"occluded_grow": (1.0,)}, "CodebookConfig.occluded_grow"),
    (CodebookConfig, {"occluded_grow": (1.3, 5.0)}, "CodebookConfig.occluded_grow"),
    (CodebookConfig, {"resting_hypotheses": -1}, "CodebookConfig.resting_hypotheses"),
    (ScoringConfig, {"appearance_weight": -0.1}, "ScoringConfig.appearance_weight"),
    (ScoringConfig, {"appearance_weight": math.inf}, "ScoringConfig.appearance_weight"),
    (ScoringConfig, {"edge_weight": math.nan}, "ScoringConfig.edge_weight"),
    (GravityConfig, {"tilt_deg": 0.0}, "GravityConfig.tilt_deg"),
    (GravityConfig, {"snap_candidates": -1}, "GravityConfig.snap_candidates"),
    (GravityConfig, {"snap_tilt_deg": 180.0}, "GravityConfig.snap_tilt_deg"),
    (GravityConfig, {"snap_iterations": 0}, "GravityConfig.snap_iterations"),
    (InplaneConfig, {"max_deg": 0.0}, "InplaneConfig.max_deg"),
    (SecondLookConfig, {"hypotheses": -1}, "SecondLookConfig.hypotheses"),
    (SecondLookConfig, {"resting": -3}, "SecondLookConfig.resting"),
    (SecondLookConfig, {"below": math.nan}, "SecondLookConfig.below"),
    (SupportConfig, {"neighbours": 0}, "SupportConfig.neighbours"),
    (SupportConfig, {"score": math.inf}, "SupportConfig.score"),
    (SupportConfig, {"tolerance_m": -0.01}, "SupportConfig.tolerance_m"),
    (SupportConfig, {"below": math.nan}, "SupportConfig.below"),
    (TableConfig, {"max_tilt_deg": 200.0}, "TableConfig.max_tilt_deg"),
    (RefinementConfig, {"passes": 0}, "RefinementConfig.passes"),
    (RefinementConfig, {"keep_after_first": -1}, "RefinementConfig.keep_after_first"),
    (RefinementConfig, {"screen_iterations": -2}, "RefinementConfig.screen_iterations"),
    (RefinementConfig, {"max_shift": 0.0}, "RefinementConfig.max_shift"),
    (RefinementConfig, {"max_shift": 1.5}, "RefinementConfig.max_shift"),
    (RefinementConfig, {"max_rotation_deg": 200.0}, "RefinementConfig.max_rotation_deg"),
    (GlobalConfig, {"processes": 3}, "GlobalConfig.processes"),
    (GlobalConfig, {"gravity": None}, "GlobalConfig.support needs GlobalConfig.gravity"),
    (GlobalConfig, {"codebook": None}, "GlobalConfig.codebook must be a CodebookConfig,"),
    (GlobalConfig, {"table": True}, "GlobalConfig.table must be a TableConfig or None"),
    (GlobalConfig, {"scoring": RefinementConfig()}, "GlobalConfig.scoring must be a Scoring"),
]


@pytest.mark.parametrize(("kind", "bad", "match"), BAD, ids=[m for _, _, m in BAD])
def test_a_bad_setting_is_one_line_naming_it(kind: type, bad: dict, match: str) -> None:
    with pytest.raises(InvalidArgumentError) as e:
        kind(**bad)
    message = str(e.value)
    assert message.startswith(match) and "\n" not in message


def test_every_setting_of_every_stage_is_checked() -> None:
    """Each field of each stage's config appears in a bad case above (or is a stage of the
    composition, checked by its type)."""
    from dataclasses import fields

    checked = {m.split(" ")[0] for _, _, m in BAD}
    for kind in (
        DetectionConfig,
        CodebookConfig,
        RefinementConfig,
        ScoringConfig,
        GravityConfig,
        InplaneConfig,
        SecondLookConfig,
        SupportConfig,
        TableConfig,
    ):
        for f in fields(kind):
            assert f"{kind.__name__}.{f.name}" in checked, f"{kind.__name__}.{f.name}"


def test_the_default_composition_and_the_ones_left_out() -> None:
    """`hybrid-global`'s stages by default; an optional stage may be left out (gravity only
    with the support left out too, as the paper's protocol does)."""
    cfg = GlobalConfig()
    assert cfg.gravity is not None and cfg.second_look is not None and cfg.support is not None
    assert cfg.table is None and cfg.inplane is None and cfg.processes == 2
    studio = GlobalConfig(gravity=None, support=None, second_look=None, inplane=InplaneConfig())
    assert studio.inplane is not None and studio.inplane.max_deg == 65.0


def test_the_dead_options_are_gone() -> None:
    """No setting that nothing set or read is left: a withholding score and the neighbours'
    expert nets."""
    from dataclasses import asdict

    names = str(asdict(GlobalConfig()))
    assert "min_score" not in names and "neighbour_experts" not in names
