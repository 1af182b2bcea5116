"""Diagnose one measurement: compare the model with it, see where it fails, find which effect is
missing, add it and show the error fall (the paper's Steps 1–3, automated, then a fit of the effect).

1. Noise level: the file's ``sigma``, else its ``snr_db``, else the noise floor above
   ``noise_band_hz`` — never a model's misfit, which would absorb the very effect we look for.  Noise colour
   (up to AR order ``noise_colour_order``): read, after the fits under white noise, from the residual of the best
   of them without its lines (:func:`newdyn.noise.colour`) — least squares stays unbiased under coloured noise,
   and a fit that explains the data leaves noise alone; when coloured, the diagnosis runs again with those
   channels whitened in every likelihood and their σ that residual's level.
2. Calibration: each calibration parameter on its likelihood grid (as in the study); a drift of one
   parameter is the hypothesis ``parameter_change:<p>``, its log-evidence exact by quadrature.
3. Signatures (Steps 1 and 3): the posteriors that each hypothesis at a range of severities would give,
   simulated noise-free, and their Hellinger distances to the measurement's posteriors.
4. Fits: each effect of :mod:`newdyn.effects` added to the model, its parameters and the drift parameters fitted
   (:func:`newdyn.hypotheses.fit`), scored by χ² and log-evidence; hypotheses ranked by evidence.  With
   ``sensors``, every fit integrates the instruments' offsets, gains and delays out over their datasheets'
   priors, and an instrument error far outside its prior (:func:`newdyn.sensors.check`) gets a wide one at prior
   odds e^−``evidence_margin``: a machine that is otherwise healthy is then a ``sensor_problem``.
5. Verdict: the best-evidence hypothesis if its fit brings χ² to the noise (≤ ``chi2_max``), else
   ``unexplained``; hypotheses of the same class within ``evidence_margin`` of it explain the data
   equally, and the unmeasured channels that would separate them are named.
6. Discovery, when no fit of the library explains the data: the form of the missing term at the place where it acts
   (:mod:`newdyn.discovery`), its best candidate written as an effect file and fitted on the full
   simulator with the drift parameters, so that its χ² and evidence stand beside the library's.
7. The best fault model's posterior, for its parameters' uncertainty: verified (quadrature, importance sampling,
   else MCMC to convergence, up to ``max_rounds``) and polished from its best draw where the verdict may rest on it;
   one batch of importance sampling where it cannot: healthy or a drift explains the data with more evidence, or the
   discovered term does where no library fit did, or the fault's own fit leaves χ² above the noise. (The polish
   restarts the fit from a draw that fits better; where that brings it to the noise, its posterior is verified then.)
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
import xarray as xr
from scipy.integrate import trapezoid
from scipy.special import logsumexp

from . import (
    alignment,
    calibration,
    concurrency,
    hypotheses,
    instrument_checks,
    io,
    likelihood,
    mcmc_calibration,
    model,
    noise,
    residuals,
    running_speed,
    slots,
    statement,
)
from . import bank as bank_module
from . import posterior as posterior_module
from . import sensors as sensors_module
from . import signatures as signature_module
from .discovery import effect_file, verify
from .hypotheses import HEALTHY, PARAMETER_CHANGE
from .measurement_checks import check_measurement, noise_level, present_channels
from .settings import Settings
from .verdicts import SENSOR_PROBLEM

log = logging.getLogger("newdyn")
# How often the record's angles are found again under the best fit and the diagnosis run again from there: a fault the
# nominal model lacks may pull them (most of all on a short record), and a fit at angles pulled off finds its values
# off too, which the next pass corrects.
REALIGNMENTS = 3
PHASE = "load_phase"  # the record's parameter that every effect's fit finds beside its own values


def coloured_level(channels: Sequence[str], sigma: np.ndarray, source: str, colour: noise.Colour,
                   level: np.ndarray) -> tuple[np.ndarray, str]:
    """The noise σ of ``channels`` and its source under a ``colour`` read with that broadband ``level``: a coloured
    channel's σ is its level, the residual's innovation σ_e (what its likelihood needs, and what the residual tells
    best) over the AR model's σ_e/σ_x, so a stated σ times that ratio, with the ratio's error, never enters; a white
    channel keeps ``sigma``."""
    orders = ", ".join(f"{c} AR({len(found['ar'])})" for c, found in colour.summary(channels).items())
    coloured = np.any(colour.ar != 0, axis=1)
    return np.where(coloured, level, sigma), f"{source} for white channels; the best white-noise fit's residual without its lines for coloured ones ({orders})"


def _with_load_phase(hypothesis: hypotheses.Hypothesis, phase: float) -> hypotheses.Hypothesis:
    """``hypothesis`` with the load's phase fitted beside its own values, within
    :data:`newdyn.alignment.FIT_HALF_WIDTH` of ``phase``."""
    width = alignment.FIT_HALF_WIDTH
    return replace(hypothesis, priors=(*hypothesis.priors, hypotheses.Prior(PHASE, phase - width, phase + width)))


def _realigned(fit: hypotheses.Fit, data, sigma, values, stated, record: alignment.Alignment, sampling, channels,
               settings: Settings) -> tuple[alignment.Alignment | None, dict[str, float]]:
    """Where the record sits found again under ``fit``, its values free beside the angles (:func:`newdyn.alignment.
    align_jointly`): None where the data do not place it elsewhere than ``record`` (found under the nominal model, whose
    misfit a fault's shape may have pulled), else the new alignment; the ``stated`` angles where the data cannot tell
    them from the found ones.  Beside it, the standard errors of the record's values under ``fit``."""
    names = [name for name in record.values if name not in fit.hypothesis.parameters]  # its fit finds the others
    index = [slots.slot_index()[name] for name in names]
    k = len(names)

    def rows(x):
        kernel = fit.hypothesis.parameter_rows(x[:, k:], values)
        kernel[:, index] = x[:, :k]
        return kernel

    low, high = (np.array([getattr(p, side) for p in fit.hypothesis.priors]) for side in ("low", "high"))
    found, angles_sd = alignment.align_jointly(data, sigma, channels, sampling, settings.max_step, rows, names, stated,
                                               record.values, fit.theta, low, high, fit.instruments, record.speed_sd)
    own = [name for name in record.values if name in fit.hypothesis.parameters]  # its fit's own finding
    sd = {**{name: float(np.sqrt(fit.covariance[i, i])) for i, name in enumerate(fit.hypothesis.parameters)
             if name in own and fit.covariance is not None}, **angles_sd}
    # The fit's own finding (an effect's load phase) moves the record too where the data place it elsewhere: a drift the
    # nominal model lacks shifts the load's line that placed the record, and where the channels barely see the load
    # (a probe alone) the lines hardly place its phase at all.
    moved = [name for name in own if name in sd and alignment.moves(record.values[name], record.sd.get(name, math.inf),
                                                                    fit.values[name], sd[name])]
    if found is None and not moved:
        return None, sd
    if found is None:
        def chi2(outputs):  # per compared number, the whole waveform through the fit's instruments
            return float(np.sum(likelihood.standardized_residuals(data, outputs, sigma, fit.instruments) ** 2)) / data.size

        held = fit.theta.copy()
        held[[fit.hypothesis.parameters.index(name) for name in moved]] = [record.values[name] for name in moved]
        at_record = hypotheses.evaluate(fit.hypothesis, held, values, sampling, channels, settings.max_step)
        found = alignment.Alignment({}, chi2(at_record), chi2(fit.model[None]), 1, "waveform", record.speed_sd)
    return replace(found, values={**record.values, **{name: fit.values[name] for name in own}, **found.values},
                   sd={**record.sd, **sd}), sd


@dataclass(frozen=True)
class _Placement:
    """Where the record sits under the best of some fits: that fit, the new alignment (None where the record stays:
    always under healthy's fit, which places it where the nominal model did) and the record values' standard errors
    under it."""

    fit: hypotheses.Fit
    again: alignment.Alignment | None
    sd: dict[str, float]


def _placed_by_best(fits: Mapping[str, hypotheses.Fit], data, sigma, values, stated, record: alignment.Alignment, sampling,
                    channels, settings: Settings) -> _Placement:
    """:func:`_realigned` under the fit of most evidence among ``fits``."""
    best = max(fits.values(), key=lambda fit: fit.log_evidence)
    if best.hypothesis.kind == HEALTHY:
        return _Placement(best, None, {})
    return _Placement(best, *_realigned(best, data, sigma, values, stated, record, sampling, channels, settings))


def _tachometer_sd(settings: Settings, recorded: Sequence[str], speed_rpm: float, sampling: model.Sampling) -> float | None:
    """How far (sd, rpm) the running speed may lie from a recorded disk speed's mean, by its sensor's datasheet (gain
    and offset; the most precise of the disk speeds recorded): the speed is then fitted from the shaft's line with that
    prior.  None where no disk speed is recorded, its sensor is exact (its mean is the speed), or the record is too
    short for that spread to turn the shaft's line by :data:`newdyn.alignment.SPEED_TURN` (the line cannot tell the
    speed better than the tachometer, and what else the nominal model misses would pull it)."""
    spreads = [math.hypot(sensor.gain_sd * speed_rpm, sensor.offset_sd * 60.0 / (2.0 * math.pi))
               for c in recorded if c in running_speed.SPEEDS and (sensor := settings.sensors.get(c)) is not None]
    spreads = [sd for sd in spreads if sd > 0]
    if not spreads or 2.0 * math.pi * min(spreads) / 60.0 * sampling.n_samples / sampling.fs < alignment.SPEED_TURN:
        return None
    return min(spreads)


def _grid_evidence(posterior: likelihood.GridPosterior) -> float:
    """log ∫ L(φ) π(φ) dφ on the grid by the trapezoidal rule, π the (normalized) prior."""
    log_integrand = posterior.log_likelihood + posterior.log_prior
    peak = float(np.max(log_integrand))
    return peak + math.log(trapezoid(np.exp(log_integrand - peak), posterior.grid))


@dataclass
class Diagnosis:
    """Everything a diagnosis found; :func:`write` turns it into files."""

    measurement: io.Measurement
    channels: tuple[str, ...]
    data: np.ndarray
    sigma: np.ndarray
    noise_source: str
    calibrations: dict[str, calibration.Calibration]
    fits: dict[str, hypotheses.Fit]
    signatures: xr.DataArray  # Hellinger distance (signature, parameter)
    verdict: dict
    versions: dict[str, np.ndarray]  # model version name -> outputs (channel, time)
    effect_posterior: object  # arviz.InferenceData of the best fault model's parameters (importance sampling or MCMC)
    discovery: verify.Discovered | None = None  # what the search for a missing term found, where it ran
    pointwise: xr.DataArray | None = None  # each version's log-likelihood (comparison_version, comparison_draw, channel, load_cycle)


def diagnose(measurement: io.Measurement, settings: Settings, grid_paths: Mapping[str, str] | None = None,
             colour: noise.Colour | None = None, level: np.ndarray | None = None, bank_path: str | None = None,
             searched: Mapping[str, hypotheses.Fit] | None = None, record: alignment.Alignment | None = None,
             realigned: int = 0, bank: xr.Dataset | None = None) -> Diagnosis:
    """Diagnose ``measurement`` (already read and checked); ``grid_paths`` are the study's shared
    coarse-grid files per calibration parameter and ``bank_path`` its bank (:mod:`newdyn.bank`), each reused when its
    condition is the measurement's (else computed here).  ``colour``
    (with the coloured channels' σ ``level``) is the noise's, when a first pass found it; without it, a first pass
    fits under white noise and, when its best fit's residual reads coloured, the diagnosis runs again whitened, each
    hypothesis the first pass searched globally (its fits ``searched``) fitted from that search's optimum instead of
    searching the same data again.  ``record`` is where the recording sits on the shaft's turn and the load's cycle
    (:mod:`newdyn.alignment`): found here under the nominal model when not given, and found again under the best
    hypothesis's fit, the diagnosis run again from there when the data place the record elsewhere (``realigned`` times
    so far, up to :data:`REALIGNMENTS`), that hypothesis fitted from its search's optimum where it searched and only its
    own findings moved the record.  A pass run again reuses the first one's ``bank``: its members only pick where
    each fit starts, whose least squares then runs at the pass's own angles and load phase."""
    check_measurement(measurement, settings.channels, settings.noise_band_hz,
                      values=slots.complete({**settings.rig, **measurement.operating}))
    configured, missing = settings, tuple(c for c in settings.channels if c not in measurement.channels)
    settings = replace(settings, channels=present_channels(measurement, settings.channels))
    rows = [measurement.channels.index(c) for c in settings.channels]
    channels, data, sampling = settings.channels, measurement.y[rows], measurement.sampling
    sigma, noise_source = noise_level(measurement, rows, settings.noise_band_hz)
    stated = slots.complete({**settings.rig, **measurement.operating})
    values = stated
    hyps = {h.name: h for h in settings.hypotheses()}
    if colour is not None:
        sigma, noise_source = coloured_level(channels, sigma, noise_source, colour, level)
    clock = time.perf_counter()
    if record is None:
        record = alignment.align(data, sigma, channels, values, sampling, settings.max_step,
                                 fit_speed=not any(c in running_speed.SPEEDS for c in measurement.channels),
                                 speed_sd=_tachometer_sd(settings, measurement.channels, values["speed_rpm"], sampling))
        log.info("%s: the record's angles %s (chi2 %.4g -> %.4g, %d simulations) in %.1f s", measurement.name,
                 {k: round(v, 4) for k, v in record.values.items()}, record.chi2_stated, record.chi2_found,
                 record.n_simulations, time.perf_counter() - clock)
    values = {**values, **record.values}
    library = hyps
    hyps = {**library, **{kind: _with_load_phase(library[kind], values[PHASE]) for kind in settings.fault_ranges}}
    searched = searched or {}
    instruments = settings.instruments(sampling.fs, colour)  # as the datasheets say; out-of-spec ones are found per fit

    coarse = {
        p: calibration.coarse_models((grid_paths or {}).get(p), spec, values, sampling, channels, settings.max_step)
        for p, spec in settings.grids.items()
    }

    def stage(what):
        nonlocal clock
        log.info("%s: %s in %.1f s", measurement.name, what, time.perf_counter() - clock)
        clock = time.perf_counter()

    tasks = [calibration.Task(data, spec, settings.priors[p], coarse[p]) for p, spec in settings.grids.items()]
    calibrations = dict(zip(settings.grids, calibration.calibrate_many(tasks, sigma, values, sampling, channels, settings.refine_points,
                                                                       settings.chi2_max, settings.max_step, instruments)))
    stage(f"noise level from {noise_source}, grid calibrations of {', '.join(settings.grids)}")

    # The signature library is the condition's, reused wherever the record is and whatever speed the data corrected the
    # nameplate's to; the members are the record's own.
    nameplate = {**stated, "speed_rpm": measurement.attrs.get("stated_speed_rpm", stated["speed_rpm"])}
    reused = bank is not None
    if not reused:
        bank = study_bank(bank_path, settings, library, nameplate, sampling, coarse if values == nameplate else None, members_at=values)
    signatures = signature_module.distances(bank, calibrations, sigma, settings.priors)
    stage(f"{signatures.sizes['signature']} signatures" + (" (the first pass's members)" if reused else ""))

    # The posterior and the comparison of model versions need ArviZ: imported beside the fits, whose least squares
    # often leave a core free.
    concurrency.import_beside("arviz")
    # Fits: healthy as it is, drifts from their grids (exact), faults from their closest signature and from the bank's
    # members, or a global search where members are too sparse and the fit may decide the verdict.
    fits = {HEALTHY: hypotheses.fit(hyps[HEALTHY], data, sigma, values, sampling, channels, max_step=settings.max_step,
                                    instruments=instruments)}
    fits.update({f"{PARAMETER_CHANGE}:{p}": _drift_fit(hyps[f"{PARAMETER_CHANGE}:{p}"], cal, instruments) for p, cal in calibrations.items()})
    # Healthy and the drifts were fitted at the load's phase where the lines put it; the effects' fits find it beside
    # their values.  The phase integrated out at each one's best values puts the evidences on one footing.
    phase_terms = concurrency.in_parallel({name: lambda fit=fit: alignment.load_phase_integral_at(
        values, fit.values, data, sigma, channels, sampling, settings.max_step, instruments) for name, fit in fits.items()})
    fits = {name: replace(fit, log_evidence=fit.log_evidence + phase_terms[name]) for name, fit in fits.items()}
    closest = signatures.mean("parameter")

    def fault_fit(kind, search_globally=False, stop=None):
        started = time.perf_counter()
        mine = closest.where(signatures["hypothesis"] == kind, drop=True)
        start = json.loads(str(mine["values"].values[int(np.argmin(mine.values))]))
        if kind in searched:  # the white-noise pass searched the same data globally: its optimum starts this fit
            fit = replace(hypotheses.fit(hyps[kind], data, sigma, values, sampling, channels, [start, searched[kind].values],
                                         settings.max_step, search=False, instruments=instruments, chains=1),
                          search=hypotheses.SEARCHED_FROM[2])
        else:
            # One chain: the start that fits the longest search window best, of the closest signature and the best
            # member (or the search's best) on each search window.  Members of a fault of at most three parameters are
            # points of a lattice dense enough that one start reaches the search's optimum; for a larger fault, its fit from
            # members is a lower bound on its evidence.  The other starts' chains reached the same optimum at the cost of
            # two more.
            fit = hypotheses.fit(hyps[kind], data, sigma, values, sampling, channels, [start], settings.max_step,
                                 instruments=instruments, members=None if search_globally else bank_module.members(bank, kind),
                                 chains=1, stop=stop)
        log.info("%s: fit of %s from %s (%d simulations, chi2 %.4g) in %.1f s", measurement.name, kind, fit.search, fit.n_simulations,
                 fit.chi2_red, time.perf_counter() - started)
        return fit

    def by_size(kinds):  # the largest first, so that the longest fit does not start last
        return sorted(kinds, key=lambda kind: -len(hyps[kind].priors))

    # A hypothesis too large for its members searches globally only where nothing else explains the data: elsewhere it
    # could take the verdict only by fitting better than what already fits to the noise, and its members' fit stands as
    # a lower bound on its evidence (the ranking's search says so).  Its members' fit runs beside the smaller faults'
    # on the chance that something explains the data; if nothing does, it is stopped and searches instead.
    large = [kind for kind in settings.fault_ranges if bank_module.needs_search(library[kind]) and kind not in searched]

    def explaining(candidates):
        return [name for name, fit in candidates.items() if _explains(fit, calibrations, settings.chi2_max)]

    small = [kind for kind in settings.fault_ranges if kind not in large]
    fitted = concurrency.in_parallel({kind: lambda kind=kind: fault_fit(kind) for kind in by_size(small)},
                                     {kind: lambda stop, kind=kind: fault_fit(kind, stop=stop) for kind in by_size(large)},
                                     lambda done: bool(explaining({**fits, **done})))
    explained = explaining({**fits, **{kind: fitted[kind] for kind in small}})
    # Where nothing explains the data, the best fit so far may place the record elsewhere (a fault the nominal model
    # lacks pulled its angles) and explain the data there: the pass is run again from there before a global search
    # spends its thousands of simulations at angles the next pass corrects.  A record placed under a fit that would
    # still not explain it is not taken before the search: under a misfit its angles are pulled as under the nominal
    # model (a stick-slip rig's best drift, χ² 15, moved disk 4's imbalance half a turn).
    placed = None
    if not explained and realigned < REALIGNMENTS:
        placed = _placed_by_best({**fits, **fitted}, data, sigma, values, stated, record, sampling, channels, settings)
        if placed.again is not None and placed.again.chi2_found <= settings.chi2_max:
            stage(f"the record's angles found again under {placed.fit.hypothesis.name}: {placed.again.values}; again from "
                  "there, before the global search")
            return diagnose(measurement, configured, grid_paths, colour, level, bank_path, searched, placed.again, realigned + 1,
                            bank)
    if not explained:
        fitted.update(concurrency.in_parallel({kind: lambda kind=kind: fault_fit(kind, search_globally=True) for kind in by_size(large)}))
    fits.update({kind: fitted[kind] for kind in settings.fault_ranges})
    stage(f"fits of {', '.join(settings.fault_ranges)}" + (f" ({', '.join(large)} from members: {', '.join(explained)} explains the data)"
                                                          if large and explained else ""))
    fits = {name: instrument_checks.checked(fit, data, sigma, settings.evidence_margin) for name, fit in fits.items()}
    if colour is None and settings.noise_colour_order:
        best = max(fits.values(), key=lambda fit: fit.log_evidence)
        found, level = noise.colour(data - _shown(best, data, sigma), settings.noise_colour_order, settings.evidence_margin)
        if not found.white:
            stage(f"noise colour {found.summary(channels)} from the residual of {best.hypothesis.name}: again, whitened")
            return diagnose(measurement, configured, grid_paths, found, level, bank_path,
                            {kind: fit for kind, fit in fits.items() if fit.search == hypotheses.SEARCHED_FROM[1]}, bank=bank)
    colour = colour or noise.white(len(channels))
    if realigned < REALIGNMENTS:
        best = max(fits.values(), key=lambda fit: fit.log_evidence)
        if placed is None or placed.fit is not best:
            placed = _placed_by_best(fits, data, sigma, values, stated, record, sampling, channels, settings)
        record = replace(record, sd={**record.sd, **placed.sd})
        if placed.again is not None:
            stage(f"the record's angles found again under {placed.fit.hypothesis.name}: {placed.again.values}; again from there")
            # Where only the placing fit's own findings moved the record (an effect's load phase), its optimum is the
            # next pass's too: where it searched globally, that pass fits it from there instead of searching again.
            # Where the angles moved, each hypothesis searches again: a stick-slip optimum found at angles 0.4 rad off
            # was a side basin the search at the new angles left (χ² 0.914 against 0.912).
            placer = placed.fit
            stayed = all(placed.again.values[name] == record.values[name] for name in record.values
                         if name not in placer.hypothesis.parameters)
            reused = {placer.hypothesis.name: placer} if stayed and placer.search == hypotheses.SEARCHED_FROM[1] else {}
            return diagnose(measurement, configured, grid_paths, colour if colour.ar.any() else None, level, bank_path,
                            {**searched, **reused}, placed.again, realigned + 1, bank)

    best_fault = max(settings.fault_ranges, key=lambda kind: fits[kind].log_evidence)
    discovery = None
    explaining = [name for name, fit in fits.items() if _explains(fit, calibrations, settings.chi2_max)]
    if settings.searches(bool(explaining)):
        discovery = verify.discover(measurement.name, verify.search_base(fits, settings.drift, explaining), data, sigma, values, sampling,
                                    settings)
        stage(f"discovery ({len(discovery.section['candidates'])} candidates)")
    ahead = _explaining_ahead(fits, calibrations, best_fault, settings.chi2_max, discovery and discovery.fit)
    if ahead is None and fits[best_fault].search in hypotheses.SEARCHED_FROM[1:]:
        # A searched misfit has a basin per switching pattern: the verdict may rest on this fault, so its fit looks
        # into the neighbouring ones before its posterior is sampled about it.
        fits[best_fault] = _in_best_basin(fits[best_fault], data, sigma, values, sampling, channels, settings, instruments)
        stage(f"{best_fault}'s neighbouring basins looked into (chi2 {fits[best_fault].chi2_red:.4g})")
    unneeded = _unneeded(fits[best_fault], ahead, settings.chi2_max)
    effect_posterior = _effect_posterior(fits[best_fault], data, sigma, values, sampling, channels, settings, unneeded,
                                         polishing=ahead is None)
    if ahead is None:
        polished = _polished(fits[best_fault], effect_posterior, data, sigma, values, sampling, channels, settings, instruments)
        # The posterior again about the better optimum where the first missed it, or where the verdict may now rest on
        # the fault (polished to the noise).
        if polished is not fits[best_fault] and (not effect_posterior.attrs["converged"] if unneeded is None
                                                 else _unneeded(polished, None, settings.chi2_max) is None):
            unneeded = None
            effect_posterior = _effect_posterior(polished, data, sigma, values, sampling, channels, settings, unneeded)
        elif unneeded is None and not effect_posterior.attrs["converged"] and _beaten(fits[best_fault], effect_posterior):
            # The sampling stopped for a polish that found nothing better: sampled about the fit to the end.
            effect_posterior = _effect_posterior(fits[best_fault], data, sigma, values, sampling, channels, settings, unneeded)
        fits[best_fault] = polished
    if not effect_posterior.attrs["converged"] and unneeded is None:
        effect_posterior = _sample_effect(fits[best_fault], data, sigma, values, sampling, channels, settings,
                                          f"{effect_posterior.attrs['method']} unverified ({effect_posterior.attrs['reason']})")
        if ahead is None:
            fits[best_fault] = _polished(fits[best_fault], effect_posterior, data, sigma, values, sampling, channels, settings,
                                         instruments)
    stage(f"posterior of {best_fault} by {effect_posterior.attrs['method']}" + (f" ({unneeded})" if unneeded else ""))

    verdict = _verdict(fits, calibrations, signatures, settings, values, sampling, data, sigma)
    if instruments is not None and np.any(instruments.scale > 0):
        verdict.update(instrument_checks.report(_read_through(fits, verdict, discovery, settings.chi2_max), data, sigma, instruments, channels,
                                                settings.evidence_margin))
        if verdict["verdict"] == "healthy" and verdict["sensor_problems"]:
            verdict["verdict"] = SENSOR_PROBLEM
        verdict["sensor_alternatives"] = instrument_checks.alternatives(fits, verdict["models"]["after"], data, sigma, instruments, channels, settings)
    verdict["effect_fit"] = {
        "hypothesis": best_fault, "parameters": _posterior_parameters(effect_posterior, hyps[best_fault].parameters),
        **{key: effect_posterior.attrs[key]
           for key in ("method", "converged", "integrated", "rhat", "ess_bulk", "pareto_k", "refits", "step", "reason")
           if key in effect_posterior.attrs},
    }
    if verdict["verdict"] == "new_dynamics" and verdict["effect"] == best_fault:
        verdict["parameters"] = verdict["effect_fit"]["parameters"]
        verdict["converged"] = bool(verdict["effect_fit"]["converged"])
    versions = {name: _shown(fits[hypothesis], data, sigma) for name, hypothesis in verdict["models"].items()}
    for key, version in (("where_nominal_fails", "nominal"), ("where_it_fails", "calibrated"), ("remaining", "after")):
        residual, sigma_e, times = colour.seen(data - versions[version], sigma, sampling.times)
        verdict[key] = residuals.where_it_fails(residual, sigma_e, channels, times, sampling.fs, values["load_freq"])
    if missing:
        verdict["missing_channels"] = _missing_channels(missing, verdict, fits, values, sampling, data, sigma, settings)
    verdict["noise"] = {"sigma": dict(zip(channels, sigma.tolist())), "source": noise_source,
                        "colour": colour.summary(channels)}
    verdict["record"] = {**record.summary(), "found_under": "the best fit" if realigned else "the nominal model", "passes": realigned + 1,
                         "speed_rpm": values["speed_rpm"], "stated_speed_rpm": nameplate["speed_rpm"]}
    # Discovery ran before the MCMC; a library fault whose polish explained the data after all drops it.
    if discovery is not None and not settings.searches(verdict["verdict"] != "unexplained"):
        discovery = None
    if discovery is not None:
        verdict["discovery"] = discovery.section
        if discovery.fit is not None:
            versions["discovered"] = _shown(discovery.fit, data, sigma)
            verdict["models"]["discovered"] = discovery.fit.hypothesis.name
            verdict["model_versions"].append(_version_row("+ discovered", discovery.fit, versions["discovered"], data, channels))
    verdict["model_comparison"], pointwise = _compare_versions(verdict, fits, calibrations, effect_posterior, discovery, data, sigma,
                                                               values, sampling, settings)
    stage("model versions compared by PSIS-LOO")
    verdict["statement"] = statement.statement(verdict, settings.chi2_max)
    return Diagnosis(measurement, channels, data, sigma, noise_source, calibrations, fits, signatures, verdict,
                     versions, effect_posterior, discovery, pointwise)


def _compare_versions(verdict, fits, calibrations, effect_posterior, discovery: verify.Discovered | None, data, sigma, values, sampling,
                      settings: Settings):
    """``az.compare`` of the model versions by PSIS-LOO over blocks of one channel and load cycle, and their
    pointwise log-likelihoods (version, draw, channel, cycle).  Draws: the drift's grid posterior, the
    library effect's posterior, the discovered term's Laplace approximation; the nominal model has none."""
    from . import model_comparison

    rng = np.random.default_rng(int(settings.mcmc.get("seed", 0)))
    n = model_comparison.DRAWS

    def version(fit, draws, base=values):
        return model_comparison.Version(
            lambda theta: hypotheses.evaluate(fit.hypothesis, theta, base, sampling, settings.channels, settings.max_step),
            draws, fit.hypothesis.parameters, fit.instruments)

    nominal, calibrated, effect = (fits[verdict["models"][key]] for key in ("nominal", "calibrated", "effect"))
    evaluators = {"nominal": version(nominal, np.zeros((n, 0)))}
    if calibrated.hypothesis.kind == PARAMETER_CHANGE:
        posterior = calibrations[calibrated.hypothesis.effect].posterior
        cdf = posterior.cdf
        theta = np.interp(rng.uniform(0, cdf[-1], n), cdf, posterior.grid)[:, None]
        evaluators["calibrated"] = version(calibrated, theta)
    stacked = np.column_stack([effect_posterior.posterior[name].values.ravel() for name in effect.hypothesis.parameters])
    evaluators["effect"] = version(effect, stacked[rng.choice(len(stacked), n, replace=len(stacked) < n)])
    cycle = model_comparison.cycles(sampling.times, values["load_freq"])
    idata = model_comparison.evaluate_versions(evaluators, data, sigma, cycle, settings.channels)
    if discovery is not None and discovery.fit is not None:
        discovered = discovery.fit
        low, high = np.array([[p.low, p.high] for p in discovered.hypothesis.priors]).T
        with discovery.as_fitted():
            idata.update(model_comparison.evaluate_versions(
                {"discovered": version(discovered, model_comparison.draws(discovered.theta, discovered.covariance, low, high, rng),
                                       slots.without_effects(values))},
                data, sigma, cycle, settings.channels))
    pointwise = xr.concat([d.log_likelihood["y"].isel(chain=0, drop=True) for d in idata.values()],
                          dim=xr.Variable("comparison_version", list(idata)))
    return model_comparison.compare(idata), pointwise.rename({"draw": "comparison_draw", "cycle": "load_cycle"})


def study_bank(path: str | None, settings: Settings, hyps: Mapping[str, hypotheses.Hypothesis], values: Mapping[str, float],
               sampling: model.Sampling, coarse: Mapping[str, np.ndarray] | None = None,
               members_at: Mapping[str, float] | None = None) -> xr.Dataset:
    """The study's bank (:mod:`newdyn.bank`) at the rig ``values`` and record ``sampling``: the file at ``path`` (made
    by the workflow's bank rule) when it was made for them, else built here on the coarse grid runs ``coarse``
    (simulated when not given); with ``members_at`` other than ``values``, the members there instead (a record's own
    angles, load phase and running speed: the fits find the load's phase from the members' best)."""
    at_condition = members_at is None or dict(members_at) == dict(values)
    bank = _condition_bank(path, settings, hyps, values, sampling, coarse, members=at_condition)
    if at_condition:
        return bank
    return bank_module.with_members(bank, hyps, list(settings.fault_ranges), members_at, sampling,
                                    settings.channels, settings.max_step)


def _condition_bank(path, settings: Settings, hyps, values, sampling, coarse, members: bool) -> xr.Dataset:
    """The study's bank at the condition ``values`` from ``path`` where it was made for them, else built here (its
    ``members`` only where they are wanted at that condition)."""
    entries = signature_module.entries(hyps, list(settings.grids), settings.drift_sizes, settings.fault_ranges, settings.severities, values)
    instruments = settings.instruments(sampling.fs)  # the datasheets; the library's noise is white
    spec = bank_module.spec(hyps, entries, list(settings.fault_ranges), values, sampling, settings.channels, settings.grids,
                            settings.priors, instruments, settings.max_step)
    if path is not None:
        with xr.open_dataset(path, engine="netcdf4") as bank:
            if bank.attrs.get("key") == bank_module.key(spec):
                return bank.load()
        log.info("%s was made for another condition or settings: the bank is built here", path)
    if coarse is None:
        coarse = {p: calibration.simulate_grid(values, p, g.axis, sampling, settings.channels, settings.max_step) for p, g in settings.grids.items()}
    return bank_module.build(hyps, entries, list(settings.fault_ranges) if members else [], values, sampling, settings.channels,
                             settings.grids, settings.priors, coarse, instruments, settings.max_step)


def _drift_fit(hypothesis: hypotheses.Hypothesis, cal: calibration.Calibration, instruments) -> hypotheses.Fit:
    """A drift of one parameter as a fit: its grid calibration (through ``instruments``), with the exact evidence by
    quadrature."""
    post = cal.posterior
    return hypotheses.Fit(hypothesis, {hypothesis.effect: post.map}, cal.best_fit, float(np.max(post.log_likelihood)),
                          cal.chi2_red, _grid_evidence(post), len(post.grid), () if post.consistent() else (hypothesis.effect,),
                          instruments=instruments)


def _effect_posterior(fit: hypotheses.Fit, data, sigma, values, sampling, channels, settings: Settings, unneeded: str | None,
                      polishing: bool = False):
    """The posterior of a fault model's parameters (InferenceData) from its fit's Laplace approximation, by quadrature or
    importance sampling (:mod:`newdyn.posterior`), converged where that is verified (else the caller samples it by
    MCMC, :func:`_sample_effect`, where the verdict may rest on the fault).  Where it cannot (``unneeded`` says why,
    :func:`_unneeded`), one batch of importance sampling: how much of the fault the data leave room for.  Where the
    caller is ``polishing`` the fit (:func:`_polished`), a batch that is not enough and holds a draw that beats the fit
    by :data:`POLISH_MARGIN` ends the sampling: the caller fits again from there and samples about the new fit."""
    hypothesis = fit.hypothesis
    log_likelihood = _log_likelihood(fit, data, sigma, values, sampling, channels, settings.max_step)
    attrs = {"hypothesis": hypothesis.name, "support": _support(hypothesis)}
    observed = _observed(data, channels, sampling)
    refit_below = fit.log_likelihood + POLISH_MARGIN if polishing else None
    if PHASE in hypothesis.parameters and fit.covariance is not None and len(hypothesis.parameters) > 1:
        # The load's phase integrated out at each point: a fault of two values stays on the quadrature.
        names, profiled = alignment.phase_profiled(hypothesis, fit.theta, fit.covariance, data, sigma, channels, sampling,
                                                   settings.max_step, values, fit.instruments)
        own = [hypothesis.parameters.index(name) for name in names]
        phase_index, phase = hypothesis.parameters.index(PHASE), fit.values[PHASE]

        def log_prior(rows):  # the phase's prior is flat: its density enters as at the fit's phase
            return hypothesis.log_prior(np.insert(rows, phase_index, phase, axis=1))

        posterior = posterior_module.sample(profiled, log_prior, names, fit.theta[own], fit.covariance[np.ix_(own, own)],
                                            settings.posterior, observed=observed, attrs={**attrs, "integrated": PHASE},
                                            verify=unneeded is None, nuisance=[PHASE], refit_below=refit_below)
    else:
        posterior = posterior_module.sample(log_likelihood, hypothesis.log_prior, hypothesis.parameters, fit.theta, fit.covariance,
                                            settings.posterior, observed=observed, attrs=attrs, verify=unneeded is None,
                                            refit_below=refit_below)
    if not posterior.attrs["converged"] and unneeded is not None:
        # No verdict rests on the fault: the unverified answer shows how much of it the data leave room for, and
        # sampling it further would change nothing.
        posterior.attrs["reason"] = f"{unneeded}; {posterior.attrs['reason']}"
    return posterior


def _log_likelihood(fit: hypotheses.Fit, data, sigma, values, sampling, channels, max_step):
    """The log-likelihood of rows of ``fit``'s hypothesis's parameters, through its instruments; −inf where a
    simulation fails."""
    def log_likelihood(rows):
        ll = likelihood.log_likelihood(data, hypotheses.evaluate(fit.hypothesis, rows, values, sampling, channels, max_step), sigma,
                                       instruments=fit.instruments)
        return np.where(np.isnan(ll), -np.inf, ll)

    return log_likelihood


def _observed(data, channels, sampling) -> dict:
    return {"y": xr.DataArray(data, dims=("channel", "time"), coords={"channel": list(channels), "time": sampling.times})}


def _support(hypothesis: hypotheses.Hypothesis) -> dict:
    return {p.name: [p.low, p.high] for p in hypothesis.priors}


# A posterior draw that beats the fit by more than this log-likelihood shows least squares stopped short of the
# optimum; below it the draws merely scatter about the optimum it found.
POLISH_MARGIN = 1.0


def _beaten(fit: hypotheses.Fit, posterior) -> bool:
    """Whether a draw of ``posterior`` beats ``fit`` by more than :data:`POLISH_MARGIN`."""
    return float(posterior.sample_stats["log_likelihood"].max()) > fit.log_likelihood + POLISH_MARGIN


def _polished(fit: hypotheses.Fit, posterior, data, sigma, values, sampling, channels, settings: Settings, instruments) -> hypotheses.Fit:
    """``fit`` again (through the datasheets' ``instruments``) from the posterior's best draw where that beats it by
    more than :data:`POLISH_MARGIN`: stick-slip's misfit has narrow valleys the least squares may miss."""
    if not _beaten(fit, posterior):
        return fit
    hypothesis = fit.hypothesis
    best = _best_draw(posterior, hypothesis.parameters)
    return _better(fit, hypotheses.fit(hypothesis, data, sigma, values, sampling, channels, [dict(zip(hypothesis.parameters, best))],
                                       settings.max_step, search=False, instruments=instruments), data, sigma, settings)


def _in_best_basin(fit: hypotheses.Fit, data, sigma, values, sampling, channels, settings: Settings, instruments) -> hypotheses.Fit:
    """``fit``, or its hypothesis's best fit in a neighbouring basin (through the datasheets' ``instruments``,
    :func:`newdyn.hypotheses.in_neighbouring_basins`) where that fits better; found from where ``fit``'s search
    ended, it keeps the search's name."""
    neighbour = hypotheses.in_neighbouring_basins(fit, data, sigma, values, sampling, channels, settings.max_step, instruments)
    return fit if neighbour is None else _better(fit, replace(neighbour, search=fit.search), data, sigma, settings)


def _better(fit: hypotheses.Fit, refit: hypotheses.Fit, data, sigma, settings: Settings) -> hypotheses.Fit:
    """``refit``, its instruments checked, where it fits better than ``fit``; else ``fit``."""
    checked = instrument_checks.checked(refit, data, sigma, settings.evidence_margin)
    return checked if checked.log_likelihood > fit.log_likelihood else fit


def _explains(fit: hypotheses.Fit, calibrations, chi2_max: float) -> bool:
    """Whether a fit brings χ² to the noise, a drift's with a consistent grid posterior (one peak)."""
    consistent = fit.hypothesis.kind != PARAMETER_CHANGE or calibrations[fit.hypothesis.effect].posterior.consistent()
    return fit.chi2_red <= chi2_max and consistent


def _read_through(fits, verdict: Mapping, discovery: verify.Discovered | None, chi2_max: float) -> hypotheses.Fit:
    """The model whose instruments the verdict reports: the final model, or the discovered term's fit where it explains
    what the library does not.  A library fit that came nearer the data only through probes far out of their spec (a
    bearing stiffness pulled toward a line, both probes' gains with it) says nothing about the probes."""
    if verdict["verdict"] == "unexplained" and discovery is not None and discovery.fit is not None and discovery.fit.chi2_red <= chi2_max:
        return discovery.fit
    return fits[verdict["models"]["after"]]


def _unneeded(fit: hypotheses.Fit, ahead: str | None, chi2_max: float) -> str | None:
    """Why no verdict rests on a fault's posterior, which then takes one batch of importance sampling: what explains
    the data ``ahead`` of it (:func:`_explaining_ahead`), or its fit leaving χ² above the noise, where the verdict is
    ``unexplained`` whatever its posterior; None where the verdict may rest on it."""
    if ahead is not None:
        return f"{ahead} explains the data with more evidence"
    if fit.chi2_red > chi2_max:
        return f"its fit leaves reduced chi2 {fit.chi2_red:.4g} above {chi2_max:g}, so no verdict rests on it"
    return None


def _explaining_ahead(fits, calibrations, fault: str, chi2_max: float, discovered: hypotheses.Fit | None = None) -> str | None:
    """What explains the data with more evidence than ``fault``'s fit, so that the verdict does not rest on its
    MCMC: the best hypothesis without a fault (healthy or a drift) that does, else — when no fit of the library
    explains the data — the ``discovered`` term if it does, else None."""
    ahead = [name for name, fit in fits.items() if fit.hypothesis.verdict_class != "new_dynamics"
             and fit.log_evidence > fits[fault].log_evidence and _explains(fit, calibrations, chi2_max)]
    if ahead:
        return max(ahead, key=lambda name: fits[name].log_evidence)
    if (discovered is not None and discovered.chi2_red <= chi2_max and discovered.log_evidence > fits[fault].log_evidence
            and not any(_explains(fit, calibrations, chi2_max) for fit in fits.values())):
        return f"the discovered {discovered.hypothesis.effect}"
    return None


def _verdict(fits, calibrations, signatures, settings: Settings, values, sampling, data, sigma) -> dict:
    """The ranked hypotheses, the verdict, the hypotheses that explain the data equally and the model
    versions nominal → calibrated → + effect (see the module docstring for the rules)."""
    names = sorted(fits, key=lambda n: -fits[n].log_evidence)
    log_z = np.array([fits[n].log_evidence for n in names])
    confidence = np.exp(log_z - logsumexp(log_z))
    closest = signatures.mean("parameter")
    ranking = []
    for name, c in zip(names, confidence):
        mine = closest.where(signatures["hypothesis"] == name, drop=True)
        ranking.append({
            "hypothesis": name, "class": fits[name].hypothesis.verdict_class, "effect": fits[name].hypothesis.effect,
            "confidence": float(c), "log_evidence": fits[name].log_evidence, "chi2": fits[name].chi2_red,
            "explains": _explains(fits[name], calibrations, settings.chi2_max), "parameters": _fit_parameters(fits[name], calibrations),
            "at_bound": list(fits[name].at_bound), "search": fits[name].search,
            "hellinger": float(mine.min()), "closest_signature": str(mine["signature"].values[int(np.argmin(mine.values))]),
            "finding_log_bayes_factor": hypotheses.contribution(fits[name].hypothesis, fits[name].values, fits[name].model, values,
                                                                sampling, settings.channels, sigma, settings.max_step),
        })
        ranking[-1]["finding_visible"] = ranking[-1]["finding_log_bayes_factor"] > settings.evidence_margin
    # A finding the data cannot tell from the model without it is no finding: an effect fitted where it does not show
    # (a joint that never slips, a crack of depth zero) only ties with its own drift, and leaves the verdict to what is
    # ahead of it without it.
    top = next(row for row in ranking if row["class"] == HEALTHY or row["finding_visible"] or not row["explains"])
    if top["explains"]:
        verdict, effect = top["class"], top["effect"]
        equivalent = [r["effect"] for r in ranking if r["class"] == verdict and r["explains"]
                      and top["log_evidence"] - r["log_evidence"] <= settings.evidence_margin]
        after = top["hypothesis"]
    else:
        verdict, effect, equivalent = "unexplained", None, []
        after = min(fits, key=lambda n: fits[n].chi2_red)
    versions = {"nominal": HEALTHY, "calibrated": _best_of(fits, "parameter_change"), "effect": _best_of(fits, "new_dynamics"),
                "after": after}
    result = {
        "verdict": verdict, "effect": effect, "equivalent": [e for e in equivalent if e is not None],
        "ranking": ranking, "models": versions,
        "model_versions": [_version_row(label, fits[versions[key]], _shown(fits[versions[key]], data, sigma), data,
                                        settings.channels)
                           for key, label in (("nominal", "nominal"), ("calibrated", "calibrated"), ("effect", "+ effect"))],
        "chi2_before": fits[HEALTHY].chi2_red, "chi2_after": fits[after].chi2_red,
        "rmse_before": _rmse(data, _shown(fits[HEALTHY], data, sigma), settings.channels),
        "rmse_after": _rmse(data, _shown(fits[after], data, sigma), settings.channels),
        "parameters": _fit_parameters(fits[after], calibrations),
    }
    if len(result["equivalent"]) > 1:
        separating = _separating_channels([fits[n] for n in names if fits[n].hypothesis.effect in result["equivalent"]
                                           and fits[n].hypothesis.verdict_class == verdict], values, sampling, data, sigma, settings)
        result["separating_channels"] = separating
        best = separating[0] if separating else None
        result["identifiability"] = (
            f"{', '.join(result['equivalent'])} explain the data equally well through {', '.join(settings.channels)} "
            f"(log-evidence within {settings.evidence_margin:g} of the best, chi2 <= {settings.chi2_max:g}); "
            + (f"measuring {best['channel']} at the same SNR would separate them (expected log Bayes factor "
               f"{best['expected_log_bayes_factor']:.3g} between the closest pair)" if best and best['expected_log_bayes_factor'] > settings.evidence_margin
               else "no single added channel would separate them")
        )
    return result


def _best_of(fits, cls: str) -> str:
    """The hypothesis of class ``cls`` with the highest evidence."""
    return max((n for n in fits if fits[n].hypothesis.verdict_class == cls), key=lambda n: fits[n].log_evidence)


def _shown(fit: hypotheses.Fit, data, sigma) -> np.ndarray:
    """What the instruments most probably show of ``fit``'s outputs (its outputs with exact instruments): what
    the residuals, the error fall and the figures compare with the data."""
    return sensors_module.reading(data, fit.model, sigma, fit.instruments)


def _version_row(label: str, fit: hypotheses.Fit, shown, data, channels) -> dict:
    name = label if label == "nominal" else f"{label} ({fit.hypothesis.effect})"
    return {"name": name, "hypothesis": fit.hypothesis.name, "chi2": fit.chi2_red, "log_evidence": fit.log_evidence,
            "log_likelihood": fit.log_likelihood, "rmse": _rmse(data, shown, channels), "values": fit.values}


def _rmse(data, fit_model, channels) -> dict[str, float]:
    return dict(zip(channels, np.sqrt(np.mean((data - fit_model) ** 2, axis=-1)).tolist()))


def _fit_parameters(fit: hypotheses.Fit, calibrations) -> dict:
    """Each fitted parameter's MAP, mean, sd and 94 % interval: the grid posterior's for a drift, the
    Laplace approximation's for a fault model (its MCMC replaces it where the verdict names it)."""
    if fit.hypothesis.kind == PARAMETER_CHANGE:
        posterior = calibrations[fit.hypothesis.effect].posterior
        low, high = posterior.hdi()
        return {fit.hypothesis.effect: {"map": posterior.map, "mean": posterior.mean, "sd": posterior.sd,
                                        "hdi_low": low, "hdi_high": high, "method": "grid"}}
    return fit.laplace_parameters()


def _separating_channels(equivalent: Sequence[hypotheses.Fit], values, sampling, data, sigma, settings: Settings) -> list[dict]:
    """Unmeasured channels ranked by how well they would separate the closest pair of ``equivalent``
    fits: ½ Σ ((m_a − m_b)/σ)², the expected log Bayes factor, with σ at the measurement's SNR."""
    others = [c for c in model.CHANNELS if c not in settings.channels]
    if not others:
        return []
    outputs = [hypotheses.evaluate(f.hypothesis, f.theta[None], values, sampling, others, settings.max_step)[0] for f in equivalent]
    snr_db, noise_sd = noise.at_measured_snr(data, sigma, outputs[0])
    rows = []
    for i, channel in enumerate(others):
        pair = min(0.5 * np.sum(((a[i] - b[i]) / noise_sd[i]) ** 2)
                   for j, a in enumerate(outputs) for b in outputs[j + 1:])
        rows.append({"channel": channel, "expected_log_bayes_factor": float(pair), "snr_db": snr_db})
    return sorted(rows, key=lambda r: -r["expected_log_bayes_factor"])


def _missing_channels(missing: Sequence[str], verdict: Mapping, fits, values, sampling, data, sigma, settings: Settings) -> list[dict]:
    """What each channel of ``diagnosis.channels`` the recording lacks would have told: the expected log Bayes factor it
    would add, at the recording's SNR, between the hypotheses that explain the data equally (their closest pair), or,
    where the verdict stands alone, between its model and the best hypothesis of another class."""
    ranked = [r["hypothesis"] for r in verdict["ranking"]]
    top = verdict["models"]["after"]
    if len(verdict["equivalent"]) > 1:
        rivals = [n for n in ranked if fits[n].hypothesis.effect in verdict["equivalent"]]
    else:
        rivals = [top, next(n for n in ranked if n != top and fits[n].hypothesis.verdict_class != fits[top].hypothesis.verdict_class)]
    rows = {row["channel"]: row for row in _separating_channels([fits[n] for n in rivals], values, sampling, data, sigma, settings)}
    return [{**rows[c], "between": rivals, "equivalent": len(verdict["equivalent"]) > 1,
             "separates": rows[c]["expected_log_bayes_factor"] > settings.evidence_margin} for c in missing]


def _sample_effect(fit: hypotheses.Fit, data, sigma, values, sampling, channels, settings: Settings, why: str):
    """emcee posterior (InferenceData) of a fault model's parameters, started from its Laplace approximation, to
    convergence, up to ``max_rounds`` rounds."""
    from .sampling import MCMCSettings

    mcmc = MCMCSettings.from_config(settings.mcmc)
    hypothesis = fit.hypothesis
    # The drifted rig stiffnesses move in the joint calibration's coordinate (1/k): the fault and the
    # drift trade off along a ridge that is nearly straight there, as kT1 and kT3 do in the study.
    variables = [
        mcmc_calibration.Variable(p.name, p.low, p.high, p.log_pdf, p.draw,
                                  mcmc_calibration.JOINT_COORDINATE if p.name in settings.drift else "linear", mirrored=True)
        for p in hypothesis.priors
    ]
    rng = np.random.default_rng(mcmc.seed)
    low, high = np.array([[p.low, p.high] for p in hypothesis.priors]).T
    initial = mcmc_calibration.sampled_rows(variables, mcmc_calibration.draw_inside(
        lambda n: rng.multivariate_normal(fit.theta, fit.covariance, n), low, high, mcmc.n_walkers))
    idata = mcmc_calibration.sample_posterior(
        variables, _log_likelihood(fit, data, sigma, values, sampling, channels, settings.max_step), initial, mcmc, rng,
        _observed(data, channels, sampling),
        {"hypothesis": hypothesis.name, "start": "Laplace approximation at the least-squares fit", "support": _support(hypothesis), "why": why},
    )
    idata.attrs["method"] = "mcmc"
    return idata


def _best_draw(idata, names) -> np.ndarray:
    log_likelihood = idata.sample_stats["log_likelihood"].values
    chain, draw = np.unravel_index(np.argmax(log_likelihood), log_likelihood.shape)
    return np.array([float(idata.posterior[n].values[chain, draw]) for n in names])


def _posterior_parameters(idata, names) -> dict:
    import arviz as az

    best = _best_draw(idata, names)
    rows = {}
    for name, b in zip(names, best):
        draws = idata.posterior[name].values.ravel()
        low, high = az.hdi(draws, hdi_prob=likelihood.HDI_PROB)
        rows[name] = {"map": float(b), "mean": float(draws.mean()), "sd": float(draws.std(ddof=1)),
                      "hdi_low": float(low), "hdi_high": float(high), "method": idata.attrs["method"]}
    return rows


VERSION_COLUMNS = ("version", "hypothesis", "chi2_red", "log_evidence")


def write(diagnosis: Diagnosis, verdict_path, table_path, netcdf_path, posterior_path, discovery_folder, settings_json: str,
          code_hash: str) -> None:
    """Write the verdict (JSON), the model versions' errors (CSV: χ², log-evidence, RMSE per channel),
    the data, model versions, posteriors and signature distances (NetCDF), the effect model's posterior
    (ArviZ NetCDF), each file atomically, and the folder ``discovery_folder`` with the
    discovered term's effect file (empty when discovery did not run)."""
    from . import provenance, sampling

    effect_file.write(discovery_folder, diagnosis.discovery and diagnosis.discovery.effect_file)
    m = diagnosis.measurement
    stamp = provenance.attributes(code_hash)
    verdict = {"statement": diagnosis.verdict["statement"], "measurement": m.name, **diagnosis.verdict, "channels": list(diagnosis.channels),
               "settings": json.loads(settings_json), **stamp}
    io.write_json(verdict_path, verdict)
    rows = [{"version": row["name"], "hypothesis": row["hypothesis"], "chi2_red": row["chi2"], "log_evidence": row["log_evidence"],
             **{f"rmse_{c}": value for c, value in row["rmse"].items()}} for row in diagnosis.verdict["model_versions"]]
    io.write_csv(table_path, [*VERSION_COLUMNS, *(f"rmse_{c}" for c in diagnosis.channels)], rows)

    times = m.sampling.times
    ds = xr.Dataset(
        {
            "y": (("channel", "time"), diagnosis.data),
            "sigma": ("channel", diagnosis.sigma),
            "model": (("version", "channel", "time"), np.stack(list(diagnosis.versions.values()))),
            "hellinger": diagnosis.signatures,
        },
        coords={"channel": list(diagnosis.channels), "time": times, "version": list(diagnosis.versions),
                "hypothesis_of_version": ("version", [diagnosis.verdict["models"][v] for v in diagnosis.versions])},
        attrs={"title": f"newdyn diagnosis of {m.name}", "measurement": m.name, "verdict": diagnosis.verdict["verdict"],
               "load_freq": float(m.operating["load_freq"]), "fs": float(m.sampling.fs), "noise_source": diagnosis.noise_source,
               "settings": settings_json, **stamp},
    )
    for p, cal in diagnosis.calibrations.items():
        post = cal.posterior
        ds[f"posterior_{p}"] = (f"grid_{p}", post.density)
        ds[f"prior_{p}"] = (f"grid_{p}", post.prior_density)
        ds[f"scaled_likelihood_{p}"] = (f"grid_{p}", post.scaled_likelihood)
        ds = ds.assign_coords({f"grid_{p}": post.grid})
    if diagnosis.discovery is not None:
        ds = ds.merge(diagnosis.discovery.forces)
    if diagnosis.pointwise is not None:
        ds["pointwise_log_likelihood"] = diagnosis.pointwise.assign_attrs(
            long_name="log-likelihood of the data in one channel over one load cycle, at each version's posterior draws")
    io.write_netcdf(ds, netcdf_path)
    sampling.save(diagnosis.effect_posterior, posterior_path)
