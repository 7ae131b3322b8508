"""P(grasp success | pose error): a kernel regression over the four error components.

After Hietanen et al. (Robotics and Autonomous Systems 143, 2021): the probability that a grasp
planned on an estimated pose succeeds, as a Nadaraya-Watson estimate over sampled executions,

    P(e) = (sum_i w_i(e) y_i + a g(e)) / (sum_i w_i(e) + a),
    w_i(e) = prod_d exp(-((e_d - x_id) / h_d)^2 / 2),
    g(e) = sigmoid(b_0 + sum_d b_d |e_d| / s_d),   b_d <= 0,

with x_i the error components of executed episodes (along the camera ray and across it [mm],
in-plane and out-of-plane rotation [deg], `perception.metrics.error_components`), y_i their
success (0/1), h_d one bandwidth per component chosen by leave-one-out likelihood, and a small
pseudo-count `a` pulling toward g where there is little data. g is a logistic regression on the
error magnitudes fitted to the same episodes by maximum likelihood, constrained to fall as any
error grows: beyond the sampled errors the estimate keeps falling with the error, where a
constant prior (the sample's overall rate) would return to that rate and overpredict success.
Models are fitted per object and scene tier by ``python -m sim.fit_success`` and stored as JSON.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from posegrasp.core.errors import AssetError, InvalidArgumentError

#: Error components, in the units the model works in.
COMPONENTS: tuple[str, ...] = ("ray_mm", "lateral_mm", "inplane_deg", "outplane_deg")
#: Weight of the overall rate where data is sparse (in units of one episode).
PRIOR_WEIGHT = 0.5
#: Candidate bandwidths per component, in its unit.
BANDWIDTHS = (0.5, 1.0, 2.0, 3.0, 5.0, 8.0, 12.0, 20.0, 40.0)
#: Scales s_d of the prior's inputs |e_d| / s_d [mm, mm, deg, deg].
PRIOR_SCALE = np.array([10.0, 10.0, 5.0, 5.0])
#: Ridge penalty on the prior's coefficients (keeps it finite on separable samples).
PRIOR_RIDGE = 1e-2


def _prior_features(E: np.ndarray) -> np.ndarray:
    return np.column_stack([np.ones(len(E)), np.abs(E) / PRIOR_SCALE])


def fit_prior(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Coefficients (b_0, b_1..b_4) of the monotone logistic prior g by penalised maximum
    likelihood, with b_1..b_4 <= 0 (success cannot rise as an error grows)."""
    from scipy.optimize import minimize

    F = _prior_features(X)

    def loss(b: np.ndarray) -> tuple[float, np.ndarray]:
        z = F @ b
        nll = np.sum(np.logaddexp(0.0, z) - y * z) / len(y) + PRIOR_RIDGE * np.sum(b * b)
        grad = F.T @ (1.0 / (1.0 + np.exp(-z)) - y) / len(y) + 2 * PRIOR_RIDGE * b
        return float(nll), grad

    bounds = [(None, None)] + [(None, 0.0)] * (F.shape[1] - 1)
    res = minimize(loss, np.zeros(F.shape[1]), jac=True, method="L-BFGS-B", bounds=bounds)
    return np.asarray(res.x, float)


def prior_at(coef: np.ndarray, E: np.ndarray) -> np.ndarray:
    """g at error components E (M, 4): the prior's success probability (M,)."""
    return 1.0 / (1.0 + np.exp(-(_prior_features(E) @ coef)))


def components_of(errors: dict[str, float]) -> np.ndarray:
    """The model's input (4,) from `perception.metrics.error_components` (metres, degrees)."""
    return np.array(
        [
            errors["ray_m"] * 1000.0,
            errors["lateral_m"] * 1000.0,
            errors["inplane_deg"],
            errors["outplane_deg"],
        ]
    )


