"""The instruments a fit's data most probably went through: a fit, or a fit to several recordings, seen through the
instrument errors far outside their datasheet's spec (:func:`newdyn.sensors.check`), and what the verdict reports of
them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from . import hypotheses, likelihood, model, sensors
from .settings import Settings


def checked(fit: hypotheses.Fit, data, sigma, margin: float) -> hypotheses.Fit:
    """``fit`` seen through the instruments the data most probably went through: each instrument error that
    :func:`newdyn.sensors.check` finds out of its spec gets the wide prior, and the likelihood, χ² and evidence
    follow — the evidence less ``margin`` per such instrument, the prior odds that one is out of its spec."""
    if fit.instruments is None:
        return fit
    found = sensors.check(data, fit.model, sigma, fit.instruments, margin)
    if not found.out_of_spec:
        return fit
    return replace(fit, instruments=found.instruments, log_likelihood=fit.log_likelihood + found.gain,
                   log_evidence=fit.log_evidence + found.log_evidence_change,
                   chi2_red=float(likelihood.reduced_chi2(data, fit.model, sigma, n_fitted=len(fit.values), instruments=found.instruments)))


def report(fit: hypotheses.Fit, data, sigma, instruments: sensors.Instruments, channels, margin: float) -> dict:
    """verdict.json's ``sensors`` (each instrument error under the final model ``fit``), ``sensor_problems`` (those
    out of their datasheet's spec, in words) and ``instruments_took`` (the final model's χ² with exact
    instruments and through the ones it was seen through)."""
    found = sensors.check(data, fit.model, sigma, instruments, margin)
    summary = sensors.summary(data, fit.model, sigma, found.instruments, channels, likelihood.HDI_PROB)
    problems = []
    for c, q, log_bayes_factor in found.out_of_spec:
        channel, quantity = channels[c], sensors.QUANTITIES[q]
        entry = summary[channel][quantity]
        entry.update(out_of_spec=True, log_bayes_factor=log_bayes_factor)
        problems.append({"channel": channel, "quantity": quantity, "value": entry["mean"], "hdi": entry["hdi"],
                         "datasheet_sd": float(instruments.sd[c, q]), "log_bayes_factor": log_bayes_factor,
                         "statement": sensors.in_words(channel, quantity, entry["mean"], model.CHANNEL_UNITS[channel])})
    took = {"chi2_exact": float(likelihood.reduced_chi2(data, fit.model, sigma, len(fit.values), instruments=instruments.exact)),
            "chi2": fit.chi2_red}
    return {"sensors": summary, "sensor_problems": problems, "instruments_took": took}


def alternatives(fits, after: str, data, sigma, instruments: sensors.Instruments, channels, settings: Settings) -> list[dict]:
    """The fits through an instrument out of its spec that explain the data (χ² ≤ ``chi2_max``) as well as the
    verdict's fit ``after`` but for the prior odds against a bad instrument: within ``evidence_margin`` of its
    evidence once those odds are given back.  A probe's gain and a bearing's stiffness, say, can scale a
    displacement alike; the data cannot choose, only the odds did.  None when ``after`` itself reads through an
    instrument out of its spec: a fit through that instrument then only adds parameters to the verdict's account."""
    if widened(fits[after], instruments):
        return []
    best, rows = fits[after].log_evidence, []
    for name, fit in fits.items():
        out_of_spec = widened(fit, instruments)
        if name == after or not out_of_spec or fit.chi2_red > settings.chi2_max:
            continue
        if fit.log_evidence + settings.evidence_margin * out_of_spec >= best - settings.evidence_margin:
            problems = report(fit, data, sigma, instruments, channels, settings.evidence_margin)["sensor_problems"]
            rows.append({"hypothesis": name, "log_evidence": fit.log_evidence, "chi2": fit.chi2_red, "sensor_problems": problems})
    return sorted(rows, key=lambda row: -row["log_evidence"])


def out_of_spec(used: sensors.Instruments, datasheets: sensors.Instruments, channels: Sequence[str]) -> list[str]:
    """The instrument errors whose priors ``used`` widened beyond the ``datasheets``, as "b1_x gain"."""
    return [f"{channels[c]} {sensors.QUANTITIES[q]}" for c, q in np.argwhere(used.scale != datasheets.scale)]


def widened(fit: hypotheses.Fit, instruments: sensors.Instruments) -> int:
    """How many of a fit's instrument priors were widened beyond the datasheets ``instruments``."""
    return 0 if fit.instruments is None else int(np.sum(fit.instruments.scale != instruments.scale))


def joint_checked(fit: hypotheses.JointFit, seen: Sequence[hypotheses.Recording], margin: float) -> hypotheses.JointFit:
    """``fit`` with each recording seen through the instruments it most probably went through, as a recording's own
    diagnosis sees each of its fits (:func:`checked`): an instrument error far out of its datasheet's spec
    gets the wide prior, the evidence less ``margin`` for each.  The joint evidence and the sum of the recordings' own
    then count alike, and a hypothesis without parameters has a log Bayes factor of exactly 0 between them."""
    checks = [None if r.instruments is None else sensors.check(r.data, m, r.sigma, r.instruments, margin)
              for r, m in zip(seen, fit.models)]
    if not any(c is not None and c.out_of_spec for c in checks):
        return fit
    k = len(fit.hypothesis.priors)
    instruments = tuple(r.instruments if c is None else c.instruments for r, c in zip(seen, checks))
    return replace(
        fit, instruments=instruments,
        log_likelihood=fit.log_likelihood + sum(c.gain for c in checks if c is not None),
        log_evidence=fit.log_evidence + sum(c.log_evidence_change for c in checks if c is not None),
        chi2_red=tuple(float(likelihood.reduced_chi2(r.data, m, r.sigma, n_fitted=k, instruments=i))
                       for r, m, i in zip(seen, fit.models, instruments)),
    )
