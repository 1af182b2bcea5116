"""A missing generalized force at one place, estimated from a model's residual, with its evidence.

The residual r (channel, time) of the model the search starts from is taken as the response to an unknown force
history at the place plus the measurement's noise: r = G c + e, where the columns of the sensitivity
G are the channels' responses to unit basis pulses of force at the place, c the force at the pulses'
centres, and e ~ N(0, σ_c²) independent.  With a Normal prior c ~ N(0, s² I) this is Bayesian linear
regression: the posterior of c and the evidence p(r | place, s) are closed-form, from one eigen-
decomposition of the whitened sensitivity's Gram matrix; they need of r and G only GᵀG, Gᵀr and rᵀr
(:class:`Moments`), so a sensitivity made of shifts of one response is never formed.  The prior scale s is marginalized over a
log-uniform prior on [s_low, s_high] (quadrature on a logarithmic grid), so places are compared by
their evidence, Occam factor included, and against the evidence of no missing force at all.

The noise is white here; where it is not, whiten r and G first.
"""

from __future__ import annotations

import functools
import math
import operator
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np
from scipy.integrate import trapezoid
from scipy.special import logsumexp

SCALE_POINTS = 61  # quadrature points of the prior scale's log-uniform prior
LOG_2PI = math.log(2.0 * math.pi)


