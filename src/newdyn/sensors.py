"""Instrument nuisances of a channel, marginalized in closed form: an offset, a gain error and a delay.

A channel reads y(t) = o + g·m(t − τ) + e(t): the model's output m through an instrument whose offset o,
gain g and delay τ are known only to a datasheet's accuracy, o ~ N(0, s_o²), g ~ N(1, s_g²), τ ~ N(0, s_τ²),
and white noise e ~ N(0, σ²).  Offset and gain enter linearly; the delay does near any τ̂,
m(t − τ) ≈ m(t − τ̂) − (τ − τ̂) ṁ(t − τ̂), so with the residual r = y − m(t − τ̂) − τ̂ ṁ(t − τ̂) and the
design B = [s_o·1, s_g·m(t − τ̂), −s_τ·ṁ(t − τ̂)] (the prior's scales folded in) r ~ N(0, σ² I + B Bᵀ), and

    rᵀ (σ² I + B Bᵀ)⁻¹ r = (‖r − B ĉ‖² + σ² ‖ĉ‖²) / σ²,   ĉ = (BᵀB + σ² I)⁻¹ Bᵀ r,
    log |σ² I + B Bᵀ| = n log σ² + log |I + BᵀB / σ²|,

ĉ being the posterior mean of (o/s_o, (g − 1)/s_g, τ/s_τ).  τ̂ comes from Gauss–Newton passes (the first at
τ̂ = 0), so the marginal over τ is Laplace's approximation at its mode, exact for offset and gain.  The first
line is a sum of squares, n + 3 of them per channel: what least squares minimizes.  A scale of zero fits
nothing (its column drops out); with all zero this is the plain Gaussian likelihood.  The delayed model is
cubic (four-point Lagrange) interpolation between samples, extrapolated at the record's two ends.

Coloured noise (:class:`newdyn.noise.Colour`, AR per channel) is whitened first: data and model pass through the
filter W, linear and time-invariant, so the same closed form holds for W y and W m with σ_e for σ, the offset's
column scaled by W's gain at zero frequency, and the likelihood is that of the samples after the filter's start.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace

import numpy as np
from numba import njit, prange
from scipy import stats

from . import noise

LOG_2PI = math.log(2.0 * math.pi)
DELAY_PASSES = 3  # Gauss–Newton passes for τ̂; the last one's linearization is the likelihood's
OUT_OF_SPEC = 100.0  # an instrument out of its spec: its error's prior this many times wider than its datasheet's


@dataclass(frozen=True)
class Sensor:
    """The prior spread of one channel's instrument errors: offset in the channel's unit, gain relative,
    delay in seconds."""

    offset_sd: float = 0.0
    gain_sd: float = 0.0
    delay_sd: float = 0.0

    def __post_init__(self):
        for name in QUANTITIES:
            value = getattr(self, f"{name}_sd")
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name}_sd must be a finite number >= 0, got {value!r}")


QUANTITIES = tuple(f.name.removesuffix("_sd") for f in fields(Sensor))  # a scale's columns, in this order
OFFSET, GAIN, DELAY = (QUANTITIES.index(q) for q in ("offset", "gain", "delay"))
NOMINAL = {"offset": 0.0, "gain": 1.0, "delay": 0.0}  # a perfect instrument


@dataclass(frozen=True, eq=False)
class Instruments:
    """The diagnosis channels' instrument priors at one sampling rate, what every likelihood integrates out, and
    the colour of their noise, which every likelihood whitens."""

    scale: np.ndarray  # (channel, quantity) prior sds: offset in the channel's unit, gain relative, delay in samples
    fs: float
    colour: noise.Colour | None = None  # None: white

    @classmethod
    def of(cls, sensors: Mapping[str, Sensor], channels: Sequence[str], fs: float,
           colour: noise.Colour | None = None) -> Instruments | None:
        """``channels``' instruments (one without a sensor is exact); None when all are exact and the noise white."""
        none = Sensor()
        scale = np.array([[getattr(sensors.get(c, none), f"{q}_sd") for q in QUANTITIES] for c in channels], dtype=float)
        scale[:, DELAY] *= fs
        colour = None if colour is None or colour.white else colour
        return cls(scale, float(fs), colour) if np.any(scale > 0) or colour is not None else None

    def widened(self, channel: int | slice, quantity: int, factor: float) -> Instruments:
        """The same instruments with ``channel``'s prior on ``quantity`` ``factor`` times wider."""
        scale = self.scale.copy()
        scale[channel, quantity] *= factor
        return replace(self, scale=scale)

    @property
    def exact(self) -> Instruments | None:
        """Exact instruments with the same noise colour; None when the noise is white."""
        return None if self.colour is None else replace(self, scale=np.zeros_like(self.scale))

    @property
    def presamples(self) -> int:
        """The samples at each channel's start that only start the whitening filter: the likelihood is the others' given them."""
        return 0 if self.colour is None else self.colour.order

    @property
    def sd(self) -> np.ndarray:
        """(channel, quantity) prior sds in the quantities' own units (the delay's in seconds)."""
        return self.scale / np.where(np.arange(len(QUANTITIES)) == DELAY, self.fs, 1.0)


