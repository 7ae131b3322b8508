"""From a mesh file to the geometry of a user object: reading and checking the mesh, its convex
decomposition, mass properties from the hulls, symmetry detection and the object frame.

Every function works in metres. A mesh is refused (`InvalidArgumentError`, one line saying why)
when it cannot become an object: unreadable, empty, degenerate, or sized as if its units were
wrong by orders of magnitude.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from posegrasp.core.errors import InvalidArgumentError

#: Length units a mesh file may be in, and their size in metres.
UNITS: dict[str, float] = {"m": 1.0, "mm": 1e-3}
#: Mesh formats read (by suffix).
MESH_SUFFIXES = (".obj", ".stl", ".ply", ".glb", ".gltf")
#: Sizes an object may have: its largest extent [m]. Outside, the units are taken to be wrong.
MIN_SIZE = 0.01
MAX_SIZE = 1.0
#: Thinnest extent an object may have [m] (a sheet without thickness has no volume).
MIN_THICKNESS = 0.002
#: A symmetry holds when the rotated surface lies this close to the surface (99th percentile of
#: the distances), as a fraction of the diameter, or within twice the sampling's own distances.
SYMMETRY_TOL = 0.01
#: n-fold symmetries tested about each candidate axis.
FOLDS = (2, 3, 4, 5, 6, 8, 10, 12)
#: Rotations [rad] a continuous symmetry must pass (irrational fractions of a turn).
CONTINUOUS_TEST_ANGLES = (0.41, 1.13, 2.27, 2.95, 4.37)
#: The most symmetry transforms a discrete group may have (the icosahedron's).
MAX_GROUP = 60
#: Meshes of more triangles are simplified to this many (quadric decimation) before CoACD cuts
#: them into hulls: reading, checking and remeshing cost it time with every triangle, and hulls
#: of at most ``max_ch_vertex`` vertices carry none of the detail lost. The visual mesh keeps
#: them all. A mesh CoACD finds not manifold (decimation leaves most so) it remeshes at its own
#: ``preprocess_resolution`` and cuts that, so the cap does not bound the cutting's time: the
#: resolution does (a coarser remesh has fewer triangles and fewer small concavities to cut).
DECOMPOSE_MAX_FACES = 5000
#: A mesh is its own single hull when its convex hull lies this close to its surface everywhere
#: (the largest distance of samples of the hull's surface from the mesh's), as a fraction of the
#: diagonal of its bounding box, or within twice the sampling's own distances: CoACD would stop
#: at one hull, after remeshing it, and the hull of the mesh itself fits it better.
CONVEX_TOL = 0.01
#: Cells per side of the grid `points_diameter` groups many points in.
DIAMETER_GRID = 16
#: Passes of quadric decimation `simplified` makes at most.
SIMPLIFY_PASSES = 4
#: Default CoACD parameters (`decompose`).
COACD_DEFAULTS: dict[str, Any] = {
    "threshold": 0.05,
    "max_convex_hull": 24,
    "preprocess_mode": "auto",
    "preprocess_resolution": 25,
    "resolution": 1000,
    "mcts_nodes": 15,
    "mcts_iterations": 80,
    "mcts_max_depth": 2,
    "merge": True,
    "decimate": True,
    "max_ch_vertex": 64,
    "seed": 0,
}


def read_mesh(path: Path | str) -> trimesh.Trimesh:
    """The triangles of a mesh file (OBJ, STL, PLY, GLB/glTF), a scene's meshes joined in the
    file's frame, in the file's units.

    Raises:
        InvalidArgumentError: the file is missing, of another format, unreadable or holds no
            triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise InvalidArgumentError(f"cannot read {path}: no such file")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InvalidArgumentError(
            f"cannot read {path}: unknown format {path.suffix!r}; valid: "
            + ", ".join(MESH_SUFFIXES)
        )
    try:
        # An OBJ's MTL may name its image up the tree (``../../textures/x.png``, as packaged
        # object sets lay theirs out): the user's own file, so it is read where it points.
        resolver = trimesh.resolvers.FilePathResolver(str(path), allow_anywhere=True)
        loaded = trimesh.load(path, force="mesh", resolver=resolver)
    except Exception as exc:  # trimesh raises whatever its parsers raise
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InvalidArgumentError(f"cannot read {path}: {first}") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise InvalidArgumentError(
            f"cannot use {path.name}: it holds no triangles (empty, or not a mesh file)"
        )
    return loaded


