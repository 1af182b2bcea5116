"""Discovery inside a diagnosis: search the residual of the model it starts from (healthy or a drift,
:func:`search_base`), fit the leading candidates on the full simulator, and say what was found — the verdict's
``discovery`` section and the best candidate's effect file.

The linearized ranking of a term that depends on the motion is first order only (a strong dry friction across
the coupling ranked behind a line at its resonance, and behind itself across the motor shaft), so the best
:data:`FULL_FIT_PLACES` places of each of the best :data:`FULL_FIT_TERMS` terms whose linearized log Bayes
factor is at least :data:`FULL_FIT_SHARE` of the best's are fitted on the full simulator with the drift
parameters, and ranked by that fit's Laplace evidence, as the library's hypotheses are.
"""

from __future__ import annotations

import contextlib
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import xarray as xr

from .. import cache, effects, hypotheses, io, kernels, model, noise, sensors, simulation, slots
from . import effect_file, force, search
from .forms import FORMS, Shape

if TYPE_CHECKING:
    from ..settings import Settings

FULL_FIT_TERMS = 2
FULL_FIT_PLACES = 2
FULL_FIT_SHARE = 0.5


@dataclass(frozen=True)
class Discovered:
    """What discovery found in a measurement."""

    section: dict  # the verdict's discovery section
    forces: xr.Dataset  # the force estimated at each place
    effect_file: tuple[str, str] | None = None  # (name, content) of the best candidate's found effect file
    fit: hypotheses.Fit | None = None  # the best candidate fitted on the full simulator
    kernel_files: tuple[Path, ...] = ()  # the generic effect files that fit ran beside, its own among them: its kernel

    @contextlib.contextmanager
    def as_fitted(self):
        """The best candidate's generic effect active inside a with-block, beside the files it was fitted with and no
        other, so that its simulations (on values :func:`newdyn.slots.without_effects`) run in the kernel its fit
        compiled."""
        with effects.alone(self.kernel_files):
            yield


def searched_from(hypothesis: hypotheses.Hypothesis, drift: Sequence[str], explains: bool) -> bool:
    """Whether the search for a missing term may linearize about ``hypothesis``'s fit: healthy, a drift of parameters
    that the found term's full fit fits jointly (``drift``), so that the search ranks terms on the very model the full
    fit adds them to, or a drift that ``explains`` the data (the search, run on request, then looks beyond it).  A
    calibration of any other parameter that does not explain the data may have absorbed part of the term (a bearing
    stiffness moved toward a line, the probes' gains pulled out of spec with it), and the residual it leaves is then
    the term less what it absorbed."""
    return hypothesis.kind == hypotheses.HEALTHY or (
        hypothesis.kind == hypotheses.PARAMETER_CHANGE and (explains or set(hypothesis.parameters) <= set(drift)))


def search_base(fits: Mapping[str, hypotheses.Fit], drift: Sequence[str], explaining: Collection[str] = ()) -> hypotheses.Fit:
    """The fit the search for a missing term starts from: of those it may linearize about (:func:`searched_from`; the
    fits named in ``explaining`` explain the data), the one with the most evidence."""
    return max((fit for name, fit in fits.items() if searched_from(fit.hypothesis, drift, name in explaining)),
               key=lambda fit: fit.log_evidence)


def discover(name: str, origin: hypotheses.Fit, data, sigma, values, sampling, settings: Settings) -> Discovered:
    """The discovery section of the verdict, the force estimated at each place and, where the search found a candidate,
    the best one's effect file and its fit on the full simulator: the search starts from the fit ``origin``
    (:func:`search_base`)."""
    base = {**values, **origin.values}
    residual, design = sensors.linearized(data, origin.model, sigma, _datasheets(origin, settings, sampling))
    found = search.discover(residual, sigma, base, sampling, settings.channels, settings.max_step, force.Nuisance.of(design, sigma))
    top = search.log_bayes_factor(found.candidates[0], found) if found.candidates else 0.0
    leading = [c for c in found.candidates if search.log_bayes_factor(c, found) >= FULL_FIT_SHARE * top]
    terms = list(dict.fromkeys(c.term for c in leading))[:FULL_FIT_TERMS]
    tried = [c for term in terms for c in [c for c in leading if c.term == term][:FULL_FIT_PLACES]]
    full, kernel_files = _full_fits(tried, data, sigma, values, origin, sampling, settings)
    ranked = sorted(tried, key=lambda c: -full[id(c)].log_evidence) + [c for c in found.candidates if id(c) not in full]

    def row(c):
        summary = {**c.summary(), "log_bayes_factor": search.log_bayes_factor(c, found)}
        if id(c) in full:
            fit = full[id(c)]
            summary.update(chi2_after=fit.chi2_red, log_evidence=fit.log_evidence, method="full simulator",
                           parameters=merged(c.parameters, fit.laplace_parameters()))
        return summary

    equal = _equivalent(found, {(c.term, c.acts_on): full[id(c)].log_evidence for c in tried}, settings.evidence_margin)
    section = {"from": origin.hypothesis.name, "peaks_hz": list(found.record.peaks.frequencies), "chi2_before": found.chi2_before,
               "candidates": [row(c) for c in ranked],
               "equivalent": [f"{term} on {place}" for term, place in equal],
               "equivalent_margin": settings.evidence_margin,
               "places": {p: {"log_bayes_factor": f.log_bayes_factor, "chi2_after": f.chi2_after}
                          for p, f in sorted(found.forces.items(), key=lambda item: -item[1].log_bayes_factor)}}
    others = [c for c in model.CHANNELS if c not in settings.channels]
    separable = [c for c in found.candidates if (c.term, c.acts_on) in equal]  # those whose fitted force is at hand
    if len(separable) > 1 and others:
        # σ of each unmeasured channel at the measurement's SNR, as for the library's equivalent hypotheses.
        noise_sd = noise.at_measured_snr(data, sigma, simulation.simulate(base, sampling, others, settings.max_step))[1]
        section["separating_channels"] = search.separating_channels(separable, found, dict(zip(others, noise_sd.tolist())))
    forces = _force_dataset(found)
    if not ranked:
        return Discovered(section, forces)
    best, fit = ranked[0], full[id(ranked[0])]
    refit = replace(best, parameters=merged(best.parameters, fit.laplace_parameters()))
    effect_name, content = effect_file.render(refit, name)
    section["effect_file"] = f"{effect_name}.py"
    section["fit"] = {"effect": effect_name, "chi2_after": fit.chi2_red, "log_evidence": fit.log_evidence,
                      "explains": fit.chi2_red <= settings.chi2_max, "parameters": fit.laplace_parameters()}
    return Discovered(section, forces, (effect_name, content), fit, tuple(kernel_files[id(best)]))


