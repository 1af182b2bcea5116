"""Diagnose a machine from several recordings, each at its own operating condition, with its own channels, noise and
instruments: one verdict with the machine's parameters shared by all of them.

Each recording is first diagnosed alone (:func:`newdyn.diagnosis.diagnose`); its verdict gives its channels, noise and
each hypothesis's optimum and evidence.  Then every hypothesis is fitted to all recordings at once, one parameter set
for all (:func:`newdyn.hypotheses.fit_joint`, started from the recordings' optima, one start for those that agree,
:func:`joint_starts`), and the machine's verdict is the hypothesis of highest joint evidence whose fit brings every
recording's χ² to the noise.

Consistency across conditions, the paper's principle: a drifted parameter has one value under every condition, a
calibration that absorbs new dynamics lands on different values under different ones.  Both are measured: the
log Bayes factor of one parameter set for all recordings against a set of its own for each (joint evidence minus
the sum of the recordings' own evidences; it falls as the recordings' optima part), and the Hellinger distances
between the recordings' posteriors of each parameter, as the paper compares posteriors (their Normal approximations;
a posterior that one recording leaves wide is far from a narrow one even where they agree, which is why the
decision rests on the Bayes factor).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from . import (
    alignment,
    comparison,
    concurrency,
    hypotheses,
    instrument_checks,
    io,
    model,
    next_condition,
    noise,
    sensors,
    slots,
    turns,
)
from .discovery import effect_file, force, search, verify
from .hypotheses import HEALTHY
from .settings import Settings


@dataclass(frozen=True)
class MachineDiagnosis:
    """A machine's verdict and, where discovery fitted a term across its recordings, that term's found effect file."""

    verdict: dict
    effect_file: tuple[str, str] | None = None  # (name, content)


@dataclass(frozen=True)
class Diagnosed:
    """One recording of the machine and its own diagnosis's verdict."""

    measurement: io.Measurement
    verdict: Mapping


def recording(diagnosed: Diagnosed, settings: Settings, reference: Mapping | None = None) -> hypotheses.Recording:
    """A recording as the joint fits see it: on the channels, with the noise and where on the shaft's turn and the load's
    cycle (and at which speed) its own diagnosis found it, and how far its start turned the shaft from the ``reference``
    record's (a recording's ``record``, :func:`reference_record`; :func:`newdyn.turns.between`), with that turn's
    standard error: the machine's angles on a shaft are stated for the reference."""
    m, v = diagnosed.measurement, diagnosed.verdict
    channels = tuple(v["channels"])
    colour = noise.Colour.from_summary(v["noise"].get("colour", {}), channels)
    record = v.get("record", {})
    turn = None
    if reference and record and record is not reference:
        turn = turns.between(record, reference["values"], reference["sd"])
    return hypotheses.Recording(
        m.y[[m.channels.index(c) for c in channels]], np.array([v["noise"]["sigma"][c] for c in channels]),
        slots.complete({**settings.rig, **m.operating, **record.get("values", {})}), m.sampling, channels,
        replace(settings, channels=channels).instruments(m.sampling.fs, colour), *(turn or (0.0, 0.0)),
    )


