"""The calibrated verification model: a logistic regression from a pose's size-free
:class:`~vgpnav_env.perception.verify.verdict.Evidence` to the probability that the pose is right
(within 5 cm / 5 deg of the truth).

Its coefficients are package data (``perception/data/verify_model.json``), fitted on the tuning
scenes' logged frames by ``benchmarks/verification/fit.py`` (:func:`fit_model`); without that file
no probability is given (nan) and the rules decide.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from functools import cache
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize
from scipy.special import expit

if TYPE_CHECKING:
    from vgpnav_env.perception.verify.verdict import Evidence

#: The evidence the model reads: shares and ratios of match counts, independent of the image size
#: and the feature budget, whether the pose lies inside a state estimate's prior, and the mount's
#: roll (a wrong pose is seldom level; the mount rule still rejects a roll past ``max_roll_deg``).
FEATURES: tuple[str, ...] = (
    "match_share",
    "explained_share",
    "agree_share",
    "rival_margin",
    "off_plane_share",
    "confident_rival",
    "placed",
    "abs_roll_deg",
)
#: The package data file of the fitted model.
MODEL_FILE = "verify_model.json"


@dataclass(frozen=True)
class VerificationModel:
    """``P(right | evidence) = expit(intercept + coef . (x - mean) / scale)`` over ``features``
    (field or property names of :class:`Evidence`); ``meta``: how it was fitted (data, sizes,
    regularisation)."""

    features: tuple[str, ...]
    mean: tuple[float, ...]
    scale: tuple[float, ...]
    coef: tuple[float, ...]
    intercept: float
    meta: dict[str, Any]

    def __post_init__(self) -> None:
        n = len(self.features)
        if not (len(self.mean) == len(self.scale) == len(self.coef) == n):
            raise ValueError(f"model arrays must have one entry per feature ({n})")
        if not all(s > 0 for s in self.scale):
            raise ValueError("model feature scales must be positive")

    def probability(self, evidence: Evidence) -> float:
        """The probability in (0, 1) that the pose of ``evidence`` is right."""
        x = np.array([float(getattr(evidence, f)) for f in self.features])
        return float(self.probabilities(x[None])[0])

    def probabilities(self, X: NDArray[np.float64]) -> NDArray[np.float64]:
        """(n,) probabilities of the feature rows ``X`` (n, len(features))."""
        z = (np.asarray(X, float) - np.array(self.mean)) / np.array(self.scale)
        return expit(self.intercept + z @ np.array(self.coef))

    def save(self, path: Path) -> None:
        Path(path).write_text(json.dumps(asdict(self), indent=1) + "\n")

    @classmethod
    def load(cls, path: Path) -> VerificationModel:
        data = json.loads(Path(path).read_text())
        return cls(
            tuple(data["features"]),
            tuple(data["mean"]),
            tuple(data["scale"]),
            tuple(data["coef"]),
            float(data["intercept"]),
            dict(data.get("meta", {})),
        )


@cache
def default_model() -> VerificationModel | None:
    """The installed model (package data), None when none is installed."""
    source = resources.files("vgpnav_env.perception").joinpath("data", MODEL_FILE)
    if not source.is_file():
        return None
    with resources.as_file(source) as path:
        return VerificationModel.load(path)


def fit_model(
    X: NDArray[np.float64],
    y: NDArray[np.bool_],
    features: tuple[str, ...] = FEATURES,
    *,
    l2: float = 1.0,
    meta: dict[str, Any] | None = None,
) -> VerificationModel:
    """The logistic regression of the labels ``y`` (n,) (pose right) on the feature rows ``X``
    (n, len(features)), standardised, with an L2 penalty ``l2`` on the coefficients (not the
    intercept); deterministic (L-BFGS from zero)."""
    X, y = np.asarray(X, float), np.asarray(y, float)
    if X.ndim != 2 or X.shape != (len(y), len(features)) or len(y) < 2:
        raise ValueError(f"need X (n, {len(features)}) and y (n,), n >= 2; got {X.shape}, {y.shape}")
    if y.min() == y.max():
        raise ValueError("the labels must contain right and wrong poses")
    mean, scale = X.mean(0), X.std(0)
    scale = np.where(scale > 1e-9, scale, 1.0)
    Z = (X - mean) / scale

    def loss(w: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        z = w[0] + Z @ w[1:]
        nll = float(np.sum(np.logaddexp(0.0, z) - y * z)) + 0.5 * l2 * float(w[1:] @ w[1:])
        r = expit(z) - y
        return nll, np.r_[r.sum(), Z.T @ r + l2 * w[1:]]

    fit = minimize(loss, np.zeros(len(features) + 1), jac=True, method="L-BFGS-B", options={"gtol": 1e-10})
    w = fit.x
    return VerificationModel(
        tuple(features),
        tuple(float(v) for v in mean),
        tuple(float(v) for v in scale),
        tuple(float(v) for v in w[1:]),
        float(w[0]),
        dict(meta or {}) | {"n": len(y), "n_right": int(y.sum()), "l2": l2},
    )
