"""The signature library: the posteriors each hypothesis would give at a range of severities (the paper's Step 1),
computed once per study and operating condition and compared with a measurement's by Hellinger distance (Step 3).

A signature is a hypothesis at one set of values (the healthy rig, each calibration parameter drifted by each of
``drift_sizes``, each effect at ``severities`` values of its severity), simulated noise-free and calibrated on each
calibration parameter's grid as a measurement is, through the instruments' datasheets.  The library keeps each
signature's log-likelihood per channel on its grid at a reference noise :data:`REFERENCE_SNR_DB` below each channel's
healthy signal.  A measurement whose noise is σ scales channel c's share by (σ_ref,c / σ_c)²: exact for exact
instruments and white noise, where the log-likelihood is −½ Σ (y − m)²/σ² but for a constant, and right to first
order in the instruments' spread otherwise.  Its refined points resolve a peak from about a fifth of σ_ref up, the
coarse grid one many times wider.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence

import numpy as np
import xarray as xr

from . import calibration, comparison, effects, hypotheses, likelihood, model, sensors, simulation, slots
from .hypotheses import HEALTHY, PARAMETER_CHANGE

REFERENCE_SNR_DB = 40.0  # the library's noise: this far below each channel's healthy signal (its std)
REFINE_POINTS = 21  # refined runs per likelihood maximum of a signature


def entries(hyps: Mapping[str, hypotheses.Hypothesis], parameters: Sequence[str], drift_sizes: Sequence[float],
            fault_ranges: Mapping[str, object], severities: int, values: Mapping[str, float]) -> list[tuple[str, dict[str, float]]]:
    """(hypothesis name, all its fitted values) of every signature: the healthy rig, each calibration
    parameter drifted by each of ``drift_sizes``, and each effect of ``fault_ranges`` at ``severities`` values
    of its severity (its first fitted parameter, in the effect's declaration order) across its range (cell
    centres), with its other parameters at their defaults (mid-range for one without a default) and
    the drift parameters at the rig's values."""
    found = [(HEALTHY, {})]
    for p in parameters:
        found += [(f"{PARAMETER_CHANGE}:{p}", {p: values[p] * (1 + size)}) for size in drift_sizes]
    for kind in fault_ranges:
        hypothesis = hyps[kind]
        effect = effects.active()[kind]
        severity = next((prior for prior in hypothesis.priors if prior.name in effect.parameter_names()), None)
        fixed = {prior.name: _default(effect, prior, values) for prior in hypothesis.priors if prior is not severity}
        if severity is None:  # nothing of the effect fitted: it has one signature, at its defaults
            found.append((kind, fixed))
            continue
        low, high = severity.low, severity.high
        found += [(kind, {severity.name: low + (i + 0.5) / severities * (high - low), **fixed}) for i in range(severities)]
    return found


def _default(effect: type[effects.Effect], prior: hypotheses.Prior, values: Mapping[str, float]) -> float:
    """A fitted parameter's value where a signature does not vary it: the effect's default (the middle
    of its range for a parameter without one), else the rig's value (a drift parameter)."""
    if prior.name not in effect.parameter_names():
        return float(values[prior.name])
    parameter = effect.parameter(prior.name)
    return parameter.default_value(values) if parameter.default is not None else 0.5 * (prior.low + prior.high)


def spec(hyps: Mapping[str, hypotheses.Hypothesis], signature_entries, values: Mapping[str, float], sampling: model.Sampling,
         channels: Sequence[str], grids: Mapping[str, calibration.GridSpec], priors: Mapping[str, calibration.NormalPrior],
         instruments: sensors.Instruments | None, max_step: float) -> dict:
    """What a library depends on, as plain data."""
    kinds = sorted({name for name, _ in signature_entries} & set(effects.active()))
    return {
        "values": dict(slots.complete(values)), "fs": sampling.fs, "t_first": sampling.t_first, "n_samples": sampling.n_samples,
        "steady": sampling.steady,
        "channels": list(channels), "grids": {p: [g.low, g.high, g.points] for p, g in grids.items()},
        "priors": {p: [prior.mean, prior.sd] for p, prior in priors.items()},
        "entries": sorted(json.dumps([name, v], sort_keys=True) for name, v in signature_entries),  # in any order
        "hypotheses": {name: [[p.name, p.low, p.high, p.mean, p.sd] for p in h.priors] for name, h in hyps.items()},
        "effects": {kind: effects.active()[kind].content_hash for kind in kinds},
        "datasheets": None if instruments is None else instruments.scale.tolist(),
        "max_step": max_step, "reference_snr_db": REFERENCE_SNR_DB, "refine_points": REFINE_POINTS,
    }