def diagnose(name: str, recordings: Sequence[Diagnosed], settings: Settings) -> MachineDiagnosis:
    """The machine's verdict (see the module docstring) from its ``recordings``, each already diagnosed alone, and the
    effect file of the term discovery fitted across them (if any)."""
    reference = reference_record(recordings)
    seen = [recording(r, settings, reference) for r in recordings]
    hyps = {h.name: h for h in settings.hypotheses()}
    own = [{row["hypothesis"]: _turned_back(row, hyps[row["hypothesis"]], s.turn) for row in r.verdict["ranking"] if row["hypothesis"] in hyps}
           for r, s in zip(recordings, seen)]

    seen_by = {n: [_at_own_load_phase(s, rows[n]) for s, rows in zip(seen, own)] for n in hyps}
    # The joint fits take each recording's load phase from its own diagnosis, and with it the phase's integral: for
    # healthy and a drift, at the joint values, as each recording's own diagnosis integrated it at its own (an effect's
    # own fit found the phase beside its values; here it is held where that fit put it, at the phase's width there).
    def phase_terms(fit, mine):
        if fit.hypothesis.verdict_class == "new_dynamics":
            return sum(alignment.load_phase_integral(s.base, s.sigma, s.channels, s.sampling, settings.max_step, alignment.FIT_HALF_WIDTH)
                       for s in mine)
        return sum(alignment.load_phase_integral_at(s.base, fit.values, s.data, s.sigma, s.channels, s.sampling, settings.max_step,
                                                    s.instruments) for s in mine)

    def joint(hypothesis):
        starts = joint_starts([rows[hypothesis.name]["parameters"] for rows in own], hypothesis.parameters)
        mine = seen_by[hypothesis.name]
        fit = instrument_checks.joint_checked(hypotheses.fit_joint(hypothesis, mine, starts, settings.max_step), mine,
                                              settings.evidence_margin)
        return replace(fit, log_evidence=fit.log_evidence + phase_terms(fit, mine))

    fits = concurrency.in_parallel({n: lambda h=h: joint(h) for n, h in hyps.items()})
    ranking = sorted((_row(fits[n], [rows[n] for rows in own], seen_by[n], settings) for n in hyps), key=lambda row: -row["log_evidence"])
    # As for one recording (newdyn.diagnosis): a finding that shows in no recording is passed over for the model without it.
    top = next(row for row in ranking if row["class"] == HEALTHY or row["finding_visible"] or not row["explains"])
    if top["explains"]:
        verdict, effect = top["class"], top["effect"]
        equivalent = [r["effect"] for r in ranking if r["class"] == verdict and r["explains"]
                      and top["log_evidence"] - r["log_evidence"] <= settings.evidence_margin]
        after = top["hypothesis"]
    else:
        verdict, effect, equivalent = "unexplained", None, []
        after = min(ranking, key=lambda row: max(row["chi2"]))["hypothesis"]
    lines = _recording_lines(recordings, seen_by[after], fits, next(row for row in ranking if row["hypothesis"] == after), settings)
    discovery, found_file = (_discovery(name, recordings, ranking, fits, seen, settings) if settings.searches(verdict != "unexplained")
                             else (None, None))
    result = {
        "machine": name, "verdict": verdict, "effect": effect, "equivalent": [e for e in equivalent if e is not None],
        "parameters": fits[after].laplace_parameters(), "model": after,
        "chi2_before": [line["chi2_before"] for line in lines], "chi2_after": [line["chi2_after"] for line in lines],
        "consistency": {row["hypothesis"]: row["consistency"] for row in ranking},
        "recordings": lines, "ranking": ranking,
        "record_next": _record_next(ranking, fits, recordings, seen, reference, settings),
        **({"record": reference} if reference else {}),  # the turn the angles on a shaft are stated for
        **({"discovery": discovery} if discovery is not None else {}),
    }
    return MachineDiagnosis({"statement": statement(result, settings.chi2_max), **result}, found_file)


def reference_record(recordings: Sequence[Diagnosed]) -> Mapping | None:
    """The record whose turn a machine's angles on a shaft are stated for: of the recording whose imbalance angles hold
    its start best (:func:`newdyn.turns.precision`), the first of equals; None where no recording has one."""
    records = [r.verdict["record"] for r in recordings if r.verdict.get("record")]
    return max(records, key=turns.precision) if records else None


def _turned_back(row: Mapping, hypothesis: hypotheses.Hypothesis, turn: float) -> Mapping:
    """A recording's own ranking row of ``hypothesis`` with its angles on a shaft stated for the machine's reference
    record, whose start turned the shaft ``turn`` less than this one's (:meth:`newdyn.hypotheses.Hypothesis.turned`)."""
    names = [n for n in hypothesis.on_shaft() if n in row.get("parameters", {})]
    if not names or not turn:
        return row
    keys = ("map", "mean", "hdi_low", "hdi_high")
    parameters = dict(row["parameters"])
    for name in names:
        shift = model.wrap_angle(parameters[name]["map"] - turn) - parameters[name]["map"]
        parameters[name] = {**parameters[name], **{k: parameters[name][k] + shift for k in keys if k in parameters[name]}}
    return {**row, "parameters": parameters}


def _at_own_load_phase(seen: hypotheses.Recording, row: Mapping) -> hypotheses.Recording:
    """A recording at the load's phase its own fit of a hypothesis found (an effect's fit finds it beside its values,
    each recording its own: a fault that reshapes the torsional response moves the load's fundamental that placed it)."""
    found = row.get("parameters", {}).get("load_phase")
    return seen if found is None else replace(seen, base={**seen.base, "load_phase": float(found["map"])})


# Two recordings' optima of a parameter agree where they are this many standard deviations of their difference apart
# or fewer: two independent Normal estimates of one value lie farther apart one time in 370.
AGREEMENT_SDS = 3.0