def _equivalent(found: search.Discovery, fitted: Mapping[tuple[str, str], float], margin: float) -> list[tuple[str, str]]:
    """(term, place) of what explains the data as well as the best: the full fits within ``margin`` of the best's
    evidence, and the best's form at the places scored only on the linearized model within ``margin`` of the best's
    score there (the linearization's error is much the same for one form at two places; it is not across forms)."""
    if not fitted:
        return []
    best = max(fitted, key=fitted.get)
    full = [pair for pair, log_evidence in sorted(fitted.items(), key=lambda item: -item[1]) if fitted[best] - log_evidence <= margin]
    return full + [pair for pair in search.equivalent(found, margin, to=best) if pair not in fitted and pair[0] == best[0]]


def in_words(section: Mapping, before: float) -> str:
    """What discovery found, in words: the best candidate, and whether its fit on the full simulator explains the data."""
    best = section["candidates"][0]
    values = ", ".join(f"{name} {row['value']:.4g} {row['unit']}".rstrip(" -") for name, row in best["parameters"].items())
    article = "an" if best["term"][0] in "aeiou" else "a"
    found = f"discovered: {article} {best['term']} term on {best['acts_on']} ({best['shape']}; {values})"
    fit = section.get("fit")
    if fit is None:
        return found
    return (f"{found} {'explains' if fit['explains'] else 'does not explain'} the data: reduced chi2 {before:.3g} -> "
            f"{fit['chi2_after']:.3g} on the full model (effect file {section['effect_file']})")


def generic_path(effect_name: str) -> Path:
    """Where a form's generic effect file lives: beside the compiled kernels, which it shares across studies."""
    return cache.folder() / "discovery" / f"{effect_name}.py"


def _force_dataset(found: search.Discovery) -> xr.Dataset:
    """The force estimated at each place (posterior mean and sd at the pulses' centres) and the imbalance
    disks' angles there, for the figures."""
    places = list(found.forces)
    times = found.forces[places[0]].times
    at = np.rint(times * found.record.linear.fs).astype(int)
    return xr.Dataset(
        {"force_mean": (("place", "pulse_time"), np.stack([found.forces[p].mean for p in places])),
         "force_sd": (("place", "pulse_time"), np.stack([found.forces[p].sd for p in places])),
         "force_log_bayes_factor": ("place", [found.forces[p].log_bayes_factor for p in places]),
         "theta1_at_pulse": ("pulse_time", found.record.trajectory.theta["1"][at]),
         "theta4_at_pulse": ("pulse_time", found.record.trajectory.theta["4"][at])},
        coords={"place": places, "pulse_time": times},
    )


