"""The image generators of the two distributions: rendered images with their annotated instances.

- `PaperGenerator`: the paper's protocol, one object alone in the randomised studio
  (`perception.training.data.studio`).
- `HeadcamGenerator`: the Fetch head camera's view of a seeded `posegrasp.world.scene.build_scene`
  (target + 0..`MAX_DISTRACTORS` distractors, randomised appearance); every object with visible
  pixels is annotated.

Each keeps one GL context for its whole life; `render(name, seed)` depends only on its arguments.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from perception.training.data.dataset import DISTS
from perception.training.data.offscreen import OffscreenRenderer
from perception.training.data.rooms import randomize_room, room_shifts
from perception.training.data.studio import HIDDEN_GROUP, Studio, StudioConfig
from posegrasp.core.errors import InvalidArgumentError, UnknownNameError
from posegrasp.core.transforms import invert_transform
from posegrasp.world import constants as C
from posegrasp.world.camera import T_world_cam, camera_intrinsics
from posegrasp.world.distractor_bank import BODY, bank_geoms, bank_name, bank_pose
from posegrasp.world.scene import PlacedObject, Scene, SceneConfig, aim_head, build_scene
from posegrasp.world.shifts import Shift
from posegrasp.world.tiers import tier_scene

#: At most this many distractors in a headcam scene (drawn uniformly from 0..3).
MAX_DISTRACTORS = 3


@dataclass
class RenderedObject:
    """One annotated instance of a rendered image.

    Attributes:
        name: class.
        T_C_O: pose in the camera (OpenCV convention), shape (4, 4) [m].
        mask: full silhouette inside the image (occluders ignored), shape (H, W), bool.
        mask_visib: visible pixels, shape (H, W), bool.
        extra: fields for scene_posegrasp.json (body name, target flag ...).
    """

    name: str
    T_C_O: np.ndarray
    mask: np.ndarray
    mask_visib: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Instance:
    """What an image annotates of one object: its class, the geoms that draw it, its pose in
    the world (4, 4) [m] and its record's fields."""

    name: str
    geoms: np.ndarray
    T_W_O: np.ndarray
    extra: dict[str, Any]


@dataclass
class RenderedImage:
    """A rendered image with its camera and annotated instances.

    Attributes:
        rgb: image, shape (H, W, 3), uint8.
        K: intrinsics, shape (3, 3) [px].
        T_C_W: world-to-camera transform, shape (4, 4) [m] (paper: the world is the object).
        objects: annotated instances.
        extra: per-image fields for scene_posegrasp.json.
    """

    rgb: np.ndarray
    K: np.ndarray
    T_C_W: np.ndarray
    objects: list[RenderedObject]
    extra: dict[str, Any] = field(default_factory=dict)


class PaperGenerator:
    """Paper-protocol images from one reusable `Studio` (one GL context per process).

    Args:
        width, height: image size [px].
    """

    def __init__(self, width: int, height: int) -> None:
        self.studio = Studio(StudioConfig(width=width, height=height))

    def render(self, name: str, seed: int) -> RenderedImage:
        """Object name seen from the studio view drawn from ``default_rng(seed)``."""
        view = self.studio.render(name, np.random.default_rng(seed))
        obj = RenderedObject(name, view.T_C_O, view.mask, view.mask)
        extra = {"roll": view.roll, "camera_distance": view.distance}
        return RenderedImage(view.rgb, view.K, view.T_C_O.copy(), [obj], extra)

    def close(self) -> None:
        """Free the GL context."""
        self.studio.close()


