"""The detection stage of a detector of any object: the requested object told by its mesh."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from perception.detector import TIERS_DETECTOR, Detection
from perception.detector_net import ANY_OBJECT
from perception.global_pose import GlobalPoseEstimator
from perception.hybrid import HybridPoseEstimator
from perception.metrics import mask_iou
from perception.stages import DetectionConfig, GlobalConfig
from perception.stages.detection import AnyObjectDetection
from perception.stages.work import Work, run_stages
from perception.training.data.distributions import HeadcamGenerator
from posegrasp.core.contract import Observation
from posegrasp.core.transforms import invert_transform
from posegrasp.world.scene import build_scene

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def image():
    gen = HeadcamGenerator(640, 480, tier="clutter")
    try:
        return gen.render("phone", 12)
    finally:
        gen.close()


def _estimator(image) -> GlobalPoseEstimator:
    """`hybrid-global`'s stages on a detector of any object whose detections are the image's
    true visible masks, each called an object, in an order no score gives away."""
    hybrid = HybridPoseEstimator.from_weights(detector_path=TIERS_DETECTOR)
    hybrid.detector.cfg = replace(hybrid.detector.cfg, classes=(ANY_OBJECT,), n_classes=2)
    seen = [o for o in image.objects if o.mask_visib.sum() > 400]
    dets = [
        Detection(ANY_OBJECT, 0.9 - 0.05 * k, np.zeros(4), o.mask_visib)
        for k, o in enumerate(sorted(seen, key=lambda o: o.extra["target"]))
    ]
    hybrid.detector.detect = lambda rgb, score_threshold=None: list(dets)
    config = GlobalConfig(detection=DetectionConfig(mask_net=False), support=None, processes=1)
    return GlobalPoseEstimator(hybrid, config, name="any-object")


def test_the_requested_object_is_the_detection_its_mesh_explains_best(image) -> None:
    est = _estimator(image)
    assert isinstance(est.stages[0], AnyObjectDetection)
    names = {o.name for o in image.objects}
    assert len(names) >= 3
    T_W_C = invert_transform(image.T_C_W)
    chosen = 0
    table = build_scene("phone", 12).table_top_z  # the scene the image was rendered of
    for o in image.objects:
        if o.mask_visib.sum() <= 400 or [p.name for p in image.objects].count(o.name) > 1:
            continue
        got = est.estimate(Observation(image.rgb, image.K, T_W_C, o.name, 12, table_top_z=table))
        assert got.info["detected"] and got.info["class"] == ANY_OBJECT
        found = got.info["choice"]
        assert len(found["verified"]) >= 2, found  # a choice was made, not taken by score
        # Each verified detection's pose says where it rests.
        assert set(found["surface_z"]) <= set(found["verified"])
        assert got.T_C_O is not None
        # The pose found is the object's: its mesh drawn there covers the object's own mask.
        assert mask_iou(_drawn(o.name, got.T_C_O, image), o.mask_visib) > 0.5, o.name
        chosen += 1
    assert chosen >= 2


def _drawn(name: str, T_C_O: np.ndarray, image) -> np.ndarray:
    import cv2

    from perception.training.data.annotations import object_mesh

    mesh = object_mesh(name)
    v = mesh.vertices @ T_C_O[:3, :3].T + T_C_O[:3, 3]
    uv = v[:, :2] / v[:, 2:3] * [image.K[0, 0], image.K[1, 1]] + image.K[:2, 2]
    out = np.zeros(image.rgb.shape[:2], np.uint8)
    for tri in np.asarray(mesh.faces):
        cv2.fillConvexPoly(out, np.round(uv[tri]).astype(np.int32), 1)
    return out.astype(bool)


def test_the_unseen_estimator_is_the_shipped_detector_and_mask_net_of_any_object() -> None:
    import json

    from perception.detector import UNSEEN_DETECTOR
    from perception.estimators import load_estimator
    from perception.mask_net import UNSEEN_MASKNET
    from perception.stages.detection import RedrawnMask
    from perception.stages.placement import TablePrior

    estimator, files = load_estimator("hybrid-global-unseen")
    assert {UNSEEN_DETECTOR.resolve(), UNSEEN_MASKNET.resolve()} <= set(files)
    assert isinstance(estimator, GlobalPoseEstimator)
    assert estimator.hybrid.detector.cfg.classes == (ANY_OBJECT,)
    assert isinstance(estimator.stage("detection"), AnyObjectDetection)
    assert isinstance(estimator.stage("table"), TablePrior)  # no neighbours say where it is
    assert estimator.config.detection.sure == 1.2  # chosen on development seeds
    mask = estimator.stage("mask")
    assert isinstance(mask, RedrawnMask) and mask.knows("bank-042") and mask.knows("phone")
    # Both nets' manifests record their training: bank scenes alone, never a scene of the six
    # built-in objects.
    entries = json.loads((UNSEEN_DETECTOR.parent / "manifest.json").read_text())
    assert "--any-object" in entries["detector"]["command"]
    for key in ("detector", "mask_net"):
        data = entries[key]["command"].split("--data ")[1].split()[0]
        assert all(p.split("=")[0].startswith("headcam_bank") for p in data.split(",")), key


@pytest.mark.parametrize("target_score", [0.3, None])
def test_a_target_may_score_under_the_detectors_threshold(image, target_score) -> None:
    # The phone's own mask, scoring between DetectionConfig.target_score and the detector's
    # threshold: a candidate when the stage asks for that score, not otherwise.
    phone = next(o for o in image.objects if o.name == "phone")
    hybrid = HybridPoseEstimator.from_weights(detector_path=TIERS_DETECTOR)
    hybrid.detector.cfg = replace(hybrid.detector.cfg, classes=(ANY_OBJECT,), n_classes=2)
    assert hybrid.detector.score_threshold == 0.5
    own = Detection(ANY_OBJECT, 0.4, np.zeros(4), phone.mask_visib)

    def detect(rgb, score_threshold=None):
        floor = hybrid.detector.score_threshold if score_threshold is None else score_threshold
        return [d for d in (own,) if d.score >= floor]

    hybrid.detector.detect = detect
    detection = DetectionConfig(mask_net=False, target_score=target_score)
    config = GlobalConfig(detection=detection, support=None, processes=1)
    est = GlobalPoseEstimator(hybrid, config, name="any-object")
    table = build_scene("phone", 12).table_top_z
    obs = Observation(
        image.rgb, image.K, invert_transform(image.T_C_W), "phone", 12, table_top_z=table
    )
    got = est.estimate(obs)
    assert got.info["detected"] is (target_score is not None)
    if target_score is not None:
        assert got.info["score"] == pytest.approx(0.4)
        assert mask_iou(_drawn("phone", got.T_C_O, image), phone.mask_visib) > 0.5


def test_an_object_the_detector_parts_in_two_is_found_whole(image) -> None:
    # The phone's mask cut in two, left and right, each half a detection of its own (as a
    # detector of any object parts an object of two colours): the halves joined are the target.
    phone = next(o for o in image.objects if o.name == "phone")
    xs = np.nonzero(phone.mask_visib.any(0))[0]
    cut = int(np.median(xs))
    halves = [phone.mask_visib.copy(), phone.mask_visib.copy()]
    halves[0][:, cut:] = False
    halves[1][:, :cut] = False
    hybrid = HybridPoseEstimator.from_weights(detector_path=TIERS_DETECTOR)
    hybrid.detector.cfg = replace(hybrid.detector.cfg, classes=(ANY_OBJECT,), n_classes=2)
    others = [o.mask_visib for o in image.objects if o.name != "phone" and o.mask_visib.sum() > 400]
    dets = [Detection(ANY_OBJECT, 0.9, np.zeros(4), m) for m in [*halves, *others]]
    for d in dets:
        ys, xs = np.nonzero(d.mask)
        d.box_xyxy[:] = [xs.min(), ys.min(), xs.max(), ys.max()]
    hybrid.detector.detect = lambda rgb, score_threshold=None: list(dets)
    config = GlobalConfig(detection=DetectionConfig(mask_net=False), support=None, processes=1)
    est = GlobalPoseEstimator(hybrid, config, name="any-object")
    table = build_scene("phone", 12).table_top_z
    obs = Observation(
        image.rgb, image.K, invert_transform(image.T_C_W), "phone", 12, table_top_z=table
    )
    got = est.estimate(obs)
    choice = got.info["choice"]
    assert choice["joined"][str(choice["picked"])] == [0, 1], choice
    assert mask_iou(_drawn("phone", got.T_C_O, image), phone.mask_visib) > 0.5


def test_a_candidate_is_on_the_table_only_at_the_tables_height(image) -> None:
    # The phone's own mask fits the phone resting on the scene's table; the same mask
    # does not fit it on a table 15 cm higher or lower, nor without a tolerance does the
    # table rule anything out.
    from perception.codebook import CodebookCache
    from perception.parallel import OneProcess
    from perception.stages import CodebookConfig
    from perception.stages.detection import on_table
    from perception.stages.hypotheses import CodebookHypotheses
    from posegrasp.world.objects import load_object

    phone = next(o for o in image.objects if o.name == "phone")
    book = CodebookConfig()
    source = CodebookHypotheses(CodebookCache(book.views, book.inplane), book)
    det = Detection("phone", 0.9, np.zeros(4), phone.mask_visib)
    match = source.match(det, None, image.K, OneProcess())
    assert match is not None
    table = build_scene("phone", 12).table_top_z
    T_W_C = invert_transform(image.T_C_W)

    def on(z, tol=0.03):
        obs = Observation(image.rgb, image.K, T_W_C, "phone", 12, table_top_z=z)
        return on_table(
            match, book, load_object("phone"), obs, DetectionConfig(table_tolerance_m=tol)
        )

    assert on(table)
    assert not on(table + 0.15) and not on(table - 0.15)
    assert on(table + 0.15, tol=None) and on(None)


def test_a_lone_candidate_is_taken_unmatched(image) -> None:
    # One detection: nothing to choose between, so no match is spent on it; its pose is found.
    phone = next(o for o in image.objects if o.name == "phone")
    hybrid = HybridPoseEstimator.from_weights(detector_path=TIERS_DETECTOR)
    hybrid.detector.cfg = replace(hybrid.detector.cfg, classes=(ANY_OBJECT,), n_classes=2)
    own = Detection(ANY_OBJECT, 0.9, np.zeros(4), phone.mask_visib)
    hybrid.detector.detect = lambda rgb, score_threshold=None: [own]
    config = GlobalConfig(detection=DetectionConfig(mask_net=False), support=None, processes=1)
    est = GlobalPoseEstimator(hybrid, config, name="any-object")
    stage = est.stage("detection")
    matched = []
    match = stage.codebook.match
    stage.codebook.match = lambda *a, **k: matched.append(1) or match(*a, **k)
    table = build_scene("phone", 12).table_top_z
    obs = Observation(
        image.rgb, image.K, invert_transform(image.T_C_W), "phone", 12, table_top_z=table
    )
    got = est.estimate(obs)
    assert got.info["choice"]["match_iou"] == [None] and got.info["choice"]["picked"] == 0
    assert got.info["detected"]
    assert mask_iou(_drawn("phone", got.T_C_O, image), phone.mask_visib) > 0.5
    assert not matched  # the choice spent no match (the hypotheses stage has its own)


def test_the_chosen_candidates_verification_is_not_run_again(image) -> None:
    # The candidate chosen was verified as the target in the choice: the stages go on from
    # that work, and it is the work they would have made anew from the chosen detection.
    est = _estimator(image)
    phone = next(o for o in image.objects if o.name == "phone")
    table = build_scene("phone", 12).table_top_z
    obs = Observation(
        image.rgb, image.K, invert_transform(image.T_C_W), "phone", 12, table_top_z=table
    )
    work = Work.of(obs)
    chosen = est.stage("detection")(work)
    assert chosen.verification is not None and chosen.winner is not None
    assert len(chosen.found.info["choice"]["verified"]) >= 2
    anew = chosen.given(
        target=chosen.found.target,
        executor=None,
        match=None,
        taken=(),
        hypotheses=(),
        verification=None,
        ranked=(),
    )
    rest = [s for s in est.stages if s.name in ("mask", "hypotheses", "verify")]
    assert [s.name for s in rest] == ["hypotheses", "verify"]  # this one draws no masks
    assert not any(s.wanted(chosen) for s in rest)
    again = run_stages(rest, anew, {})
    assert [v.score for v in again.ranked] == [v.score for v in chosen.ranked]
    assert all(
        np.array_equal(a.T_C_O, b.T_C_O) for a, b in zip(again.ranked, chosen.ranked, strict=True)
    )
    got = est.estimate(obs)
    assert {"mask", "hypotheses", "verify"}.isdisjoint(got.info["timings_ms"])
    assert np.array_equal(got.T_C_O, chosen.winner.T_C_O) or got.info["verify"]["second_look"]
    assert mask_iou(_drawn("phone", got.T_C_O, image), phone.mask_visib) > 0.5


def test_a_sure_candidate_on_the_table_ends_the_verifying(image) -> None:
    # With `sure` met by the first shortlisted candidate, it is the only one verified and the
    # one taken; without, the whole shortlist is verified.
    est = _estimator(image)
    table = build_scene("phone", 12).table_top_z
    obs = Observation(
        image.rgb, image.K, invert_transform(image.T_C_W), "phone", 12, table_top_z=table
    )
    every = est.estimate(obs).info["choice"]
    assert len(every["verified"]) >= 2
    first = next(iter(every["verified"]))
    rests = (
        every["surface_z"].get(first) is not None and abs(every["surface_z"][first] - table) <= 0.03
    )
    cfg = est.config
    eager = est.with_config(replace(cfg, detection=replace(cfg.detection, sure=0.01)))
    got = eager.estimate(obs).info["choice"]
    if rests:  # the first rests on the table: sure of it at once
        assert list(got["verified"]) == [first] and got["picked"] == int(first)
    else:  # it does not: the next ones are verified too
        assert len(got["verified"]) >= 2
    strict = est.with_config(replace(cfg, detection=replace(cfg.detection, sure=100.0)))
    assert strict.estimate(obs).info["choice"]["verified"] == every["verified"]
