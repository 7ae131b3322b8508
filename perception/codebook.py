"""Global pose hypotheses from a viewpoint codebook: silhouettes over the whole rotation group.

A detected object's visible mask says much about its orientation and, through its size and
position, about its translation. The codebook holds, per object, the silhouette of every
rotation of a grid over SO(3) (viewpoints on a Fibonacci sphere x in-plane steps), each seen by
a virtual camera whose axis passes through the object's origin (the crop frame C' of
docs/DESIGN.md §6), drawn into a square of `SILHOUETTE_PX` pixels around its own box and
packed into bits. Matching a detection is one pass of bitwise IoU over all of them; every match
gives a full pose:

- rotation: ``R_C_O = R_corr(uv) @ R_C'_O`` (`perception.geometry.r_corr`), ``uv`` the pixel of
  the origin;
- the origin's pixel: the mask box's centre plus the template's origin offset, scaled by the
  ratio of the box sizes;
- distance: the template's distance scaled by the ratio of the box sizes and focal lengths.

The silhouettes come from a `perception.parts.SilhouetteSource` (today the convex parts'
projected hulls, as in `perception.refine`); a mesh source can take its place without changing
the matching. The verification of the poses refined from these hypotheses is
`perception.scoring`'s.
"""

from __future__ import annotations

import hashlib
import itertools
import math
import sys
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from perception.geometry import r_corr
from perception.parallel import Executor
from perception.parts import ConvexParts, SilhouetteSource
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import data_root, in_repo

#: Side of the square a silhouette is drawn into [px].
SILHOUETTE_PX = 64
#: The silhouette's longer box side fills this share of the square.
FILL = 0.875
#: The virtual camera of the templates: focal length [px] and distance to the origin [m].
TEMPLATE_F = 1000.0
TEMPLATE_Z = 1.0
#: Templates matched at a time (a block of their bits stays in the cache).
MATCH_BLOCK = 512
#: A mask with pixels this close to the image's edge [px] counts as cut off by it.
EDGE_BAND_PX = 2


