"""P(grasp success | pose error): the kernel model and its fitting CLI's input checks."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from perception.success_model import PRIOR_WEIGHT, SuccessModel, components_of, load_models
from posegrasp.core.errors import AssetError, InvalidArgumentError
from sim import fit_success


def _step_data(n: int = 300, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Success exactly when the ray error is below 10 mm; the other components are noise."""
    rng = np.random.default_rng(seed)
    X = np.column_stack(
        [rng.uniform(0, 30, n), rng.uniform(0, 30, n), rng.uniform(0, 10, n), rng.uniform(0, 10, n)]
    )
    return X, (X[:, 0] < 10).astype(float)


def test_the_fit_finds_the_component_that_matters() -> None:
    X, y = _step_data()
    m = SuccessModel.fit(X, y)
    assert m.bandwidth[0] < min(m.bandwidth[1:])
    p = m.predict(np.array([[3.0, 15, 5, 5], [25.0, 15, 5, 5]]))
    assert p[0] > 0.9 and p[1] < 0.1
    # Better than the constant-rate model on its own data, by leave-one-out likelihood.
    rate = y.mean()
    constant = float(np.mean(y * np.log(rate) + (1 - y) * np.log(1 - rate)))
    assert m.log_likelihood > constant


def test_leave_one_out_likelihood_by_hand() -> None:
    X = np.array([[0.0, 0, 0, 0], [1.0, 0, 0, 0], [100.0, 0, 0, 0]])
    y = np.array([1.0, 1.0, 0.0])
    h = np.array([1.0, 1.0, 1.0, 1.0])
    w01 = np.exp(-0.5)  # between the first two; the third is too far to count
    rate = 2 / 3
    p0 = (w01 * 1 + PRIOR_WEIGHT * rate) / (w01 + PRIOR_WEIGHT)
    p2 = (0 + PRIOR_WEIGHT * rate) / (0 + PRIOR_WEIGHT)
    want = (2 * np.log(p0) + np.log(1 - p2)) / 3
    assert SuccessModel.loo_log_likelihood(X, y, h) == pytest.approx(want, rel=1e-9)


def test_json_round_trip_and_bad_files(tmp_path: Path) -> None:
    X, y = _step_data(60)
    m = SuccessModel.fit(X, y, sweeps=1)
    path = tmp_path / "m.json"
    path.write_text(json.dumps({"models": {"phone/isolated": m.to_json()}}))
    again = load_models(path)["phone/isolated"]
    E = np.array([[5.0, 5, 2, 2]])
    assert again.predict(E)[0] == pytest.approx(m.predict(E)[0], rel=1e-6)
    path.write_text("{}")
    with pytest.raises(AssetError, match=r"sim\.fit_success"):
        load_models(path)


