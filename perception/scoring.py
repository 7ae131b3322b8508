"""The verification scores: how well a pose agrees with the image, beyond its silhouette.

A refined pose is scored by its silhouette IoU with the detected visible mask (the refiner's)
plus two terms from one drawing of the object's convex pieces at that pose in a window around
the mask (docs/DESIGN.md §7, "Verification"):

- appearance: the Pearson correlation of the pieces' colours with the image, over the mask's
  pixels the pose covers;
- edges: the share of the pieces' outlines (every boundary between pieces and with the
  background) that lies on the image's Canny edges, each outline pixel weighted by
  exp(-d^2 / 2 sigma^2) of its distance d to the nearest edge.

The pieces are drawn far to near, each after every piece it hides (`perception.parts.Separations`).
A `Scorer` holds what one detection's poses are scored against; it pickles, so a pose scores the
same on any process.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from perception.overlay import mask_box
from perception.parts import Parts
from posegrasp.core.errors import InvalidArgumentError

#: Width of the edge agreement's fall-off with the distance to an image edge [px].
EDGE_SIGMA_PX = 1.5
#: Image edges are searched in the mask's box grown by this much [px].
EDGE_MARGIN_PX = 10


@dataclass(frozen=True)
class ScoringConfig:
    """Weights of the verification score: IoU + `appearance_weight` x appearance +
    `edge_weight` x edges.

    Attributes:
        appearance_weight: weight of the colour correlation, >= 0.
        edge_weight: weight of the outlines' agreement with image edges, >= 0.
    """

    appearance_weight: float = 0.05
    edge_weight: float = 0.3

    def __post_init__(self) -> None:
        for key in ("appearance_weight", "edge_weight"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value >= 0):
                raise InvalidArgumentError(
                    f"ScoringConfig.{key} must be finite and >= 0, got {value}"
                )


@dataclass(frozen=True)
class Scores:
    """The verification of one pose.

    Attributes:
        score: IoU + weighted appearance + weighted edges.
        iou: silhouette IoU with the visible mask.
        appearance: the colour correlation in [-1, 1] (0: undefined).
        edges: the outlines' agreement with image edges in [0, 1] (0: undefined).
    """

    score: float
    iou: float
    appearance: float
    edges: float


@dataclass(frozen=True, eq=False)
class Scorer:
    """What one detection's poses are scored against.

    Attributes:
        parts: the object's convex pieces and their colours.
        K: the intrinsics (3, 3) [px].
        rgb: the image (H, W, 3) uint8.
        mask: the detection's visible mask (H, W) bool.
        edge_distance: `image_edges` of `box`.
        box: the window (x0, y0, x1, y1) [px] the pieces are drawn in.
        config: the weights.
    """

    parts: Parts
    K: np.ndarray
    rgb: np.ndarray
    mask: np.ndarray
    edge_distance: np.ndarray
    box: tuple[int, int, int, int]
    config: ScoringConfig

    @classmethod
    def of(
        cls, parts: Parts, K: np.ndarray, rgb: np.ndarray, mask: np.ndarray, config: ScoringConfig
    ) -> Scorer:
        """The scorer of a detection's `mask` (H, W) bool in `rgb`: its window is the mask's box
        grown by `EDGE_MARGIN_PX` inside the image."""
        x0, y0, x1, y1 = mask_box(mask) or (0, 0, 1, 1)
        H, W = mask.shape
        m = EDGE_MARGIN_PX
        box = max(0, x0 - m), max(0, y0 - m), min(W, x1 + m), min(H, y1 + m)
        return cls(parts, K, rgb, mask, image_edges(rgb, box), box, config)

    def score(self, T: np.ndarray, iou: float) -> Scores:
        """The scores of pose T (4, 4) whose silhouette IoU with the mask is `iou`."""
        app, edges = verification_scores(
            self.parts, T, self.K, self.rgb, self.mask, self.edge_distance, self.box
        )
        cfg = self.config
        return Scores(iou + cfg.appearance_weight * app + cfg.edge_weight * edges, iou, app, edges)


def drawing_order(depth: np.ndarray, hides: np.ndarray) -> list[int]:
    """Piece indices far first: by decreasing mean `depth`, except that a piece is drawn after
    every piece it hides (`hides[i, j]`: j hides i); a cycle (pieces that are not separable)
    falls back to the depths."""
    order = [int(i) for i in np.argsort(depth)[::-1]]
    rank = np.empty(len(order), int)
    rank[order] = np.arange(len(order))
    if not (hides & (rank[:, None] > rank[None, :])).any():
        return order
    # before[j]: the pieces j hides, as bits; each step draws the farthest piece whose hidden
    # pieces are all drawn
    before = [
        int.from_bytes(np.packbits(col, bitorder="little").tobytes(), "little") for col in hides.T
    ]
    drawn, out, left = 0, [], order
    while left:
        pick = next((j for j in left if not before[j] & ~drawn), left[0])
        out.append(pick)
        drawn |= 1 << pick
        left = [j for j in left if j != pick]
    return out


def _far_to_near(
    parts: Parts, T: np.ndarray, K: np.ndarray, origin: tuple[int, int]
) -> list[tuple[int, np.ndarray]] | None:
    """Each piece's projected hull at pose T, as (piece index, polygon in 1/16 px relative to
    the pixel `origin`), in drawing order (`drawing_order`: far first, each piece after those
    it hides); None when a vertex lies behind the camera."""
    depth, drawn = [], []
    for piece in parts.pieces:
        X = piece @ T[:3, :3].T + T[:3, 3]
        if X[:, 2].min() < 1e-3:
            return None
        depth.append(float(X[:, 2].mean()))
        drawn.append(((X @ K.T)[:, :2] / X[:, 2:3] - np.array(origin)).astype(np.float32))
    camera = -T[:3, :3].T @ T[:3, 3]
    out = []
    for i in drawing_order(np.array(depth), parts.separations.in_front(camera)):
        hull = cv2.convexHull(drawn[i], returnPoints=False)[:, 0]
        out.append((i, np.round(drawn[i][hull] * 16).astype(np.int32)))
    return out


def _appearance(
    ids: np.ndarray,
    colours: np.ndarray,
    rgb: np.ndarray,
    mask: np.ndarray,
    box: tuple[int, int, int, int],
) -> float:
    """Pearson correlation, over the mask's pixels the pose covers, of the pieces' colours (as
    float32) drawn by the id map `ids` (`id_map` of the window `box`) with the image (all
    three channels together): near 1 when the coloured parts lie where the image shows those
    colours; 0 when undefined."""
    x0, y0, x1, y1 = box
    sel = (ids != 0) & mask[y0:y1, x0:x1]
    if np.count_nonzero(sel) < 20:
        return 0.0
    a = colours.astype(np.float32)[ids[sel] - 1].reshape(-1).astype(np.float64)
    b = rgb[y0:y1, x0:x1][sel].reshape(-1).astype(np.float64)
    a -= a.mean()
    b -= b.mean()
    den = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b / den) if den > 0 else 0.0


def verification_scores(
    parts: Parts,
    T: np.ndarray,
    K: np.ndarray,
    rgb: np.ndarray,
    mask: np.ndarray,
    edge_distance: np.ndarray,
    box: tuple[int, int, int, int],
) -> tuple[float, float]:
    """How well pose T agrees with the image, from one drawing of the pieces in the window
    `box` (x0, y0, x1, y1) [px], which holds the mask:

    - appearance: the Pearson correlation, over the mask's pixels the pose covers, of the
      pieces' colours (`Parts.colours`) with the image;
    - edges: how well the pieces' outlines (every boundary between pieces and with the
      background) lie on image edges, `edge_distance` being `image_edges` of the same window:
      the mean of exp(-d^2 / 2 sigma^2) over the outline pixels, sigma `EDGE_SIGMA_PX`, in
      [0, 1].

    Both are 0 when undefined (too few pixels, or a vertex behind the camera)."""
    ids = id_map(parts, T, K, box)
    if ids is None:
        return 0.0, 0.0
    return _appearance(ids, parts.colours, rgb, mask, box), _edges(ids, edge_distance)


def id_map(
    parts: Parts, T: np.ndarray, K: np.ndarray, box: tuple[int, int, int, int]
) -> np.ndarray | None:
    """Which piece (1-based, 0: none) covers each pixel of the window `box` (x0, y0, x1, y1)
    [px] at pose T, far pieces drawn first, (h, w) uint8; None when a vertex lies behind the
    camera."""
    x0, y0, x1, y1 = box
    polygons = _far_to_near(parts, T, K, (x0, y0))
    if polygons is None:
        return None
    ids = np.zeros((y1 - y0, x1 - x0), np.uint8)
    for i, pts in polygons:
        cv2.fillConvexPoly(ids, pts, i + 1, cv2.LINE_8, 4)
    return ids


def image_edges(rgb: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    """Distance [px] of every pixel of the window `box` to the nearest Canny edge of the
    image, (h, w) float32."""
    x0, y0, x1, y1 = box
    gray = cv2.cvtColor(np.ascontiguousarray(rgb[y0:y1, x0:x1]), cv2.COLOR_RGB2GRAY)
    edges = cv2.Canny(cv2.GaussianBlur(gray, (3, 3), 0), 20, 60)
    return cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 3)


def _edges(ids: np.ndarray, edge_distance: np.ndarray) -> float:
    """The edge agreement of `verification_scores` from the id map of its window."""
    outline = np.zeros(ids.shape, bool)
    outline[:, 1:] |= ids[:, 1:] != ids[:, :-1]
    outline[1:, :] |= ids[1:, :] != ids[:-1, :]
    # A window without edges holds huge distances, whose squares would overflow; any distance
    # past 1e4 px weighs exactly 0, as the unclipped one did.
    d = np.minimum(edge_distance[outline], 1e4)
    if d.size < 10:
        return 0.0
    return float(np.mean(np.exp(-(d * d) / (2 * EDGE_SIGMA_PX * EDGE_SIGMA_PX))))