def joint_starts(alone: Sequence[Mapping[str, Mapping]], names: Sequence[str]) -> list[dict[str, float]]:
    """Where a joint fit of the parameters ``names`` starts, from each recording's own posterior of them (``alone``, one
    mapping of name -> {"map", "sd"} per recording): recordings whose optima agree on every parameter (see
    :data:`AGREEMENT_SDS`) share one start, the optimum of the one that pins the parameters best (the least product of
    its sds), which the others' likelihoods hardly move; each group of agreeing recordings gives one.  A drift that is
    one value under every condition is then fitted from one start, a calibration that absorbs new dynamics, whose
    optima part, from each.  Not their precision-weighted mean: where a likelihood is not Normal (a joint that slips)
    that point can lie in no recording's basin."""
    groups: list[list[Mapping[str, Mapping]]] = []
    for rows in alone:
        group = next((g for g in groups if all(_agree(rows, other, names) for other in g)), None)
        if group is None:
            groups.append([rows])
        else:
            group.append(rows)
    narrowest = [min(group, key=lambda rows: math.prod(rows[n]["sd"] for n in names)) for group in groups]
    return [{n: float(rows[n]["map"]) for n in names} for rows in narrowest]


def _agree(a: Mapping[str, Mapping], b: Mapping[str, Mapping], names: Sequence[str]) -> bool:
    """Whether two recordings' optima agree on every parameter; an optimum without a finite positive width agrees with
    none."""
    def width(p):
        return p["sd"] if 0 < p["sd"] < np.inf else np.nan

    return all(abs(a[n]["map"] - b[n]["map"]) <= AGREEMENT_SDS * np.hypot(width(a[n]), width(b[n])) for n in names)


def _record_next(ranking: Sequence[Mapping], fits, recordings: Sequence[Diagnosed], seen: Sequence[hypotheses.Recording],
                 reference: Mapping | None, settings: Settings) -> dict | None:
    """Where other hypotheses explain every recording with evidences within the margin of the best: the operating
    conditions that would tell them from it (:mod:`newdyn.next_condition`), moved from the first recording's condition,
    on the configured channels at the recordings' median SNR, the imbalances at the ``reference`` record's angles (the
    turn the fits' angles on a shaft are stated for).  None where the best stands alone, explains nothing or no
    operating range is configured."""
    top = ranking[0]
    rivals = [row["hypothesis"] for row in ranking[1:]
              if row["explains"] and top["log_evidence"] - row["log_evidence"] <= settings.evidence_margin]
    if not (top["explains"] and rivals and settings.operating_range):
        return None
    snr_db = float(np.median([noise.at_measured_snr(s.data, s.sigma, s.data)[0] for s in seen]))
    angles = {n: reference["values"][n] for n in model.IMBALANCE_ANGLES if n in reference["values"]} if reference else {}
    return next_condition.rank(fits[top["hypothesis"]], [fits[n] for n in rivals], recordings[0].measurement.operating,
                               settings.operating_range, {**settings.rig, **angles}, seen[0].sampling, settings.channels, snr_db,
                               settings.max_step, settings.evidence_margin,
                               np.random.default_rng(int(settings.mcmc.get("seed", 0))))


