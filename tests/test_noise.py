"""`--noise` for noisy-oracle: parsing, and common random numbers across noise levels."""

from __future__ import annotations

import numpy as np
import pytest

from perception.metrics import error_components
from posegrasp.core.cli import ArgumentParser
from posegrasp.core.contract import Observation
from posegrasp.core.errors import InvalidArgumentError
from sim.episodes.pose_noise import NOISE_FORMAT, parse_noise
from sim.episodes.registry import (
    DEFAULT_ESTIMATOR,
    NoisyOracleEstimator,
    add_estimator_arguments,
    make_estimator,
)


def test_parse_noise_units() -> None:
    n = parse_noise("5,2.5,2,1")
    assert (n.ray, n.lateral) == pytest.approx((0.005, 0.0025))
    assert (n.inplane, n.outplane) == pytest.approx((np.deg2rad(2), np.deg2rad(1)))
    assert n.mode == "gaussian"


@pytest.mark.parametrize(
    "text",
    ["", "1,2,3", "1,2,3,4,5", "a,b,c,d", "-1,0,0,0", "nan,0,0,0", "2000,0,0,0", "0,0,200,0"],
)
def test_parse_noise_rejects_with_the_format(text: str) -> None:
    with pytest.raises(InvalidArgumentError, match="RAY_MM,LATERAL_MM,INPLANE_DEG,OUTPLANE_DEG"):
        parse_noise(text)


def test_the_shared_arguments_check_estimator_and_noise_while_parsing(capsys) -> None:
    p = ArgumentParser(prog="x")
    add_estimator_arguments(p)
    args = p.parse_args(["--estimator", "noisy-oracle", "--noise", "5,5,2,2@3"])
    assert (args.estimator, args.noise) == ("noisy-oracle", "5,5,2,2@3")  # kept as given
    assert p.parse_args([]).estimator == DEFAULT_ESTIMATOR and p.parse_args([]).noise is None
    for argv, words in ((["--noise", "5,5"], NOISE_FORMAT), (["--estimator", "x"], "oracle, ")):
        with pytest.raises(SystemExit) as exc:
            p.parse_args(argv)
        err = capsys.readouterr().err
        assert exc.value.code == 2 and err.count("\n") == 1 and words in err
    gate = ArgumentParser(prog="y")
    add_estimator_arguments(gate, default=None, noise=False, also=("none",))
    assert gate.parse_args([]).estimator is None and gate.parse_args(["--estimator", "none"])
    with pytest.raises(SystemExit):
        gate.parse_args(["--noise", "1,1,1,1"])  # no --noise there
    capsys.readouterr()


def test_noise_only_for_the_noisy_oracle() -> None:
    assert isinstance(make_estimator("noisy-oracle", parse_noise("1,1,1,1")), NoisyOracleEstimator)
    with pytest.raises(InvalidArgumentError, match="noisy-oracle only"):
        make_estimator("oracle", parse_noise("1,1,1,1"))


def test_a_seed_draws_the_same_errors_at_every_level() -> None:
    """Common random numbers: doubling every sigma doubles every error component."""
    T = np.eye(4)
    T[:3, 3] = [0.05, -0.02, 0.8]
    obs = Observation(np.zeros((4, 4, 3), np.uint8), np.eye(3), np.eye(4), "phone", 1234)
    small = NoisyOracleEstimator(parse_noise("2.5,2.5,1,1")).estimate_from_truth(obs, T, ()).T_C_O
    large = NoisyOracleEstimator(parse_noise("5,5,2,2")).estimate_from_truth(obs, T, ()).T_C_O
    zero = NoisyOracleEstimator(parse_noise("0,0,0,0")).estimate_from_truth(obs, T, ()).T_C_O
    np.testing.assert_allclose(zero, T, atol=1e-12)
    es, el = error_components(small, T), error_components(large, T)
    for k in ("ray_m", "lateral_m", "inplane_deg", "outplane_deg"):
        assert el[k] == pytest.approx(2 * es[k], rel=1e-6, abs=1e-9)
    other = (
        NoisyOracleEstimator(parse_noise("2.5,2.5,1,1"))
        .estimate_from_truth(Observation(obs.rgb, obs.K, obs.T_world_cam, "phone", 1235), T, ())
        .T_C_O
    )
    assert not np.allclose(other, small)


def test_spread_noise_draws_each_sigma_on_its_own() -> None:
    n = parse_noise("spread:40,40,16,16")
    assert n.mode == "spread" and n.ray == pytest.approx(0.04)
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 0.8]
    errs = []
    for seed in range(400):
        obs = Observation(np.zeros((4, 4, 3), np.uint8), np.eye(3), np.eye(4), "phone", seed)
        e = error_components(NoisyOracleEstimator(n).estimate_from_truth(obs, T, ()).T_C_O, T)
        errs.append([e["ray_m"] * 1000, e["lateral_m"] * 1000, e["inplane_deg"], e["outplane_deg"]])
    E = np.array(errs)
    assert E[:, 0].max() < 5 * 40 and E[:, 2].max() < 5 * 16
    # The components are drawn independently: no correlation between them.
    assert abs(np.corrcoef(E[:, 0], E[:, 2])[0, 1]) < 0.2
    assert abs(np.corrcoef(E[:, 0], E[:, 1])[0, 1]) < 0.2


def test_a_draw_is_an_independent_set_of_errors_for_the_same_scenes() -> None:
    base = parse_noise("5,5,2,2")
    assert base.draw == 0 and parse_noise("5,5,2,2@0") == base
    other = parse_noise("5,5,2,2@3")
    assert other.draw == 3
    a = base.rng(1_000_000_000).normal(size=4)
    np.testing.assert_array_equal(a, base.rng(1_000_000_000).normal(size=4))  # reproducible
    assert not np.allclose(a, other.rng(1_000_000_000).normal(size=4))
    # Draw 0 is the stream every earlier report used.
    np.testing.assert_array_equal(a, np.random.default_rng([1_000_000_000, 7919]).normal(size=4))
    for bad in ("5,5,2,2@", "5,5,2,2@-1", "5,5,2,2@x", "5,5,2,2@99999999999"):
        with pytest.raises(InvalidArgumentError, match=r"draw in 0\.\."):
            parse_noise(bad)