def test_inputs_are_checked() -> None:
    with pytest.raises(InvalidArgumentError):
        SuccessModel.fit(np.zeros((3, 4)), np.zeros(3))
    m = SuccessModel.fit(*_step_data(30), sweeps=1)
    with pytest.raises(InvalidArgumentError):
        m.predict(np.array([np.nan, 0, 0, 0]))
    assert components_of(
        {"ray_m": 0.002, "lateral_m": 0.001, "inplane_deg": 3.0, "outplane_deg": 4.0}
    ) == pytest.approx([2.0, 1.0, 3.0, 4.0])


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--objects", "teapot"], "valid objects"),
        (["--episodes", "1"], "valid: integers 3..10000"),
        (["--objects", "phone,phone"], "phone twice"),
        (["--tier", "banana"], "valid tiers"),
        (["--workers", "0"], "valid: integers 1..64"),
        (["--out", "{tmp}"], "unrecognized arguments: --out"),
    ],
)
def test_fit_cli_rejects_bad_input_in_one_line(tmp_path: Path, capsys, argv, message) -> None:
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    # Refused while parsing, before any work.
    assert fit_success.main([*argv, "--models", str(tmp_path / "m.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not (tmp_path / "m.json").exists()


def test_the_prior_falls_with_every_error_beyond_the_sample() -> None:
    X, y = _step_data()
    m = SuccessModel.fit(X, y)
    assert m.prior is not None and np.all(m.prior[1:] <= 0.0)
    far = np.array([[300.0, 15, 5, 5], [3.0, 15, 5, 5]])
    p = m.predict(far)
    # 300 mm along the ray is ten times the sampled range: the estimate follows the prior down,
    # where the overall rate (1/3 here) would have been returned before.
    assert p[0] < 0.05 and p[1] > 0.9
    constant = SuccessModel(m.X, m.y, m.bandwidth)  # the same kernel with the constant prior
    assert constant.predict(far[0]) == pytest.approx(m.rate, abs=1e-6)


def test_the_prior_improves_the_leave_one_out_likelihood() -> None:
    rng = np.random.default_rng(3)
    X = rng.uniform(0, 40, (200, 4))
    y = (rng.uniform(size=200) < 1 / (1 + np.exp(0.2 * (X[:, 0] - 20)))).astype(float)
    m = SuccessModel.fit(X, y)
    assert m.log_likelihood > SuccessModel.loo_log_likelihood(X, y, m.bandwidth)


def _report(tier: str, rows: list[tuple[str, float | None, bool]]) -> dict:
    def error(ray: float | None) -> dict | None:
        if ray is None:
            return None
        return {"ray_m": ray / 1000, "lateral_m": 0.0, "inplane_deg": 1.0, "outplane_deg": 1.0}

    episodes = [
        {"object": o, "tier": tier, "success": s, "pose_error": error(ray)} for o, ray, s in rows
    ]
    return {"estimator": "hybrid", "tier": tier, "episodes": episodes}


def test_refit_and_check_from_the_cli(tmp_path: Path, capsys) -> None:
    X, y = _step_data(80)
    old = SuccessModel(X, y, np.full(4, 5.0))  # a file written before the prior existed
    path = tmp_path / "m.json"
    path.write_text(json.dumps({"models": {"phone/far": old.to_json()}}))
    assert fit_success.main(["--refit", "--models", str(path)]) == 0
    new = load_models(path)["phone/far"]
    assert new.prior is not None and new.log_likelihood > SuccessModel.loo_log_likelihood(
        X, y, np.full(4, 5.0)
    )
    run = tmp_path / "run.json"
    rows = [("phone", 2.0, True), ("phone", 200.0, False), ("phone", None, False)]
    run.write_text(json.dumps(_report("far", rows)))
    pred, k, n = fit_success.check({"phone/far": new}, _report("far", rows))
    assert (k, n) == (1, 2)  # the episode without an estimate is not a pose error
    want = np.mean([new.predict(np.array([2.0, 0, 1, 1])), new.predict(np.array([200, 0, 1, 1]))])
    assert pred == pytest.approx(want)
    capsys.readouterr()
    assert fit_success.main(["--check", str(run), "--models", str(path)]) == 0
    assert "measured 50.0% (1/2 episodes with an estimate)" in capsys.readouterr().out
    run.write_text(json.dumps(_report("hard", rows)))
    assert fit_success.main(["--check", str(run), "--models", str(path)]) == 2
    assert "no success model for phone/hard" in capsys.readouterr().err


def test_a_place_report_is_checked_against_the_place_models(tmp_path: Path, capsys) -> None:
    """The models of the place task are keyed apart from the lift's; a place report asks for
    them and names the one it misses."""
    X, y = _step_data(80)
    model = SuccessModel.fit(X, y)
    assert fit_success.model_key("phone", "far") == "phone/far"
    assert fit_success.model_key("phone", "far", "place") == "phone/far/place"
    rows = [("phone", 2.0, True), ("phone", 200.0, False)]
    place = _report("far", rows) | {"task": "place"}
    lift_only = {"phone/far": model}
    with pytest.raises(AssetError, match="no success model for phone/far/place"):
        fit_success.check(lift_only, place)
    pred, k, n = fit_success.check({"phone/far/place": model}, place)
    assert (k, n) == (1, 2) and 0 <= pred <= 1