def sphere_rotations(views: int, inplane: int) -> np.ndarray:
    """A grid over SO(3): `views` viewpoints on a Fibonacci sphere times `inplane` equal turns
    about the viewing axis.

    Returns:
        R_C'_O, shape (views * inplane, 3, 3): the rotations of the object in the crop frame C'
        (its axis through the object's origin), viewpoint-major.
    """
    if views < 1 or inplane < 1:
        raise InvalidArgumentError(f"views and inplane must be >= 1, got {views}, {inplane}")
    k = np.arange(views) + 0.5
    z = 1 - 2 * k / views
    phi = k * math.pi * (3 - math.sqrt(5))
    r = np.sqrt(1 - z * z)
    cam_in_o = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)  # unit, O -> camera
    out = np.empty((views, inplane, 3, 3))
    for i, c in enumerate(cam_in_o):
        zc = -c  # the camera looks at the origin
        up = np.array([0.0, 0.0, 1.0]) if abs(zc[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        xc = np.cross(up, zc)
        xc /= np.linalg.norm(xc)
        yc = np.cross(zc, xc)
        R_cp_o = np.stack([xc, yc, zc])  # rows: the camera axes in O
        for j in range(inplane):
            a = 2 * math.pi * j / inplane
            ca, sa = math.cos(a), math.sin(a)
            Rz = np.array([[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]])
            out[i, j] = Rz @ R_cp_o
    return out.reshape(-1, 3, 3)


#: Rotations a codebook draws at a time (`Codebook.build`).
BUILD_BATCH = 256


def _pack(sil: np.ndarray) -> np.ndarray:
    """A (S, S) bool silhouette as S * S / 64 uint64 words."""
    return np.packbits(sil.reshape(-1)).view(np.uint64)


@dataclass(frozen=True)
class Codebook:
    """The templates of one object.

    Attributes:
        name: the object.
        rotations: R_C'_O per template, (N, 3, 3).
        bits: packed silhouettes, (N, SILHOUETTE_PX**2 / 64) uint64.
        side: each template's box side at `TEMPLATE_F`, `TEMPLATE_Z` [px], (N,).
        offset: the origin's pixel minus the box centre, in units of the box side, (N, 2).
    """

    name: str
    rotations: np.ndarray
    bits: np.ndarray
    side: np.ndarray
    offset: np.ndarray

    @classmethod
    def build(
        cls, name: str, views: int, inplane: int, source: SilhouetteSource | None = None
    ) -> Codebook:
        """Draw the templates of `name` on the `sphere_rotations(views, inplane)` grid, saying so
        in one line on standard error (it takes seconds; the estimator's `CodebookCache` keeps
        the result, by default in ``<data root>/codebooks``, so it happens once per object)."""
        print(
            f"building the {name}'s silhouette codebook ({views} views x {inplane} turns; once: "
            f"it is cached in {in_repo(data_root() / 'codebooks')})",
            file=sys.stderr,
            flush=True,
        )
        pieces = (source or ConvexParts()).parts(name).pieces
        verts = np.concatenate(pieces)
        ends = np.cumsum([0] + [len(p) for p in pieces])
        pieces_at = [slice(int(i0), int(i1)) for i0, i1 in itertools.pairwise(ends)]
        R = sphere_rotations(views, inplane)
        S = SILHOUETTE_PX
        bits = np.empty((len(R), S * S // 64), np.uint64)
        side, offset = np.empty(len(R)), np.empty((len(R), 2))
        sil = np.zeros((S, S), np.uint8)
        # A batch of rotations at a time: every vertex under all of them at once would fill
        # memory (rotations x vertices x 3) and wait on it.
        for n0 in range(0, len(R), BUILD_BATCH):
            X = np.einsum("nij,vj->inv", R[n0 : n0 + BUILD_BATCH], verts)
            uv = TEMPLATE_F * X[:2] / (TEMPLATE_Z + X[2])  # (2, batch, vertices)
            lo, hi = uv.min(2).T, uv.max(2).T
            centre, span = (lo + hi) / 2, (hi - lo).max(1)
            side[n0 : n0 + len(span)] = span
            offset[n0 : n0 + len(span)] = -centre / span[:, None]  # the origin projects at (0, 0)
            px = (uv - centre.T[:, :, None]) * (FILL * S / span)[:, None] + S / 2
            px = px.transpose(1, 2, 0)
            px32, pts16 = px.astype(np.float32), np.round(px * 16).astype(np.int32)
            for k in range(len(span)):
                sil[:] = 0
                _fill(sil, px32[k], pts16[k], pieces_at)
                bits[n0 + k] = _pack(sil.view(bool))
        return cls(name, R, bits, side, offset)

    def save(self, path: Path) -> None:
        """Write the codebook to an .npz file (atomically)."""
        tmp = path.with_name(path.name + ".part.npz")
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(tmp, rotations=self.rotations, bits=self.bits, side=self.side, offset=self.offset)
        tmp.replace(path)

    @classmethod
    def load(cls, name: str, path: Path) -> Codebook:
        """A codebook written by `save`."""
        with np.load(path) as z:
            return cls(name, z["rotations"], z["bits"], z["side"], z["offset"])

    @cached_property
    def counts(self) -> np.ndarray:
        """Pixels of each template's silhouette, (N,) int64."""
        return np.bitwise_count(self.bits).sum(1, dtype=np.int64)

    def match(
        self,
        mask_bits: np.ndarray,
        hidden_bits: np.ndarray | None = None,
        templates: slice = slice(None),
    ) -> np.ndarray:
        """Silhouette IoU of a packed observed mask with every template (or those of
        `templates`), (N,); template pixels in `hidden_bits` (where something else may hide
        the object) do not count against it. Each template's IoU is the same whichever others
        are matched with it.

        With T a template, M the mask and H the hidden pixels outside it, the union is
        ``|T| - |T & H| + |M| - |T & M|``: only the intersections are counted (at most
        `SILHOUETTE_PX`**2 pixels: 16-bit sums), a block of templates at a time so that the
        block stays in the cache."""
        mask_bits = np.ascontiguousarray(mask_bits, np.uint64)
        hidden = None
        if hidden_bits is not None:
            hidden = np.asarray(hidden_bits, np.uint64) & ~mask_bits
        bits = self.bits[templates]
        inter = np.empty(len(bits), np.int64)
        covered = np.zeros(len(bits), np.int64)
        buf = np.empty((MATCH_BLOCK, bits.shape[1]), np.uint64)
        for a in range(0, len(bits), MATCH_BLOCK):
            block = bits[a : a + MATCH_BLOCK]
            out = buf[: len(block)]
            both = np.bitwise_and(block, mask_bits, out=out)
            inter[a : a + len(block)] = np.bitwise_count(both).sum(1, dtype=np.uint16)
            if hidden is not None:
                both = np.bitwise_and(block, hidden, out=out)
                covered[a : a + len(block)] = np.bitwise_count(both).sum(1, dtype=np.uint16)
        size = int(np.bitwise_count(mask_bits).sum())
        union = self.counts[templates] - covered + size - inter
        return inter / np.maximum(union, 1)


def _fill(canvas: np.ndarray, px32: np.ndarray, pts16: np.ndarray, pieces: list[slice]) -> None:
    """Fill the union of the convex hulls of each piece's projected points: `px32` (N, 2)
    float32 [px], `pts16` the same in sixteenths of a pixel (N, 2) int32, `pieces` each piece's
    points."""
    for piece in pieces:
        hull = cv2.convexHull(px32[piece], returnPoints=False)[:, 0]
        cv2.fillConvexPoly(canvas, pts16[piece][hull], 1, cv2.LINE_8, 4)


@dataclass(frozen=True)
class MaskView:
    """A detected mask framed as the templates are.

    Attributes:
        bits: the packed silhouette, (SILHOUETTE_PX**2 / 64,) uint64.
        centre: the centre of the mask's box in the image [px], (2,).
        side: the longer side of the box it is framed by [px] (the mask's own box, or one grown
            towards an occluder).
        hidden: packed pixels where something else may hide the object, or None.
    """

    bits: np.ndarray
    centre: np.ndarray
    side: float
    hidden: np.ndarray | None = None


def _framed(image: np.ndarray, centre: np.ndarray, side: float) -> np.ndarray:
    """A bool image (H, W) drawn into the templates' square around a box of `side` at `centre`."""
    S = SILHOUETTE_PX
    k = FILL * S / side
    # Pixel centres at integer coordinates in both: canvas = (image - centre) * k + S / 2.
    A = np.array([[k, 0.0, S / 2 - k * centre[0]], [0.0, k, S / 2 - k * centre[1]]])
    m = cv2.warpAffine(image.astype(np.float32), A, (S, S), flags=cv2.INTER_LINEAR)
    return _pack(m >= 0.5)


def frame_mask(mask: np.ndarray) -> MaskView | None:
    """The mask (H, W) bool drawn into the templates' square around its box; None when empty."""
    ys, xs = np.nonzero(mask)
    if xs.size == 0:
        return None
    lo = np.array([xs.min(), ys.min()], float) - 0.5  # pixel edges
    hi = np.array([xs.max(), ys.max()], float) + 0.5
    centre, s = (lo + hi) / 2, float(max(hi - lo))
    return MaskView(_framed(mask, centre, s), centre, s)


def _edge_touch(mask: np.ndarray, band: int = EDGE_BAND_PX) -> np.ndarray:
    """Where the mask meets the image's edge: its pixels in the outer `band` rows and columns
    (a detector's mask may stop a pixel short of the edge), moved out of the image, (n, 2)
    [px]."""
    H, W = mask.shape
    cols = (-1, mask[:, :band].any(1)), (W, mask[:, W - band :].any(1))
    rows = (-1, mask[:band].any(0)), (H, mask[H - band :].any(0))
    pts = [np.stack([np.full(np.count_nonzero(m), u), np.flatnonzero(m)], 1) for u, m in cols]
    pts += [np.stack([np.flatnonzero(m), np.full(np.count_nonzero(m), v)], 1) for v, m in rows]
    return np.concatenate(pts).astype(float)


def occluded_views(
    mask: np.ndarray, occluder: np.ndarray | None, view: MaskView, grow: tuple[float, ...]
) -> list[MaskView]:
    """Where an occluder or the image's edge touches the mask, the mask framed as if the object
    went on behind it: its box side times each factor of `grow`, the box moved towards where it
    is cut off so that its far edge stays; each view carries the occluder's pixels and those
    beyond the image as hidden. The unchanged framing comes first (factor 1, hidden pixels
    included). Empty when nothing touches the mask."""
    if not grow:
        return []
    hidden = np.zeros(mask.shape, bool) if occluder is None else occluder & ~mask
    touch = []
    if occluder is not None:
        near = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        ys, xs = np.nonzero(near & hidden)
        if len(xs) >= 3:
            touch.append(np.stack([xs, ys], 1).astype(float))
    if len(edge := _edge_touch(mask)) >= 3:
        touch.append(edge)
    if not touch:
        return []
    d = np.concatenate(touch).mean(0) - view.centre
    if (n := float(np.linalg.norm(d))) < 1e-6:
        return []
    d /= n

    image = np.ones(mask.shape, bool)

    def hidden_bits(centre: np.ndarray, side: float) -> np.ndarray:
        """The occluder's pixels and those beyond the image, framed."""
        return _framed(hidden, centre, side) | ~_framed(image, centre, side)

    out = [MaskView(view.bits, view.centre, view.side, hidden_bits(view.centre, view.side))]
    for g in grow:
        side = view.side * g
        centre = view.centre + d * (side - view.side) / 2
        out.append(MaskView(_framed(mask, centre, side), centre, side, hidden_bits(centre, side)))
    return out


def hypothesis_pose(book: Codebook, index: int, view: MaskView, K: np.ndarray) -> np.ndarray:
    """The full pose T_C_O (4, 4) that template `index` gives for the framed mask `view` seen
    with intrinsics K."""
    scale = view.side / book.side[index]
    uv = view.centre + book.offset[index] * view.side
    f = math.sqrt(K[0, 0] * K[1, 1])
    dist = TEMPLATE_Z * (f / TEMPLATE_F) / scale
    ray = np.linalg.solve(K, np.array([uv[0], uv[1], 1.0]))
    T = np.eye(4)
    T[:3, :3] = r_corr(uv, K) @ book.rotations[index]
    T[:3, 3] = dist * ray / np.linalg.norm(ray)
    return T


def resting_templates(
    book: Codebook,
    view: MaskView,
    K: np.ndarray,
    up_C: np.ndarray,
    ups_O: np.ndarray,
    tilt_deg: float,
) -> np.ndarray:
    """Which templates, framed by `view`, give a pose within `tilt_deg` of resting: the
    object's axis that would point up (any of `ups_O`, (k, 3) in O, one per resting pose)
    within that angle of the world's vertical `up_C` (in the camera frame); (N,) bool. The
    ray's correction is taken at the view's centre (within a degree or two of each template's
    own)."""
    w = r_corr(view.centre, K).T @ up_C  # the vertical in the template camera's frame
    up_O = np.einsum("nji,j->ni", book.rotations, w)  # ... in each template's object frame
    return (up_O @ ups_O.T).max(1) >= math.cos(math.radians(tilt_deg))


def rotation_cosines(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """cos of the angle between every rotation of A (a, 3, 3) and every one of B (b, 3, 3):
    (trace(R_a R_b^T) - 1) / 2, (a, b)."""
    return (A.reshape(len(A), 9) @ B.reshape(len(B), 9).T - 1) / 2


def top_hypotheses(
    scores: np.ndarray, rotations: np.ndarray, k: int, min_angle_deg: float, pool: int = 400
) -> list[int]:
    """Indices of up to `k` best-scoring templates, each at least `min_angle_deg` in rotation
    from every better one kept (greedy non-maximum suppression over the best `pool`)."""
    if len(scores) > pool:  # the stable sort's first `pool`, without sorting all of them
        bar = np.partition(scores, len(scores) - pool)[len(scores) - pool]
        best = np.flatnonzero(scores >= bar)
        order = best[np.argsort(-scores[best], kind="stable")[:pool]]
    else:
        order = np.argsort(-scores, kind="stable")
    n = len(rotations)  # scores may hold several framings of the same templates, one after another
    R = rotations[order % n]
    near = rotation_cosines(R, R) > math.cos(math.radians(min_angle_deg))
    kept: list[int] = []
    for a in range(len(order)):
        if not near[a, kept].any():
            kept.append(a)
            if len(kept) == k:
                break
    return [int(order[a]) for a in kept]


class CodebookCache:
    """Codebooks by object, built on first use and kept on disk (`folder`) and in memory.

    A file is named by the object, the grid and a digest of the pieces it was drawn from
    (`pieces_digest`), so an object made again from another mesh under the same name (``add_object
    --force``) gets a codebook of its own, never the old one's."""

    def __init__(
        self,
        views: int,
        inplane: int,
        folder: Path | None = None,
        source: SilhouetteSource | None = None,
    ) -> None:
        self.views, self.inplane = views, inplane
        self.folder = folder if folder is not None else data_root() / "codebooks"
        self.source = source or ConvexParts()
        self._books: dict[str, Codebook] = {}

    def get(self, name: str) -> Codebook:
        """The codebook of object `name`."""
        if name not in self._books:
            digest = pieces_digest(self.source.parts(name).pieces)
            path = self.folder / f"{name}_{self.views}x{self.inplane}_{digest}.npz"
            try:
                book = Codebook.load(name, path)
            except (OSError, KeyError, ValueError):
                book = Codebook.build(name, self.views, self.inplane, self.source)
                try:
                    book.save(path)
                except OSError:
                    pass  # a read-only data folder: the codebook stays in memory
            self._books[name] = book
        return self._books[name]


def pieces_digest(pieces: list[np.ndarray]) -> str:
    """A short digest of an object's convex pieces (their vertices in O, in order)."""
    h = hashlib.sha256()
    for p in pieces:
        h.update(np.ascontiguousarray(p, np.float64).tobytes())
        h.update(b"|")
    return h.hexdigest()[:12]


#: A framing of a detected mask as the codebook matches it: packed mask bits, packed hidden
#: pixels or None (`MaskView`).
Framing = tuple[np.ndarray, np.ndarray | None]


@dataclass(frozen=True, eq=False)
class TemplateMatch:
    """A codebook's matching as a job of `perception.parallel`: an item is (framings, the
    templates to match), its result each framing's IoUs with those templates
    (`Codebook.match`). Each template's IoU is the same whichever others are matched with it,
    so the templates may be split between processes."""

    book: Codebook

    def run(self, item: tuple[list[Framing], slice]) -> list[np.ndarray]:
        """Each framing's IoUs with the item's templates."""
        framings, templates = item
        return [self.book.match(bits, hidden, templates) for bits, hidden in framings]

    def scores(self, framings: list[Framing], executor: Executor) -> np.ndarray:
        """Each framing's IoUs with every template, the framings' arrays joined
        (framing-major): the two halves of the templates as two items of `executor`."""
        half = len(self.book.rotations) // 2
        items = [(framings, slice(0, half)), (framings, slice(half, None))]
        first, later = executor.map(self, items)
        return np.concatenate([np.concatenate(pair) for pair in zip(first, later, strict=True)])
