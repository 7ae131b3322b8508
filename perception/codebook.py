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

The silhouettes come from a `SilhouetteSource` (today the convex parts' projected hulls, as in
`perception.refine`); a mesh source can take its place without changing the matching.
"""

from __future__ import annotations

import itertools
import math
import sys
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from perception.geometry import r_corr
from posegrasp.core.errors import InvalidArgumentError
from posegrasp.core.paths import data_root, in_repo
from posegrasp.world.objects import load_object

#: Side of the square a silhouette is drawn into [px].
SILHOUETTE_PX = 64
#: The silhouette's longer box side fills this share of the square.
FILL = 0.875
#: The virtual camera of the templates: focal length [px] and distance to the origin [m].
TEMPLATE_F = 1000.0
TEMPLATE_Z = 1.0
#: Templates matched at a time (a block of their bits stays in the cache).
MATCH_BLOCK = 512
#: Width of the edge agreement's fall-off with the distance to an image edge [px].
EDGE_SIGMA_PX = 1.5
#: A mask with pixels this close to the image's edge [px] counts as cut off by it.
EDGE_BAND_PX = 2


class SilhouetteSource(Protocol):
    """Draws an object's silhouette: projected points and the convex pieces they form."""

    def pieces(self, name: str) -> list[np.ndarray]:
        """The object's convex pieces: vertices in O [m], each (n_i, 3)."""
        ...