@dataclass
class SuccessModel:
    """A fitted Nadaraya-Watson model.

    Attributes:
        X: error components of the sampled episodes, (N, 4) in `COMPONENTS` units.
        y: their success, (N,) in {0, 1}.
        bandwidth: h per component, (4,).
        log_likelihood: leave-one-out log-likelihood per episode at `bandwidth`.
        prior: coefficients of the monotone prior g (5,) (`fit_prior`); None: the overall rate
            (models fitted before the prior existed).
    """

    X: np.ndarray
    y: np.ndarray
    bandwidth: np.ndarray
    log_likelihood: float = float("nan")
    prior: np.ndarray | None = None

    @property
    def rate(self) -> float:
        """The overall success rate of the sample."""
        return float(self.y.mean())

    def _weights(self, E: np.ndarray, h: np.ndarray) -> np.ndarray:
        d = (E[:, None, :] - self.X[None, :, :]) / h
        return np.exp(-0.5 * np.sum(d * d, axis=-1))

    def prior_values(self, E: np.ndarray) -> np.ndarray:
        """The prior g at error components E (M, 4), (M,)."""
        if self.prior is None:
            return np.full(len(E), self.rate)
        return prior_at(self.prior, E)

    def predict(self, E: np.ndarray) -> np.ndarray:
        """P(success) at error components E, (M, 4) or (4,); returns (M,) or a scalar array."""
        E = np.asarray(E, float)
        single = E.ndim == 1
        E = np.atleast_2d(E)
        if E.shape[1] != len(COMPONENTS) or not np.all(np.isfinite(E)):
            raise InvalidArgumentError(f"error components must be finite (M, 4), got {E.shape}")
        w = self._weights(E, self.bandwidth)
        g = self.prior_values(E)
        p = (w @ self.y + PRIOR_WEIGHT * g) / (w.sum(axis=1) + PRIOR_WEIGHT)
        return p[0] if single else p

    @staticmethod
    def loo_log_likelihood(
        X: np.ndarray, y: np.ndarray, h: np.ndarray, prior: np.ndarray | None = None
    ) -> float:
        """Mean leave-one-out log-likelihood of the outcomes y at bandwidths h; `prior` is g at
        each X (N,) (None: the overall rate; g itself is fitted on all N, a 5-parameter leak)."""
        d = (X[:, None, :] - X[None, :, :]) / h
        w = np.exp(-0.5 * np.sum(d * d, axis=-1))
        np.fill_diagonal(w, 0.0)
        g = np.full(len(y), y.mean()) if prior is None else prior
        p = (w @ y + PRIOR_WEIGHT * g) / (w.sum(axis=1) + PRIOR_WEIGHT)
        p = np.clip(p, 1e-6, 1 - 1e-6)
        return float(np.mean(y * np.log(p) + (1 - y) * np.log(1 - p)))

    @classmethod
    def fit(cls, X: np.ndarray, y: np.ndarray, sweeps: int = 3) -> SuccessModel:
        """The prior g (`fit_prior`), then bandwidths by leave-one-out likelihood, one component
        at a time over `BANDWIDTHS` (coordinate ascent, `sweeps` passes).

        Raises:
            InvalidArgumentError: fewer than 5 episodes, or shapes that do not match.
        """
        X, y = np.asarray(X, float), np.asarray(y, float)
        if X.ndim != 2 or X.shape[1] != len(COMPONENTS) or len(y) != len(X) or len(y) < 5:
            raise InvalidArgumentError(
                f"need at least 5 episodes of (4,) error components, got {X.shape} and {y.shape}"
            )
        coef = fit_prior(X, y)
        g = prior_at(coef, X)
        h = np.full(len(COMPONENTS), 5.0)
        best = cls.loo_log_likelihood(X, y, h, g)
        for _ in range(sweeps):
            for d in range(len(COMPONENTS)):
                for cand in BANDWIDTHS:
                    trial = h.copy()
                    trial[d] = cand
                    ll = cls.loo_log_likelihood(X, y, trial, g)
                    if ll > best + 1e-12:
                        best, h = ll, trial
        return cls(X, y, h, best, coef)

    def to_json(self) -> dict:
        """A JSON-serialisable dict."""
        return {
            "components": list(COMPONENTS),
            "bandwidth": self.bandwidth.tolist(),
            "log_likelihood": self.log_likelihood,
            "X": np.round(self.X, 4).tolist(),
            "y": self.y.astype(int).tolist(),
        } | ({} if self.prior is None else {"prior": self.prior.tolist()})

    @classmethod
    def from_json(cls, d: dict) -> SuccessModel:
        """The model of `to_json`."""
        if d.get("components") != list(COMPONENTS):
            raise AssetError(f"a success model over {COMPONENTS} was expected")
        return cls(
            np.asarray(d["X"], float),
            np.asarray(d["y"], float),
            np.asarray(d["bandwidth"], float),
            float(d["log_likelihood"]),
            None if d.get("prior") is None else np.asarray(d["prior"], float),
        )


def load_models(path: Path) -> dict[str, SuccessModel]:
    """Models by ``"<object>/<tier>"`` from a file of ``python -m sim.fit_success``.

    Raises:
        AssetError: missing or malformed file (with the command that writes it).
    """
    try:
        raw = json.loads(Path(path).read_text())
        return {k: SuccessModel.from_json(v) for k, v in raw["models"].items()}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise AssetError(
            f"cannot read success models from {path} ({exc}); write them with "
            "`python -m sim.fit_success`"
        ) from None