@njit(cache=True, error_model="numpy", inline="always")
def _cubic(u):
    """Weights of four samples at offsets −1, 0, 1, 2 for the value and the slope of their cubic at offset u."""
    value = (-u * (u - 1) * (u - 2) / 6, (u + 1) * (u - 1) * (u - 2) / 2, -(u + 1) * u * (u - 2) / 2, (u + 1) * u * (u - 1) / 6)
    slope = (-(3 * u * u - 6 * u + 2) / 6, (3 * u * u - 4 * u - 1) / 2, -(3 * u * u - 2 * u - 2) / 2, (3 * u * u - 1) / 6)
    return value, slope


@njit(cache=True, error_model="numpy", inline="always")
def _cubic_of(a, b, c, d, weights):
    """(m, dm/dk) by ``weights`` (:func:`_cubic`) of four consecutive samples a, b, c, d."""
    (wa, wb, wc, wd), (sa, sb, sc, sd) = weights
    return wa * a + wb * b + wc * c + wd * d, sa * a + sb * b + sc * c + sd * d


@njit(cache=True, error_model="numpy", inline="always")
def _inner(signal, inside):
    """range(start, stop) of the k whose four samples k + inside − 1 .. k + inside + 2 lie in the record, and those
    samples as four views indexed by k − start.  They share one set of weights, so their loop has no branch and runs in
    SIMD lanes: an index that cannot be negative loads each lane's samples from consecutive memory, where k + inside − 1,
    which can (and wraps around), gathered them one at a time.  The few other k (the ends) take :func:`_delayed_at`'s
    extrapolation."""
    n = signal.size
    start = min(max(1 - inside, 0), n)
    stop = max(min(n - 2 - inside, n), start)
    first, count = start + inside - 1, stop - start  # first >= 0 whenever count > 0
    return start, stop, (signal[first:first + count], signal[first + 1:first + 1 + count], signal[first + 2:first + 2 + count],
                         signal[first + 3:first + 3 + count])


@njit(cache=True, error_model="numpy", inline="always")
def _delayed_at(signal, k, late, inside, weights):
    """(m, dm/dk) of ``signal`` at k − ``late``: the cubic through the four samples around it, or the four
    nearest an end of the record beyond it.  ``inside`` (the first of the four for k = 0) and ``weights``
    serve every k whose four samples lie in the record; the ends compute their own."""
    n = signal.size
    first = k + inside
    if first < 1 or first > n - 3:
        first = min(max(first, 1), n - 3)
        weights = _cubic(k - late - first)
    return _cubic_of(signal[first - 1], signal[first], signal[first + 1], signal[first + 2], weights)


@njit(cache=True, error_model="numpy", inline="always")
def _summed(sums, y, m, slope, late):
    """``sums`` (Σm, Σm², Σd, Σmd, Σd², Σr, Σmr, Σdr, Σr²) with one sample's d = −ṁ and r = y − m + late·d added."""
    s_m, s_mm, s_d, s_md, s_dd, s_r, s_mr, s_dr, s_rr = sums
    d = -slope
    r = y - m + late * d
    return s_m + m, s_mm + m * m, s_d + d, s_md + m * d, s_dd + d * d, s_r + r, s_mr + m * r, s_dr + d * r, s_rr + r * r