def _whitened(residual: np.ndarray, sigma: np.ndarray, sensitivity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(r/σ flattened over channel and time, G/σ with matching rows) with shape checks."""
    residual, sigma, sensitivity = (np.asarray(a, dtype=float) for a in (residual, sigma, sensitivity))
    if residual.ndim != 2:
        raise ValueError(f"residual must be (n_channels, n_samples), got shape {residual.shape}")
    if sigma.shape != (residual.shape[0],) or not np.all(np.isfinite(sigma) & (sigma > 0)):
        raise ValueError(f"sigma must be {residual.shape[0]} positive finite values, got {sigma!r}")
    if sensitivity.ndim != 3 or sensitivity.shape[:2] != residual.shape:
        raise ValueError(f"sensitivity must be ({residual.shape[0]}, {residual.shape[1]}, n_basis), got shape {sensitivity.shape}")
    return (residual / sigma[:, None]).ravel(), (sensitivity / sigma[:, None, None]).reshape(residual.size, -1)


def log_evidence_without_force(residual: np.ndarray, sigma: np.ndarray) -> float:
    """log p(r | no missing force): the residual is the noise alone."""
    r = np.asarray(residual, dtype=float) / np.asarray(sigma, dtype=float)[:, None]
    return _log_evidence_of_noise(float(np.sum(r**2)), r.size, _log_sigma(residual, sigma))


def _log_evidence_of_noise(squares: float, size: int, log_sigma: float) -> float:
    """log N(r; 0, σ²I) from Σ(r/σ)², the number of data and Σ log σ over them."""
    return -0.5 * (squares + size * LOG_2PI) - log_sigma


@dataclass(frozen=True)
class Nuisance:
    """Errors of known prior beside the force: r = G c + B b + e, b ~ N(0, I) per channel (the instruments' offset,
    gain and delay, :func:`newdyn.sensors.linearized`), e ~ N(0, σ² I).  Integrating b out gives each channel the
    covariance σ² (I + B Bᵀ/σ²); :meth:`whiten` takes it back to σ² I (x − U diag(d) Uᵀ x, with U, S the left
    singular vectors and values of B and d = 1 − (1 + S²/σ²)^−½), so that the regression above holds for the whitened
    r and G as it stands.  Every evidence of whitened data lacks the same −½ Σ log(1 + S²/σ²), which cancels in every
    Bayes factor.  A prior much wider than what the data say of b projects B's span out of r and G alike."""

    basis: np.ndarray  # (channel, time, k) U
    shrink: np.ndarray  # (channel, k) d

    @classmethod
    def of(cls, design: np.ndarray, sigma: np.ndarray) -> Nuisance:
        """From the design B (channel, time, k), the prior's scales folded in, and the noise σ per channel."""
        basis, singular, _ = np.linalg.svd(np.asarray(design, dtype=float), full_matrices=False)
        return cls(basis, 1.0 - 1.0 / np.sqrt(1.0 + (singular / np.asarray(sigma, dtype=float)[:, None]) ** 2))

    def whiten(self, x: np.ndarray) -> np.ndarray:
        """``x`` (channel, time) or (channel, time, column) with the errors' covariance taken out."""
        x = np.asarray(x, dtype=float)
        columns = x if x.ndim == 3 else x[..., None]
        whitened = columns - self.basis @ (self.shrink[..., None] * (np.swapaxes(self.basis, 1, 2) @ columns))
        return whitened if x.ndim == 3 else whitened[..., 0]

    def whitened_products(self, gram: np.ndarray, projection: np.ndarray, crossed: np.ndarray,
                          residual: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each channel's GᵀG and Gᵀr of the whitened columns LG and a whitened ``residual`` r (channel, time) from
        products of the columns G as they are, never formed: ``gram`` GᵀG (channel, column, column), ``projection`` Gᵀr
        (channel, column) and ``crossed`` GᵀU (channel, column, k).  (LG)ᵀLG = GᵀG − GᵀU diag(2d − d²) UᵀG and
        (LG)ᵀr = Gᵀr − GᵀU diag(d) Uᵀr."""
        along = np.einsum("ctk,ct->ck", self.basis, residual)
        return (gram - (crossed * (2.0 * self.shrink - self.shrink**2)[:, None, :]) @ np.swapaxes(crossed, 1, 2),
                projection - np.einsum("cjk,ck->cj", crossed, self.shrink * along))


@dataclass(frozen=True)
class Moments:
    """What the regression needs of r and G, summed over the channels (and records) with each channel's σ divided out:
    GᵀG, Gᵀr and rᵀr; and the number of data and Σ log σ over them."""

    gram: np.ndarray
    projection: np.ndarray
    squares: float
    size: int
    log_sigma: float

    @classmethod
    def of(cls, residual: np.ndarray, sigma: np.ndarray, sensitivity: np.ndarray) -> Moments:
        """From ``residual`` (channel, time), noise σ per channel and the columns of ``sensitivity`` (channel, time, column)."""
        r, g = _whitened(residual, sigma, sensitivity)
        responding = g[np.any(g != 0.0, axis=1)]  # rows of channels the force moves at all
        return cls(responding.T @ responding, g.T @ r, float(r @ r), r.size, _log_sigma(residual, sigma))

    @classmethod
    def of_channels(cls, gram: np.ndarray, projection: np.ndarray, residual: np.ndarray, sigma: np.ndarray) -> Moments:
        """From each channel's GᵀG (channel, column, column) and Gᵀr (channel, column), ``residual`` (channel, time) and σ."""
        residual, sigma = np.asarray(residual, dtype=float), np.asarray(sigma, dtype=float)
        weights = sigma**-2.0
        return cls(np.tensordot(weights, gram, axes=1), weights @ projection, float(weights @ np.sum(residual**2, axis=1)),
                   residual.size, _log_sigma(residual, sigma))

    def __add__(self, other: Moments) -> Moments:
        return Moments(self.gram + other.gram, self.projection + other.projection, self.squares + other.squares,
                       self.size + other.size, self.log_sigma + other.log_sigma)

    @property
    def log_evidence_without(self) -> float:
        """log p(r | no missing force): r is the noise alone."""
        return _log_evidence_of_noise(self.squares, self.size, self.log_sigma)


def _log_sigma(residual: np.ndarray, sigma: np.ndarray) -> float:
    return np.shape(residual)[1] * float(np.sum(np.log(sigma)))


@dataclass(frozen=True)
class Regression:
    """The posterior of coefficients c in r = G c + e, c ~ N(0, s² I), s log-uniform, and the evidence."""

    mean: np.ndarray
    sd: np.ndarray
    scale: float  # the prior scale s of highest posterior weight
    log_evidence: float  # log p(r | G), s marginalized; in the residual's units
    log_bayes_factor: float  # against r being the noise alone
    chi2_before: float  # reduced χ² of the residual
    chi2_after: float  # reduced χ² of the residual less G times the posterior mean


def regress_records(residuals: Sequence[np.ndarray], sigmas: Sequence[np.ndarray], sensitivities: Sequence[np.ndarray],
                    scale_range: tuple[float, float]) -> Regression:
    """Bayesian linear regression of each record's ``residual`` (channel, time), noise σ per channel, on the columns of
    its ``sensitivity`` (channel, time, column), the prior scale's log-uniform range ``scale_range``.  Several records
    (recordings of one machine, each its own channels, noise and length) share one coefficient vector, each record's
    ``sensitivity`` giving every column (zero where a column is another record's own)."""
    return regress_moments(functools.reduce(operator.add, map(Moments.of, residuals, sigmas, sensitivities)), scale_range)


def regress_moments(moments: Moments, scale_range: tuple[float, float]) -> Regression:
    """:func:`regress_records` from the data's :class:`Moments`."""
    s_low, s_high = (float(x) for x in scale_range)
    if not 0.0 < s_low < s_high:
        raise ValueError(f"scale_range must be 0 < low < high, got {scale_range!r}")
    # Eigenvectors V and eigenvalues S² of GᵀG (G's right singular vectors and squared singular values), and
    # w = Vᵀ Gᵀ r: the regression in V's coordinates, without dividing by the small singular values.
    squared, v = np.linalg.eigh(moments.gram)
    squared = np.maximum(squared, 0.0)
    w = v.T @ moments.projection
    log_scales = np.linspace(math.log(s_low), math.log(s_high), SCALE_POINTS)
    variance = np.exp(2.0 * log_scales)[:, None]  # s² (scale, 1)
    spread = 1.0 + variance * squared  # eigenvalues of the whitened residual's covariance along U
    log_z = -0.5 * (np.sum(np.log(spread) - variance * w**2 / spread, axis=1) + moments.squares + moments.size * LOG_2PI)
    log_z -= moments.log_sigma  # back to the residuals' units
    # Log-uniform prior on s: density 1/(log s_high − log s_low) in log s, integrated by the trapezoidal rule.
    log_weights = np.log(trapezoid(np.eye(SCALE_POINTS), log_scales, axis=1) / (log_scales[-1] - log_scales[0]))
    log_evidence = float(logsumexp(log_z + log_weights))
    posterior_weights = np.exp(log_z + log_weights - log_evidence)  # p(s | r) at the quadrature points
    means = (variance * w / spread) @ v.T  # (scale, basis)
    variances = (variance / spread) @ (v.T) ** 2  # diagonal of V diag(s²/(1 + s² S²)) Vᵀ
    mean = posterior_weights @ means
    sd = np.sqrt(np.maximum(posterior_weights @ (variances + means**2) - mean**2, 0.0))
    remaining = moments.squares - 2.0 * mean @ moments.projection + mean @ moments.gram @ mean  # |r − G·mean|²
    return Regression(
        mean=mean, sd=sd, scale=float(np.exp(log_scales[np.argmax(posterior_weights)])), log_evidence=log_evidence,
        log_bayes_factor=log_evidence - moments.log_evidence_without,
        chi2_before=moments.squares / moments.size, chi2_after=float(remaining / moments.size),
    )


@dataclass(frozen=True)
class ForceEstimate(Regression):
    """The missing force at a place: the regression on pulses, its coefficients the force at their centres
    (N·m on a torsional place, N on a lateral one)."""

    place: str
    times: np.ndarray  # the basis pulses' centres [s]


def estimate(place: str, moments: Moments, times: np.ndarray, scale_range: tuple[float, float]) -> ForceEstimate:
    """The force at ``place`` behind a residual, from the :class:`Moments` of it and of the channels' responses to unit
    pulses of force at the place centred at ``times``; ``scale_range``: the range [s_low, s_high] of the log-uniform
    prior on the force's scale, in the force's units."""
    if np.shape(times) != np.shape(moments.projection):
        raise ValueError(f"times must give the centres of the {np.size(moments.projection)} basis pulses, got shape {np.shape(times)}")
    fit = regress_moments(moments, scale_range)
    return ForceEstimate(**{f.name: getattr(fit, f.name) for f in fields(fit)}, place=place, times=np.asarray(times, dtype=float))