def _texture_image(material: Any) -> Any:
    """A trimesh material's texture image (PIL), or None: an OBJ's material holds its image, a
    glTF's PBR material its base colour texture."""
    return getattr(material, "image", None) or getattr(material, "baseColorTexture", None)


def mesh_colour(mesh: trimesh.Trimesh) -> np.ndarray:
    """The mesh's main colour as rgba in [0, 1] (4,): the material's diffuse colour or the
    average vertex or face colour; a neutral clay when it has none."""
    default = np.array([0.72, 0.6, 0.45, 1.0])
    visual: Any = mesh.visual  # trimesh's visuals differ in kind; each is read for what it has
    try:
        if visual.kind == "texture" and getattr(visual, "material", None) is not None:
            material = visual.material
            colour = getattr(material, "main_color", None)
            image = _texture_image(material)
            if image is not None:
                arr = np.asarray(image.convert("RGBA"), float).reshape(-1, 4) / 255.0
                return np.r_[arr[:, :3].mean(axis=0), 1.0]
            if colour is not None:
                return np.r_[np.asarray(colour[:3], float) / 255.0, 1.0]
        if visual.kind in ("vertex", "face"):
            cols = np.asarray(visual.vertex_colors, float)[:, :3] / 255.0
            if len(cols):
                return np.r_[cols.mean(axis=0), 1.0]
    except (AttributeError, ValueError, TypeError):
        pass
    return default