@njit(cache=True, error_model="numpy", inline="always")
def _channel_moments(data, signal, late):
    """:func:`_moments`' sums over time of one channel of one model delayed by ``late`` samples, the inner samples
    (:func:`_inner`) first; compiled into :func:`_moments`, whose fast-math lets the sums be reassociated so that they
    run in SIMD lanes, their rounding no worse than a sequential sum's."""
    n = signal.size
    inside = math.floor(-late)
    weights = _cubic(-late - inside)
    start, stop, (a, b, c, d) = _inner(signal, inside)
    inner_data = data[start:stop]
    sums = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for j in range(stop - start):
        m, slope = _cubic_of(a[j], b[j], c[j], d[j], weights)
        sums = _summed(sums, inner_data[j], m, slope, late)
    for i in range(n - (stop - start)):
        k = i if i < start else i + stop - start
        m, slope = _delayed_at(signal, k, late, inside, weights)
        sums = _summed(sums, data[k], m, slope, late)
    return sums


@njit(cache=True, error_model="numpy", nogil=True, fastmath={"reassoc", "contract"})
def _moments(data, model, shift):
    """Sums over time of each (model, channel)'s delayed design, unscaled, u = [1, m(k − shift), −ṁ(k − shift)],
    and of its residual r = y − m(k − shift) − shift·ṁ(k − shift): (Σ u uᵀ (B, C, 3, 3), Σ u r (B, C, 3), Σ r² (B, C)).
    One pass over the samples, nothing of length n kept; the (model, channel) pairs one after another, in one compiled
    function with the sums' loop in it.  Reassociated sums called from another compiled function (a parallel loop's,
    or a plain one's) came out of numba's cache different in the last bits from the same code compiled in the
    process, so that a new checkout's first run differed from its reruns; one function compiles to the same either
    way.  Threads run whole likelihoods side by side instead (:func:`newdyn.calibration.calibrate_many`, the fits)."""
    n_models, n_channels, n = model.shape
    gram = np.zeros((n_models, n_channels, 3, 3))
    projection = np.zeros((n_models, n_channels, 3))
    squares = np.zeros((n_models, n_channels))
    for bc in range(n_models * n_channels):
        b, c = bc // n_channels, bc % n_channels
        s_m, s_mm, s_d, s_md, s_dd, s_r, s_mr, s_dr, s_rr = _channel_moments(data[c], model[b, c], shift[b, c])
        g = gram[b, c]
        g[0, 0], g[0, 1], g[0, 2], g[1, 1], g[1, 2], g[2, 2] = n, s_m, s_d, s_mm, s_md, s_dd
        g[1, 0], g[2, 0], g[2, 1] = s_m, s_d, s_md
        projection[b, c, 0], projection[b, c, 1], projection[b, c, 2] = s_r, s_mr, s_dr
        squares[b, c] = s_rr
    return gram, projection, squares


@njit(cache=True, error_model="numpy", parallel=True, nogil=True)
def _left(data, model, shift, fitted):
    """r − Bĉ per sample (B, C, n), as :func:`_moments` linearizes: y − m(k − τ̂) − τ̂·ṁ(k − τ̂) − (o + (g − 1)·m(k − τ̂)
    − τ·ṁ(k − τ̂)), with ``fitted`` (B, C, 3) the posterior means (o, g − 1, τ) in the scale's units."""
    n_models, n_channels = model.shape[:2]
    left = np.empty(model.shape)
    for bc in prange(n_models * n_channels):
        b, c = bc // n_channels, bc % n_channels
        _channel_left(left[b, c], data[c], model[b, c], shift[b, c], fitted[b, c])
    return left


