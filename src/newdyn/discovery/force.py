"""A missing generalized force at one place, estimated from a model's residual, with its evidence.

The residual r (channel, time) of the model the search starts from is taken as the response to an unknown force
history at the place plus the measurement's noise: r = G c + e, where the columns of the sensitivity
G are the channels' responses to unit basis pulses of force at the place, c the force at the pulses'
centres, and e ~ N(0, σ_c²) independent.  With a Normal prior c ~ N(0, s² I) this is Bayesian linear
regression: the posterior of c and the evidence p(r | place, s) are closed-form, from one eigen-
decomposition of the whitened sensitivity's Gram matrix.  The prior scale s is marginalized over a
log-uniform prior on [s_low, s_high] (quadrature on a logarithmic grid), so places are compared by
their evidence, Occam factor included, and against the evidence of no missing force at all.

The noise is white here; where it is not, whiten r and G first.
"""

from __future__ import annotations

import math
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
    return float(-0.5 * (np.sum(r**2) + r.size * LOG_2PI) - r.shape[1] * np.sum(np.log(sigma)))


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
        whitened = columns - self.basis @ (self.shrink[..., None] * self._along(columns))
        return whitened if x.ndim == 3 else whitened[..., 0]

    def whiten_gram(self, columns: np.ndarray, gram: np.ndarray) -> np.ndarray:
        """The Gram matrices (channel, column, column) of :meth:`whiten`'s ``columns`` from those of the columns as they
        are: (LG)ᵀLG = GᵀG − (UᵀG)ᵀ diag(2d − d²) UᵀG."""
        along = self._along(np.asarray(columns, dtype=float))
        return gram - np.swapaxes(along, 1, 2) @ ((2.0 * self.shrink - self.shrink**2)[..., None] * along)

    def _along(self, columns: np.ndarray) -> np.ndarray:
        return np.swapaxes(self.basis, 1, 2) @ columns


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


def regress(residual: np.ndarray, sigma: np.ndarray, sensitivity: np.ndarray, scale_range: tuple[float, float],
            gram: np.ndarray | None = None) -> Regression:
    """Bayesian linear regression of ``residual`` (channel, time), noise σ per channel, on the columns of
    ``sensitivity`` (channel, time, column), the prior scale's log-uniform range ``scale_range``; ``gram``: each
    channel's sensitivityᵀsensitivity (channel, column, column) where it is known at less cost than from the columns."""
    return regress_records([residual], [sigma], [sensitivity], scale_range, None if gram is None else [gram])


def regress_records(residuals: Sequence[np.ndarray], sigmas: Sequence[np.ndarray], sensitivities: Sequence[np.ndarray],
                    scale_range: tuple[float, float], grams: Sequence[np.ndarray] | None = None) -> Regression:
    """:func:`regress` on several records at once (recordings of one machine, each its own channels, noise and length):
    one coefficient vector for all, each record's ``sensitivity`` giving every column (zero where a column is
    another record's own)."""
    whitened = [_whitened(*record) for record in zip(residuals, sigmas, sensitivities)]
    r, g = np.concatenate([w[0] for w in whitened]), np.concatenate([w[1] for w in whitened])
    s_low, s_high = (float(x) for x in scale_range)
    if not 0.0 < s_low < s_high:
        raise ValueError(f"scale_range must be 0 < low < high, got {scale_range!r}")
    if grams is None:
        responding = g[np.any(g != 0.0, axis=1)]  # rows of channels the force moves at all
        gram = responding.T @ responding
    else:
        gram = sum(np.tensordot(np.asarray(sigma, dtype=float) ** -2, each, axes=1) for sigma, each in zip(sigmas, grams))
    # Eigenvectors V and eigenvalues S² of GᵀG (G's right singular vectors and squared singular values), and
    # w = Vᵀ Gᵀ r: the regression in V's coordinates, without dividing by the small singular values.
    squared, v = np.linalg.eigh(gram)
    squared = np.maximum(squared, 0.0)
    w = v.T @ (g.T @ r)
    log_scales = np.linspace(math.log(s_low), math.log(s_high), SCALE_POINTS)
    variance = np.exp(2.0 * log_scales)[:, None]  # s² (scale, 1)
    spread = 1.0 + variance * squared  # eigenvalues of the whitened residual's covariance along U
    log_z = -0.5 * (np.sum(np.log(spread) - variance * w**2 / spread, axis=1) + r @ r + r.size * LOG_2PI)
    # back to the residuals' units
    log_z -= sum(residual.shape[1] * float(np.sum(np.log(sigma))) for residual, sigma in zip(residuals, sigmas))
    # Log-uniform prior on s: density 1/(log s_high − log s_low) in log s, integrated by the trapezoidal rule.
    log_weights = np.log(trapezoid(np.eye(SCALE_POINTS), log_scales, axis=1) / (log_scales[-1] - log_scales[0]))
    log_evidence = float(logsumexp(log_z + log_weights))
    posterior_weights = np.exp(log_z + log_weights - log_evidence)  # p(s | r) at the quadrature points
    means = (variance * w / spread) @ v.T  # (scale, basis)
    variances = (variance / spread) @ (v.T) ** 2  # diagonal of V diag(s²/(1 + s² S²)) Vᵀ
    mean = posterior_weights @ means
    sd = np.sqrt(np.maximum(posterior_weights @ (variances + means**2) - mean**2, 0.0))
    remaining = r - g @ mean
    return Regression(
        mean=mean, sd=sd, scale=float(np.exp(log_scales[np.argmax(posterior_weights)])), log_evidence=log_evidence,
        log_bayes_factor=log_evidence - sum(log_evidence_without_force(*record) for record in zip(residuals, sigmas)),
        chi2_before=float(r @ r / r.size), chi2_after=float(remaining @ remaining / r.size),
    )


@dataclass(frozen=True)
class ForceEstimate(Regression):
    """The missing force at a place: the regression on pulses, its coefficients the force at their centres
    (N·m on a torsional place, N on a lateral one)."""

    place: str
    times: np.ndarray  # the basis pulses' centres [s]


def estimate(
    place: str,
    residual: np.ndarray,
    sigma: np.ndarray,
    sensitivity: np.ndarray,
    times: np.ndarray,
    scale_range: tuple[float, float],
    gram: np.ndarray | None = None,
) -> ForceEstimate:
    """The force at ``place`` behind ``residual`` (channel, time), with noise σ per channel.

    ``sensitivity`` (channel, time, basis): each channel's response to a unit pulse of force at the
    place centred at ``times[j]``; ``scale_range``: the range [s_low, s_high] of the log-uniform prior on
    the force's scale, in the force's units; ``gram`` as :func:`regress` takes it.
    """
    if np.shape(times) != (np.shape(sensitivity)[-1],):
        raise ValueError(f"times must give the centres of the {np.shape(sensitivity)[-1]} basis pulses, got shape {np.shape(times)}")
    fit = regress(residual, sigma, sensitivity, scale_range, gram)
    return ForceEstimate(**{f.name: getattr(fit, f.name) for f in fields(fit)}, place=place, times=np.asarray(times, dtype=float))
