"""An object's convex pieces: what the codebook, the refiner and the verification draw.

Every built-in object is made of convex primitives and every user object of convex collision
hulls (`posegrasp.world.objects.ObjectModel.convex_pieces`), so a silhouette is the union of the
convex hulls of each piece's projected vertices. `Parts` holds one object's pieces as data (it
pickles, so work on another process draws exactly what this one draws); a `SilhouetteSource`
gives them by name, `ConvexParts` from the objects' own geometry.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np

from posegrasp.world.objects import load_object


class SilhouetteSource(Protocol):
    """Where an object's silhouette comes from: the convex pieces it is the union of."""

    def parts(self, name: str) -> Parts:
        """The object's convex pieces and their colours."""
        ...


@dataclass(frozen=True, eq=False)
class Parts:
    """One object's convex pieces.

    Attributes:
        name: the object.
        pieces: the vertices of each piece in O [m], each (n_i, 3).
        colours: RGB of each piece, (pieces, 3) in [0, 1].
    """

    name: str
    pieces: list[np.ndarray]
    colours: np.ndarray

    @cached_property
    def stacked(self) -> tuple[np.ndarray, np.ndarray]:
        """Every piece's vertices in one array (n, 3) [m], and where each piece starts in it
        (pieces + 1,), the last entry n."""
        return np.concatenate(self.pieces), np.cumsum([0] + [len(p) for p in self.pieces])

    @cached_property
    def separations(self) -> Separations:
        """Which piece hides which, by the planes between them (`Separations`)."""
        return Separations.of(self.pieces)


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
                assert b is not None  # None only with n (a flat piece)
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


class ConvexParts:
    """The convex pieces of any object (`ObjectModel.convex_pieces`): a built-in object's
    primitive parts, a user object's collision hulls (`python -m sim.add_object`); each object's
    loaded once."""

    def __init__(self) -> None:
        self._parts: dict[str, Parts] = {}

    def parts(self, name: str) -> Parts:
        """The pieces of `name` with their colours.

        Raises:
            UnknownNameError: name is not a known object (the message lists them).
        """
        if name not in self._parts:
            convex = load_object(name).convex_pieces()
            pieces = [np.unique(np.asarray(m.vertices), axis=0) for m, _ in convex]
            colours = np.array([rgba[:3] for _, rgba in convex])
            self._parts[name] = Parts(name, pieces, colours)
        return self._parts[name]

    def pieces(self, name: str) -> list[np.ndarray]:
        """The vertices of each convex piece of `name` in O [m], each (n_i, 3)."""
        return self.parts(name).pieces