@njit(cache=True, error_model="numpy")
def _channel_left(out, data, signal, late, fitted):
    """:func:`_left` of one channel of one model delayed by ``late`` samples into ``out``, the inner samples first."""
    n = signal.size
    inside = math.floor(-late)
    weights = _cubic(-late - inside)
    offset, gain, shift = fitted[0], 1.0 + fitted[1], late - fitted[2]
    start, stop, (a, b, c, d) = _inner(signal, inside)
    inner_data, inner_out = data[start:stop], out[start:stop]
    for j in range(stop - start):
        m, slope = _cubic_of(a[j], b[j], c[j], d[j], weights)
        inner_out[j] = inner_data[j] - offset - gain * m - shift * slope
    for i in range(n - (stop - start)):
        k = i if i < start else i + stop - start
        m, slope = _delayed_at(signal, k, late, inside, weights)
        out[k] = data[k] - offset - gain * m - shift * slope


@dataclass(frozen=True)
class _Solution:
    """The closed form at the delay's mode for a batch of models (leading axes flattened to B)."""

    shift: np.ndarray  # (B, C) the delay the last pass linearized about, in samples
    c_hat: np.ndarray  # (B, C, 3) posterior means in prior sds
    gram: np.ndarray  # (B, C, 3, 3) I + BᵀB/σ²
    quadratic: np.ndarray  # (B, C) rᵀ(σ²I + BBᵀ)⁻¹r
    lead: tuple  # the batch's leading axes


def _solve(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, scale: np.ndarray) -> tuple[_Solution, np.ndarray, np.ndarray]:
    """Gauss–Newton passes on the delay (one when no channel has a delay prior), then the closed form; also the
    flattened model (B, C, n) and variance (B, C)."""
    n_channels, n = data.shape
    lead = np.broadcast_shapes(model.shape[:-2], sigma.shape[:-1])
    flat = np.ascontiguousarray(np.broadcast_to(model, lead + (n_channels, n))).reshape(-1, n_channels, n)
    variance = np.broadcast_to(sigma**2, lead + (n_channels,)).reshape(-1, n_channels)
    shift = np.zeros(flat.shape[:2])
    for remaining in reversed(range(DELAY_PASSES if np.any(scale[:, DELAY] > 0) else 1)):
        sums, projection, squares = _moments(data, flat, shift)
        design_gram = sums * scale[:, :, None] * scale[:, None, :]  # BᵀB, the prior's scales folded in
        design_projection = projection * scale  # Bᵀr
        gram = np.eye(3) + design_gram / variance[..., None, None]
        c_hat = np.linalg.solve(gram, (design_projection / variance[..., None])[..., None])[..., 0]
        if remaining:
            shift = scale[:, DELAY] * c_hat[..., DELAY]
    left = squares - 2 * np.einsum("...k,...k->...", c_hat, design_projection) + np.einsum("...k,...kl,...l->...", c_hat, design_gram, c_hat)
    quadratic = left / variance + np.einsum("...k,...k->...", c_hat, c_hat)
    return _Solution(shift, c_hat, gram, quadratic, lead), flat, variance


def _seen(data, model, sigma, instruments: Instruments):
    """(data, model, σ, prior scales) as the likelihood sees them: whitened by the noise's colour.  Whitening W is
    linear and time-invariant, so it commutes with the delay and the gain, and takes a constant offset o to
    o·(1 − Σa): the offset's column is scaled by that.  The data come back C-contiguous, as a fit's window of the record
    is not: the compiled sums then have one layout to be compiled for, not one more in the first fit of a clone."""
    data = np.ascontiguousarray(data)
    colour = instruments.colour
    if colour is None:
        return data, model, sigma, instruments.scale
    scale = instruments.scale.copy()
    scale[:, OFFSET] *= 1.0 - colour.ar.sum(axis=1)
    return colour.whiten(data), colour.whiten(model), sigma * colour.innovation, scale


def _solved(data, model, sigma, instruments: Instruments):
    """:func:`_solve` on what the likelihood sees, and that."""
    seen_data, seen_model, seen_sigma, scale = _seen(data, model, sigma, instruments)
    return (*_solve(seen_data, seen_model, seen_sigma, scale), seen_data, scale)


