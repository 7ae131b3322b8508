"""Scene shifts of `posegrasp.world.shifts`: parsing, and changes of the image that leave the
physics alone.

Every factor changes the head image of a scene and nothing else: the state after settling, the
collision geoms and everything simulated are the same to the bit as in the unshifted scene of
the same seed, and they stay so while physics runs. The slow test plays the oracle's episodes
under every factor at its strongest and under ``all:3``, and finds the outcome of the unshifted
episode each time.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from importlib.util import find_spec

import mujoco
import numpy as np
import pytest

from posegrasp.core.errors import AssetError, InvalidArgumentError, UnknownNameError
from posegrasp.world import constants as C
from posegrasp.world.camera import (
    CameraRenderer,
    RenderOptions,
    T_world_cam,
    body_mask,
    camera_intrinsics,
)
from posegrasp.world.distractor_bank import BODY, DISTRACTOR_IDS
from posegrasp.world.layout import MIN_GAP, gap
from posegrasp.world.scene import Scene, SceneConfig, build_scene
from posegrasp.world.shifts import FACTORS, Shift, parse_shifts
from posegrasp.world.tiers import tier_scene

#: Tests that stand distractors need pybullet's meshes (installed by `make setup`; CI checks).
needs_bank = pytest.mark.skipif(
    find_spec("pybullet_data") is None, reason="the distractor bank: pip install pybullet"
)

#: Model arrays of the bodies that the physics reads (the shifts' one body is added last).
BODY_FIELDS = ("body_mass", "body_inertia", "body_ipos", "body_iquat", "body_pos", "body_quat")
#: Other model arrays that the physics reads: each the same with and without shifts.
PHYSICS_FIELDS = (
    "opt.timestep",
    "opt.gravity",
    "dof_damping",
    "dof_armature",
    "jnt_range",
    "actuator_gainprm",
    "actuator_biasprm",
)
#: Geom arrays that collisions read, compared over the geoms that can collide.
COLLISION_FIELDS = (
    "geom_type",
    "geom_size",
    "geom_pos",
    "geom_quat",
    "geom_bodyid",
    "geom_contype",
    "geom_conaffinity",
    "geom_condim",
    "geom_friction",
    "geom_margin",
    "geom_gap",
    "geom_solref",
    "geom_solimp",
    "geom_priority",
)


def _rgb(scene: Scene) -> np.ndarray:
    with CameraRenderer(scene.model, 640, 480, RenderOptions(shadows=False)) as r:
        return r.rgb(scene.data, C.HEAD_CAMERA)


def _field(model: mujoco.MjModel, name: str) -> np.ndarray:
    obj: object = model
    for part in name.split("."):
        obj = getattr(obj, part)
    return np.asarray(obj)


def _colliding(model: mujoco.MjModel) -> np.ndarray:
    return np.flatnonzero((model.geom_contype != 0) | (model.geom_conaffinity != 0))


def assert_same_physics(a: Scene, b: Scene) -> None:
    """Scenes a (unshifted) and b agree on everything simulated, to the bit."""
    ma, mb = a.model, b.model
    assert (ma.nq, ma.nv, ma.nu) == (mb.nq, mb.nv, mb.nu)
    for name in BODY_FIELDS:
        np.testing.assert_array_equal(getattr(ma, name), getattr(mb, name)[: ma.nbody])
    for name in PHYSICS_FIELDS:
        np.testing.assert_array_equal(_field(ma, name), _field(mb, name), err_msg=name)
    ga, gb = _colliding(ma), _colliding(mb)
    np.testing.assert_array_equal(ga, gb)
    for name in COLLISION_FIELDS:
        np.testing.assert_array_equal(getattr(ma, name)[ga], getattr(mb, name)[gb], err_msg=name)
    for name in ("qpos", "qvel", "qacc", "ctrl", "act"):
        np.testing.assert_array_equal(getattr(a.data, name), getattr(b.data, name), err_msg=name)
    np.testing.assert_array_equal(a.data.xpos, b.data.xpos[: ma.nbody])
    np.testing.assert_array_equal(a.data.xquat, b.data.xquat[: ma.nbody])
    np.testing.assert_array_equal(a.ctrl_home, b.ctrl_home)


@pytest.fixture(scope="module")
def unshifted() -> tuple[Scene, np.ndarray]:
    scene = build_scene("phone", 3)
    return scene, _rgb(scene)


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("camera", (Shift("camera", 2),)),
        ("camera:3, light_colour:1", (Shift("light_colour", 1), Shift("camera", 3))),
        (" walls : 1 ", (Shift("walls", 1),)),
        ("all", tuple(Shift(f, 2) for f in FACTORS)),
        ("all:3", tuple(Shift(f, 3) for f in FACTORS)),
        ("", ()),
        ("none", ()),
    ],
)
@needs_bank
def test_parse_shifts(spec: str, expected: tuple[Shift, ...]) -> None:
    assert parse_shifts(spec) == expected
    assert parse_shifts(",".join(map(str, expected))) == expected  # str(Shift) reads back


@pytest.mark.parametrize(
    ("spec", "error", "says"),
    [
        ("bogus", UnknownNameError, "light_colour, light_intensity"),
        ("light_color:2", UnknownNameError, "valid scene shifts"),
        ("camera:4", InvalidArgumentError, "levels 1 mild, 2 medium, 3 strong"),
        ("camera:0", InvalidArgumentError, "invalid level"),
        ("camera:x", InvalidArgumentError, "invalid level"),
        ("camera:", InvalidArgumentError, "invalid level"),
        ("all:5", InvalidArgumentError, "invalid level"),
        ("camera,,walls", InvalidArgumentError, "empty scene shift"),
        ("camera,camera:3", InvalidArgumentError, "camera asked for more than once"),
        ("all,walls:3", InvalidArgumentError, "walls asked for more than once"),
    ],
)
def test_bad_shift_specs_say_so_in_one_line(spec: str, error: type, says: str) -> None:
    with pytest.raises(error) as info:
        parse_shifts(spec)
    message = str(info.value)
    assert says in message and "\n" not in message


def test_shift_values_are_checked() -> None:
    with pytest.raises(InvalidArgumentError, match="level 4"):
        Shift("camera", 4)
    with pytest.raises(InvalidArgumentError, match="level True"):
        Shift("camera", True)  # type: ignore[arg-type]
    with pytest.raises(UnknownNameError, match=r"valid scene shifts: .*camera, all; NAME"):
        Shift("lights")
    with pytest.raises(InvalidArgumentError, match="Shift values"):
        build_scene("phone", 0, SceneConfig(shifts=("camera:3",)))  # type: ignore[arg-type]
    with pytest.raises(InvalidArgumentError, match="more than once"):
        build_scene("phone", 0, SceneConfig(shifts=(Shift("walls", 1), Shift("walls", 3))))


def test_distractors_without_pybullet_say_how_to_install_it(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "pybullet_data", None)  # `import pybullet_data` fails
    with pytest.raises(AssetError, match="pip install pybullet") as info:
        parse_shifts("camera,distractors:1")
    assert "\n" not in str(info.value)
    with pytest.raises(AssetError, match="pip install pybullet"):
        parse_shifts("all:3")
    with pytest.raises(AssetError, match="pip install pybullet"):
        build_scene("phone", 0, SceneConfig(shifts=(Shift("distractors", 1),)))
    assert parse_shifts("camera:3,walls") == (Shift("walls", 2), Shift("camera", 3))


@needs_bank
@pytest.mark.parametrize("factor", list(FACTORS))
def test_each_factor_changes_the_image_and_nothing_simulated(
    factor: str, unshifted: tuple[Scene, np.ndarray]
) -> None:
    base, base_rgb = unshifted
    scene = build_scene("phone", 3, SceneConfig(shifts=(Shift(factor, 3),)))
    rgb = _rgb(scene)
    changed = (rgb != base_rgb).any(axis=2).mean()
    assert changed > 0.01, f"{factor} changed {changed:.2%} of the image"
    assert_same_physics(base, scene)
    # The head camera's pose is its true pose, and the target is still in view.
    fresh = mujoco.MjData(scene.model)
    fresh.qpos[:] = scene.data.qpos
    mujoco.mj_kinematics(scene.model, fresh)
    mujoco.mj_camlight(scene.model, fresh)
    T = T_world_cam(scene.model, scene.data, C.HEAD_CAMERA)
    np.testing.assert_array_equal(T, T_world_cam(scene.model, fresh, C.HEAD_CAMERA))
    with CameraRenderer(scene.model, 640, 480, RenderOptions(shadows=False)) as r:
        mask = body_mask(scene.model, r.segmentation(scene.data, C.HEAD_CAMERA), scene.target.body)
    assert mask.sum() > 400
    # The target's origin projects where the target is drawn.
    K = camera_intrinsics(scene.model, C.HEAD_CAMERA, 640, 480)
    p = np.linalg.inv(T) @ np.append(scene.object_pose()[:3, 3], 1.0)
    u, v = (K @ p[:3])[:2] / p[2]
    rows, cols = np.nonzero(mask)
    assert rows.min() - 5 <= v <= rows.max() + 5 and cols.min() - 5 <= u <= cols.max() + 5
    if factor != "camera":
        np.testing.assert_array_equal(T, T_world_cam(base.model, base.data, C.HEAD_CAMERA))


@needs_bank
def test_physics_runs_on_the_same_with_every_shift() -> None:
    cfg = tier_scene("clutter")
    base = build_scene("car", 5, cfg)
    shifted = build_scene("car", 5, replace(cfg, shifts=parse_shifts("all:3")))
    for scene in (base, shifted):
        scene.step(0.5)
    assert_same_physics(base, shifted)


@needs_bank
def test_same_seed_and_shift_give_the_same_image_bytes() -> None:
    cfg = SceneConfig(shifts=parse_shifts("all:3"))
    a, b = build_scene("chair", 2, cfg), build_scene("chair", 2, cfg)
    assert _rgb(a).tobytes() == _rgb(b).tobytes()
    # Each factor draws from its own stream: the same alone as among the others.
    alone = build_scene("chair", 2, SceneConfig(shifts=(Shift("table_texture", 3),)))
    np.testing.assert_array_equal(_texture(alone, "room_wood_tex"), _texture(a, "room_wood_tex"))
    other_seed = build_scene("chair", 3, cfg)
    assert not np.array_equal(other_seed.model.tex_data, a.model.tex_data)


def _texture(scene: Scene, name: str) -> np.ndarray:
    m = scene.model
    t = m.texture(name).id
    n = m.tex_height[t] * m.tex_width[t] * m.tex_nchannel[t]
    return m.tex_data[m.tex_adr[t] : m.tex_adr[t] + n]


def _footprint(vertices: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull

    xy = vertices[:, :2]
    return xy[ConvexHull(xy).vertices]


def _geom_vertices(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> np.ndarray:
    mesh = model.geom_dataid[g]
    v = model.mesh_vert[
        model.mesh_vertadr[mesh] : model.mesh_vertadr[mesh] + model.mesh_vertnum[mesh]
    ]
    return v @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]


@needs_bank
@pytest.mark.parametrize("level", [1, 2, 3])
def test_distractors_stand_on_the_table_clear_of_the_objects(level: int) -> None:
    scene = build_scene(
        "pistol", 7, tier_scene("clutter", SceneConfig(shifts=(Shift("distractors", level),)))
    )
    m, d = scene.model, scene.data
    geoms = np.flatnonzero(m.geom_bodyid == m.body(BODY).id)
    assert 1 <= len(geoms) <= {1: 2, 2: 4, 3: 7}[level]
    objects = []
    for placed in scene.objects:
        T = scene.object_pose(placed.body)
        objects.append(_footprint(np.asarray(placed.model.mesh.vertices) @ T[:3, :3].T + T[:3, 3]))
    shapes = []
    for g in geoms:
        assert m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0
        assert int(m.geom(g).name.split("/")[-1]) in DISTRACTOR_IDS
        v = _geom_vertices(m, d, g)
        assert v[:, 2].min() == pytest.approx(scene.table_top_z, abs=1e-5)
        shapes.append(_footprint(v))
    for i, F in enumerate(shapes):
        # The objects settled up to a millimetre from where their footprints were laid out.
        assert all(gap(F, G) >= MIN_GAP - 2e-3 for G in objects)
        assert all(gap(F, G) >= MIN_GAP - 1e-6 for G in shapes[i + 1 :])


@needs_bank
def test_occlusion_is_measured_without_the_shifts() -> None:
    cfg = tier_scene("hard")
    base = build_scene("phone", 11, cfg)
    shifted = build_scene("phone", 11, replace(cfg, shifts=parse_shifts("distractors:3,camera:3")))
    assert shifted.occlusion == base.occlusion
    assert_same_physics(base, shifted)


@pytest.mark.slow
@needs_bank
@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("name", ["phone", "car"])
def test_the_oracle_grasps_the_same_under_every_shift(name: str, seed: int) -> None:
    from sim.episodes.episode import EpisodeConfig, play_episode
    from sim.episodes.registry import make_estimator

    def play(spec: str):
        cfg = EpisodeConfig(scene=SceneConfig(shifts=parse_shifts(spec)))
        return play_episode(name, seed, make_estimator("oracle"), cfg)

    base = play("")
    for spec in [*(f"{f}:3" for f in FACTORS), "all:3"]:
        r = play(spec)
        outcome = (r.success, r.failure_reason, r.grasp_part, r.notes)
        assert outcome == (base.success, base.failure_reason, base.grasp_part, base.notes), spec
        if spec.startswith(("camera", "all")):
            # The oracle's pose goes through the moved camera and back: the world pose the
            # robot grasps on differs by rounding alone.
            assert r.lift_height == pytest.approx(base.lift_height, abs=1e-9), spec
        else:
            assert r.lift_height == base.lift_height, spec
            np.testing.assert_array_equal(r.T_C_O_true, base.T_C_O_true)


@pytest.mark.slow
@needs_bank
@pytest.mark.parametrize("task", ["lift", "place"])
def test_the_oracles_outcomes_through_sim_evaluate_are_the_same_under_all_shifts(
    task: str, tmp_path
) -> None:
    """``sim.evaluate --estimator oracle`` with and without ``--shift all:3``: every episode
    ends alike, lifts as high and (place) rests where it rests without the shifts. The camera
    factor moves the camera, so the oracle's pose goes through another camera frame and back:
    lengths and the final pose agree to 1e-9, the only differences being rounding; an angle
    near zero is an arccos of a cosine near 1, where a rounding of 1e-16 reads as 1e-6 deg, so
    the angles agree to 1e-5 deg."""
    import json

    from sim import evaluate

    reports = {}
    for name, extra in (("plain", []), ("shifted", ["--shift", "all:3"])):
        out = tmp_path / f"{name}.json"
        argv = ["--estimator", "oracle", "--objects", "phone", "--episodes", "2"]
        argv += ["--tier", "isolated", "--task", task, *extra, "--json", str(out)]
        assert evaluate.main(argv) == 0
        reports[name] = json.loads(out.read_text())
    plain, shifted = reports["plain"], reports["shifted"]
    assert "shifts" not in plain and shifted["shifts"] == [f"{f}:3" for f in FACTORS]
    assert shifted.get("task", "lift") == plain.get("task", "lift") == task
    for a, b in zip(plain["episodes"], shifted["episodes"], strict=True):
        assert (a["seed"], a["success"], a["failure_reason"], a["grasp_part"]) == (
            b["seed"],
            b["success"],
            b["failure_reason"],
            b["grasp_part"],
        )
        assert a["lift_height"] == pytest.approx(b["lift_height"], abs=1e-9)
        if task == "lift":
            assert "place" not in a and "place" not in b
            continue
        pa, pb = a["place"], b["place"]
        assert pa["goal"] == pb["goal"] and pa["placed"] == pb["placed"]
        np.testing.assert_allclose(pa["T_world_O_final"], pb["T_world_O_final"], rtol=0, atol=1e-9)
        for key, tol in [("translation_m", 1e-9), ("mssd_m", 1e-9), ("rotation_deg", 1e-5)]:
            assert pa["errors"][key] == pytest.approx(pb["errors"][key], abs=tol), key
        assert pa["errors"]["tilt_deg"] == pytest.approx(pb["errors"]["tilt_deg"], abs=1e-5)