def _full_fits(candidates: Sequence[search.Candidate], data, sigma, values, origin: hypotheses.Fit, sampling,
               settings: Settings) -> tuple[dict[int, hypotheses.Fit], dict[int, list[Path]]]:
    """Each candidate's :func:`_full_fit` and the generic effect files it ran beside (its own among them), by ``id``.
    A fit runs in a kernel of generic files alone, no library effect in it (the fit starts from healthy or a drift).
    One whose kernel (its form's generic file) is compiled already runs in it; the others share one kernel that holds
    all their files, each absent from the others' fits (an absent effect adds nothing, so the numbers are the same):
    one compile, not one per candidate."""
    files = {id(c): _generic_file(c.term, c.acts_on, c.shape) for c in candidates}
    fresh = sorted((c for c in candidates if not _compiled(files[id(c)])), key=lambda c: files[id(c)].name)
    together = fresh if len(fresh) > 1 else []
    group = [files[id(c)] for c in together]
    rig = slots.without_effects(values)  # healthy or a drift: no library effect takes part, nor is compiled in
    fits = {}
    if together:
        with effects.alone(group) as loaded:
            for c, effect in zip(together, loaded):
                fits[id(c)] = _full_fit(c, effect, data, sigma, rig, origin, sampling, settings)
    for c in candidates:
        if id(c) not in fits:
            with effects.alone([files[id(c)]]) as (effect,):
                fits[id(c)] = _full_fit(c, effect, data, sigma, rig, origin, sampling, settings)
    return fits, {id(c): group if files[id(c)] in group else [files[id(c)]] for c in candidates}


def _compiled(path: Path) -> bool:
    """Whether the kernel of the effect file ``path`` alone is compiled already."""
    with effects.alone([path]):
        return kernels.is_compiled(effects.active())


def _full_fit(candidate: search.Candidate, effect: type[effects.Effect], data, sigma, values, origin: hypotheses.Fit,
              sampling, settings: Settings) -> hypotheses.Fit:
    """``candidate`` (``effect``, its form's generic effect file, active) and the drift parameters fitted on the full
    simulator, within :func:`newdyn.discovery.effect_file.prior_range` of its linearized fit."""
    ranges = {effect.name: {key: effect_file.prior_range(key, row)[:2] for key, row in candidate.parameters.items()}}
    hypothesis = hypotheses.library(settings.calibration_priors(), ranges, settings.drift)[-1]
    found = {key: float(row["value"]) for key, row in candidate.parameters.items()}
    # From the drift the term was found beside, and from the drift's prior mean: a drift that absorbed part of the
    # term (kT1 pushed to its grid's edge by a friction across the coupling) can hold the fit in its basin.
    starts = [{**found, **origin.values}, found] if origin.values else [found]
    return hypotheses.fit(hypothesis, data, sigma, values, sampling, settings.channels, starts, settings.max_step, search=False,
                          instruments=_datasheets(origin, settings, sampling))


def fit_across(term: str, place: str, shape: Shape, parameters: Sequence[Mapping], recordings: Sequence[hypotheses.Recording],
               drifted: Mapping[str, float], settings: Settings) -> hypotheses.JointFit:
    """A term found across a machine's recordings (its form's generic effect file at ``place`` with ``shape``) and the
    drift parameters fitted to all ``recordings`` at once on the full simulator, from the search's ``parameters`` (one
    mapping per recording) and the ``drifted`` values.  One shape and drift for all; a phased form's amplitude and phase
    are each recording's own, as the search fitted them (separate recordings share no clock nor angle mark).  Each
    parameter's range covers what :func:`newdyn.discovery.effect_file.prior_range` gives around every recording's value."""
    own = [key for key in parameters[0] if FORMS[term].phased and key not in shape.values]
    recordings = [replace(r, base=slots.without_effects(r.base)) for r in recordings]
    with effects.alone([_generic_file(term, place, shape)]) as (effect,):
        ranges = {effect.name: {key: (min(effect_file.prior_range(key, row[key])[0] for row in parameters),
                                      max(effect_file.prior_range(key, row[key])[1] for row in parameters)) for key in parameters[0]}}
        hypothesis = hypotheses.library(settings.calibration_priors(), ranges, settings.drift)[-1]
        start = {p.name: p.mean if p.sd is not None else 0.5 * (p.low + p.high) for p in hypothesis.priors}  # a drift not fitted
        start.update(drifted)
        start.update({key: [float(row[key]["value"]) for row in parameters] if key in own else float(parameters[0][key]["value"])
                      for key in parameters[0]})
        return hypotheses.fit_joint(hypothesis, recordings, [start], settings.max_step, own)


def _generic_file(term: str, place: str, shape: Shape) -> Path:
    """The generic effect file of the form ``term`` at ``place`` (with ``shape``'s disk), written where it is not yet."""
    effect_name, content = effect_file.render_generic(term, place, shape)
    path = generic_path(effect_name)
    if not path.is_file() or path.read_text(encoding="utf-8") != content:
        io.atomic_write(path, lambda tmp: Path(tmp).write_text(content, encoding="utf-8"))
    return path


def _datasheets(origin: hypotheses.Fit, settings: Settings, sampling) -> sensors.Instruments | None:
    """The instruments as their datasheets say, with the noise colour the library's fits were whitened by."""
    return settings.instruments(sampling.fs, origin.instruments.colour if origin.instruments is not None else None)


def merged(linearized: Mapping, full: Mapping) -> dict:
    """The candidate's parameters with their full-simulator fit's values where it has them (units kept)."""
    return {key: ({**row, **{k: full[key][k] for k in ("mean", "sd", "hdi_low", "hdi_high")}, "value": full[key]["map"]}
                  if key in full else dict(row)) for key, row in linearized.items()}