@dataclass(frozen=True)
class Texture:
    """A mesh's texture, with the mesh as drawn: its own vertices, so that a vertex on a seam of
    the texture keeps a coordinate on each side.

    Attributes:
        vertices: (V, 3) [m].
        faces: (F, 3) vertex indices.
        uv: (V, 2) texture coordinates, u to the right, v up from the image's bottom row (OBJ's
            convention; trimesh turns glTF's into it).
        image: the texture (H, W, 3) uint8, top row first.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    image: np.ndarray

    def moved(self, T: np.ndarray) -> Texture:
        """This texture on the mesh moved by T (4, 4)."""
        v = self.vertices @ T[:3, :3].T + T[:3, 3]
        return Texture(v, self.faces, self.uv, self.image)


def mesh_texture(mesh: trimesh.Trimesh, factor: float) -> Texture | None:
    """The texture of a mesh as read (`read_mesh`: an OBJ with its MTL and image, a GLB with its
    embedded image), its vertices scaled by `factor` into metres; None when it has no texture
    image with a coordinate for every vertex."""
    visual: Any = mesh.visual
    image = _texture_image(getattr(visual, "material", None))
    uv = getattr(visual, "uv", None)
    if getattr(visual, "kind", None) != "texture" or image is None or uv is None:
        return None
    uv = np.asarray(uv, float)
    v = np.asarray(mesh.vertices, float) * factor
    if uv.shape != (len(v), 2) or not np.all(np.isfinite(uv)) or not np.all(np.isfinite(v)):
        return None
    pixels = np.asarray(image.convert("RGB"), np.uint8)
    return Texture(v, np.asarray(mesh.faces, np.int64), uv, pixels)


def scaled_mesh(mesh: trimesh.Trimesh, units: str, scale: float, source: str) -> trimesh.Trimesh:
    """The mesh in metres (its units times `scale`), cleaned of unused and non-finite vertices
    and of degenerate faces, checked for a size an object can have.

    Args:
        mesh: as read, in the file's units.
        units: one of `UNITS`.
        scale: extra factor applied after the units.
        source: the file's name, for messages.

    Raises:
        InvalidArgumentError: unknown units, an empty or degenerate mesh, or a size that says
            the units are wrong (largest extent outside `MIN_SIZE`..`MAX_SIZE`).
    """
    if units not in UNITS:
        raise InvalidArgumentError(f"unknown units {units!r}; valid: {', '.join(UNITS)}")
    v = np.asarray(mesh.vertices, float) * UNITS[units] * scale
    f = np.asarray(mesh.faces, np.int64)
    if not np.all(np.isfinite(v)):
        keep = np.all(np.isfinite(v[f].reshape(len(f), -1)), axis=1)
        f = f[keep]
    out = trimesh.Trimesh(v, f, process=True, validate=False)
    if len(f):
        area = trimesh.triangles.area(out.triangles)
        out.update_faces(area > 0)
        out.remove_unreferenced_vertices()
    if len(out.faces) == 0 or out.area <= 0:
        raise InvalidArgumentError(f"cannot use {source}: every triangle is degenerate (no area)")
    ext = np.asarray(out.extents)
    size = float(ext.max())
    given = f"{units}" + (f" x {scale:g}" if scale != 1 else "")
    if size > MAX_SIZE:
        hint = " (are the units mm? give --units mm)" if units == "m" else " (check --scale)"
        raise InvalidArgumentError(
            f"cannot use {source}: it is {size:.3g} m wide read in {given}, more than an object "
            f"the gripper can take ({MAX_SIZE:g} m){hint}"
        )
    if size < MIN_SIZE:
        hint = " (are the units m? give --units m)" if units == "mm" else " (check --scale)"
        raise InvalidArgumentError(
            f"cannot use {source}: it is {size * 1000:.3g} mm wide read in {given}, less than "
            f"{MIN_SIZE * 1000:g} mm{hint}"
        )
    if float(ext.min()) < MIN_THICKNESS:
        raise InvalidArgumentError(
            f"cannot use {source}: it is flat ({ext.min() * 1000:.2g} mm thick, "
            f"{ext.max() * 1000:.3g} mm wide); an object needs at least "
            f"{MIN_THICKNESS * 1000:g} mm of thickness"
        )
    return out


def centred(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, np.ndarray]:
    """The mesh moved so that its bounding-box centre is the origin, and that shift T (4, 4)
    (new = T @ old)."""
    T = np.eye(4)
    T[:3, 3] = -(mesh.bounds[0] + mesh.bounds[1]) / 2
    out = mesh.copy()
    out.apply_transform(T)
    return out, T


@dataclass
class Decomposition:
    """A convex decomposition.

    Attributes:
        hulls: the convex hulls [m], each watertight.
        tool: the decomposition's tool and version.
        parameters: the parameters it was run with.
        seconds: how long it took [s], the simplification included.
        faces: the triangles of the mesh it cut: the mesh's own, or at most
            `DECOMPOSE_MAX_FACES` where it had more.
        simplified_from: the mesh's own triangles where it was simplified first, else None.
        convex: the mesh was its own hull (`is_convex`), so CoACD was not run.
    """

    hulls: list[trimesh.Trimesh]
    tool: dict[str, str]
    parameters: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0
    faces: int = 0
    simplified_from: int | None = None
    convex: bool = False


def decompose(mesh: trimesh.Trimesh, **overrides: Any) -> Decomposition:
    """Approximate convex decomposition with CoACD (`COACD_DEFAULTS`, updated by `overrides`).
    A mesh that is convex within `CONVEX_TOL` is its own hull (reduced to ``max_ch_vertex``
    vertices), without CoACD. Otherwise a mesh of over `DECOMPOSE_MAX_FACES` triangles is
    simplified to that many first (quadric decimation); one that is not watertight is remeshed
    by CoACD's own preprocessing.

    Raises:
        InvalidArgumentError: an unknown parameter, or CoACD found no hull.
    """
    import coacd

    unknown = sorted(set(overrides) - set(COACD_DEFAULTS))
    if unknown:
        raise InvalidArgumentError(
            f"unknown decomposition parameter(s) {', '.join(unknown)}; valid: "
            + ", ".join(COACD_DEFAULTS)
        )
    params = {**COACD_DEFAULTS, **overrides}
    from importlib.metadata import version

    tool = {"name": "coacd", "version": version("coacd")}
    t = time.perf_counter()
    if is_convex(mesh, int(params["seed"])):
        hull = reduced_hull(mesh, int(params["max_ch_vertex"]))
        n = len(mesh.faces)
        return Decomposition([hull], tool, params, time.perf_counter() - t, n, None, True)
    coacd.set_log_level("error")
    cut = simplified(mesh, DECOMPOSE_MAX_FACES)
    parts = coacd.run_coacd(
        coacd.Mesh(np.asarray(cut.vertices, float), np.asarray(cut.faces, np.int64)), **params
    )
    seconds = time.perf_counter() - t
    hulls = []
    for v, _f in parts:
        if len(v) >= 4:
            hull = trimesh.convex.convex_hull(np.asarray(v, float))
            if hull.volume > 0:
                hulls.append(hull)
    if not hulls:
        raise InvalidArgumentError("the convex decomposition found no hull of positive volume")
    return Decomposition(
        hulls,
        tool,
        params,
        seconds,
        len(cut.faces),
        len(mesh.faces) if cut is not mesh else None,
    )


def points_diameter(points: np.ndarray) -> float:
    """The largest distance between two of `points` (N, 3) [m], exact.

    Only the vertices of the points' convex hull can be the pair. Where they are many (a dense
    smooth mesh has every vertex on its hull), they are grouped in the cells of a grid
    (`DIAMETER_GRID` cells a side): the farthest of the groups' most outlying points bound the
    diameter from below, and only pairs of groups that can hold a pair farther apart (their
    centres' distance and both radii) are compared point by point, the likeliest first."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if len(pts) > 64:
        from scipy.spatial import ConvexHull, QhullError

        try:
            pts = pts[ConvexHull(pts).vertices]
        except QhullError:  # degenerate (flat or collinear) point sets: all of them
            pass
    if len(pts) <= 1024:
        return math.sqrt(_farthest_sq(pts, pts))
    lo, span = pts.min(axis=0), float(np.ptp(pts, axis=0).max())
    n = DIAMETER_GRID
    cell = np.minimum((n * (pts - lo) / span).astype(np.int64), n - 1)
    key = (cell[:, 0] * n + cell[:, 1]) * n + cell[:, 2]
    order = np.argsort(key, kind="stable")
    cuts = np.flatnonzero(np.diff(key[order])) + 1
    groups = [pts[g] for g in np.split(order, cuts)]
    centres = np.array([g.mean(axis=0) for g in groups])
    radii = np.array(
        [np.linalg.norm(g - c, axis=1).max() for g, c in zip(groups, centres, strict=True)]
    )
    middle = pts.mean(axis=0)
    outliers = np.array([g[np.argmax(np.linalg.norm(g - middle, axis=1))] for g in groups])
    best = _farthest_sq(outliers, outliers)  # a pair's distance: a bound from below
    bound = np.linalg.norm(centres[:, None] - centres[None], axis=-1) + radii[:, None] + radii
    i, j = np.triu_indices(len(groups))
    for k in np.argsort(-bound[i, j], kind="stable"):
        if bound[i[k], j[k]] ** 2 <= best:
            break  # no pair of groups left can hold a pair farther apart
        best = max(best, _farthest_sq(groups[i[k]], groups[j[k]]))
    return math.sqrt(best)


def _farthest_sq(a: np.ndarray, b: np.ndarray) -> float:
    """The largest squared distance between a point of `a` and one of `b` (each (N, 3))."""
    d = a[:, None, :] - b[None, :, :]
    return float(np.einsum("ijk,ijk->ij", d, d).max())


def is_convex(mesh: trimesh.Trimesh, seed: int = 0) -> bool:
    """Whether the mesh's convex hull lies within `CONVEX_TOL` of its surface everywhere: the
    largest distance of 5,000 samples of the hull's surface from 20,000 of the mesh's."""
    tester = SurfaceDistance(mesh, seed)
    tol = max(CONVEX_TOL * tester.diameter, 2.0 * tester.baseline)
    on_hull, _ = trimesh.sample.sample_surface(mesh.convex_hull, 5000, seed=seed + 2)
    return float(tester.distances(on_hull).max()) <= tol


def reduced_hull(mesh: trimesh.Trimesh, max_vertices: int) -> trimesh.Trimesh:
    """The mesh's convex hull with at most `max_vertices` vertices: where it has more, the hull
    of its vertices farthest out along the most evenly spread directions (a Fibonacci sphere)
    that pick at most that many, so that it lies inside the whole hull, touching it at each."""
    hull = mesh.convex_hull
    v = np.asarray(hull.vertices)
    if len(v) <= max_vertices:
        return hull
    lo, hi, kept = 4, 16 * max_vertices, np.argmax(v @ _fibonacci(4).T, axis=0)
    while lo <= hi:  # the most directions whose extreme vertices are few enough
        n = (lo + hi) // 2
        picked = np.unique(np.argmax(v @ _fibonacci(n).T, axis=0))
        if len(picked) <= max_vertices:
            kept, lo = picked, n + 1
        else:
            hi = n - 1
    return trimesh.convex.convex_hull(v[np.unique(kept)])


def _fibonacci(n: int) -> np.ndarray:
    """`n` unit directions spread evenly over the sphere (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def simplified(mesh: trimesh.Trimesh, max_faces: int) -> trimesh.Trimesh:
    """`mesh` itself if it has at most `max_faces` triangles, else its quadric decimation to
    that many (fast-simplification's, deterministic; a pass that stops short, as on a mesh of
    many seams, is followed by another, `SIMPLIFY_PASSES` in all)."""
    out = mesh
    for _ in range(SIMPLIFY_PASSES):
        if len(out.faces) <= max_faces:
            break
        out = out.simplify_quadric_decimation(face_count=max_faces)
    return out


@dataclass(frozen=True)
class MassProperties:
    """Mass distribution of a rigid object, uniform density over its hulls.

    Attributes:
        mass: [kg].
        volume: summed hull volume [m^3].
        density: [kg/m^3].
        com: centre of mass (3,) [m].
        inertia: about the centre of mass, axes of the mesh frame (3, 3) [kg m^2].
    """

    mass: float
    volume: float
    density: float
    com: np.ndarray
    inertia: np.ndarray


def mass_properties(
    hulls: list[trimesh.Trimesh], mass: float | None = None, density: float | None = None
) -> MassProperties:
    """Mass, centre of mass and inertia of the union of convex hulls at uniform density (their
    overlaps counted twice; CoACD's hulls barely overlap). Works whether or not the visual mesh
    is watertight, since every hull is.

    Args:
        hulls: watertight convex hulls [m].
        mass: the total mass [kg]; or
        density: the density [kg/m^3] (exactly one of the two).

    Raises:
        InvalidArgumentError: neither or both given, or not positive.
    """
    if (mass is None) == (density is None):
        raise InvalidArgumentError("give exactly one of mass and density")
    vols = np.array([h.volume for h in hulls])
    volume = float(vols.sum())
    if volume <= 0:
        raise InvalidArgumentError("the hulls enclose no volume")
    if mass is not None:
        if not mass > 0:
            raise InvalidArgumentError(f"mass must be positive, got {mass}")
        density = mass / volume
    assert density is not None
    if not density > 0:
        raise InvalidArgumentError(f"density must be positive, got {density}")
    coms = np.array([h.center_mass for h in hulls])
    com = (vols[:, None] * coms).sum(axis=0) / volume
    inertia = np.zeros((3, 3))
    for h, vol, c in zip(hulls, vols, coms, strict=True):
        d = c - com
        inertia += density * np.asarray(h.moment_inertia) + density * vol * (
            (d @ d) * np.eye(3) - np.outer(d, d)
        )
    return MassProperties(float(density * volume), volume, float(density), com, inertia)


def transform_inertia(props: MassProperties, T: np.ndarray) -> MassProperties:
    """The same mass distribution after the rigid transform T (4, 4) of the mesh."""
    R = T[:3, :3]
    return MassProperties(
        props.mass, props.volume, props.density, R @ props.com + T[:3, 3], R @ props.inertia @ R.T
    )


# -- symmetries -----------------------------------------------------------------------------


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    x, y, z = axis / np.linalg.norm(axis)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def _about(axis: np.ndarray, angle: float, centre: np.ndarray) -> np.ndarray:
    """Rotation by `angle` about the line through `centre` along `axis`, (4, 4)."""
    T = np.eye(4)
    T[:3, :3] = _axis_rotation(axis, angle)
    T[:3, 3] = centre - T[:3, :3] @ centre
    return T


def surface_centre(mesh: trimesh.Trimesh) -> np.ndarray:
    """Area-weighted centroid of the surface (3,) [m]; it lies on every symmetry axis, also of
    a mesh that is not watertight."""
    area = np.asarray(mesh.area_faces)
    return (np.asarray(mesh.triangles_center) * area[:, None]).sum(axis=0) / area.sum()


class SurfaceDistance:
    """Distances of points from a mesh's surface, measured to 20,000 samples of it (a KD-tree).

    Attributes:
        diameter: the diagonal of the mesh's bounding box [m].
        baseline: the sampling's own resolution: the 99th percentile of the distances of 2,000
            further samples of the surface [m].
    """

    def __init__(self, mesh: trimesh.Trimesh, seed: int = 0) -> None:
        dense, _ = trimesh.sample.sample_surface(mesh, 20000, seed=seed)
        self.points, _ = trimesh.sample.sample_surface(mesh, 2000, seed=seed + 1)
        self.tree = cKDTree(dense)
        self.diameter = float(np.linalg.norm(mesh.extents))
        self.baseline = float(np.percentile(self.distances(self.points), 99))

    def distances(self, points: np.ndarray) -> np.ndarray:
        """Each point's distance from the nearest sample of the surface [m]."""
        d, _ = self.tree.query(points)
        return np.asarray(d, float)


class SymmetryTester(SurfaceDistance):
    """Measures how far a rigid motion moves a mesh's surface off itself: a motion's error is
    the 99th percentile of the distances of the moved 2,000 test samples from the surface. The
    error of the identity is the sampling's own resolution.
    """

    def __init__(self, mesh: trimesh.Trimesh, seed: int = 0) -> None:
        super().__init__(mesh, seed)
        self.tol = max(SYMMETRY_TOL * self.diameter, 2.0 * self.baseline)

    def error(self, T: np.ndarray) -> float:
        """99th percentile of the distances of the moved surface from the surface [m]."""
        moved = self.points @ T[:3, :3].T + T[:3, 3]
        return float(np.percentile(self.distances(moved), 99))

    def holds(self, T: np.ndarray) -> bool:
        """Whether T maps the surface onto itself within the tolerance."""
        return self.error(T) <= self.tol


def _principal_axes(mesh: trimesh.Trimesh, centre: np.ndarray) -> np.ndarray:
    """Unit eigenvectors (rows) of the area-weighted second moment of the surface about centre."""
    area = np.asarray(mesh.area_faces)
    d = np.asarray(mesh.triangles_center) - centre
    cov = (d * area[:, None]).T @ d / area.sum()
    _, vecs = np.linalg.eigh(cov)
    return vecs.T


def _distinct(axes: list[np.ndarray]) -> list[np.ndarray]:
    out: list[np.ndarray] = []
    for a in axes:
        a = a / np.linalg.norm(a)
        if all(abs(a @ b) < 0.999 for b in out):
            out.append(a)
    return out


def _close_group(gens: list[np.ndarray]) -> list[np.ndarray]:
    """The group the transforms generate (identity included), at most `MAX_GROUP` elements."""
    group = [np.eye(4)]
    frontier = list(gens)
    while frontier and len(group) < MAX_GROUP:
        T = frontier.pop()
        if any(np.allclose(T, G, atol=1e-6) for G in group):
            continue
        group.append(T)
        frontier += [T @ G for G in group] + [G @ T for G in group]
    return group


@dataclass(frozen=True)
class Symmetries:
    """An object's proper symmetries, in BOP's models_info form.

    Attributes:
        discrete: transforms T_O_O' (4, 4) [m] besides the identity.
        continuous: (axis (3,), offset (3,) [m]) pairs: rotations by any angle about the line.
        source: "detected", "given" or "none".
        errors: the measured error of each symmetry, as a fraction of the diameter.
    """

    discrete: tuple[np.ndarray, ...] = ()
    continuous: tuple[tuple[np.ndarray, np.ndarray], ...] = ()
    source: str = "none"
    errors: tuple[float, ...] = ()

    def models_info(self) -> dict[str, Any]:
        """The ``symmetries_discrete`` and ``symmetries_continuous`` entries of BOP's
        models_info (translations and offsets in mm)."""
        out: dict[str, Any] = {}
        if self.discrete:
            rows = []
            for T in self.discrete:
                M = np.array(T, float)
                M[:3, 3] *= 1000.0
                rows.append([round(float(v), 9) for v in M.ravel()])
            out["symmetries_discrete"] = rows
        if self.continuous:
            out["symmetries_continuous"] = [
                {
                    "axis": [round(float(v), 9) for v in a],
                    "offset": [round(float(v) * 1000.0, 6) for v in c],
                }
                for a, c in self.continuous
            ]
        return out

    def describe(self) -> str:
        """One line: what the symmetries are."""
        if not self.discrete and not self.continuous:
            return "none"
        parts = [
            f"continuous about ({', '.join(f'{v:.2f}' for v in a)})" for a, _ in self.continuous
        ]
        if self.discrete:
            parts.append(f"{len(self.discrete)} discrete")
        return ", ".join(parts) + f" ({self.source})"

    def rotations(self, steps: int = 72) -> list[np.ndarray]:
        """The rotation parts (3, 3) of the symmetries, identity included, a continuous one
        taken every 360 / `steps` degrees (and composed with each discrete one)."""
        disc = [np.eye(3)] + [np.asarray(T)[:3, :3] for T in self.discrete]
        if not self.continuous:
            return disc
        out = []
        for a, _ in self.continuous:
            for k in range(steps):
                Rc = _axis_rotation(a, 2 * math.pi * k / steps)
                out += [Rc @ Rd for Rd in disc]
        return out

    def angle_deg(self, u: np.ndarray, v: np.ndarray) -> float:
        """The smallest angle [deg] between direction v and a symmetric image of direction u:
        how far apart two resting poses with these up directions are, up to symmetry."""
        cos = max(float((R @ u) @ v) for R in self.rotations())
        return math.degrees(math.acos(min(1.0, max(-1.0, cos))))

    def transformed(self, T: np.ndarray) -> Symmetries:
        """The same symmetries in the frame of the mesh moved by T (4, 4)."""
        Ti = np.linalg.inv(T)
        R = T[:3, :3]
        return Symmetries(
            tuple(T @ S @ Ti for S in self.discrete),
            tuple((R @ a, R @ c + T[:3, 3]) for a, c in self.continuous),
            self.source,
            self.errors,
        )


def detect_symmetries(mesh: trimesh.Trimesh, seed: int = 0) -> Symmetries:
    """The proper symmetries of a mesh's shape.

    Candidate axes pass through the surface's centroid along its principal axes and the frame's
    axes. A continuous symmetry about an axis holds when every rotation of
    `CONTINUOUS_TEST_ANGLES` maps the surface onto itself (`SymmetryTester`); then half turns
    about axes across it are tried. Otherwise each n-fold rotation of `FOLDS` is tried, the
    largest n holding about each axis kept, and the group they generate is returned.
    """
    tester = SymmetryTester(mesh, seed)
    c = surface_centre(mesh)
    axes = _distinct([*_principal_axes(mesh, c), *np.eye(3)])
    for a in axes:
        a = a if a[int(np.argmax(np.abs(a)))] > 0 else -a  # an axis's sign means nothing
        if all(tester.holds(_about(a, ang, c)) for ang in CONTINUOUS_TEST_ANGLES):
            errors = [max(tester.error(_about(a, ang, c)) for ang in CONTINUOUS_TEST_ANGLES)]
            flips = []
            across = [b - (b @ a) * a for b in axes if abs(b @ a) < 0.999]
            across.append(np.cross(a, np.eye(3)[int(np.argmin(np.abs(a)))]))
            for b in _distinct([b for b in across if np.linalg.norm(b) > 1e-6]):
                T = _about(b, math.pi, c)
                if tester.holds(T):
                    flips.append(T)
                    errors.append(tester.error(T))
                    break  # one half turn across the axis, composed with the rotations, is all
            d = tester.diameter
            return Symmetries(tuple(flips), ((a, c),), "detected", tuple(e / d for e in errors))
    gens, errors = [], []
    for a in axes:
        for n in sorted(FOLDS, reverse=True):
            T = _about(a, 2 * math.pi / n, c)
            if tester.holds(T):
                gens.append(T)
                errors.append(tester.error(T) / tester.diameter)
                break
    if not gens:
        return Symmetries()
    group = _close_group(gens)
    return Symmetries(tuple(group[1:]), (), "detected", tuple(errors))


def given_symmetries(specs: list[str], mesh: trimesh.Trimesh) -> Symmetries:
    """Symmetries named on the command line, about axes of the mesh's frame through the
    surface's centroid: ``none``, or ``AXIS:N`` with AXIS one of x, y, z and N 2..60 (an n-fold
    rotation) or ``inf`` (continuous).

    Raises:
        InvalidArgumentError: a malformed specification.
    """
    if specs == ["none"]:
        return Symmetries(source="given")
    c = surface_centre(mesh)
    gens, cont = [], []
    for spec in specs:
        axis, _, n = str(spec).partition(":")
        if axis not in ("x", "y", "z") or not n:
            raise InvalidArgumentError(
                f"invalid --symmetry {spec!r}; valid: none, or AXIS:N with AXIS x, y or z and N "
                "2..60 or inf"
            )
        a = np.eye(3)["xyz".index(axis)]
        if n == "inf":
            cont.append((a, c))
            continue
        try:
            k = int(n)
        except ValueError:
            k = 0
        if not 2 <= k <= 60:
            raise InvalidArgumentError(f"invalid --symmetry {spec!r}; valid N: 2..60 or inf")
        gens.append(_about(a, 2 * math.pi / k, c))
    if len(cont) > 1:
        raise InvalidArgumentError("give at most one continuous symmetry (AXIS:inf)")
    discrete = tuple(gens) if cont else tuple(_close_group(gens)[1:])
    tester = SymmetryTester(mesh)
    errs = [tester.error(T) / tester.diameter for T in discrete]
    errs += [tester.error(_about(a, 1.13, c)) / tester.diameter for a, c in cont]
    return Symmetries(discrete, tuple(cont), "given", tuple(errs))


# -- the object frame -----------------------------------------------------------------------


def upright_rotation(up: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) that turns direction `up` to +z."""
    u = np.asarray(up, float) / np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(u, z)
    s, c = float(np.linalg.norm(axis)), float(u @ z)
    if s < 1e-9:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    return _axis_rotation(axis / s, math.atan2(s, c))


def canonical_frame(mesh: trimesh.Trimesh, up: np.ndarray) -> np.ndarray:
    """T_O_S (4, 4): the object frame O of a mesh given in frame S, standing with direction
    `up` (in S) pointing up: z along `up`, x along the longest horizontal direction of the
    surface (its principal axis seen from above), origin at the bounding-box centre in O."""
    R1 = upright_rotation(up)
    v = np.asarray(mesh.vertices) @ R1.T
    area = np.asarray(mesh.area_faces)
    centres = np.asarray(mesh.triangles_center) @ R1.T
    xy = centres[:, :2] - (centres[:, :2] * area[:, None]).sum(axis=0) / area.sum()
    cov = (xy * area[:, None]).T @ xy
    _, vecs = np.linalg.eigh(cov)
    major = vecs[:, 1]
    yaw = -math.atan2(major[1], major[0])
    Rz = _axis_rotation(np.array([0.0, 0.0, 1.0]), yaw)
    R = Rz @ R1
    v = np.asarray(mesh.vertices) @ R.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -(v.min(axis=0) + v.max(axis=0)) / 2
    del v
    return T