class HeadcamGenerator:
    """Head-camera images of seeded table scenes: a new scene per image (or per few views of
    it, `render_views`), one GL context.

    Args:
        width, height: image size [px].
    """

    def __init__(
        self, width: int, height: int, tier: str | None = None, rooms: str | None = None
    ) -> None:
        self.width, self.height = width, height
        self.tier, self.rooms = tier, rooms
        self.renderer = OffscreenRenderer(width, height)

    def _config(self, seed: int, **fields: Any) -> SceneConfig:
        """The scene config of an image of scene `seed`: randomised appearance, and with
        `rooms` the room's distractors from the training bank."""
        if self.rooms is not None:
            fields.update(shifts=room_shifts(seed, self.rooms), distractor_bank="training")
        return SceneConfig(randomize_appearance=True, **fields)

    def _room(self, scene: Scene) -> dict[str, Any]:
        """Put `scene` in its room (`perception.training.data.rooms`) when the generator draws
        rooms; the room's draws (empty without rooms), for its images' records."""
        if self.rooms is None:
            return {}
        bodies = [o.body for o in scene.objects]
        return randomize_room(scene.model, scene.data, bodies, scene.seed, self.rooms)

    def _scene(self, name: str, seed: int) -> Scene:
        """``build_scene(name, seed)``: of the generator's tier, or without one, with a number of
        distractors drawn from ``default_rng([seed, 1])`` (when they do not fit on the table, one
        fewer is tried until none is left)."""
        if self.tier is not None:
            return build_scene(name, seed, tier_scene(self.tier, self._config(seed)))
        wanted = int(np.random.default_rng([seed, 1]).integers(0, MAX_DISTRACTORS + 1))
        for n in range(wanted, 0, -1):
            try:
                return build_scene(name, seed, self._config(seed, n_distractors=n))
            except InvalidArgumentError:  # the objects did not fit on the table
                pass
        return build_scene(name, seed, self._config(seed))

    def render(self, name: str, seed: int) -> RenderedImage:
        """The head camera's view of `_scene` with its visible objects (view 0 of
        `render_views`)."""
        return self.render_views(name, seed, [0])[0]

    def render_views(self, name: str, seed: int, views: Sequence[int]) -> list[RenderedImage]:
        """Several head-camera views of one `_scene`, which is built and settled once.

        View 0 is the scene as built, the head aimed at the target. View v > 0 aims the head at
        object v mod n of the scene's n objects (v mod n = 0: the target again), offset by up to
        `SceneConfig.aim_jitter` per axis drawn from ``default_rng([seed, 2, v])``; the head is
        set kinematically from its settled posture (nothing else moves), so a view depends only
        on (name, seed, v). The image's ``target`` and its objects' ``target`` flags name the
        object the head is aimed at.
        """
        scene = self._scene(name, seed)
        room = self._room(scene)
        model, data = scene.model, scene.data
        settled, moved = data.qpos.copy(), False
        jitter = SceneConfig().aim_jitter
        images = []
        for v in views:
            aimed = scene.objects[v % len(scene.objects)]
            if moved or v > 0:  # every view starts from the settled posture
                data.qpos[:] = settled
                if v > 0:
                    offset = np.random.default_rng([seed, 2, v]).uniform(-jitter, jitter, 3)
                    aim_head(model, data, data.body(aimed.body).xpos + offset)
                mujoco.mj_forward(model, data)
                moved = v > 0
            images.append(self._image(scene, aimed, v, room))
        return images

    def _image(
        self, scene: Scene, aimed: PlacedObject, view: int, room: dict[str, Any]
    ) -> RenderedImage:
        """The head camera's current view of scene with its visible objects (and with rooms,
        the `room`'s draws in its record).

        Each object's full silhouette is drawn with every geom but its own hidden and read
        back, as depth, only inside a box that holds its projection; its visible pixels are
        those where that depth is not behind the scene's depth there (the same triangles under
        the same camera write the same depths), so no segmentation render is needed. Objects
        whose boxes do not overlap share one draw; objects outside the image are not drawn.
        """
        model = scene.model
        instances = [
            Instance(
                placed.name,
                np.flatnonzero(model.geom_bodyid == model.body(placed.body).id),
                scene.object_pose(placed.body),
                {"body": placed.body, "target": placed is aimed},
            )
            for placed in scene.objects
        ]
        extra = {"target": aimed.name, "n_distractors": len(scene.objects) - 1}
        if view > 0:
            extra["view"] = view
        if self.rooms is not None:
            extra["room"] = room
        return self._shot(scene.model, scene.data, instances, extra)

    def _shot(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        instances: list[Instance],
        extra: dict[str, Any],
    ) -> RenderedImage:
        """The head camera's image of the scene with the visible ones of `instances` and their
        masks (see `_image`), `extra` its record's fields."""
        r, cam = self.renderer, model.camera(C.HEAD_CAMERA).id
        K = camera_intrinsics(model, C.HEAD_CAMERA, self.width, self.height)
        T_C_W = invert_transform(T_world_cam(model, data, C.HEAD_CAMERA))
        r.draw(model, data, cam)
        rgb = r.read_rgb()
        todo = []  # (instance, window, pose, the scene's depth in the window)
        for inst in instances:
            T_C_O = T_C_W @ inst.T_W_O
            window = _geoms_window(model, data, inst.geoms, T_C_W, K, self.width, self.height)
            window = window or (0, 0, self.width, self.height)
            if T_C_O[2, 3] > 0 and window[2] > window[0] and window[3] > window[1]:
                todo.append((inst, window, T_C_O, r.read_depth(window)))
        masks: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        groups = model.geom_group.copy()
        try:
            for batch in _disjoint_batches([t[1] for t in todo]):
                shown = np.zeros(model.ngeom, bool)
                for k in batch:
                    shown[todo[k][0].geoms] = True
                model.geom_group[:] = np.where(shown, groups, HIDDEN_GROUP)
                r.draw(model, data, cam)
                for k in batch:
                    _, window, _, scene_depth = todo[k]
                    depth = r.read_depth(window)
                    drawn = depth < 1.0
                    masks[k] = (drawn, drawn & (depth <= scene_depth))
        finally:
            model.geom_group[:] = groups
        objects = []
        for k, (inst, (x0, y0, x1, y1), T_C_O, _) in enumerate(todo):
            drawn, seen = masks[k]
            if not seen.any():
                continue
            full = np.zeros((self.height, self.width), bool)
            visib = np.zeros_like(full)
            full[y0:y1, x0:x1], visib[y0:y1, x0:x1] = drawn, seen
            objects.append(RenderedObject(inst.name, T_C_O, full, visib, inst.extra))
        return RenderedImage(rgb, K, T_C_W, objects, extra)

    def close(self) -> None:
        """Free the GL context."""
        self.renderer.close()