class ConvexParts:
    """The convex pieces of any object (`ObjectModel.convex_pieces`): a built-in object's
    primitive parts, a user object's collision hulls (`python -m sim.add_object`)."""

    def __init__(self) -> None:
        self._cache: dict[str, list[np.ndarray]] = {}

    def pieces(self, name: str) -> list[np.ndarray]:
        if name not in self._cache:
            self._cache[name] = [
                np.unique(np.asarray(m.vertices), axis=0)
                for m, _ in load_object(name).convex_pieces()
            ]
        return self._cache[name]


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
        pieces = (source or ConvexParts()).pieces(name)
        verts = np.concatenate(pieces)
        slices = np.cumsum([0] + [len(p) for p in pieces])
        R = sphere_rotations(views, inplane)
        S = SILHOUETTE_PX
        X = np.einsum("nij,vj->nvi", R, verts)
        uv = TEMPLATE_F * X[..., :2] / (TEMPLATE_Z + X[..., 2:3])
        lo, hi = uv.min(1), uv.max(1)
        centre, side = (lo + hi) / 2, (hi - lo).max(1)
        offset = -centre / side[:, None]  # the origin projects at (0, 0)
        px = (uv - centre[:, None]) * (FILL * S / side)[:, None, None] + S / 2
        bits = np.empty((len(R), S * S // 64), np.uint64)
        sil = np.zeros((S, S), np.uint8)
        for n in range(len(R)):
            sil[:] = 0
            _fill(sil, px[n], slices)
            bits[n] = _pack(sil.view(bool))
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


def _fill(canvas: np.ndarray, px: np.ndarray, slices: np.ndarray) -> None:
    """Fill the union of the convex hulls of each piece's projected points (N, 2) [px]."""
    pts16 = np.round(px * 16).astype(np.int32)
    for i0, i1 in itertools.pairwise(slices):
        hull = cv2.convexHull(px[i0:i1].astype(np.float32), returnPoints=False)[:, 0] + i0
        cv2.fillConvexPoly(canvas, pts16[hull], 1, cv2.LINE_8, 4)


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


#: Two pieces count as separated by a face plane of one of them when the other reaches through
#: it by at most this share of its own depth along the plane's normal (parts are modelled
#: touching or slightly sunk into each other: a keypad half a millimetre into its base).
SEPARATION_SLACK = 0.25


@dataclass(frozen=True)
class Separations:
    """For every ordered pair (i, j) of an object's convex pieces, a plane of the object frame
    from the faces of either hull with piece i on its inner side and piece j on its outer side:
    seen from the outer side, j hides i where they overlap, and from the inner side i hides j
    (a ray crosses the plane once). Painting far pieces first by their mean depth alone gets
    this wrong when a small piece lies on a face turned away from the camera (a button on top
    of a base seen from below).

    Attributes:
        normal: (P, P, 3) unit normals, pointing from i's side to j's.
        offset: (P, P) plane offsets: the plane is normal . x = offset [m].
        known: (P, P) whether a face plane separates the pair (within `SEPARATION_SLACK`);
            where not, the mean depths decide.
    """

    normal: np.ndarray
    offset: np.ndarray
    known: np.ndarray

    @classmethod
    def of(cls, pieces: list[np.ndarray]) -> Separations:
        P = len(pieces)
        normal, offset = np.zeros((P, P, 3)), np.zeros((P, P))
        known = np.zeros((P, P), bool)
        faces = [_face_planes(v) for v in pieces]
        for i, j in itertools.permutations(range(P), 2):
            best, plane = -math.inf, None
            # i's faces with j outside them, then j's faces with i outside them (turned round)
            for own, other, sign in ((i, j, 1.0), (j, i, -1.0)):
                n, b = faces[own]
                if n is None:
                    continue
                reach = pieces[other] @ n.T - b  # >= 0: outside the face
                margin = reach.min(0) / np.maximum(np.ptp(pieces[other] @ n.T, axis=0), 1e-9)
                k = int(np.argmax(margin))
                if margin[k] > best:
                    best, plane = margin[k], (sign * n[k], sign * b[k])
            if plane is not None and best >= -SEPARATION_SLACK:
                normal[i, j], offset[i, j], known[i, j] = plane[0], plane[1], True
        return cls(normal, offset, known)

    def in_front(self, camera: np.ndarray) -> np.ndarray:
        """(P, P) bool: piece j hides piece i where they overlap, seen from `camera` (its
        position in the object frame [m])."""
        return self.known & (self.normal @ camera > self.offset)


def _face_planes(vertices: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The outward unit normals (F, 3) and offsets (F,) of the hull faces of a piece (normal .
    x <= offset inside), or (None, None) for a flat piece."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        eq = ConvexHull(vertices).equations
    except (QhullError, ValueError):
        return None, None
    return eq[:, :3], -eq[:, 3]


_SEPARATIONS: dict[bytes, Separations] = {}


def separations(pieces: list[np.ndarray]) -> Separations:
    """`Separations.of(pieces)`, computed once per set of pieces."""
    key = b"".join(np.ascontiguousarray(v, np.float64).tobytes() + b"|" for v in pieces)
    if key not in _SEPARATIONS:
        _SEPARATIONS[key] = Separations.of(pieces)
    return _SEPARATIONS[key]


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
    pieces: list[np.ndarray], T: np.ndarray, K: np.ndarray, origin: tuple[int, int]
) -> list[tuple[int, np.ndarray]] | None:
    """Each piece's projected hull at pose T, as (piece index, polygon in 1/16 px relative to
    the pixel `origin`), in drawing order (`drawing_order`: far first, each piece after those
    it hides); None when a vertex lies behind the camera."""
    depth, drawn = [], []
    for piece in pieces:
        X = piece @ T[:3, :3].T + T[:3, 3]
        if X[:, 2].min() < 1e-3:
            return None
        depth.append(float(X[:, 2].mean()))
        drawn.append(((X @ K.T)[:, :2] / X[:, 2:3] - np.array(origin)).astype(np.float32))
    camera = -T[:3, :3].T @ T[:3, 3]
    out = []
    for i in drawing_order(np.array(depth), separations(pieces).in_front(camera)):
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
    pieces: list[np.ndarray],
    colours: np.ndarray,
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
      pieces' colours (`colours`, (pieces, 3) in [0, 1]) with the image;
    - edges: how well the pieces' outlines (every boundary between pieces and with the
      background) lie on image edges, `edge_distance` being `image_edges` of the same window:
      the mean of exp(-d^2 / 2 sigma^2) over the outline pixels, sigma `EDGE_SIGMA_PX`, in
      [0, 1].

    Both are 0 when undefined (too few pixels, or a vertex behind the camera)."""
    ids = id_map(pieces, T, K, box)
    if ids is None:
        return 0.0, 0.0
    return _appearance(ids, colours, rgb, mask, box), _edges(ids, edge_distance)


def id_map(
    pieces: list[np.ndarray], T: np.ndarray, K: np.ndarray, box: tuple[int, int, int, int]
) -> np.ndarray | None:
    """Which piece (1-based, 0: none) covers each pixel of the window `box` (x0, y0, x1, y1)
    [px] at pose T, far pieces drawn first, (h, w) uint8; None when a vertex lies behind the
    camera."""
    x0, y0, x1, y1 = box
    polygons = _far_to_near(pieces, T, K, (x0, y0))
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
    d = edge_distance[outline]
    if d.size < 10:
        return 0.0
    return float(np.mean(np.exp(-(d * d) / (2 * EDGE_SIGMA_PX * EDGE_SIGMA_PX))))
