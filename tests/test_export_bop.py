"""The BOP export of evaluation episodes: its files, and that they are the episodes' views."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from perception.training.data.bop import read_png
from posegrasp.core.contract import Observation
from posegrasp.world import constants as C
from posegrasp.world.scene import SceneConfig
from posegrasp.world.shifts import parse_shifts
from sim import export_bop as xb
from sim.episodes.episode import Episode, EpisodeConfig
from sim.evaluation.bop_results import MAP_FILE, BopPosesEstimator, read_export

OBJECTS = ["car", "phone"]
SEED = C.EVAL_SEED_BASE
TIER = "isolated"


@pytest.fixture(scope="module")
def export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bop") / "export"
    xb.export_bop(out, OBJECTS, 1, SEED, TIER, progress=False)
    return out


@pytest.fixture(scope="module")
def episodes():
    eps = {o: Episode(o, SEED, EpisodeConfig(tier=TIER)) for o in OBJECTS}
    yield eps
    for ep in eps.values():
        ep.close()


def scene_id(export: Path, obj: str) -> int:
    return read_export(export).images[(obj, SEED)][0]


def scene(export: Path, obj: str) -> Path:
    return export / "test" / f"{scene_id(export, obj):06d}"


def load(path: Path):
    return json.loads(path.read_text())


def test_the_export_files_parse_and_have_bop_keys(export: Path) -> None:
    assert set(load(export / "camera.json")) == {
        "cx",
        "cy",
        "fx",
        "fy",
        "width",
        "height",
        "depth_scale",
    }
    info = load(export / "models" / "models_info.json")
    assert sorted(info) == [str(i) for i in range(1, 7)]
    for entry in info.values():
        assert {"diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z"} <= set(entry)
        assert (export / "models" / "obj_000001.ply").read_bytes().startswith(b"ply\n")
    car, phone = scene_id(export, "car"), scene_id(export, "phone")
    targets = load(export / "test_targets_bop19.json")
    assert targets == sorted(
        [
            {"im_id": 0, "inst_count": 1, "obj_id": 1, "scene_id": car},
            {"im_id": 0, "inst_count": 1, "obj_id": 4, "scene_id": phone},
        ],
        key=lambda t: t["scene_id"],
    )
    assert load(export / "test_targets_bop24.json") == [
        {"im_id": 0, "scene_id": t["scene_id"]} for t in targets
    ]
    models = sorted(p.name for p in (export / "models").iterdir())
    assert sorted(p.name for p in (export / "models_eval").iterdir()) == models
    for name in models:
        assert (export / "models_eval" / name).read_bytes() == (
            export / "models" / name
        ).read_bytes()
    for obj in OBJECTS:
        sdir = scene(export, obj)
        cam = load(sdir / "scene_camera.json")["0"]
        assert set(cam) == {"cam_K", "depth_scale", "cam_R_w2c", "cam_t_w2c"}
        gt = load(sdir / "scene_gt.json")["0"]
        assert [set(g) for g in gt] == [{"cam_R_m2c", "cam_t_m2c", "obj_id"}]
        (gi,) = load(sdir / "scene_gt_info.json")["0"]
        keys = {"bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib"}
        assert set(gi) == keys | {"visib_fract"}
        # Isolated and in view: all but the few pixels the table top hides where the object
        # rests on it are visible, and the depth covers the whole silhouette.
        assert gi["px_count_all"] == gi["px_count_valid"] > 500
        assert gi["px_count_visib"] == pytest.approx(gi["visib_fract"] * gi["px_count_all"])
        assert 0.99 < gi["visib_fract"] <= 1.0
        x, y, w, h = gi["bbox_visib"]
        assert 0 <= x and x + w < 640 and 0 <= y and y + h < 480
    ex = read_export(export)
    assert (ex.tier, ex.seed_start, ex.objects, ex.episodes) == (TIER, SEED, tuple(OBJECTS), 1)
    assert load(export / MAP_FILE)["complete"] is True


def test_the_rgb_is_what_the_episode_observes(export: Path, episodes) -> None:
    for obj, ep in episodes.items():
        rgb = read_png(scene(export, obj) / "rgb" / "000000.png", export, None)
        np.testing.assert_array_equal(rgb, ep.observe().rgb)


def test_the_depth_png_is_the_rendered_depth_within_its_step(export: Path, episodes) -> None:
    for obj, ep in episodes.items():
        sdir = scene(export, obj)
        png = cv2.imread(str(sdir / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint16 and png.shape == (480, 640)
        scale = load(sdir / "scene_camera.json")["0"]["depth_scale"]
        depth_mm = ep.renderer.depth(ep.scene.data, C.HEAD_CAMERA).astype(np.float64) * 1000.0
        valid = png > 0
        assert valid.mean() > 0.99  # the room closes the view
        err = np.abs(png[valid] * scale - depth_mm[valid])
        assert err.max() <= scale / 2 + 1e-6 * depth_mm[valid].max()


def test_scene_gt_holds_the_true_pose_in_mm(export: Path, episodes) -> None:
    for obj, ep in episodes.items():
        (gt,) = load(scene(export, obj) / "scene_gt.json")["0"]
        assert gt["obj_id"] == {"car": 1, "phone": 4}[obj]
        np.testing.assert_allclose(
            np.reshape(gt["cam_R_m2c"], (3, 3)), ep.T_C_O_true[:3, :3], rtol=0, atol=1e-15
        )
        np.testing.assert_allclose(gt["cam_t_m2c"], ep.T_C_O_true[:3, 3] * 1000, atol=1e-12)


def test_a_csv_of_the_export_gt_gives_the_true_poses(
    export: Path, episodes, tmp_path: Path
) -> None:
    lines = ["scene_id,im_id,obj_id,score,R,t,time"]
    for obj in OBJECTS:
        sid = scene_id(export, obj)
        for g in load(scene(export, obj) / "scene_gt.json")["0"]:
            R = " ".join(repr(x) for x in g["cam_R_m2c"])
            t = " ".join(repr(x) for x in g["cam_t_m2c"])
            lines.append(f"{sid},0,{g['obj_id']},1.0,{R},{t},-1")
    csv = tmp_path / "gt.csv"
    csv.write_text("\n".join(lines) + "\n")
    est = BopPosesEstimator(csv, export)
    for obj, ep in episodes.items():
        o = ep.observe()
        e = est.estimate(Observation(o.rgb, o.K, o.T_world_cam, obj, SEED))
        np.testing.assert_allclose(e.T_C_O, ep.T_C_O_true, rtol=0, atol=1e-12)
        assert e.neighbours == () and e.info["score"] == 1.0


def test_no_gt_and_a_second_export_into_the_same_folder(tmp_path: Path, capsys) -> None:
    out = tmp_path / "nogt"
    args = ["--tier", TIER, "--objects", "car", "--episodes", "1", "--out", str(out)]
    assert xb.main([*args, "--no-gt"]) == 0
    (sdir,) = (out / "test").iterdir()
    assert sorted(p.name for p in sdir.iterdir()) == ["depth", "rgb", "scene_camera.json"]
    assert (out / "test_targets_bop19.json").is_file()
    assert (out / "test_targets_bop24.json").is_file()
    assert read_export(out).ground_truth is False
    # The same export again rewrites the same bytes.
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert xb.main([*args, "--no-gt"]) == 0
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before
    capsys.readouterr()
    assert xb.main(args) == 2  # with ground truth: another export
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --out") and "holds another export" in err
    assert "without ground truth" in err and "\n" not in err


def test_a_folder_of_other_files_is_refused(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    protocol = xb.export_protocol(["car"], 1, SEED, TIER, True)
    with pytest.raises(xb.InvalidArgumentError, match="not a posegrasp BOP export"):
        xb.check_out_folder(tmp_path, protocol)


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--tier", "nope"], "valid tiers: isolated, clutter"),
        (["--objects", "car,boat"], "valid objects: car, faucet"),
        (["--episodes", "0"], "--episodes 0; valid: integers 1..100000"),
        (["--seed-start", "-1"], "--seed-start -1; valid: integers 0.."),
        (["--sensor", "lidar"], "valid sensors: ideal, kinect-v1, azure-tof"),
    ],
)
def test_a_bad_argument_is_one_line_naming_the_valid_choices(
    tmp_path: Path, capsys, args: list[str], named: str
) -> None:
    out = tmp_path / "out"
    assert xb.main([*args, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and named in err and "\n" not in err
    assert not out.exists()


def test_masks_per_instance_agree_with_scene_gt_info(export: Path) -> None:
    for obj in OBJECTS:
        sdir = scene(export, obj)
        infos = load(sdir / "scene_gt_info.json")["0"]
        for gt_idx, info in enumerate(infos):
            full = cv2.imread(str(xb.mask_path(sdir, 0, gt_idx, False)), cv2.IMREAD_UNCHANGED)
            visib = cv2.imread(str(xb.mask_path(sdir, 0, gt_idx, True)), cv2.IMREAD_UNCHANGED)
            assert full.dtype == np.uint8 and full.shape == (480, 640)
            assert set(np.unique(full)) <= {0, 255} and set(np.unique(visib)) <= {0, 255}
            assert int((visib > 0).sum()) == info["px_count_visib"]
            assert not np.any((visib > 0) & (full == 0))  # the visible part of the silhouette
            x, y, w, h = info["bbox_visib"]
            ys, xs = np.nonzero(visib)
            assert (xs.min(), ys.min()) == (x, y)
            assert abs(xs.max() - x - w) <= 1 and abs(ys.max() - y - h) <= 1


def test_the_map_holds_each_image_table_height(export: Path, episodes) -> None:
    ex = read_export(export)
    for obj, ep in episodes.items():
        assert ex.table_top_z[(obj, SEED)] == float(ep.scene.table_top_z)
        assert ep.observe().table_top_z == ex.table_top_z[(obj, SEED)]


def test_an_episode_vsd_is_that_against_the_exported_depth(export: Path) -> None:
    from perception import metrics

    ep = Episode("car", SEED, EpisodeConfig(tier=TIER))
    try:
        T = ep.T_C_O_true.copy()
        T[:3, 3] += [0.01, -0.005, 0.02]
        res = ep.act(T)
        model = ep.scene.target.model
        sdir = scene(export, "car")
        png = cv2.imread(str(sdir / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
        depth = png.astype(np.float64) * xb.DEPTH_SCALE / 1000.0
        K = np.reshape(load(sdir / "scene_camera.json")["0"]["cam_K"], (3, 3))
        vertices, faces = np.asarray(model.mesh.vertices), np.asarray(model.mesh.faces)
        args = (T[:3, :3], T[:3, 3], ep.T_C_O_true[:3, :3], ep.T_C_O_true[:3, 3])
        expected = metrics.vsd(*args, depth, K, vertices, faces, model.diameter)
    finally:
        ep.close()
    assert len(res.vsd) == len(metrics.BOP_VSD_TAUS) and 0.0 < max(res.vsd) < 1.0
    # The live depth is the exported one before its 0.1 mm steps.
    np.testing.assert_allclose(res.vsd, expected, atol=2e-3)
    assert res.to_json()["vsd"] == res.vsd


def test_png16_bytes_decode_to_the_same_values() -> None:
    img = np.arange(12 * 7, dtype=np.uint16).reshape(12, 7) * 777
    back = cv2.imdecode(np.frombuffer(xb.png16_bytes(img), np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(back, img)
    d = xb.depth_to_png(np.array([[0.5, np.inf], [7.0, 0.0]]))
    np.testing.assert_array_equal(d, [[5000, 0], [0, 0]])


def test_a_sensor_export_writes_the_sensor_images_and_records_it(
    export: Path, tmp_path: Path, capsys
) -> None:
    sensor = "kinect-v1+camera"
    out = tmp_path / "kinect"
    args = ["--tier", TIER, "--objects", "car", "--episodes", "1", "--out", str(out)]
    assert xb.main([*args, "--sensor", sensor]) == 0
    assert load(out / MAP_FILE)["sensor"] == sensor and load(export / MAP_FILE)["sensor"] == "ideal"
    ep = Episode("car", SEED, EpisodeConfig(tier=TIER, obs_mode="rgbd", sensor=sensor))
    try:
        obs = ep.observe()
    finally:
        ep.close()
    sdir = scene(out, "car")
    np.testing.assert_array_equal(read_png(sdir / "rgb" / "000000.png", out, None), obs.rgb)
    png = cv2.imread(str(sdir / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(png, xb.depth_to_png(obs.depth))
    ideal_png = cv2.imread(str(scene(export, "car") / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert (png == 0).sum() > (ideal_png == 0).sum() and not np.array_equal(png, ideal_png)
    # BOP's px_count_valid counts the object's pixels with depth, under the sensor.
    (info,) = load(sdir / "scene_gt_info.json")["0"]
    (ideal_info,) = load(scene(export, "car") / "scene_gt_info.json")["0"]
    assert info["px_count_all"] == ideal_info["px_count_all"]
    assert info["px_count_valid"] < ideal_info["px_count_valid"]
    capsys.readouterr()
    # The folder holds that sensor's export: another sensor does not rewrite it.
    assert xb.main([*args, "--sensor", "azure-tof"]) == 2
    err = capsys.readouterr().err.strip()
    assert f"sensor {sensor})" in err and "sensor azure-tof" in err and "\n" not in err


def test_a_map_written_before_sensors_were_recorded_is_the_ideal_one(
    export: Path, tmp_path: Path
) -> None:
    old = load(export / MAP_FILE)
    del old["sensor"]
    (tmp_path / MAP_FILE).write_text(json.dumps(old))
    xb.check_out_folder(tmp_path, xb.export_protocol(OBJECTS, 1, SEED, TIER, True))  # no error
    with pytest.raises(xb.InvalidArgumentError, match=r"sensor ideal\).*sensor azure-tof"):
        xb.check_out_folder(tmp_path, xb.export_protocol(OBJECTS, 1, SEED, TIER, True, "azure-tof"))


def test_a_shifted_export_writes_the_shifted_images_and_records_the_shifts(
    export: Path, tmp_path: Path, capsys
) -> None:
    spec = "camera:3,light_colour:3"
    out = tmp_path / "shifted"
    args = ["--tier", TIER, "--objects", "car", "--episodes", "1", "--out", str(out)]
    assert xb.main([*args, "--shift", spec]) == 0
    assert "shifts light_colour:3,camera:3" in capsys.readouterr().out
    assert load(out / MAP_FILE)["shifts"] == ["light_colour:3", "camera:3"]
    assert load(export / MAP_FILE)["shifts"] == [] and read_export(export).shifts == ()
    assert read_export(out).shifts == parse_shifts(spec)
    cfg = EpisodeConfig(scene=SceneConfig(shifts=parse_shifts(spec)), tier=TIER, obs_mode="rgbd")
    ep = Episode("car", SEED, cfg)
    try:
        obs, T_true = ep.observe(), ep.T_C_O_true
    finally:
        ep.close()
    sdir = scene(out, "car")
    rgb = read_png(sdir / "rgb" / "000000.png", out, None)
    np.testing.assert_array_equal(rgb, obs.rgb)
    assert not np.array_equal(
        rgb, read_png(scene(export, "car") / "rgb" / "000000.png", export, None)
    )
    # The camera moved in its head link: the ground truth is the pose in the moved camera.
    (gt,) = load(sdir / "scene_gt.json")["0"]
    np.testing.assert_allclose(np.reshape(gt["cam_R_m2c"], (3, 3)), T_true[:3, :3], atol=1e-12)
    (ideal_gt,) = load(scene(export, "car") / "scene_gt.json")["0"]
    assert not np.allclose(gt["cam_t_m2c"], ideal_gt["cam_t_m2c"], atol=1.0)
    # The folder holds that export: other shifts, or none, do not rewrite it.
    for other in (["--shift", "camera:1"], []):
        assert xb.main([*args, *other]) == 2
        err = capsys.readouterr().err.strip()
        assert "shifts light_colour:3,camera:3)" in err and "\n" not in err


def test_a_bad_shift_is_one_line_naming_the_factors_and_levels(tmp_path: Path, capsys) -> None:
    for spec, says in [("fog", "valid scene shifts: light_colour, "), ("walls:7", "levels 1 mild")]:
        assert xb.main(["--shift", spec, "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("error:") and says in err and "\n" not in err
    assert not (tmp_path / "out").exists()


def test_a_map_written_before_shifts_were_recorded_has_none(export: Path, tmp_path: Path) -> None:
    old = load(export / MAP_FILE)
    del old["shifts"]
    (tmp_path / MAP_FILE).write_text(json.dumps(old))
    xb.check_out_folder(tmp_path, xb.export_protocol(OBJECTS, 1, SEED, TIER, True))  # no error
    with pytest.raises(xb.InvalidArgumentError, match=r"sensor ideal\).*shifts walls:2$"):
        shifted = xb.export_protocol(OBJECTS, 1, SEED, TIER, True, shifts=parse_shifts("walls"))
        xb.check_out_folder(tmp_path, shifted)
