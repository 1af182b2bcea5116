"""Find the missing term: where the force acts, and which form of the catalogue it has.

From the residual r (channel, time) of the model the search starts from (healthy or a drift) and noise σ:

1. the residual's spectral peaks above the noise (whitened periodogram, a line's power far above the
   noise's unit mean) give the frequencies that forms with one try;
2. at every place a force can act, the force history that explains r best, and its evidence
   (:func:`.force.estimate` on the linear model's pulse responses): where the missing force acts, the
   places whose log Bayes factor against no force is at least :data:`PLACE_SHARE` of the best's;
3. every form of :data:`.forms.FORMS` at each of those places it can act, each shape it proposes: its basis
   forces along the calibrated motion, normalized to unit RMS so that one log-uniform prior on the
   force's RMS holds for all, through the linear model, then Bayesian linear regression on them
   (:func:`.force.regress_records`); the shapes marginalized with the form's prior.  Candidates are ranked by
   that evidence; those within ``evidence_margin`` of the best explain the data equally.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import signal, stats
from scipy.special import logsumexp

from .. import io, likelihood, model
from ..effects.base import TORSIONAL_PLACES
from . import force
from .forms import ESTIMABLE_PLACES, FORMS, Form, Peaks, Shape, Trajectory
from .linear import LinearRig

PEAKS = 3  # spectral peaks tried as frequencies
PEAK_POWER = 25.0  # a peak's whitened power (noise: mean 1, exponential) to count as a line
ZERO_PADDING = 4
SCALE_DECADES = (-5.0, 1.0)  # log-uniform prior range of a force's RMS, relative to the place's natural scale
PULSE_SPACING = 0.002  # s, between the force estimate's basis pulses
# A place is tried when a free force there explains at least this share of what a free force at the best
# place explains (log Bayes factors against no force): on a rig whose channels each see one domain, this
# keeps the domain the force acts in and leaves the other, whose free forces explain nothing.
PLACE_SHARE = 0.5
PLACES_PER_TERM = 3  # each form's best places that become candidates (with their parameters' posteriors)


def natural_scale(place: str, values: Mapping[str, float]) -> float:
    """A force's natural size at ``place``: the mean torque T0 on the shaft line, the motor rotor's
    imbalance force u·Ω² laterally."""
    return values["T0"] if place in TORSIONAL_PLACES else values["u1"] * model.omega(values) ** 2


def scale_range(place: str, values: Mapping[str, float]) -> tuple[float, float]:
    scale = natural_scale(place, values)
    return scale * 10.0 ** SCALE_DECADES[0], scale * 10.0 ** SCALE_DECADES[1]


def spectral_peaks(residual: np.ndarray, sigma: np.ndarray, fs: float, n: int = PEAKS) -> Peaks:
    """Up to ``n`` lines in the residual, strongest first: peaks of the whitened periodogram summed over
    channels (the noise's mean 1 per channel) above :data:`PEAK_POWER`."""
    whitened = residual / sigma[:, None]
    size = ZERO_PADDING * whitened.shape[1]
    power = np.sum(np.abs(np.fft.rfft(whitened - whitened.mean(axis=1, keepdims=True), size)) ** 2, axis=0) / whitened.shape[1]
    frequencies = np.fft.rfftfreq(size, 1.0 / fs)
    found, _ = signal.find_peaks(power, height=PEAK_POWER * len(sigma), distance=2 * ZERO_PADDING)
    strongest = found[np.argsort(power[found])[::-1]][:n]
    return Peaks(tuple(float(frequencies[i]) for i in strongest), fs / whitened.shape[1])


@dataclass(frozen=True)
class Record:
    """One record as the forms are scored on it: the calibrated model's residual (channel, time) and noise, the model's
    motion and linearized response on the grid from t = 0, the record's first sample there, the residual's lines, and
    the instruments' errors that the residual and every form's columns are whitened against (:class:`.force.Nuisance`)."""

    residual: np.ndarray
    sigma: np.ndarray
    trajectory: Trajectory
    linear: LinearRig
    first: int
    peaks: Peaks
    nuisance: force.Nuisance | None


def _whitened(x: np.ndarray, nuisance: force.Nuisance | None) -> np.ndarray:
    return np.asarray(x, dtype=float) if nuisance is None else nuisance.whiten(x)


@dataclass(frozen=True)
class Candidate:
    """A form at a place, fitted on the linear model: its evidence, best shape and parameters."""

    term: str
    acts_on: str
    log_evidence: float
    shape: Shape
    frequency_hz: float | None
    order: float | None
    parameters: Mapping[str, Mapping[str, float | str]]  # name -> value, sd, hdi_low, hdi_high, unit
    chi2_after: float
    force: np.ndarray  # the fitted force history on the trajectory's grid

    def summary(self) -> dict:
        return {"term": self.term, "acts_on": self.acts_on, "frequency_hz": self.frequency_hz, "order": self.order,
                "shape": self.shape.label, "parameters": {k: dict(v) for k, v in self.parameters.items()},
                "chi2_after": self.chi2_after, "log_evidence": self.log_evidence, "method": "linearized model"}


@dataclass(frozen=True)
class Discovery:
    """Candidates ranked by evidence, the force estimated at each place, and what the search saw."""

    candidates: list[Candidate]
    scores: tuple[tuple[str, str, float], ...]  # (term, place, log-evidence) of every form scored, best first
    forces: dict[str, force.ForceEstimate]
    log_evidence_without: float
    chi2_before: float  # of the residual, the instruments' errors taken out
    record: Record  # what the forms were scored on


def record_start(sampling: model.Sampling) -> int:
    """The record's first sample on the grid k/fs from t = 0, where the search simulates the rig: t_first·fs, which must
    be a whole number to within the time stamps' own tolerance (:data:`newdyn.io.TIME_JITTER` sample intervals)."""
    first = sampling.t_first * sampling.fs
    if abs(first - round(first)) > io.TIME_JITTER:
        raise ValueError(f"time starts at {sampling.t_first:.10g} s, {first:.6g} sample intervals after t = 0 where the "
                         f"search for a missing term needs a whole number (t_first·fs, as 0.5 s at 5000 Hz gives 2500)")
    return round(first)


def discover(residual: np.ndarray, sigma: np.ndarray, values: Mapping[str, float], sampling: model.Sampling,
             channels: Sequence[str], max_step: float, nuisance: force.Nuisance | None = None) -> Discovery:
    """Search the catalogue for the term behind ``residual`` (channel, time) of the model with ``values``, the
    instruments' errors (``nuisance``, :func:`newdyn.sensors.linearized`) fitted jointly with every force."""
    sigma = np.asarray(sigma, dtype=float)
    residual = _whitened(residual, nuisance)
    first = record_start(sampling)
    n_grid = first + sampling.n_samples
    trajectory = Trajectory.simulate(values, sampling.fs, n_grid, max_step, sampling.steady)
    linear = LinearRig.build(values, sampling.fs, n_grid, channels)
    peaks = spectral_peaks(residual, sigma, sampling.fs)

    spacing = max(1, round(PULSE_SPACING * sampling.fs))
    forces = {}
    for place in ESTIMABLE_PLACES:
        pulses = linear.pulses(place, first, sampling.n_samples, spacing)
        gram, projection = pulses.gram, pulses.project(residual)
        if nuisance is not None:
            gram, projection = nuisance.whitened_products(gram, projection, pulses.project(nuisance.basis), residual)
        moments = force.Moments.of_channels(gram, projection, residual, sigma)
        forces[place] = force.estimate(place, moments, pulses.centres / sampling.fs, scale_range(place, values))

    places = _places({place: f.log_bayes_factor for place, f in forces.items()})
    record = Record(residual, sigma, trajectory, linear, first, peaks, nuisance)
    scored = _scored(places, [record])
    seen = Counter()
    candidates = []
    for entry in scored:  # best first: each form's best places
        seen[entry[1].term] += 1
        if seen[entry[1].term] <= PLACES_PER_TERM:
            candidates.append(_candidate(*entry, trajectory))
    r = residual / sigma[:, None]
    scores = tuple((form.term, place, log_evidence) for log_evidence, form, place, *_ in scored)
    return Discovery(candidates, scores, forces, force.log_evidence_without_force(residual, sigma), float(np.mean(r**2)), record)


@dataclass(frozen=True)
class Across:
    """The search over several records of one machine (each at its own operating condition): each record's own
    discovery, and every form scored on all of them with one shape, best first (:func:`discover_across`)."""

    alone: list[Discovery]
    # term, acts_on, shape, log_evidence, log_bayes_factor, chi2_after; frequency_hz and parameters (as a candidate's)
    # one per record
    scores: list[dict]
    log_evidence_without: float
    shapes: list[Shape]  # each score's best shape


def discover_across(records: Sequence[tuple], max_step: float) -> Across:
    """Search the catalogue for one term behind every record's residual: ``records`` of (residual, sigma, values,
    sampling, channels, nuisance) as :func:`discover` takes them.  Each form is scored with one shape for all records (one order
    of a disk, one frequency, one clearance), so that a line that moves with the speed is told from one that stays; the
    places tried are those whose free forces explain, summed over the records, at least :data:`PLACE_SHARE` of the
    best's."""
    alone = [discover(residual, sigma, values, sampling, channels, max_step, nuisance)
             for residual, sigma, values, sampling, channels, nuisance in records]
    seen = [found.record for found in alone]
    places = _places({place: sum(found.forces[place].log_bayes_factor for found in alone) for place in ESTIMABLE_PLACES})
    without = sum(found.log_evidence_without for found in alone)
    scores, best_shapes = [], []
    for log_evidence, form, place, shapes, weights, fit, scales in _scored(places, seen):
        best = int(np.argmax(weights))
        shape = shapes[best]
        scores.append({"term": form.term, "acts_on": place, "shape": shape.label, "order": form.order(shape),
                       "frequency_hz": [form.frequency_hz(shape, record.trajectory) for record in seen],
                       "log_evidence": log_evidence, "log_bayes_factor": log_evidence - without, "chi2_after": fit.chi2_after,
                       "parameters": [_posterior(form, _record_coefficients(form, fit, i), scale, shapes, best, weights, place)
                                      for i, scale in enumerate(scales)]})
        best_shapes.append(shape)
    return Across(alone, scores, without, best_shapes)


def _record_coefficients(form: type[Form], fit: force.Regression, record: int) -> force.Regression:
    """The regression's coefficients that act in ``record``: a phased form's block of that record, else all of them."""
    if not form.phased or len(fit.mean) == len(form.coefficients):
        return fit
    block = slice(record * len(form.coefficients), (record + 1) * len(form.coefficients))
    return replace(fit, mean=fit.mean[block], sd=fit.sd[block])


def _places(log_bayes_factors: Mapping[str, float]) -> list[str]:
    """The places a force acts on: those whose free force explains at least :data:`PLACE_SHARE` of the best's."""
    best = max(log_bayes_factors.values())
    return [p for p, value in log_bayes_factors.items() if value > 0 and value >= PLACE_SHARE * best]


def _scored(places: Sequence[str], records: Sequence[Record]) -> list[tuple]:
    """:func:`_score` of every form at each of ``places`` it can act on, best first."""
    return sorted((scored for form in FORMS.values() for place in form.places() if place in places
                   if (scored := _score(form, place, records)) is not None), key=lambda s: -s[0])


def _score(form: type[Form], place: str, records: Sequence[Record]):
    """(log-evidence with the shapes marginalized, form, place, the shapes, their posterior weights, the best shape's
    regression and the force per unit coefficient in each record, its basis RMS), or None when the form proposes no shape
    at ``place``.  Over several records one shape holds for all (those any record proposes); a phased form's coefficients
    are each record's own, and any other's one force for all, its basis normalized by its RMS over all records."""
    shapes = form.shapes(records[0].trajectory, place, records[0].peaks)
    for record in records[1:]:
        shapes += [shape for shape in form.shapes(record.trajectory, place, record.peaks) if shape not in shapes]
    if not shapes:
        return None
    ranges = [scale_range(place, record.trajectory.values) for record in records]
    prior_range = (min(low for low, _ in ranges), max(high for _, high in ranges))
    fits, scales = [], []
    for shape in shapes:
        columns, rms = zip(*(_columns(form, place, shape, record) for record in records))
        if form.phased and len(records) > 1:  # block-diagonal: record i's coefficients move record i alone
            columns = [np.concatenate([c if j == i else np.zeros_like(c) for j in range(len(records))], axis=2)
                       for i, c in enumerate(columns)]
        elif len(records) > 1:  # one coefficient, one force for all records: each basis normalized over all of them
            pooled = np.sqrt(np.average(np.square(rms), axis=0, weights=[r.residual.shape[1] for r in records]))
            columns = [c * (r / pooled) for c, r in zip(columns, rms)]
            rms = (pooled,) * len(records)
        fits.append(force.regress_records([r.residual for r in records], [r.sigma for r in records], columns, prior_range))
        scales.append(rms)
    log_z = np.array([f.log_evidence for f in fits]) + form.log_prior(records[0].trajectory, records[0].peaks, len(shapes))
    log_evidence = float(logsumexp(log_z))
    best = int(np.argmax(log_z))
    return log_evidence, form, place, shapes, np.exp(log_z - log_evidence), fits[best], scales[best]


def _columns(form: type[Form], place: str, shape: Shape, record: Record) -> tuple[np.ndarray, np.ndarray]:
    """The channels' responses over the record (channel, time, coefficient) to the form's basis at ``shape``, each basis
    force normalized to unit RMS over the record, and those RMS."""
    window = slice(record.first, record.first + record.residual.shape[1])
    basis = form.basis(record.trajectory, place, shape)
    rms = np.sqrt(np.mean(basis[:, window] ** 2, axis=1))
    rms = np.where(rms > 0, rms, 1.0)
    return _whitened(np.moveaxis(record.linear.response(place, basis / rms[:, None])[:, :, window], 1, 2), record.nuisance), rms


def _candidate(log_evidence, form, place, shapes, shape_weights, fit, scales, trajectory) -> Candidate:
    best, scale = int(np.argmax(shape_weights)), scales[0]
    parameters = _posterior(form, fit, scale, shapes, best, shape_weights, place)
    return Candidate(form.term, place, log_evidence, shapes[best], form.frequency_hz(shapes[best], trajectory),
                     form.order(shapes[best]), parameters, fit.chi2_after,
                     (fit.mean / scale) @ form.basis(trajectory, place, shapes[best]))


def _posterior(form: type[Form], fit: force.Regression, scale: np.ndarray, shapes: Sequence[Shape], best: int,
               shape_weights: np.ndarray, place: str, draws: int = 4000) -> dict:
    """Each named parameter's mean, sd and 94 % HDI: the coefficients' Normal posterior (drawn, and turned
    into the form's parameters), the shape's over the shapes tried."""
    rng = np.random.default_rng(0)
    coefficients = (fit.mean + fit.sd * rng.standard_normal((draws, len(fit.mean)))) / scale
    named = [form.parameters(c, shapes[best], place) for c in coefficients]
    rows = {}
    for name, (value, unit) in form.parameters(fit.mean / scale, shapes[best], place).items():
        if name in shapes[best].values:  # a shape parameter: its posterior over the shapes tried
            grid = np.array([s.values[name] for s in shapes])
            samples = rng.choice(grid, size=draws, p=shape_weights)
        else:
            samples = np.array([n[name][0] for n in named])
        circular = name == "phase"  # an angle: its mean, spread and interval on the circle
        low, high = _hdi(samples, circular)
        mean = stats.circmean(samples, math.pi, -math.pi) if circular else np.mean(samples)
        sd = stats.circstd(samples, math.pi, -math.pi) if circular else np.std(samples)
        rows[name] = {"value": float(value), "mean": float(mean), "sd": float(sd), "hdi_low": low, "hdi_high": high, "unit": unit}
    return rows


def _hdi(samples: np.ndarray, circular: bool) -> tuple[float, float]:
    import arviz as az

    low, high = az.hdi(np.asarray(samples, dtype=float), hdi_prob=likelihood.HDI_PROB, circular=circular)
    return float(low), float(high)


def separating_channels(candidates: Sequence[Candidate], discovery: Discovery, sigma: Mapping[str, float]) -> list[dict]:
    """Channels ranked by how well they would separate the closest pair of ``candidates`` (which explain the
    measured channels equally): ½ Σ ((m_a − m_b)/σ_c)², the expected log Bayes factor, m the channel's
    response to each candidate's fitted force through the linearized rig, σ_c the noise there."""
    trajectory, first = discovery.record.trajectory, discovery.record.first
    channels = list(sigma)
    linear = LinearRig.build(trajectory.values, discovery.record.linear.fs, trajectory.t.size, channels)
    responses = [linear.response(c.acts_on, c.force)[:, first:] for c in candidates]
    rows = []
    for i, channel in enumerate(channels):
        pair = min(0.5 * float(np.sum(((a[i] - b[i]) / sigma[channel]) ** 2))
                   for j, a in enumerate(responses) for b in responses[j + 1:])
        rows.append({"channel": channel, "expected_log_bayes_factor": pair})
    return sorted(rows, key=lambda r: -r["expected_log_bayes_factor"])


def log_bayes_factor(candidate: Candidate, discovery: Discovery) -> float:
    return candidate.log_evidence - discovery.log_evidence_without


def equivalent(discovery: Discovery, margin: float, to: tuple[str, str] | None = None) -> list[tuple[str, str]]:
    """(term, place) of every form scored whose evidence is within ``margin`` of the best's (or of the form and
    place ``to``), candidate or not: a line at one frequency, say, is fitted as well at any place whose response
    reaches the measured channels."""
    if not discovery.scores:
        return []
    top = max(log_evidence for term, place, log_evidence in discovery.scores if to is None or (term, place) == to)
    return [(term, place) for term, place, log_evidence in discovery.scores if top - log_evidence <= margin]
