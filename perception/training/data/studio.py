"""The paper protocol's renderer (docs/DESIGN.md §8): one object in a randomised studio.

One lightweight MuJoCo model holds every object (at the world origin, in its own frame: T_world_O
is the identity), a box-shaped room of six textured walls, a pool of clutter primitives, a pool of
lights and one camera. It is compiled once; each sample only changes model fields (which object is
visible, camera pose, walls, clutter, lights, colours) and re-runs kinematics, so a sample costs
two renders (RGB and segmentation) and no compilation.

Domain randomisation per sample (every choice drawn from the sample's `rng`):

- camera: direction uniform on the sphere (below the object too), distance uniform in
  `distance` x the object's diameter, aimed at a point uniformly inside a ball of radius
  `aim_offset` x diameter around the object's origin; its roll is set so that the label's
  in-plane angle theta (the roll of the virtual camera C', `perception.geometry.encode`) is drawn
  uniformly from -60..60 deg in 3 deg steps, as the paper's dataset was made;
- room: random orientation and size (the camera always inside), each wall a random texture from a
  fixed bank (`perception.training.data.textures`), tint, scale and shininess;
- clutter: 0..`max_clutter` boxes, spheres, cylinders, capsules and ellipsoids with random
  textures, never in front of the object (the object is never occluded);
- lights: 1..`max_lights` spot, point or directional lights of random position, colour and
  intensity, and a random headlight;
- object: a small jitter of every part's colour, random specular and shininess.

Shadows and reflections are off. The texture bank is drawn from the fixed `bank_seed`, so a sample
depends only on its own seed, not on which samples the process rendered before.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from perception.training.data.offscreen import OffscreenRenderer
from perception.training.data.textures import PLAIN_TEXTURE, add_texture_bank, bank_texture_name
from perception.training.data.views import roll_to_theta, unit_vector
from posegrasp.core.errors import StateError, UnknownNameError
from posegrasp.core.transforms import invert_transform, mat_to_quat
from posegrasp.world.camera import R_CV_FROM_MJ, T_world_cam, camera_intrinsics
from posegrasp.world.objects import OBJECT_NAMES, VISUAL_GROUP, ObjectModel, load_object

CAMERA = "studio"
#: Geom group of the room and the clutter (drawn by default, left out of the mask pass).
BACKGROUND_GROUP = 1
#: Geom group never drawn by the default visual options (hides inactive objects and clutter).
HIDDEN_GROUP = 5
#: Clutter geom types with the radius [m] of their bounding sphere given their size, shape (3,).
_CLUTTER_RADIUS: dict[mujoco.mjtGeom, Callable[[np.ndarray], float]] = {
    mujoco.mjtGeom.mjGEOM_BOX: lambda size: float(np.linalg.norm(size)),
    mujoco.mjtGeom.mjGEOM_SPHERE: lambda size: float(size[0]),
    mujoco.mjtGeom.mjGEOM_CYLINDER: lambda size: float(np.hypot(size[0], size[1])),
    mujoco.mjtGeom.mjGEOM_CAPSULE: lambda size: float(size[0] + size[1]),
    mujoco.mjtGeom.mjGEOM_ELLIPSOID: lambda size: float(size.max()),
}
_CLUTTER_TYPES = tuple(_CLUTTER_RADIUS)
_WALL_THICKNESS = 0.01


@dataclass(frozen=True)
class StudioConfig:
    """How paper-protocol views are sampled. Lengths in [m], angles in [rad] unless stated.

    Attributes:
        width, height: image size [px].
        fovy_deg: vertical field of view [deg] (the head camera's is 50).
        distance: range of the camera's distance from the object origin, in object diameters.
        aim_offset: radius of the ball around the object origin the camera aims into, in object
            diameters (so the object is not always centred).
        max_clutter: at most this many clutter primitives per sample.
        max_lights: at most this many lights per sample (at least one).
        room_margin: the walls lie this far beyond the camera's distance from the object.
        n_textures: size of the background texture bank.
        texture_size: side of each bank texture [px].
        bank_seed: seed of the texture bank (fixed: part of the generator's definition).
        msaa: multisampling anti-aliasing samples per pixel (0 = off; costs render time).
        inplane_deg: range of the label's in-plane angle theta [deg], both ends included.
        inplane_step_deg: grid step of theta [deg].
    """

    width: int = 256
    height: int = 256
    fovy_deg: float = 50.0
    distance: tuple[float, float] = (1.2, 1.8)
    aim_offset: float = 0.12
    max_clutter: int = 8
    max_lights: int = 4
    room_margin: tuple[float, float] = (0.2, 3.0)
    n_textures: int = 96
    texture_size: int = 128
    bank_seed: int = 20190226
    msaa: int = 2
    inplane_deg: tuple[float, float] = (-60.0, 60.0)
    inplane_step_deg: float = 3.0


@dataclass(frozen=True)
class StudioView:
    """One rendered paper-protocol sample.

    Attributes:
        rgb: image, shape (H, W, 3), uint8.
        mask: pixels of the object, shape (H, W), bool (the object is never occluded, so this is
            both its silhouette and its visible mask; it can be cut by the image border).
        K: intrinsics, shape (3, 3) [px].
        T_C_O: object pose in the camera (OpenCV convention), shape (4, 4) [m].
        roll: the label's in-plane angle theta [rad], on the configured grid.
        distance: camera-to-object-origin distance [m].
    """

    rgb: np.ndarray
    mask: np.ndarray
    K: np.ndarray
    T_C_O: np.ndarray
    roll: float
    distance: float


# --- the model -------------------------------------------------------------------------------


def build_studio_spec(objects: Sequence[ObjectModel], cfg: StudioConfig) -> mujoco.MjSpec:
    """The studio model: objects at the origin, room, clutter and light pools, one camera."""
    spec = mujoco.MjSpec()
    spec.modelname = "posegrasp_studio"
    spec.stat.extent = 1.0
    spec.stat.center = [0.0, 0.0, 0.0]
    spec.visual.map.znear = 0.01
    spec.visual.map.zfar = 50.0
    spec.visual.global_.offwidth = max(cfg.width, 64)
    spec.visual.global_.offheight = max(cfg.height, 64)
    spec.visual.quality.offsamples = cfg.msaa
    bank = add_texture_bank(spec, cfg.n_textures, cfg.texture_size, cfg.bank_seed)

    def slot_material(name: str) -> str:
        mat = spec.add_material()
        mat.name = name
        mat.texuniform = True
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = bank[0]
        return name

    room = spec.worldbody.add_body()
    room.name = "room"
    room.mocap = True

    def add_box(parent: mujoco.MjsBody, name: str, size: list[float], group: int) -> None:
        # A visual-only box with its own material slot.
        g = parent.add_geom()
        g.name = name
        g.type = mujoco.mjtGeom.mjGEOM_BOX
        g.size = size
        g.contype = g.conaffinity = 0
        g.group = group
        g.material = slot_material(name)

    for i in range(6):
        add_box(room, f"wall_{i}", [1.0, 1.0, _WALL_THICKNESS], BACKGROUND_GROUP)
    for i in range(cfg.max_clutter):
        add_box(spec.worldbody, f"clutter_{i}", [0.05, 0.05, 0.05], HIDDEN_GROUP)
    for i in range(cfg.max_lights):
        light = spec.worldbody.add_light()
        light.name = f"light_{i}"
        light.castshadow = False
    cam = spec.worldbody.add_camera()
    cam.name = CAMERA
    cam.fovy = cfg.fovy_deg
    for obj in objects:
        obj.add_to_spec(spec, obj.name, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
        for part in obj.parts:
            mat = spec.add_material()
            mat.name = f"{obj.name}/{part.name}"
            spec.geom(f"{obj.name}/{part.name}").material = mat.name
    return spec


class Studio:
    """The compiled paper-protocol model with its renderer; render samples with `render`.

    The GL context is created on the first render. Call `close()` (or use as a context manager).
    """

    def __init__(
        self, config: StudioConfig | None = None, objects: Sequence[str] = OBJECT_NAMES
    ) -> None:
        self.config = cfg = config or StudioConfig()
        for n in objects:
            if n not in OBJECT_NAMES:
                raise UnknownNameError("object", n, OBJECT_NAMES)
        self.objects = {n: load_object(n) for n in objects}
        self.model = build_studio_spec(list(self.objects.values()), cfg).compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._cam = m.camera(CAMERA).id
        self._room = m.body("room").mocapid[0]
        self._walls = [m.geom(f"wall_{i}").id for i in range(6)]
        self._clutter = [m.geom(f"clutter_{i}").id for i in range(cfg.max_clutter)]
        self._bank = [m.texture(bank_texture_name(i)).id for i in range(cfg.n_textures)]
        self._plain = m.texture(PLAIN_TEXTURE).id
        self._geoms: dict[str, np.ndarray] = {}
        self._mats: dict[str, np.ndarray] = {}
        for name, obj in self.objects.items():
            self._geoms[name] = np.array([m.geom(f"{name}/{p.name}").id for p in obj.parts])
            self._mats[name] = np.array([m.material(f"{name}/{p.name}").id for p in obj.parts])
        # The compiler marks geoms built at their body's origin as "same frame" and then ignores
        # geom_pos/geom_quat; these geoms are moved per sample.
        m.geom_sameframe[self._walls + self._clutter] = mujoco.mjtSameFrame.mjSAMEFRAME_NONE
        self._base_rgba = m.geom_rgba.copy()
        self.K = camera_intrinsics(m, CAMERA, cfg.width, cfg.height)
        self._renderer = OffscreenRenderer(cfg.width, cfg.height)
        # The last render's object name, roll and distance (`render_turned` draws it again).
        self._last: tuple[str, float, float] | None = None
        self._opt_all = mujoco.MjvOption()
        self._opt_object = mujoco.MjvOption()
        self._opt_object.geomgroup[:] = 0
        self._opt_object.geomgroup[VISUAL_GROUP] = 1

    # -- randomisation ------------------------------------------------------------------------

    def _show_only(self, name: str) -> None:
        m = self.model
        for other, geoms in self._geoms.items():
            m.geom_group[geoms] = VISUAL_GROUP if other == name else HIDDEN_GROUP

    def _set_material(self, mat: int, rng: np.random.Generator) -> None:
        m = self.model
        m.mat_texid[mat, mujoco.mjtTextureRole.mjTEXROLE_RGB] = (
            self._bank[rng.integers(len(self._bank))] if rng.random() < 0.85 else self._plain
        )
        tint = rng.uniform(0.5, 1.0, 3) if rng.random() < 0.5 else np.full(3, rng.uniform(0.5, 1))
        m.mat_rgba[mat] = [*tint, 1.0]
        m.mat_texrepeat[mat] = rng.uniform(0.5, 8.0, 2)
        m.mat_specular[mat] = rng.uniform(0.0, 0.5)
        m.mat_shininess[mat] = rng.uniform(0.0, 1.0)

    def _place_camera(self, diameter: float, rng: np.random.Generator) -> tuple[float, float]:
        cfg, m = self.config, self.model
        distance = rng.uniform(*cfg.distance) * diameter
        position = unit_vector(rng) * distance
        aim = unit_vector(rng) * cfg.aim_offset * diameter * rng.random() ** (1 / 3)
        lo, hi = cfg.inplane_deg
        steps = round((hi - lo) / cfg.inplane_step_deg)
        theta = np.radians(lo + cfg.inplane_step_deg * rng.integers(0, steps + 1))
        R_world_cv = roll_to_theta(position, aim, theta, self.K)
        m.cam_pos[self._cam] = position
        m.cam_quat[self._cam] = mat_to_quat(R_world_cv @ R_CV_FROM_MJ)
        return float(theta), float(distance)

    def _place_room(self, distance: float, rng: np.random.Generator) -> None:
        m, d = self.model, self.data
        d.mocap_quat[self._room] = unit_vector(rng, 4)
        d.mocap_pos[self._room] = 0.0
        half = distance + rng.uniform(*self.config.room_margin, 3)
        for i, g in enumerate(self._walls):
            axis, sign = i // 2, 1.0 if i % 2 else -1.0
            pos = np.zeros(3)
            pos[axis] = sign * (half[axis] + _WALL_THICKNESS)
            m.geom_pos[g] = pos
            others = [k for k in range(3) if k != axis]
            # A wall normal to axis: a box whose local z is that axis.
            R = np.eye(3)[:, [*others, axis]]
            if np.linalg.det(R) < 0:
                R[:, 0] *= -1
            m.geom_quat[g] = mat_to_quat(R)
            m.geom_size[g] = [half[others[0]] + 0.05, half[others[1]] + 0.05, _WALL_THICKNESS]
            self._set_material(m.geom_matid[g], rng)

    def _place_clutter(self, radius: float, rng: np.random.Generator) -> None:
        """Clutter anywhere in view except in front of the object's bounding sphere."""
        m, cfg = self.model, self.config
        cam_pos = m.cam_pos[self._cam].copy()
        R_world_cv = np.zeros(9)
        mujoco.mju_quat2Mat(R_world_cv, m.cam_quat[self._cam])
        R_world_cv = R_world_cv.reshape(3, 3) @ R_CV_FROM_MJ
        to_obj = -cam_pos
        d_obj = float(np.linalg.norm(to_obj))
        half_angle_obj = np.arcsin(min(1.0, radius / d_obj))
        Kinv = np.linalg.inv(self.K)
        n = int(rng.integers(cfg.max_clutter + 1))
        for i, g in enumerate(self._clutter):
            if i >= n:
                m.geom_group[g] = HIDDEN_GROUP
                continue
            gtype = _CLUTTER_TYPES[rng.integers(len(_CLUTTER_TYPES))]
            size = rng.uniform(0.02, 0.25, 3)
            r = _CLUTTER_RADIUS[gtype](size)
            uv = rng.uniform(-0.2, 1.2, 2) * [cfg.width, cfg.height]
            ray = R_world_cv @ (Kinv @ np.array([uv[0], uv[1], 1.0]))
            ray = ray / np.linalg.norm(ray)
            depth = rng.uniform(0.1, 3.0)
            q = cam_pos + depth * ray
            quat = unit_vector(rng, 4)
            # Occlusion test: does the clutter's bounding sphere overlap the object's image disc
            # while being nearer than the object's far side?
            angle = np.arccos(np.clip(ray @ to_obj / d_obj, -1.0, 1.0))
            half_angle = np.arcsin(min(1.0, r / depth))
            overlaps = angle < half_angle_obj + half_angle
            nearer = depth - r < d_obj + radius
            touches = np.linalg.norm(q) < r + radius or depth < r + 0.02
            if (overlaps and nearer) or touches:
                m.geom_group[g] = HIDDEN_GROUP
                continue
            m.geom_group[g] = BACKGROUND_GROUP
            m.geom_type[g] = gtype
            m.geom_size[g] = size
            m.geom_pos[g] = q
            m.geom_quat[g] = quat
            self._set_material(m.geom_matid[g], rng)

    def _place_lights(self, rng: np.random.Generator) -> None:
        m, cfg = self.model, self.config
        n = int(rng.integers(1, cfg.max_lights + 1))
        total = rng.uniform(0.6, 1.5)
        kinds = (
            mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
            mujoco.mjtLightType.mjLIGHT_POINT,
            mujoco.mjtLightType.mjLIGHT_SPOT,
        )
        for i in range(cfg.max_lights):
            m.light_active[i] = i < n
            m.light_type[i] = kinds[rng.choice(3, p=[0.4, 0.35, 0.25])]
            pos = unit_vector(rng) * rng.uniform(0.5, 3.0)
            m.light_pos[i] = pos
            direction = -pos / np.linalg.norm(pos) + rng.normal(0.0, 0.15, 3)
            m.light_dir[i] = direction / np.linalg.norm(direction)
            m.light_cutoff[i] = rng.uniform(30.0, 80.0)
            m.light_exponent[i] = rng.uniform(0.0, 10.0)
            m.light_attenuation[i] = [1.0, 0.0, 0.0]
            colour = np.clip(1.0 + rng.normal(0.0, 0.12, 3), 0.6, 1.2)
            m.light_diffuse[i] = colour * total / n * rng.uniform(0.7, 1.3)
            m.light_specular[i] = rng.uniform(0.0, 0.5)
            m.light_ambient[i] = 0.0
        hl = m.vis.headlight
        hl.ambient[:] = rng.uniform(0.1, 0.4)
        hl.diffuse[:] = rng.uniform(0.05, 0.4)
        hl.specular[:] = rng.uniform(0.0, 0.2)

    def _jitter_object(self, name: str, rng: np.random.Generator) -> None:
        m = self.model
        geoms, mats = self._geoms[name], self._mats[name]
        gain = rng.uniform(0.85, 1.15)
        rgb = self._base_rgba[geoms, :3] * gain + rng.normal(0.0, 0.03, (len(geoms), 3))
        m.geom_rgba[geoms, :3] = np.clip(rgb, 0.0, 1.0)
        m.mat_specular[mats] = rng.uniform(0.0, 0.7)
        m.mat_shininess[mats] = rng.uniform(0.0, 1.0)
        m.mat_emission[mats] = rng.uniform(0.0, 0.1)

    # -- rendering ----------------------------------------------------------------------------

    def render(self, name: str, rng: np.random.Generator) -> StudioView:
        """Render object name from a random view with a random background and lighting."""
        if name not in self.objects:
            raise UnknownNameError("object", name, list(self.objects))
        obj = self.objects[name]
        radius = float(np.linalg.norm(obj.extents) / 2)
        self._show_only(name)
        roll, distance = self._place_camera(obj.diameter, rng)
        self._place_room(distance, rng)
        self._place_clutter(radius, rng)
        self._place_lights(rng)
        self._jitter_object(name, rng)
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        r, m, d = self._renderer, self.model, self.data
        rgb = r.render(m, d, self._cam, self._opt_all)
        # The object is never occluded, so its mask is the segmentation of the object alone.
        # Segmentation colours encode (scene geom index + 1) in R, G, B; black is background.
        # The object alone has fewer than 256 geoms, so R alone tells object from background.
        mask = r.render(m, d, self._cam, self._opt_object, segment=True)[..., 0] > 0
        T_world_C = T_world_cam(self.model, self.data, CAMERA)
        T_C_O = invert_transform(T_world_C)  # T_world_O is the identity
        self._last = (name, roll, distance)
        return StudioView(rgb, mask, self.K.copy(), T_C_O, roll, distance)

    def render_turned(self, name: str, R_O: np.ndarray) -> StudioView:
        """The scene of the last `render` again, with object name turned by R_O about its origin.

        Camera, room, clutter, lights and colours stay as that render left them, so the two
        images differ by the object's turn alone.

        Args:
            name: the object of the last `render`.
            R_O: the turn, in the object's own frame, shape (3, 3).

        Returns:
            The view; its T_C_O is the last render's with R_O applied in the object's frame.
        """
        last = self._last
        if last is None or last[0] != name:
            raise StateError(f"render_turned({name!r}) needs a render of {name!r} just before it")
        m, d, r = self.model, self.data, self._renderer
        adr = m.jnt_qposadr[m.joint(f"{name}/free").id]
        d.qpos[adr + 3 : adr + 7] = mat_to_quat(np.asarray(R_O, dtype=float))
        try:
            mujoco.mj_kinematics(m, d)
            rgb = r.render(m, d, self._cam, self._opt_all)
            mask = r.render(m, d, self._cam, self._opt_object, segment=True)[..., 0] > 0
            T_C_O = invert_transform(T_world_cam(m, d, CAMERA))
            T_C_O[:3, :3] = T_C_O[:3, :3] @ R_O
        finally:
            d.qpos[adr + 3 : adr + 7] = m.qpos0[adr + 3 : adr + 7]
            mujoco.mj_kinematics(m, d)
        return StudioView(rgb, mask, self.K.copy(), T_C_O, last[1], last[2])

    def close(self) -> None:
        """Free the GL context."""
        self._renderer.close()

    def __enter__(self) -> Studio:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