def _discovery(name: str, recordings: Sequence[Diagnosed], ranking: Sequence[Mapping], fits, seen: Sequence[hypotheses.Recording],
               settings: Settings) -> tuple[dict, tuple[str, str] | None]:
    """One term of the catalogue behind every recording's residual (:func:`newdyn.discovery.search.discover_across`),
    from healthy or the drift the recordings' evidence favours among those the term's fit fits jointly
    (:func:`newdyn.discovery.verify.searched_from`), fitted to all of them: each form with one shape for all
    recordings, so that a line that moves with the speed is an order of a disk and one that stays a fixed frequency.
    Each term's best place, best first, what each recording alone would have said, and the best term added to the
    model: fitted to all recordings on the full simulator with that drift (:func:`newdyn.discovery.verify.fit_across`),
    each recording's reduced χ² before and after; and that term's found effect file (:func:`effect_file.render_across`)."""
    drift = next(row["hypothesis"] for row in ranking
                 if verify.searched_from(fits[row["hypothesis"]].hypothesis, settings.drift, row["explains"]))
    fit = fits[drift]
    records = []
    for i, s in enumerate(seen):
        instruments = fit.instruments[i] if fit.instruments else s.instruments
        residual, design = sensors.linearized(s.data, fit.models[i], s.sigma, instruments)
        records.append((residual, s.sigma, {**s.base, **fit.values}, s.sampling, s.channels, force.Nuisance.of(design, s.sigma)))
    across = search.discover_across(records, settings.max_step)
    best = {}
    for row in across.scores:  # each term's best place, best first
        best.setdefault(row["term"], row)
    top = across.scores[0]["log_evidence"] if across.scores else 0.0
    section = {"from": drift, "candidates": list(best.values()),
               "equivalent": [f"{row['term']} on {row['acts_on']}" for row in across.scores
                              if top - row["log_evidence"] <= settings.evidence_margin],
               "alone": [{"peaks_hz": list(found.record.peaks.frequencies), "equivalent_terms": _equal_terms(found, settings.evidence_margin)}
                         for found in across.alone]}
    if not across.scores:
        return section, None
    row = across.scores[0]
    found = instrument_checks.joint_checked(
        verify.fit_across(row["term"], row["acts_on"], across.shapes[0], row["parameters"], seen, fit.values, settings), seen,
        settings.evidence_margin)
    # Each recording's rows of the term, the full fit's values in place of the linearized ones.
    full = [verify.merged(linearized, {**found.laplace_parameters(), **own})
            for linearized, own in zip(row["parameters"], found.own_parameters() or [{}] * len(seen))]
    own_keys = [key for key in full[0] if found.own_values and key in found.own_values[0]]
    effect_name, content = effect_file.render_across(
        row["term"], row["acts_on"], across.shapes[0], {key: value for key, value in full[0].items() if key not in own_keys},
        [{key: rows[key] for key in own_keys} for rows in full], name, [r.measurement.name for r in recordings])
    section["effect_file"] = f"{effect_name}.py"
    section["fit"] = {"effect": found.hypothesis.name, "chi2_before": list(fit.chi2_red), "chi2_after": list(found.chi2_red),
                      "log_evidence": found.log_evidence, "log_bayes_factor": found.log_evidence - fit.log_evidence,
                      "explains": all(chi2 <= settings.chi2_max for chi2 in found.chi2_red),
                      "parameters": found.laplace_parameters(), "own_parameters": found.own_parameters()}
    return section, (effect_name, content)


def _equal_terms(found: search.Discovery, margin: float) -> list[str]:
    """The terms that explain one recording alone as well as its best one (within ``margin``), best first."""
    return list(dict.fromkeys(term for term, _ in search.equivalent(found, margin)))


def _row(fit: hypotheses.JointFit, alone: Sequence[Mapping], seen: Sequence[hypotheses.Recording], settings: Settings) -> dict:
    """A hypothesis's line in the machine's ranking: joint evidence and misfits, what it adds in each recording, and how
    consistent the recordings are."""
    separate = float(sum(row["log_evidence"] for row in alone))
    added = [_added(fit, i, s, settings) for i, s in enumerate(seen)]
    log_bayes_factor = fit.log_evidence - separate
    hellinger = {
        p: max((comparison.hellinger_gaussians(a["parameters"][p]["mean"], a["parameters"][p]["sd"],
                                               b["parameters"][p]["mean"], b["parameters"][p]["sd"])
                for a, b in itertools.combinations(alone, 2)), default=0.0)
        for p in fit.hypothesis.parameters
    }
    return {
        "hypothesis": fit.hypothesis.name, "class": fit.hypothesis.verdict_class, "effect": fit.hypothesis.effect,
        "log_evidence": fit.log_evidence, "chi2": list(fit.chi2_red),
        "explains": all(chi2 <= settings.chi2_max for chi2 in fit.chi2_red), "parameters": fit.laplace_parameters(),
        "at_bound": list(fit.at_bound), "finding_log_bayes_factor": added, "finding_visible": max(added) > settings.evidence_margin,
        "consistency": {"log_bayes_factor": log_bayes_factor, "separate_log_evidence": separate,
                        "consistent": log_bayes_factor > -settings.evidence_margin, "hellinger": hellinger,
                        "explains_each_alone": all(row["explains"] for row in alone)},
    }


def _recording_lines(recordings: Sequence[Diagnosed], seen: Sequence[hypotheses.Recording], fits, after: Mapping,
                     settings: Settings) -> list[dict]:
    """Per recording: its condition, channels, its own verdict, χ² before (nominal) and after (the machine's model, whose
    ranking row is ``after``), and whether the machine's finding is visible in it: the expected log Bayes factor of its
    contribution there."""
    found = fits[after["hypothesis"]]
    lines = []
    for i, (r, s) in enumerate(zip(recordings, seen)):
        contribution = after["finding_log_bayes_factor"][i]
        lines.append({
            "name": r.measurement.name, "condition": dict(r.measurement.operating), "channels": list(s.channels),
            "missing_channels": [row["channel"] for row in r.verdict.get("missing_channels", [])],
            "own_verdict": r.verdict["verdict"], "own_effect": r.verdict["effect"],
            "chi2_before": fits[HEALTHY].chi2_red[i], "chi2_after": found.chi2_red[i],
            "finding_log_bayes_factor": contribution, "finding_visible": contribution > settings.evidence_margin,
            "turn": found.turns[i] if found.turns else s.turn,
            "instruments_out_of_spec": instrument_checks.out_of_spec(found.instruments[i], s.instruments, s.channels)
            if found.instruments else [],
        })
    return lines


