"""Tests of the dataset generator (`python -m perception.training.datagen`) and loader."""

from __future__ import annotations

import itertools
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from perception.geometry import encode, invert_transform, project
from perception.training.data import bop
from perception.training.data import dataset as ds
from perception.training.data.annotations import full_silhouette
from perception.training.data.render_split import SEED_BASES
from perception.training.data.sheets import draw_annotations
from perception.training.data.writer import WALL_TIME_FILE
from perception.training.datagen import main
from posegrasp.core.errors import AssetError, StateError
from posegrasp.world import constants as C
from posegrasp.world.camera import T_world_cam, camera_intrinsics
from posegrasp.world.objects import OBJECT_NAMES, load_object
from posegrasp.world.scene import SceneConfig, build_scene

N_PAPER = 8
N_HEADCAM = 3


def _run(*args: str) -> int:
    return main([*args, "--quiet"])


@pytest.fixture(scope="module")
def paper(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("paper")
    assert (
        _run("--dist", "paper", "--split", "val", "--count", str(N_PAPER), "--out", str(out)) == 0
    )
    return out


@pytest.fixture(scope="module")
def headcam(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("headcam")
    args = ["--dist", "headcam", "--split", "test", "--count", str(N_HEADCAM), "--out", str(out)]
    assert _run(*args) == 0
    return out


def _files(root: Path) -> dict[str, bytes]:
    """Every file's bytes but the wall times, which are measured."""
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != WALL_TIME_FILE
    }


def _silhouette(
    name: str, T_C_O: np.ndarray, K: np.ndarray, shape: tuple[int, int], ss: int = 4
) -> np.ndarray:
    """The mesh's silhouette, rasterised triangle by triangle (independent of MuJoCo).

    Rasterised at ss x ss samples per pixel; a pixel is inside if most of its samples are.
    """
    mesh = load_object(name).mesh
    pts = np.asarray(mesh.vertices) @ T_C_O[:3, :3].T + T_C_O[:3, 3]
    uv = (project(K, pts) + 0.5) * ss - 0.5  # pixel centres of the finer grid
    img = np.zeros((shape[0] * ss, shape[1] * ss), np.uint8)
    fixed = np.round(uv * 16).astype(np.int32)
    for tri in np.asarray(mesh.faces):
        cv2.fillConvexPoly(img, fixed[tri], 1, cv2.LINE_8, 4)
    return img.reshape(shape[0], ss, shape[1], ss).mean(axis=(1, 3)) > 0.5


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


# --- layout ----------------------------------------------------------------------------------


def test_bop_layout_and_units(paper: Path) -> None:
    sdir = paper / "val" / "000000"
    for im_id in range(N_PAPER):
        assert (sdir / "rgb" / f"{im_id:06d}.png").is_file()
        assert (sdir / "mask" / f"{im_id:06d}_000000.png").is_file()
        assert (sdir / "mask_visib" / f"{im_id:06d}_000000.png").is_file()
    gt = json.loads((sdir / "scene_gt.json").read_text())
    cam = json.loads((sdir / "scene_camera.json").read_text())
    info = json.loads((sdir / "scene_gt_info.json").read_text())
    pg = json.loads((sdir / "scene_posegrasp.json").read_text())
    assert sorted(gt, key=int) == [str(i) for i in range(N_PAPER)]
    for key in gt:
        (entry,) = gt[key]
        (extra,) = pg[key]["objects"]
        T = np.asarray(extra["T_C_O"])
        # BOP stores millimetres, our sidecar metres.
        np.testing.assert_allclose(entry["cam_t_m2c"], T[:3, 3] * 1000.0, rtol=1e-12)
        np.testing.assert_allclose(np.reshape(entry["cam_R_m2c"], (3, 3)), T[:3, :3])
        assert entry["obj_id"] == OBJECT_NAMES.index(extra["class"]) + 1
        assert extra["class"] == OBJECT_NAMES[int(key) % 6]
        assert pg[key]["seed"] == SEED_BASES["val"] + int(key)
        assert cam[key]["depth_scale"] == 1.0 and len(cam[key]["cam_K"]) == 9
        (gi,) = info[key]
        assert set(gi) >= {"bbox_obj", "bbox_visib", "px_count_all", "px_count_visib"}
        assert 0.0 < gi["visib_fract"] <= 1.0
    top = json.loads((paper / "info.json").read_text())
    assert top["splits"]["val"]["seed_range"] == [SEED_BASES["val"], SEED_BASES["val"] + N_PAPER]
    assert top["splits"]["val"]["count"] == N_PAPER
    models = json.loads((paper / "models" / "models_info.json").read_text())
    for oid, name in enumerate(OBJECT_NAMES, start=1):
        assert (paper / "models" / f"obj_{oid:06d}.ply").read_bytes().startswith(b"ply\n")
        m = models[str(oid)]
        assert m["diameter"] == pytest.approx(load_object(name).diameter * 1000.0)
        assert m["size_x"] == pytest.approx(load_object(name).extents[0] * 1000.0, rel=1e-5)
        assert "symmetries_discrete" not in m  # no object has a symmetry


def test_split_seed_ranges_are_disjoint() -> None:
    bases = sorted(SEED_BASES.values())
    assert all(b - a >= 100_000_000 for a, b in itertools.pairwise(bases))


# --- the annotations are right ---------------------------------------------------------------


def test_paper_pose_projects_onto_mask(paper: Path) -> None:
    data = ds.PoseDataset(paper, "val")
    assert len(data) == N_PAPER
    for sample in data:
        (obj,) = sample.objects
        assert sample.rgb.shape == (256, 256, 3)
        np.testing.assert_array_equal(obj.mask, obj.mask_visib)  # nothing occludes the object
        x0, y0, x1, y1 = obj.box_xyxy
        assert x0 < obj.uv[0] < x1 and y0 < obj.uv[1] < y1
        np.testing.assert_allclose(obj.uv, project(sample.K, obj.T_C_O[:3, 3]))
        sil = _silhouette(obj.name, obj.T_C_O, sample.K, obj.mask.shape)
        assert _iou(sil, obj.mask) > 0.9, (sample.im_id, _iou(sil, obj.mask))
        # The paper's in-plane angles: -60..60 deg in 3 deg steps, and the label's theta is it.
        theta = np.degrees(sample.extra["roll"])
        assert -60 <= theta <= 60 and abs(theta / 3 - round(theta / 3)) < 1e-6
        assert abs(np.degrees(encode(obj.T_C_O, sample.K)[1]) - theta) < 1e-6
        # The camera 1.2-1.8 object diameters from the object's origin.
        dist = sample.extra["camera_distance"]
        assert dist == pytest.approx(np.linalg.norm(obj.T_C_O[:3, 3]))
        assert 1.2 <= dist / load_object(obj.name).diameter <= 1.8


def test_paper_K_matches_sim_intrinsics(paper: Path) -> None:
    from perception.training.data.studio import CAMERA, Studio

    studio = Studio()  # no GL context is created without rendering
    K = camera_intrinsics(studio.model, CAMERA, 256, 256)
    np.testing.assert_array_equal(ds.load_sample(paper, "val", 0).K, K)
    cam = json.loads((paper / "camera.json").read_text())
    assert (cam["fx"], cam["cx"], cam["width"]) == (K[0, 0], K[0, 2], 256)


def test_studio_renders_the_same_scene_with_the_object_turned(paper: Path) -> None:
    from perception.training.data.studio import Studio

    sample = ds.load_sample(paper, "val", 0)
    name = sample.objects[0].name
    with Studio() as studio:
        view = studio.render(name, np.random.default_rng(sample.seed))
        np.testing.assert_array_equal(view.rgb, sample.rgb)  # a recorded seed re-renders
        same = studio.render_turned(name, np.eye(3))
        np.testing.assert_array_equal(same.rgb, view.rgb)
        flip = np.diag([-1.0, -1.0, 1.0])
        turned = studio.render_turned(name, flip)
        np.testing.assert_allclose(turned.T_C_O[:3, :3], view.T_C_O[:3, :3] @ flip, atol=1e-9)
        np.testing.assert_allclose(turned.T_C_O[:3, 3], view.T_C_O[:3, 3], atol=1e-9)
        assert _iou(_silhouette(name, turned.T_C_O, turned.K, turned.mask.shape), turned.mask) > 0.9
        # Only the object moved: away from the pixels it covers in either image (and their
        # anti-aliased rim), nothing changed.
        rim = cv2.dilate((view.mask | turned.mask).astype(np.uint8), np.ones((5, 5)))
        outside = rim == 0
        np.testing.assert_array_equal(turned.rgb[outside], view.rgb[outside])
        assert not np.array_equal(turned.rgb, view.rgb)
        again = studio.render(name, np.random.default_rng(sample.seed))
        np.testing.assert_array_equal(again.rgb, sample.rgb)  # the turn was undone
        other = next(n for n in OBJECT_NAMES if n != name)
        with pytest.raises(StateError, match="needs a render"):
            studio.render_turned(other, flip)


def test_headcam_matches_the_seeded_scene(headcam: Path) -> None:
    data = ds.PoseDataset(headcam, "test")
    assert len(data) == N_HEADCAM
    sample = data[0]
    assert sample.rgb.shape == (480, 640, 3)
    target = [o for o in sample.objects if o.extra["target"]]
    assert len(target) == 1 and target[0].name == OBJECT_NAMES[0]
    # The recorded seed rebuilds the same scene.
    scene = build_scene(
        OBJECT_NAMES[0],
        sample.seed,
        SceneConfig(n_distractors=sample.extra["n_distractors"], randomize_appearance=True),
    )
    np.testing.assert_allclose(sample.K, camera_intrinsics(scene.model, C.HEAD_CAMERA, 640, 480))
    T_C_W = invert_transform(T_world_cam(scene.model, scene.data, C.HEAD_CAMERA))
    for obj in sample.objects:
        np.testing.assert_allclose(
            obj.T_C_O, T_C_W @ scene.object_pose(obj.extra["body"]), atol=1e-9
        )


def test_headcam_masks_and_poses(headcam: Path) -> None:
    n_objects = 0
    for sample in ds.PoseDataset(headcam, "test"):
        for obj in sample.objects:
            n_objects += 1
            assert not (obj.mask_visib & ~obj.mask).any()
            assert obj.mask_visib.any() and 0.0 < obj.visib_fract <= 1.0
            full = _silhouette(obj.name, obj.T_C_O, sample.K, obj.mask.shape)
            if obj.info["bbox_obj"] == obj.info["bbox_visib"]:  # inside the image
                assert _iou(full, obj.mask) > 0.9
    assert n_objects >= N_HEADCAM


def test_truncated_silhouette_counts_pixels_outside_the_image() -> None:
    obj = load_object("car")
    K = np.array([[300.0, 0, 99.5], [0, 300.0, 99.5], [0, 0, 1]])
    T = np.eye(4)
    T[:3, 3] = [0.12, 0.0, 0.6]  # the car's front leaves the image on the right
    cut = _silhouette("car", T, K, (200, 200))
    # Ground truth: the same view on an image 200 px wider on the right.
    wide = _silhouette("car", T, K, (200, 400))
    assert wide[:, :200].sum() == cut.sum() and wide[:, 200:].sum() > 0.1 * wide.sum()
    n, box = full_silhouette(obj.mesh, T, K, cut)
    assert n == pytest.approx(wide.sum(), rel=0.01)
    assert box == pytest.approx(bop.bbox_xywh(wide), abs=1)


# --- reproducible and resumable --------------------------------------------------------------


def test_wall_time_is_recorded_per_split(paper: Path) -> None:
    times = json.loads((paper / WALL_TIME_FILE).read_text())
    assert set(times) == {"val"} and times["val"] > 0


def test_depth_read_inside_a_window_is_that_part_of_the_whole_one() -> None:
    # The generator reads each object's depth back only inside its projected box: the box must
    # hold every pixel the object covers, and the part read must equal the whole read there.
    from perception.training.data.distributions import HeadcamGenerator, _geoms_window
    from perception.training.data.studio import HIDDEN_GROUP

    gen = HeadcamGenerator(320, 240)
    try:
        scene = build_scene("chair", 5, SceneConfig(n_distractors=3))
        model, data, r = scene.model, scene.data, gen.renderer
        cam = model.camera(C.HEAD_CAMERA).id
        K = camera_intrinsics(model, C.HEAD_CAMERA, 320, 240)
        T_C_W = invert_transform(T_world_cam(model, data, C.HEAD_CAMERA))
        groups = model.geom_group.copy()
        seen = 0
        for placed in scene.objects:
            bid = model.body(placed.body).id
            geoms = np.flatnonzero(model.geom_bodyid == bid)
            x0, y0, x1, y1 = _geoms_window(model, data, geoms, T_C_W, K, 320, 240)
            model.geom_group[:] = np.where(model.geom_bodyid == bid, groups, HIDDEN_GROUP)
            r.draw(model, data, cam)
            whole, part = r.read_depth(), r.read_depth((x0, y0, x1, y1))
            model.geom_group[:] = groups
            np.testing.assert_array_equal(part, whole[y0:y1, x0:x1])
            inside = np.zeros_like(whole, bool)
            inside[y0:y1, x0:x1] = True
            assert not (whole[~inside] < 1.0).any()
            seen += int((part < 1.0).any())
        assert seen >= 2
    finally:
        gen.close()


def test_visible_masks_from_depth_match_a_segmentation_render() -> None:
    # The generator tells an object's visible pixels by comparing its own depth with the
    # scene's; a segmentation render of the same view must agree but for depth ties.
    from perception.training.data.distributions import HeadcamGenerator
    from posegrasp.world.camera import CameraRenderer, body_mask

    gen = HeadcamGenerator(320, 240, tier="hard")
    try:
        checked, occluded, wrong, seen = 0, 0, 0, 0
        for seed in range(3):
            image = gen.render("phone", 40 + seed)
            scene = gen._scene("phone", 40 + seed)
            model = scene.model
            cam = model.camera(C.HEAD_CAMERA).id
            np.testing.assert_array_equal(gen.renderer.render(model, scene.data, cam), image.rgb)
            with CameraRenderer(model, 320, 240) as ref:
                seg = ref.segmentation(scene.data, cam)
            for obj in image.objects:
                expected = body_mask(model, seg, obj.extra["body"])
                assert not (obj.mask_visib & ~obj.mask).any()
                wrong += int((obj.mask_visib != expected).sum())
                seen += int(expected.sum())
                occluded += int(obj.mask.sum() > obj.mask_visib.sum())
                checked += 1
        assert checked >= 6 and occluded >= 2
        assert wrong <= 0.001 * seen, (wrong, seen)
    finally:
        gen.close()


def test_same_arguments_give_identical_bytes(paper: Path, tmp_path: Path) -> None:
    out = tmp_path / "again"
    args = ["--dist", "paper", "--split", "val", "--count", str(N_PAPER), "--out", str(out)]
    assert _run(*args, "--workers", "2") == 0
    assert _files(out) == _files(paper)


def test_resume_skips_done_samples(paper: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "resume"
    shutil.copytree(paper, out)
    sdir = out / "val" / "000000"
    # An interrupted run: image 5 has no record (and a stray temporary file), image 6 nothing.
    bop.record_path(sdir, 5).unlink()
    (sdir / "rgb" / "000005.png.tmp").write_bytes(b"partial")
    for p in [bop.record_path(sdir, 6), bop.rgb_path(sdir, 6), *sdir.glob("mask*/000006_*")]:
        p.unlink()
    kept = bop.rgb_path(sdir, 0)
    kept.write_bytes(kept.read_bytes())  # same bytes, new mtime
    stamp = kept.stat().st_mtime_ns
    capsys.readouterr()
    args = ["--dist", "paper", "--split", "val", "--count", str(N_PAPER), "--out", str(out)]
    assert _run(*args) == 0
    assert f"rendered 2, {N_PAPER - 2} already done" in capsys.readouterr().out
    assert kept.stat().st_mtime_ns == stamp  # done samples are not rewritten
    assert not (sdir / "rgb" / "000005.png.tmp").exists()  # reused and renamed
    assert _files(out) == _files(paper)


def test_extending_a_split_keeps_its_samples(paper: Path, tmp_path: Path) -> None:
    out = tmp_path / "extend"
    args = ["--dist", "paper", "--split", "val", "--out", str(out)]
    assert _run(*args, "--count", "3") == 0
    assert _run(*args, "--count", str(N_PAPER)) == 0
    assert _files(out) == _files(paper)


# --- corrupt files are detected --------------------------------------------------------------


def test_corrupt_png_is_detected(paper: Path, tmp_path: Path) -> None:
    out = tmp_path / "corrupt"
    shutil.copytree(paper, out)
    png = bop.rgb_path(out / "val" / "000000", 2)
    png.write_bytes(png.read_bytes()[:-100])
    with pytest.raises(AssetError, match=r"corrupt PNG .*000002\.png.*python -m perception"):
        ds.load_sample(out, "val", 2)
    ds.load_sample(out, "val", 1)  # the others still load
    mask = bop.mask_path(out / "val" / "000000", 3, 0, visib=True)
    mask.write_bytes(b"not a png")
    with pytest.raises(AssetError, match=r"mask_visib"):
        ds.load_sample(out, "val", 3)
    mask.unlink()
    with pytest.raises(AssetError, match=r"missing dataset file"):
        ds.load_sample(out, "val", 3)


def test_corrupt_json_is_detected(paper: Path, tmp_path: Path) -> None:
    out = tmp_path / "corrupt_json"
    shutil.copytree(paper, out)
    gt = out / "val" / "000000" / "scene_gt.json"
    gt.write_text(gt.read_text()[:50])
    with pytest.raises(AssetError) as err:
        ds.load_sample(out, "val", 0)
    msg = str(err.value)
    assert "scene_gt.json" in msg and "--dist paper --split val --count 8" in msg
    assert "\n" not in msg


# --- command line ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--dist", "paper", "--split", "val", "--count", "2", "--objects", "cat"], "car, faucet"),
        (["--dist", "paper", "--split", "val", "--count", "0"], "valid: integers 1.."),
        (["--dist", "photo", "--split", "val", "--count", "1"], "paper, headcam"),
        (["--dist", "paper", "--split", "dev", "--count", "1"], "train, val, test"),
        (["--dist", "paper", "--split", "val", "--count", "x"], "invalid --count 'x'"),
        (["--dist", "paper", "--split", "val", "--count", "1", "--workers", "0"], "1..64"),
        (["--dist", "paper", "--split", "val", "--count", "1", "--width", "0"], "1..4096"),
        (["--dist", "headcam", "--split", "val", "--count", "1", "--tier", "x"], "any-pose, far"),
        (["--dist", "paper", "--split", "val", "--count", "1", "--tier", "far"], "headcam"),
    ],
)
def test_cli_bad_arguments_give_one_line(args, needle, tmp_path: Path, capsys) -> None:
    assert main([*args, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and needle in err
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("sub", ["", "/sub"])
def test_cli_unwritable_output(sub: str, tmp_path: Path, capsys) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    args = ["--dist", "paper", "--split", "val", "--count", "1", "--out", f"{blocker}{sub}"]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--out" in err and "a file, not a folder" in err


def test_cli_refuses_to_mix_arguments(paper: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "mix"
    shutil.copytree(paper, out)
    args = ["--dist", "paper", "--split", "val", "--count", "2", "--out", str(out)]
    assert main([*args, "--width", "128", "--height", "128"]) != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "use another --out" in err
    assert main([*args, "--objects", "phone"]) != 0
    assert "--objects" in capsys.readouterr().err
    # A folder of an older paper protocol (camera 1.6-4.5 diameters away) is not resumed.
    info = json.loads((out / "info.json").read_text())
    (out / "info.json").write_text(json.dumps(info | {"version": "2"}))
    assert main(args) != 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "version 2" in err and "use another --out" in err


def test_cli_help(capsys) -> None:
    assert main(["--help"]) == 0
    assert "--dist" in capsys.readouterr().out


def test_preview_contact_sheet(paper: Path, tmp_path: Path) -> None:
    sheet = tmp_path / "sheet.png"
    args = ["--dist", "paper", "--split", "val", "--count", str(N_PAPER), "--out", str(paper)]
    assert _run(*args, "--preview", str(sheet)) == 0
    img = cv2.imread(str(sheet))
    assert img.shape == (2 * 256, 6 * 256, 3)
    # The axes are drawn: pure red, green and blue-ish strokes appear on the sheet.
    drawn = draw_annotations(ds.load_sample(paper, "val", 0))
    assert (drawn != ds.load_sample(paper, "val", 0).rgb).any()


def test_datagen_does_not_import_torch() -> None:
    code = (
        "import sys, perception.training.datagen, perception.training.data.dataset; "
        "print('torch' in sys.modules)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout.strip() == "False"


def test_headcam_tier_images_are_of_the_tier(tmp_path: Path) -> None:
    out = tmp_path / "clutter"
    args = ["--dist", "headcam", "--split", "val", "--count", "2", "--tier", "clutter"]
    assert main([*args, "--width", "160", "--height", "120", "--out", str(out), "--quiet"]) == 0
    assert ds.load_info(out)["tier"] == "clutter"
    for i in range(2):
        sample = ds.load_sample(out, "val", i)
        assert 4 <= 1 + sample.extra["n_distractors"] <= 6
    # A folder of one tier refuses another.
    again = [*args[:-1], "far", "--width", "160", "--height", "120", "--out", str(out), "--quiet"]
    assert main(again) != 0