#: Second word of the seed sequence of a bank scene's own draws: how many meshes, which one the
#: head is aimed at.
BANK_STREAM = 0xB4


class BankGenerator(HeadcamGenerator):
    """Head-camera images of table scenes whose only objects in sight are meshes of one bank
    (`posegrasp.world.distractor_bank.BANKS`: ``training``, pybullet's random meshes 0-899;
    ``held-out``, 900-999), each annotated as an object of its own (``bank-NNN``, `bank_name`):
    what a detector of objects it has never seen learns from, and is measured on. None of the
    six built-in objects is drawn.

    Scene `seed` is the plain head-camera scene of one built-in object, which is hidden, with
    the `distractors` shift at a level drawn from ``default_rng([seed, BANK_STREAM])`` (2, 4 or
    7 meshes from the bank standing around where it stands, on any of their six
    faces), the head then aimed at one of the meshes (drawn from the same stream, offset by up
    to `SceneConfig.aim_jitter` per axis); with `rooms`, in a room of that family
    (`perception.training.data.rooms`, the meshes recoloured as objects are). One view per
    scene.
    """

    def __init__(
        self, width: int, height: int, rooms: str | None = None, bank: str = "training"
    ) -> None:
        super().__init__(width, height, None, rooms)
        self.bank = bank

    def _config(self, seed: int, **fields: Any) -> SceneConfig:
        level = int(np.random.default_rng([seed, BANK_STREAM]).integers(1, 4))
        shifts = (Shift("distractors", level),)
        return SceneConfig(
            randomize_appearance=True, shifts=shifts, distractor_bank=self.bank, **fields
        )

    def _scene(self, name: str, seed: int) -> Scene:
        return build_scene(name, seed, self._config(seed))

    def render_views(self, name: str, seed: int, views: Sequence[int]) -> list[RenderedImage]:
        """The one view of bank scene `seed` (`views` must be ``[0]``)."""
        if list(views) != [0]:
            raise InvalidArgumentError("a bank scene has one view")
        scene = self._scene(name, seed)
        model, data = scene.model, scene.data
        for placed in scene.objects:
            model.geom_group[model.geom_bodyid == model.body(placed.body).id] = HIDDEN_GROUP
        room = {}
        if self.rooms is not None:
            room = randomize_room(model, data, [BODY], seed, self.rooms)
        meshes = bank_geoms(model)
        rng = np.random.default_rng([seed, BANK_STREAM, 1])
        aimed = meshes[int(rng.integers(len(meshes)))][0] if meshes else None
        if aimed is not None:
            jitter = SceneConfig().aim_jitter
            aim_head(model, data, data.geom_xpos[aimed] + rng.uniform(-jitter, jitter, 3))
            mujoco.mj_forward(model, data)
        instances = [
            Instance(
                bank_name(mesh_id), np.array([g]), bank_pose(model, data, g), {"target": g == aimed}
            )
            for g, mesh_id in meshes
        ]
        extra: dict[str, Any] = {"bank_meshes": len(meshes)}
        if aimed is not None:
            extra["target"] = bank_name(dict(meshes)[aimed])
        if self.rooms is not None:
            extra["room"] = room
        return [self._shot(model, data, instances, extra)]


