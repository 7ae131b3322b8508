"""studies/any_object_recall.py: recall and false detections of a detector of any object."""

from __future__ import annotations

import importlib.util
from types import SimpleNamespace

import numpy as np
import pytest

from perception.detector import Detection
from perception.detector_net import ANY_OBJECT
from perception.training.data.dataset import PoseDataset
from perception.training.datagen import main as datagen
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import REPO_ROOT

_spec = importlib.util.spec_from_file_location(
    "any_object_recall", REPO_ROOT / "studies" / "any_object_recall.py"
)
study = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(study)


class _Truth:
    """A detector that finds every object of an image as its true mask, plus one false
    detection in the image's top-left corner."""

    cfg = SimpleNamespace(classes=(ANY_OBJECT,))

    def __init__(self, data: PoseDataset) -> None:
        self.data = data

    def detect(self, rgb: np.ndarray, score_threshold: float | None = None) -> list[Detection]:
        s = next(
            self.data[i] for i in range(len(self.data)) if np.array_equal(self.data[i].rgb, rgb)
        )
        out = [Detection(ANY_OBJECT, 0.9, o.box_xyxy, o.mask_visib) for o in s.objects]
        corner = np.zeros(rgb.shape[:2], bool)
        corner[:5, :5] = True
        return [*out, Detection(ANY_OBJECT, 0.8, np.array([0, 0, 4, 4.0]), corner)]


@pytest.mark.slow
def test_true_masks_are_all_found_and_the_corner_is_a_false_detection(tmp_path) -> None:
    args = ["--dist", "headcam", "--bank", "--split", "val", "--count", "3", "--quiet"]
    assert datagen([*args, "--width", "320", "--height", "240", "--out", str(tmp_path)]) == 0
    data = PoseDataset(tmp_path, "val")
    r = study.measure(_Truth(data), data, 3, 0.3)
    assert r["images"] == 3 and r["objects"] > 0
    assert r["recall"] == 1.0 and r["false_per_image"] == pytest.approx(1.0)
    # Counting one object alone: its instances only, and the others' detections are not false.
    name = data[0].objects[0].name
    one = study.measure(_Truth(data), data, 3, 0.3, [name])
    assert 0 < one["objects"] < r["objects"] and one["recall"] == 1.0
    assert one["false_per_image"] == pytest.approx(1.0)


def test_the_splits_are_checked_in_one_line(tmp_path) -> None:
    assert study.check_splits("headcam_bank:val") == [("headcam_bank", "val")]
    (tmp_path / "mine" / "val").mkdir(parents=True)
    mine = f"{tmp_path}/mine"
    assert study.check_splits(f"{mine}:val") == [(mine, "val")]
    with pytest.raises(InvalidArgumentError, match="FOLDER:SPLIT"):
        study.check_splits(f"{mine}:test")
    for bad in ("headcam_bank", "nowhere:val", "headcam_bank:dev", " , "):
        with pytest.raises(InvalidArgumentError, match="FOLDER:SPLIT"):
            study.check_splits(bad)


def test_detections_of_any_object_are_no_neighbours_to_rest_on() -> None:
    # A detector of any object names none of its detections: their meshes are unknown, so the
    # support of the neighbours verifies none of them (it used to look the name up and raise).
    from perception.stages import SupportConfig
    from perception.stages.placement import NeighbourSupport

    mask = np.zeros((20, 20), bool)
    mask[5:10, 5:10] = True
    target = Detection("phone", 0.9, np.array([5, 5, 10, 10.0]), mask)
    other = Detection(ANY_OBJECT, 0.9, np.array([10, 5, 15, 10.0]), np.roll(mask, 5, axis=1))
    asked = []
    stage = NeighbourSupport(SupportConfig(), 10.0, lambda d, w: asked.append(d))
    z, seen = stage.surface(target, [target, other], None, lambda d: asked.append(d))
    assert z is None and seen == [] and asked == []