def _added(fit: hypotheses.JointFit, i: int, seen: hypotheses.Recording, settings: Settings) -> float:
    """What ``fit``'s hypothesis adds in recording ``i`` (:func:`newdyn.hypotheses.contribution`)."""
    return hypotheses.contribution(fit.hypothesis, fit.values, fit.models[i], seen.base, seen.sampling, seen.channels, seen.sigma,
                                   settings.max_step)


def statement(verdict: Mapping, chi2_max: float) -> str:
    """The machine's verdict in one sentence: what explains every recording with one parameter set, where it shows, and
    which hypotheses the recordings contradict."""
    lines = verdict["recordings"]
    differing = [k for k in model.OPERATING_PARAMETERS if len({line["condition"][k] for line in lines}) > 1]

    def condition(line):
        return ", ".join(f"{k} {line['condition'][k]:g}" for k in differing) or "the same condition"

    chi2 = ", ".join(f"{line['name']} {line['chi2_before']:.3g} -> {line['chi2_after']:.3g}" for line in lines)
    fitted = ", ".join(f"{n} = {p['mean']:.4g} (94 % HDI {p['hdi_low']:.4g} to {p['hdi_high']:.4g})"
                       for n, p in verdict["parameters"].items())
    kind = verdict["verdict"]
    if kind == "healthy":
        head = f"healthy: the nominal model explains all {len(lines)} recordings (reduced chi2 {chi2})"
    elif kind == "unexplained":
        head = (f"unexplained: no hypothesis explains all {len(lines)} recordings with one parameter set (reduced chi2 <= "
                f"{chi2_max:g}); the closest, {verdict['model']}, leaves {chi2}")
    else:
        name = "new dynamics" if kind == "new_dynamics" else "parameter change"
        shows = "; ".join(f"{'visible' if line['finding_visible'] else 'not visible'} in {line['name']} ({condition(line)})"
                          for line in lines)
        head = (f"{name}: {verdict['effect']} with {fitted}, one set for all {len(lines)} recordings, brings reduced chi2 "
                f"{chi2}; {shows}")
    # What the paper looks for: a hypothesis that explains each recording on its own, but with values that differ.
    contradicted = [h for h, c in verdict["consistency"].items() if c["explains_each_alone"] and not c["consistent"]]
    if contradicted:
        head += ("; each recording alone is explained by, but together they contradict, " + ", ".join(
            f"{h} (log Bayes factor {verdict['consistency'][h]['log_bayes_factor']:.3g} for one set against one per recording)"
            for h in contradicted))
    if verdict.get("discovery", {}).get("candidates"):
        head += "; " + _discovered(verdict["discovery"], [f"{line['name']} ({condition(line)})" for line in lines])
    if verdict.get("record_next"):
        head += "; " + next_condition.sentence(verdict["record_next"])
    return head


def _discovered(section: Mapping, recordings: Sequence[str]) -> str:
    """What the search across the recordings found, in words: the best term with its line in each recording, how far
    ahead of the next term it is, and whether a recording alone could have told them apart."""
    best, *others = section["candidates"]
    lines = ", ".join(f"{f:.4g} Hz in {name}" for f, name in zip(best["frequency_hz"], recordings) if f is not None)
    article = "an" if best["term"][0] in "aeiou" else "a"
    words = (f"searched across the recordings: {article} {best['term']} term on {best['acts_on']} ({best['shape']}"
             f"{': ' + lines if lines else ''}) explains them all with one shape (log Bayes factor "
             f"{best['log_bayes_factor']:.4g} against none)")
    if others:
        words += f", ahead of {others[0]['term']} by {best['log_evidence'] - others[0]['log_evidence']:.4g}"
        alone = [name for name, row in zip(recordings, section["alone"])
                 if {best["term"], others[0]["term"]} <= set(row["equivalent_terms"])]
        if alone:
            words += f", which {' and '.join(alone)} alone could not tell apart"
    if "fit" in section:
        fit = section["fit"]
        chi2 = ", ".join(f"{name} {before:.3g} -> {after:.3g}" for name, before, after in zip(recordings, fit["chi2_before"], fit["chi2_after"]))
        words += (f"; added to the model, it {'explains' if fit['explains'] else 'does not explain'} them (reduced chi2 {chi2}; "
                  f"effect file {section['effect_file']})")
    return words