def build(hyps: Mapping[str, hypotheses.Hypothesis], signature_entries, values: Mapping[str, float], sampling: model.Sampling,
          channels: Sequence[str], grids: Mapping[str, calibration.GridSpec], priors: Mapping[str, calibration.NormalPrior],
          coarse: Mapping[str, np.ndarray], instruments: sensors.Instruments | None, max_step: float) -> xr.Dataset:
    """The library: each signature simulated noise-free and calibrated on every grid of ``grids`` (whose coarse
    model runs are ``coarse``) at the reference noise through ``instruments`` (the datasheets, white noise)."""
    clean = simulation.simulate_batch(
        np.vstack([hyps[name].parameter_rows(np.array([[v[p] for p in hyps[name].parameters]]), values)
                   for name, v in signature_entries]),
        sampling, channels, max_step,
    )
    sigma = np.std(clean[0], axis=-1) * 10 ** (-REFERENCE_SNR_DB / 20)  # the first signature is the healthy rig
    tasks = [calibration.Task(signal, spec_, priors[p], coarse[p]) for signal in clean for p, spec_ in grids.items()]
    found = iter(calibration.calibrate_many(tasks, sigma, values, sampling, channels, REFINE_POINTS, np.inf, max_step, instruments))
    calibrated = [{p: next(found) for p in grids} for _ in clean]
    points = max(len(c[p].posterior.grid) for c in calibrated for p in grids)
    grid = np.full((len(clean), len(grids), points), np.nan)
    per_channel = np.full((len(clean), len(grids), points, len(channels)), np.nan)
    for i, calibrations in enumerate(calibrated):
        for j, p in enumerate(grids):
            n = len(calibrations[p].posterior.grid)
            grid[i, j, :n] = calibrations[p].posterior.grid
            per_channel[i, j, :n] = calibrations[p].channel_log_likelihood
    return xr.Dataset(
        {"grid": (("signature", "parameter", "point"), grid),
         "log_likelihood": (("signature", "parameter", "point", "channel"), per_channel),
         "sigma_ref": ("channel", sigma)},
        coords={"signature": [" ".join([name] + [f"{k}={x:.4g}" for k, x in sorted(v.items())]) for name, v in signature_entries],
                "hypothesis": ("signature", [name for name, _ in signature_entries]),
                "values": ("signature", [json.dumps(v, sort_keys=True) for _, v in signature_entries]),
                "parameter": list(grids), "channel": list(channels)},
        attrs={"title": "newdyn signature library", "reference_snr_db": REFERENCE_SNR_DB},
    )


def distances(library: xr.Dataset, calibrations: Mapping[str, calibration.Calibration], sigma: np.ndarray,
              priors: Mapping[str, calibration.NormalPrior]) -> xr.DataArray:
    """Step 3: the Hellinger distance (signature, parameter) between each signature's posterior at the measurement's
    noise ``sigma`` (per channel, in the library's channel order) and the measurement's ``calibrations``."""
    scale = (library["sigma_ref"].values / np.asarray(sigma, dtype=float)) ** 2
    grids, per_channel = library["grid"].values, library["log_likelihood"].values
    found = np.empty(grids.shape[:2])
    for j, p in enumerate(library["parameter"].values.tolist()):
        mine = calibrations[p].posterior
        for i in range(grids.shape[0]):
            kept = np.isfinite(grids[i, j])
            grid = grids[i, j, kept]
            signature = likelihood.grid_posterior(grid, per_channel[i, j, kept] @ scale, priors[p].log_pdf(grid))
            found[i, j] = comparison.hellinger_densities(mine.grid, mine.density, signature.grid, signature.density)
    return xr.DataArray(
        found, dims=("signature", "parameter"),
        coords={name: library[name] for name in ("signature", "hypothesis", "values", "parameter")},
        attrs={"long_name": "Hellinger distance between the measurement's posterior and a noise-free signature's at its noise",
               "units": "1"},
    )