def standardized_residuals(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, instruments: Instruments) -> np.ndarray:
    """(..., C, n − presamples + 3) numbers whose squares sum to each channel's rᵀC⁻¹r: the misfit left in σ (whitened
    when the noise is coloured), then ĉ; what least squares minimizes."""
    solution, flat, variance, seen_data, scale = _solved(data, model, sigma, instruments)
    left = _left(seen_data, flat, solution.shift, scale * solution.c_hat)
    z = np.concatenate([left / np.sqrt(variance)[..., None], solution.c_hat], axis=-1)
    return z.reshape(solution.lead + z.shape[-2:])


def log_likelihood(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, instruments: Instruments, per_channel: bool = False) -> np.ndarray:
    """log p(y | m) with each channel's offset, gain and delay integrated over their priors; with coloured noise,
    of the samples after the first :attr:`Instruments.presamples` given those."""
    solution, _, variance, seen_data, _ = _solved(data, model, sigma, instruments)
    per = -0.5 * (solution.quadratic + np.linalg.slogdet(solution.gram)[1] + seen_data.shape[-1] * (np.log(variance) + LOG_2PI))
    per = per.reshape(solution.lead + data.shape[:1])
    return per if per_channel else per.sum(axis=-1)


def estimate(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, instruments: Instruments) -> dict[str, np.ndarray]:
    """Posterior mean and sd of each channel's offset [channel unit], gain [–] and delay [s] given ``model``
    (..., C, n): ``{quantity: (..., C), quantity_sd: (..., C)}``; a quantity without a prior stays nominal."""
    solution = _solved(data, model, sigma, instruments)[0]
    sd = np.sqrt(np.diagonal(np.linalg.inv(solution.gram), axis1=-2, axis2=-1))
    found = {}
    for i, quantity in enumerate(QUANTITIES):
        found[quantity] = (NOMINAL[quantity] + instruments.sd[:, i] * solution.c_hat[..., i]).reshape(solution.lead + data.shape[:1])
        found[f"{quantity}_sd"] = (instruments.sd[:, i] * sd[..., i]).reshape(solution.lead + data.shape[:1])
    return found


def summary(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, instruments: Instruments, channels: Sequence[str],
            hdi_prob: float) -> dict[str, dict[str, dict[str, float | list[float]]]]:
    """``{channel: {quantity: {mean, sd, hdi}}}`` of the quantities with a prior, given one ``model`` (C, n); the
    posterior is Normal, so its ``hdi_prob`` highest-density interval is the mean ± that many sds."""
    found, half = estimate(data, model, sigma, instruments), stats.norm.ppf(0.5 + hdi_prob / 2)
    return {c: {q: {"mean": float(found[q][i]), "sd": float(found[f"{q}_sd"][i]),
                    "hdi": [float(found[q][i] - half * found[f"{q}_sd"][i]), float(found[q][i] + half * found[f"{q}_sd"][i])]}
                for j, q in enumerate(QUANTITIES) if instruments.scale[i, j] > 0}
            for i, c in enumerate(channels) if np.any(instruments.scale[i] > 0)}


@dataclass(frozen=True)
class Check:
    """Which instrument errors lie outside their spec, given one model of the machine."""

    instruments: Instruments  # the priors, with those out of spec widened OUT_OF_SPEC times
    gain: float  # log p(y | m, instruments) − log p(y | m, datasheet priors)
    out_of_spec: tuple[tuple[int, int, float], ...]  # (channel, quantity, log Bayes factor of widening it, given those before)
    log_evidence_change: float  # gain less the prior odds, margin per instrument out of spec


