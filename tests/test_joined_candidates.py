"""The candidates of the detection stage of a detector of any object: detections alone, and
those whose masks touch taken together."""

from __future__ import annotations

import numpy as np
import pytest

from perception.detector import Detection
from perception.stages.detection import TOUCH_PX, candidates, touching


def _det(score: float, y0: int, x0: int, y1: int, x1: int) -> Detection:
    mask = np.zeros((60, 80), bool)
    mask[y0:y1, x0:x1] = True
    return Detection("object", score, np.array([x0, y0, x1 - 1, y1 - 1], float), mask)


def test_masks_touch_within_the_gap_and_not_beyond() -> None:
    a = _det(0.9, 10, 10, 20, 20)
    near = _det(0.9, 10, 20 + TOUCH_PX - 1, 20, 40)  # TOUCH_PX - 1 pixels apart
    far = _det(0.9, 10, 20 + TOUCH_PX + 1, 20, 40)  # TOUCH_PX + 1 apart
    diagonal = _det(0.9, 20 + TOUCH_PX - 1, 20 + TOUCH_PX - 1, 40, 40)
    assert touching([a.mask, near.mask]) == {(0, 1)}
    assert touching([a.mask, far.mask]) == set()
    assert touching([a.mask, diagonal.mask]) == {(0, 1)}
    assert touching([a.mask, np.zeros_like(a.mask)]) == set()
    # Boxes that meet while the masks do not: an L around a square it does not reach.
    ell = np.zeros((60, 80), bool)
    ell[0:50, 0:5] = True
    ell[45:50, 0:50] = True
    square = np.zeros((60, 80), bool)
    square[10:20, 20:30] = True
    assert touching([ell, square]) == set()


def test_touching_detections_are_joined_up_to_the_limit() -> None:
    # A chain 0-1-2 and, apart, 3; detection 4 scores under the threshold.
    dets = [
        _det(0.9, 10, 0, 20, 10),
        _det(0.8, 10, 10, 20, 20),
        _det(0.7, 10, 20, 20, 30),
        _det(0.95, 40, 60, 50, 70),
        _det(0.2, 40, 40, 50, 60),
    ]
    alone = candidates(dets, 0.3, 1)
    assert [c.members for c in alone] == [(0,), (1,), (2,), (3,)]
    assert not any(c.joined for c in alone)
    two = candidates(dets, 0.3, 2)
    assert [c.members for c in two] == [(0,), (1,), (2,), (3,), (0, 1), (1, 2)]
    three = candidates(dets, 0.3, 3)
    assert [c.members for c in three][-1] == (0, 1, 2)  # 0 and 2 joined only through 1
    assert (0, 2) not in [c.members for c in three]
    whole = three[-1].detection
    assert whole.mask.sum() == sum(d.mask.sum() for d in dets[:3])
    assert whole.score == pytest.approx(0.7)
    np.testing.assert_array_equal(whole.box_xyxy, [0, 10, 29, 19])
    # The one under the threshold joins nothing, though it touches 3.
    assert all(4 not in c.members for c in candidates(dets, 0.3, 3))
    assert (3, 4) in [c.members for c in candidates(dets, 0.1, 2)]