def _disjoint_batches(windows: Sequence[tuple[int, int, int, int]]) -> list[list[int]]:
    """Indices of windows (x0, y0, x1, y1) [ends excluded] in batches whose windows do not
    overlap, greedily in order: what one batch draws in a window is its own object alone."""
    batches: list[list[int]] = []
    for k, (x0, y0, x1, y1) in enumerate(windows):
        for batch in batches:
            if all(
                x1 <= windows[j][0]
                or windows[j][2] <= x0
                or y1 <= windows[j][1]
                or windows[j][3] <= y0
                for j in batch
            ):
                batch.append(k)
                break
        else:
            batches.append([k])
    return batches


def _geoms_window(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    geoms: np.ndarray,
    T_C_W: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
) -> tuple[int, int, int, int] | None:
    """A pixel box (x0, y0, x1, y1) [ends excluded] that holds every pixel of the geoms `geoms`:
    the projection of the corners of their bounding boxes, widened by 2 px and clipped to the
    image; None (the whole image) when a corner lies near or behind the camera plane."""
    if len(geoms) == 0:
        return None
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    aabb = model.geom_aabb[geoms]  # (G, 6): centre and half sizes in the geom frame
    local = aabb[:, None, :3] + signs[None] * aabb[:, None, 3:]  # (G, 8, 3)
    R = data.geom_xmat[geoms].reshape(-1, 3, 3)
    world = np.einsum("gij,gkj->gki", R, local) + data.geom_xpos[geoms][:, None]
    cam = world.reshape(-1, 3) @ T_C_W[:3, :3].T + T_C_W[:3, 3]
    if np.any(cam[:, 2] < 1e-2):
        return None
    uv = cam[:, :2] / cam[:, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]
    lo = np.floor(uv.min(axis=0) - 2.0)
    hi = np.ceil(uv.max(axis=0) + 3.0)
    x0, x1 = (int(np.clip(v, 0, width)) for v in (lo[0], hi[0]))
    y0, y1 = (int(np.clip(v, 0, height)) for v in (lo[1], hi[1]))
    return x0, y0, x1, y1


def make_generator(
    dist: str,
    width: int,
    height: int,
    tier: str | None = None,
    rooms: str | None = None,
    bank: str | None = None,
) -> PaperGenerator | HeadcamGenerator:
    """The generator of a distribution (one of `DISTS`) at width x height [px]; `tier`, `rooms`
    (`perception.training.data.rooms`) and `bank` (`BankGenerator`, without a tier) apply to
    ``headcam``."""
    if dist == "paper":
        return PaperGenerator(width, height)
    if dist == "headcam" and bank is not None:
        return BankGenerator(width, height, rooms, bank)
    if dist == "headcam":
        return HeadcamGenerator(width, height, tier, rooms)
    raise UnknownNameError("distribution", dist, DISTS)