def check(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, instruments: Instruments, margin: float) -> Check:
    """The instrument errors whose prior, widened :data:`OUT_OF_SPEC` times, raises the likelihood of ``model``
    (C, n) by more than ``margin``: with prior odds e^−margin that an instrument is out of its spec, those the
    data say more probably are.  Per channel, greedily: the quantity whose widening gains most, then the others
    given it (a speed sensor's gain error also moves its mean, which its offset alone would take in part).
    Channels are independent, so widening a quantity on every channel at once gives each channel's gain."""
    used, found = instruments, []
    current = log_likelihood(data, model, sigma, used, per_channel=True)
    while True:
        gains = np.stack([log_likelihood(data, model, sigma, used.widened(slice(None), q, OUT_OF_SPEC), per_channel=True)
                          for q in range(len(QUANTITIES))], axis=-1) - current[:, None]
        gains[(instruments.scale <= 0) | (used.scale != instruments.scale)] = -np.inf  # no prior, or widened already
        best = np.argmax(gains, axis=-1)
        out = [(int(c), int(best[c]), float(gains[c, best[c]])) for c in np.flatnonzero(gains.max(axis=-1) > margin)]
        if not out:
            break
        for c, q, _ in out:
            used = used.widened(c, q, OUT_OF_SPEC)
        found += out
        current = log_likelihood(data, model, sigma, used, per_channel=True)
    gain = float(np.sum(current - log_likelihood(data, model, sigma, instruments, per_channel=True))) if found else 0.0
    return Check(used, gain, tuple(found), gain - margin * len(found))


def in_words(channel: str, quantity: str, value: float, unit: str) -> str:
    """An instrument error as a user reads it: "w1 reads 2.1 % high", "b1_x lags by 0.42 ms"."""
    if quantity == "gain":
        return f"{channel} reads {abs(value - 1) * 100:.2g} % {'high' if value > 1 else 'low'}"
    if quantity == "delay":
        return f"{channel} {'lags' if value > 0 else 'leads'} by {abs(value) * 1e3:.2g} ms"
    return f"{channel} reads {abs(value):.2g} {unit} {'high' if value > 0 else 'low'}"


def linearized(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, instruments: Instruments | None) -> tuple[np.ndarray, np.ndarray]:
    """The closed form's residual and design about the delay's mode for one ``model`` (C, n), the noise taken as white:
    r = y − m(t − τ̂) − τ̂·ṁ(t − τ̂), what perfect instruments leave of the data, and B (C, n, 3) = [s_o·1, s_g·m(t − τ̂),
    −s_τ·ṁ(t − τ̂)], so that r = B b + (what the model lacks) + e with b ~ N(0, I): a regression on r with B's columns
    marginalizes the instrument errors jointly with whatever else it fits.  Exact instruments: y − m and no column."""
    data, model = np.asarray(data, dtype=float), np.asarray(model, dtype=float)
    if instruments is None:
        return data - model, np.zeros((*data.shape, 0))
    shift = _solve(np.ascontiguousarray(data), model, sigma, instruments.scale)[0].shift[0]
    value, slope = _delayed(model, shift)
    design = np.stack([np.ones_like(value), value, -slope], axis=-1) * instruments.scale[:, None, :]
    return data - value - shift[:, None] * slope, design


def _delayed(signal: np.ndarray, late: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(m, dm/dk) of each channel's ``signal`` (C, n) at k − ``late`` (C,) samples, as the compiled sums take them
    (:func:`_delayed_at`): the cubic through the four samples around it, or the four nearest an end beyond it."""
    n = signal.shape[-1]
    k = np.arange(n)
    first = np.clip(k + np.floor(-late).astype(int)[:, None], 1, n - 3)
    value, slope = _cubic.py_func(k - late[:, None] - first)
    samples = [np.take_along_axis(signal, first + j, axis=-1) for j in (-1, 0, 1, 2)]
    return sum(w * x for w, x in zip(value, samples)), sum(w * x for w, x in zip(slope, samples))


def reading(data: np.ndarray, model: np.ndarray, sigma: np.ndarray, instruments: Instruments | None) -> np.ndarray:
    """What the instruments most probably show of ``model`` (..., C, n): o + g·m(t − τ) at the posterior
    means (to first order in τ about its mode); the model itself with exact instruments."""
    if instruments is None:
        return model
    data = np.ascontiguousarray(data)
    solution = _solved(data, model, sigma, instruments)[0]
    shape = solution.lead + data.shape
    flat = np.ascontiguousarray(np.broadcast_to(model, shape)).reshape(-1, *data.shape)
    return (data - _left(data, flat, solution.shift, instruments.scale * solution.c_hat)).reshape(shape)
