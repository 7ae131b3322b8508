"""Paired comparison of two evaluation reports (`python -m sim.compare`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from perception import metrics
from posegrasp.core.errors import InvalidArgumentError
from sim import compare as cmp
from sim.evaluation import Protocol, make_report, stats


def _episode(obj: str, seed: int, tier: str, ok: bool, margin: float | None) -> dict:
    """An episode record as `sim.evaluate` writes it (schema `sim.evaluation.report_schema`)."""
    return {
        "object": obj,
        "seed": seed,
        "estimator": "x",
        "tier": tier,
        "success": ok,
        "failure_reason": None if ok else "missed",
        "friction_margin": margin if ok else None,
        "pose_error": None,
        "notes": [],
        "timings_ms": {},
        "wall_ms": 1.0,
    }


def _write(path: Path, eps: list[dict], tier: str, noise: str | None = None, **fields) -> Path:
    objects = sorted({e["object"] for e in eps})
    protocol = Protocol(objects, max(1, len(eps)), seed_start=1, tier=tier, noise=noise)
    report = make_report(eps, protocol, "x")
    report.update(fields)
    path.write_text(json.dumps(report))
    return path


def _report(
    path: Path,
    successes: dict[tuple[str, int], bool],
    tier: str = "isolated",
    execution: dict | None = None,
) -> Path:
    eps = [_episode(o, s, tier, ok, 0.2 + 0.01 * s) for (o, s), ok in successes.items()]
    return _write(path, eps, tier, **({} if execution is None else {"execution": execution}))


def test_mcnemar_exact_by_hand() -> None:
    assert stats.mcnemar_exact(0, 0) == 1.0
    assert stats.mcnemar_exact(0, 6) == pytest.approx(2 * 0.5**6)
    assert stats.mcnemar_exact(6, 0) == pytest.approx(2 * 0.5**6)
    # 2 vs 8 discordant: 2 * P(X <= 2), X ~ Bin(10, 1/2) = 2 * 56 / 1024
    assert stats.mcnemar_exact(2, 8) == pytest.approx(2 * 56 / 1024)
    # One-sided, the test of a loss: at least 5 of 5 discordant pairs go A's way.
    assert stats.mcnemar_exact(5, 0, one_sided=True) == pytest.approx(0.5**5)
    assert stats.mcnemar_exact(0, 5, one_sided=True) == pytest.approx(1.0)
    assert stats.mcnemar_exact(5, 2, one_sided=True) == pytest.approx(29 / 128)


def test_paired_difference_and_bootstrap() -> None:
    rng = np.random.default_rng(0)
    a = np.ones(50, bool)
    same = stats.paired(a, a.copy(), 500, rng)
    assert same["difference"] == 0.0 and same["bootstrap_low"] == same["bootstrap_high"] == 0.0
    b = a.copy()
    b[:10] = False
    r = stats.paired(a, b, 2000, rng)
    assert r["difference"] == pytest.approx(-0.2)
    assert r["a_only"] == 10 and r["b_only"] == 0
    assert r["bootstrap_low"] < -0.2 < r["bootstrap_high"] < 0.0
    assert r["mcnemar_p"] == pytest.approx(2 * 0.5**10)


def test_only_common_episodes_are_paired(tmp_path: Path) -> None:
    a = _report(tmp_path / "a.json", {("phone", 1): True, ("phone", 2): True, ("car", 1): True})
    b = _report(tmp_path / "b.json", {("phone", 1): False, ("phone", 2): True, ("car", 9): True})
    res = cmp.compare(cmp.load_report(a), cmp.load_report(b), boot=200)
    assert res["paired_episodes"] == 2 and res["only_in_a"] == 1 and res["only_in_b"] == 1
    assert list(res["per_object"]) == ["phone"]
    assert res["overall"]["difference"] == pytest.approx(-0.5)


def test_reports_of_other_tiers_share_nothing(tmp_path: Path) -> None:
    a = _report(tmp_path / "a.json", {("phone", 1): True})
    b = _report(tmp_path / "b.json", {("phone", 1): True}, tier="clutter")
    with pytest.raises(InvalidArgumentError, match="share no"):
        cmp.compare(cmp.load_report(a), cmp.load_report(b))


def test_cli_prints_a_table_and_writes_json(tmp_path: Path, capsys) -> None:
    a = _report(tmp_path / "a.json", {("phone", s): True for s in range(10)})
    b = _report(tmp_path / "b.json", {("phone", s): s % 2 == 0 for s in range(10)})
    out = tmp_path / "cmp.json"
    assert cmp.main([str(a), str(b), "--json", str(out), "--boot", "200"]) == 0
    text = capsys.readouterr().out
    assert "McNemar p" in text and "overall" in text
    assert json.loads(out.read_text())["overall"]["b_only"] == 0


def test_cli_json_to_standard_output_keeps_the_table_apart(tmp_path: Path, capsys) -> None:
    a = _report(tmp_path / "a.json", {("phone", s): True for s in range(10)})
    b = _report(tmp_path / "b.json", {("phone", s): s % 2 == 0 for s in range(10)})
    assert cmp.main([str(a), str(b), "--json", "-", "--boot", "200"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["overall"]["a_only"] == 5  # stdout is the JSON alone
    assert "McNemar p" in captured.err and "wrote" not in captured.out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["nope.json", "nope2.json"], "is not a report"),
        (["{a}", "{a}", "--boot", "5"], "valid: integers 100..100000"),
        (["{a}", "{a}", "--curve", "--plot", "p.xyz"], "valid suffixes: .png, .pdf, .svg"),
        (["{a}", "{a}", "--plot", "p.png"], "need --curve"),
    ],
)
def test_cli_bad_input_is_one_line(tmp_path: Path, capsys, argv, message) -> None:
    a = _report(tmp_path / "a.json", {("phone", 1): True})
    argv = [x.replace("{a}", str(a)) for x in argv]
    try:
        assert cmp.main(argv) == 2
    except SystemExit as exc:  # refused while parsing
        assert exc.code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_runs_of_other_execution_settings_are_not_paired(tmp_path: Path, capsys) -> None:
    outcomes = {("phone", s): True for s in range(10)}
    fast = {"transit": "kinematic", "timestep": 0.004}
    a = _report(tmp_path / "a.json", outcomes, execution=fast)
    b = _report(tmp_path / "b.json", outcomes, execution={**fast, "transit": "dynamic"})
    c = _report(tmp_path / "c.json", outcomes, execution=fast)
    old = _report(tmp_path / "old.json", outcomes)
    report = json.loads(old.read_text())
    del report["execution"]  # as recorded before reports said
    old.write_text(json.dumps(report))
    assert cmp.main([str(a), str(b), "--boot", "200"]) == 2
    err = capsys.readouterr().err.strip()
    assert "transit: 'kinematic' against 'dynamic'" in err and len(err.splitlines()) == 1
    assert cmp.main([str(a), str(c), "--boot", "200"]) == 0
    # A report without the record does not pair with anything: the reader names the field.
    assert cmp.main([str(a), str(old), "--boot", "200"]) == 2
    assert "lacks the field execution" in capsys.readouterr().err
    assert cmp.main([str(a), str(c), str(b), "--curve", "--boot", "200"]) == 2


def test_margin_difference_on_pairs_both_grasped() -> None:
    rng = np.random.default_rng(0)
    a = [(True, 0.20), (True, 0.30), (False, None), (True, 0.25)]
    b = [(True, 0.25), (False, None), (True, 0.1), (True, 0.30)]
    m = stats.margin_difference(a, b, 500, rng)
    assert m["pairs"] == 2 and m["difference"] == pytest.approx(0.05)
    assert m["bootstrap_low"] == pytest.approx(0.05) and m["bootstrap_high"] == pytest.approx(0.05)
    assert stats.margin_difference([(False, None)], [(True, 0.2)], 100, rng) is None


def test_margin_error_correlation() -> None:
    margin_error_correlation = stats.margin_error_correlation

    eps = [
        {
            "friction_margin": 0.1 + 0.01 * i,
            "pose_error": {"translation_m": 0.001 * i, "rotation_deg": 10.0 - i},
        }
        for i in range(10)
    ]
    rho = margin_error_correlation([*eps, {"friction_margin": None, "pose_error": None}])
    assert rho["episodes"] == 10
    assert rho["translation_m"] == pytest.approx(1.0)  # larger error, looser grasp
    assert rho["rotation_deg"] == pytest.approx(-1.0)
    assert rho["add_m"] is None  # not reported
    # Too few episodes, or a constant side: no figure rather than a meaningless one.
    assert margin_error_correlation(eps[:4])["translation_m"] is None
    flat = [dict(e, friction_margin=0.2) for e in eps]
    assert margin_error_correlation(flat)["translation_m"] is None


def test_curve_chains_paired_comparisons(tmp_path: Path, capsys) -> None:
    """Three runs on the same scenes: each is compared with the one before; a plot is drawn."""
    paths = []
    for k, lost in enumerate((0, 1, 8)):
        eps = [_episode("phone", s, "hard", s >= lost, 0.2) for s in range(40)]
        paths.append(_write(tmp_path / f"r{k}.json", eps, "hard", noise=f"{k},{k},{k},{k}"))
    png = tmp_path / "curve.png"
    assert cmp.main(["--curve", *map(str, paths), "--plot", str(png)]) == 0
    out = capsys.readouterr().out
    assert "40/40" in out and "39/40" in out and "32/40" in out
    assert "0.0156" in out  # 7 lost, 0 won: exact two-sided McNemar p = 2 * 0.5**7
    assert png.stat().st_size > 5_000
    # Three reports without --curve, or --plot alone, are refused.
    assert cmp.main([*map(str, paths)]) == 2
    assert cmp.main([str(paths[0]), str(paths[1]), "--plot", str(png)]) == 2


def test_compare_validates_each_report_and_names_the_field(tmp_path: Path, capsys) -> None:
    good = _report(tmp_path / "a.json", {("phone", 1): True, ("phone", 2): False})
    cases = {
        "overall.successes": lambda r: r["overall"].pop("successes"),
        "episodes[1].seed": lambda r: r["episodes"][1].pop("seed"),
        "schema": lambda r: r.pop("schema"),
    }
    for field, damage in cases.items():
        report = json.loads(good.read_text())
        damage(report)
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps(report))
        assert cmp.main([str(good), str(bad)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and field.split(".")[-1].split("[")[0] in err, err
    report = json.loads(good.read_text())
    report["episodes"][0]["success"] = "yes"
    bad.write_text(json.dumps(report))
    assert cmp.main([str(good), str(bad)]) == 2
    assert "episodes[0].success: 'yes' is not of type 'boolean'" in capsys.readouterr().err


def test_paired_mean_difference_by_hand() -> None:
    rng = np.random.default_rng(0)
    a, b = np.array([0.0, 0.5, 1.0]), np.array([0.5, 0.5, 1.0])
    r = stats.paired_mean_difference(a, b, 2000, rng)
    assert r["episodes"] == 3 and r["a"] == pytest.approx(0.5) and r["b"] == pytest.approx(2 / 3)
    assert r["difference"] == pytest.approx(1 / 6)
    # A resample's mean difference is k/6 for k of its 3 draws on the first pair: k = 0 with
    # chance 8/27 (the low end is 0), k = 3 with 1/27 (the high end lies within (1/3, 1/2)).
    assert r["bootstrap_low"] == 0.0 and 1 / 3 <= r["bootstrap_high"] <= 0.5
    with pytest.raises(InvalidArgumentError, match="non-empty"):
        stats.paired_mean_difference(np.zeros(2), np.zeros(3), 100, rng)


def test_image_width_is_the_episodes() -> None:
    from sim.episodes.episode import EpisodeConfig

    assert cmp.IMAGE_WIDTH == EpisodeConfig().width


def _with_errors(obj: str, seed: int, mssd: float | None, mspd: float | None, vsd=False) -> dict:
    """An episode with BOP errors; None: no estimate (`vsd`: add one VSD error per tau)."""
    e = _episode(obj, seed, "hard", True, 0.2)
    if mssd is not None:
        e["pose_error"] = {"translation_m": 0.01, "rotation_deg": 1.0, "mssd_rel_diameter": mssd}
        if mspd is not None:
            e["pose_error"]["mspd_px"] = mspd
    if vsd:
        n = len(metrics.BOP_VSD_TAUS)
        e["vsd"] = None if mssd is None else [min(1.0, 2 * mssd + 0.02 * i) for i in range(n)]
    return e


def test_average_recalls_pair_per_episode(tmp_path: Path) -> None:
    """The paired recalls equal BOP's recalls of each whole report (linear in episodes), and an
    episode without an estimate counts 0."""
    rng = np.random.default_rng(3)
    mssd_a = [None, *rng.uniform(0.0, 0.6, 29)]
    mssd_b = [*rng.uniform(0.0, 0.4, 29), None]
    mspd_a = [None, *rng.uniform(0.0, 60.0, 28), None]  # the last: infinite, left out
    mspd_b = list(rng.uniform(0.0, 40.0, 30))
    pairs_a = enumerate(zip(mssd_a, mspd_a, strict=True))
    pairs_b = enumerate(zip(mssd_b, mspd_b, strict=True))
    eps_a = [_with_errors("phone", s, m, p, vsd=True) for s, (m, p) in pairs_a]
    eps_b = [_with_errors("phone", s, m, p, vsd=True) for s, (m, p) in pairs_b]
    a = _write(tmp_path / "a.json", eps_a, "hard")
    b = _write(tmp_path / "b.json", eps_b, "hard")
    res = cmp.compare_reports(a, b, boot=500)
    ar = res["average_recall"]
    assert set(ar) == {"ar_mssd", "ar_mspd", "ar_vsd"}
    for eps, side in ((eps_a, "a"), (eps_b, "b")):
        pe = [e["pose_error"] or {} for e in eps]
        whole = {
            "ar_mssd": metrics.ar_mssd([p.get("mssd_rel_diameter") for p in pe], 1.0),
            "ar_mspd": metrics.ar_mspd([p.get("mspd_px") for p in pe], 640),
            "ar_vsd": metrics.ar_vsd([e["vsd"] for e in eps]),
        }
        for name, value in whole.items():
            assert ar[name][side] == pytest.approx(value), name
    for r in ar.values():
        assert r["difference"] == pytest.approx(r["b"] - r["a"]) and r["episodes"] == 30
        assert r["bootstrap_low"] <= r["difference"] <= r["bootstrap_high"]
    # One episode by hand: MSSD 0.12 of the diameter is below 8 of the 10 thresholds.
    one = cmp.episode_recalls({"episodes": [_with_errors("car", 1, 0.12, 7.0)]}, "r")
    assert one[("car", "hard", 1)] == pytest.approx({"ar_mssd": 0.8, "ar_mspd": 0.9})
    # Without VSD errors in one report, AR_VSD is not paired.
    for e in eps_b:
        del e["vsd"]
    b = _write(tmp_path / "b.json", eps_b, "hard")
    assert set(cmp.compare_reports(a, b, boot=100)["average_recall"]) == {"ar_mssd", "ar_mspd"}


def test_cli_prints_the_paired_recalls(tmp_path: Path, capsys) -> None:
    eps = [_with_errors("phone", s, 0.12, 10.0) for s in range(30)]
    a = _write(tmp_path / "a.json", eps, "hard")
    better = [_with_errors("phone", s, 0.01, 1.0) for s in range(30)]
    b = _write(tmp_path / "b.json", better, "hard")
    assert cmp.main([str(a), str(b), "--boot", "200"]) == 0
    out = capsys.readouterr().out
    assert "AR_MSSD  A 0.800 B 1.000, B - A +0.200" in out and "AR_MSPD" in out
    assert "AR_VSD" not in out


def test_labels_name_the_estimators_and_paths_only_to_tell_them_apart(
    tmp_path: Path, capsys
) -> None:
    eps = [_episode("phone", s, "hard", True, 0.2) for s in range(40)]
    a = _write(tmp_path / "a.json", eps, "hard", estimator="hybrid")
    b = _write(tmp_path / "b.json", eps, "hard", estimator="hybrid-global")
    c = _write(tmp_path / "c.json", eps, "hard", estimator="hybrid-global")
    assert cmp.main([str(a), str(b), "--boot", "200"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("B = hybrid-global against A = hybrid: 40 paired")
    assert cmp.main([str(b), str(c), "--boot", "200"]) == 0
    out = capsys.readouterr().out
    assert f"B = hybrid-global ({c}) against A = hybrid-global ({b})" in out


def test_other_observation_modes_are_warned_of(tmp_path: Path, capsys) -> None:
    eps = [_episode("phone", s, "hard", True, 0.2) for s in range(40)]
    a = _write(tmp_path / "a.json", eps, "hard", estimator="e")
    b = _write(tmp_path / "b.json", eps, "hard", estimator="e", obs_mode="rgbd")
    assert cmp.main([str(a), str(b), "--boot", "200"]) == 0
    captured = capsys.readouterr()
    assert "B = e (rgbd) against A = e (rgb)" in captured.out
    warning = [line for line in captured.err.splitlines() if "obs_mode" in line]
    assert len(warning) == 1 and "A saw rgb and B rgbd" in warning[0]


def test_a_small_sample_says_to_read_the_exact_test(tmp_path: Path, capsys) -> None:
    """Six pairs, three won and none lost: the bootstrap interval excludes 0 (a resample misses
    all three with chance 1/64) while the exact McNemar p is 0.25."""
    a = _report(tmp_path / "a.json", {("phone", s): s >= 3 for s in range(6)})
    b = _report(tmp_path / "b.json", {("phone", s): True for s in range(6)})
    assert cmp.main([str(a), str(b), "--boot", "2000"]) == 0
    captured = capsys.readouterr()
    assert "0.2500" in captured.out
    lines = [x for x in captured.err.splitlines() if x.startswith("warning")]
    assert len(lines) == 1
    assert (
        "only 6 paired episodes" in lines[0]
        and "overall (interval excludes 0, p = 0.25)" in lines[0]
    )
    assert "read the exact McNemar p" in lines[0]
    # Enough episodes on which the two agree: no warning.
    a = _report(tmp_path / "a.json", {("phone", s): s >= 10 for s in range(40)})
    b = _report(tmp_path / "b.json", {("phone", s): True for s in range(40)})
    assert cmp.main([str(a), str(b), "--boot", "2000"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_runs_of_other_sensors_are_not_paired(tmp_path: Path, capsys) -> None:
    eps = [_episode("phone", s, "isolated", True, 0.2) for s in range(40)]
    old = _write(tmp_path / "old.json", eps, "isolated")  # records no sensor: the ideal one
    ideal = _write(tmp_path / "ideal.json", eps, "isolated", sensor="ideal")
    kinect = _write(tmp_path / "kinect.json", eps, "isolated", sensor="kinect-v1")
    # A report whose episodes record the sensor (`sim.episodes.episode.EpisodeResult.to_json`).
    by_episode = _write(
        tmp_path / "episodes.json", [{**e, "sensor": "kinect-v1"} for e in eps], "isolated"
    )
    assert cmp.main([str(old), str(kinect), "--boot", "200"]) == 2
    err = capsys.readouterr().err.strip()
    assert f"{old} observed through sensor 'ideal' and {kinect} through 'kinect-v1'" in err
    assert len(err.splitlines()) == 1 and "pair runs of one sensor" in err
    assert cmp.main([str(old), str(ideal), "--boot", "200"]) == 0
    assert cmp.main([str(kinect), str(by_episode), "--boot", "200"]) == 0
    assert cmp.main([str(old), str(ideal), str(by_episode), "--curve", "--boot", "200"]) == 2
    capsys.readouterr()
    mixed = _write(
        tmp_path / "mixed.json",
        [{**e, "sensor": "kinect-v1" if i else "azure-tof"} for i, e in enumerate(eps)],
        "isolated",
    )
    assert cmp.main([str(kinect), str(mixed), "--boot", "200"]) == 2
    assert "holds episodes of several sensors (azure-tof, kinect-v1)" in capsys.readouterr().err


def _confident(seed: int, held: bool, confidence: float | None) -> dict:
    """An episode whose estimator gave `confidence` (None: gave none, the field left out)."""
    e = _episode("phone", seed, "hard", held, 0.2)
    return e if confidence is None else {**e, "confidence": confidence}


def test_cli_pairs_the_risk_coverage_area(tmp_path: Path, capsys) -> None:
    """A ranks its held grasps last, B first: B's area is higher on the same episodes; a report
    written before the area was recorded pairs it from its episodes' confidences."""
    held = [s % 3 != 0 for s in range(30)]
    a = _write(
        tmp_path / "a.json", [_confident(s, h, -float(h)) for s, h in enumerate(held)], "hard"
    )
    eps_b = [_confident(s, h, float(h) + s / 100) for s, h in enumerate(held)]
    b = _write(tmp_path / "b.json", eps_b, "hard")
    out = tmp_path / "cmp.json"
    assert cmp.main([str(a), str(b), "--boot", "200", "--json", str(out)]) == 0
    area = json.loads(out.read_text())["risk_coverage_area"]
    ra, rb = (json.loads(p.read_text())["overall"]["risk_coverage"]["area"] for p in (a, b))
    assert area["a"] == pytest.approx(ra) and area["b"] == pytest.approx(rb)
    assert area["episodes"] == 30 and area["difference"] == pytest.approx(rb - ra)
    assert rb > ra and area["bootstrap_low"] > 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("RC area"))
    assert line.startswith(f"RC area  A {ra:.3f} B {rb:.3f}, B - A {rb - ra:+.3f} [")
    # B as written before the area was recorded: no group holds it, the episodes still do.
    old = json.loads(b.read_text())
    for g in [old["overall"], *old["per_object"].values()]:
        del g["risk_coverage"]
    b.write_text(json.dumps(old))
    assert cmp.main([str(a), str(b), "--boot", "200", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["risk_coverage_area"] == area
    # An estimator that gives no confidence: the areas are not paired, and the line says why.
    c = _write(tmp_path / "c.json", [_confident(s, h, None) for s, h in enumerate(held)], "hard")
    assert cmp.main([str(a), str(c), "--boot", "200"]) == 0
    text = capsys.readouterr().out
    assert f"RC area  A {ra:.3f} B -: B gives no confidence, so the areas do not pair" in text
    assert cmp.main([str(c), str(c), "--boot", "200"]) == 0
    assert "RC area  neither estimator gives a confidence" in capsys.readouterr().out


def test_reports_of_different_tasks_are_not_paired(tmp_path: Path, capsys) -> None:
    """A lift report (recording no task) and a place report of the same episodes are refused in
    one line; two of one task pair."""
    eps = [_episode("phone", s, "isolated", True, 0.2) for s in range(1, 4)]
    lift = _write(tmp_path / "lift.json", eps, "isolated")
    place = _write(tmp_path / "place.json", eps, "isolated", task="place")
    assert cmp.main([str(lift), str(place)]) == 2
    err = capsys.readouterr().err
    assert f"{lift} is of the lift task and {place} of the place task" in err
    assert len(err.splitlines()) == 1 and "pair runs of one task" in err
    assert cmp.main([str(place), str(place)]) == 0
