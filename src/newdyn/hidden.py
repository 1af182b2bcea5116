"""Blind test: hidden cases drawn from a seed, written without their truth, scored after diagnosis.

A hidden set is ``cases`` measurements drawn from ``seed``: healthy rigs, pure parameter changes of a
random rig parameter and size, and every active effect (:mod:`newdyn.effects`, or the configured
classes) at random parameter values, in equal shares.  :func:`draw_cases` draws them,
:func:`write_truth` puts the truth into the set's only file that holds it,
:func:`write_case_measurement` writes each case as a measurement file with nothing but the signal,
the operating condition and provenance (no scenario, fault, class, parameter value, record or noise
level), and :func:`score` compares the diagnoses' verdicts with the truth.

A set with ``instruments`` sees every case through imperfect instruments: each channel with a datasheet in
``diagnosis.sensors`` gets an offset, gain and delay drawn from that datasheet's Normal prior (from a stream of
its own, so the machines are those of the same set without instruments), and ``out_of_spec`` of its cases get
one instrument error on a compared channel :data:`OUT_OF_SPEC_SDS` datasheet sds off instead.

A set with ``recordings: [low, high]`` is a set of machines: each case is a machine with that many recordings (drawn
in the range), each at an operating condition drawn uniformly in the config's ``operating_range``, on a non-empty
subset of the compared channels, with its own noise; redrawn until the machine's finding shows in one of them at
least (the nominal model's reduced χ² there ≥ :data:`VISIBLE_CHI2`), since a finding no recording shows is no one's
to find.  Each recording is a measurement ``<machine>/r<k>``; the machine's verdict is scored like a case's, and
beside it each recording's own verdict, as if it had been diagnosed alone (:func:`score_recordings`).

Every case also draws what a real machine leaves open (:func:`draw_record`, from a stream of its own, so that every
other draw is what it would be without it): the imbalances' angles ``phi1`` and ``phi4`` (the machine's, shared by a
machine's recordings) and, for each recording, the load pulsation's phase ``load_phase``, the model time ``start`` of
its first sample (on the sampling grid) and the running speed's offset ``speed_offset_rpm`` from the nameplate.  The
file's time stamps start at 0 and its ``speed_rpm`` states the nameplate: a generator that shares the model's clock,
phases and speed would prove nothing about a diagnosis that has to find them.  The truth holds them as the case's
(and each recording's) ``record``; no verdict is scored on them.

An effect's draw ranges default to its parameters' ``hidden`` ranges (:attr:`Parameter.draw_range`,
in its file, with how they were measured; ``hidden.faults`` in the config overrides them): each
range's weak end still leaves a reduced-χ² excess the best drift of one rig parameter cannot remove.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence

import numpy as np

from . import effects, faults, io, model, noise, provenance, sensors, simulation, slots, turns
from .hidden_sets import case_names, recording_names
from .verdicts import HEALTHY, NEW_DYNAMICS, PARAMETER_CHANGE, SENSOR_PROBLEM, UNEXPLAINED, VERDICTS

OUT_OF_SPEC_SDS = (10.0, 30.0)  # an out-of-spec instrument error, in its datasheet's sds (either sign)
MAX_DRAWS = 1000  # tries per case before a range is declared to admit no valid draw
CHI2_MAX = 1.1  # a fault's fit explains the data when its reduced χ² is at most this
VISIBLE_CHI2 = 2.0  # a hidden machine's finding lifts the nominal model's reduced χ² to this in one recording at least
# What a real machine leaves open, drawn for every case (draw_record): angles uniform in ANGLE_RANGE [rad] — the
# imbalances' (a machine's) and the load pulsation's phase (a recording's) —, the model time of a recording's first
# sample in START_RANGE [s] on the sampling grid, and the running speed's offset from the nameplate [rpm].
RECORD_STREAM = 4  # the tag of a case's record stream: [seed, case index, RECORD_STREAM(, recording + 1)]
ANGLE_RANGE = (-math.pi, math.pi)
START_RANGE = (0.5, 1.5)
SPEED_OFFSET_RPM = (-5.0, 5.0)
RECORDING_ANGLES = tuple(n for n in model.ANGLE_PARAMETERS if n in model.RECORD_PARAMETERS)  # load_phase


def fault_classes() -> tuple[str, ...]:
    """The new-dynamics classes: every active effect (:func:`newdyn.effects.active`), at call time."""
    return tuple(effects.active())


def predicted_labels() -> tuple[str, ...]:
    """Every label a verdict can give a case: its classes, and unexplained."""
    return (*faults.classes(), UNEXPLAINED)


def default_ranges() -> dict[str, dict[str, tuple[float, float]]]:
    """Each active effect's blind-draw ranges, by kind and parameter (:attr:`Parameter.draw_range`)."""
    return {kind: {p.name: p.draw_range for p in effect.parameters} for kind, effect in effects.active().items()}


def __getattr__(name: str):
    """``FAULT_CLASSES``, ``CLASSES`` and ``PREDICTED_LABELS`` of the effects active now (a user's effect
    may be added after import, :func:`newdyn.effects.use`)."""
    derived = {"FAULT_CLASSES": fault_classes, "CLASSES": faults.classes, "PREDICTED_LABELS": predicted_labels}
    if name in derived:
        return derived[name]()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ----------------------------------------------------------------------------------------- drawing


def draw_cases(
    hidden: Mapping,
    set_name: str,
    base_values: Mapping[str, float],
    ranges: Mapping[str, Mapping[str, Sequence[float]]] | None = None,
    classes: Sequence[str] | None = None,
    datasheets: Mapping[str, Mapping[str, float]] | None = None,
    compared: Sequence[str] = (),
    fs: float = simulation.DEFAULT_SAMPLING.fs,
) -> list[dict]:
    """The cases of hidden set ``set_name``, deterministic from the set's seed.

    ``hidden`` is the config's ``hidden`` section (its ``sets`` and ``parameter_change`` are read);
    ``ranges`` (kind -> parameter -> [low, high]) the effects' draw ranges, :func:`newdyn.study.hidden_ranges`
    (default: :func:`default_ranges`); ``classes`` the classes of a set that names none of its own,
    :func:`newdyn.study.hidden_classes` (default: every class, :func:`newdyn.faults.classes`).

    With the set's ``instruments``, ``datasheets`` (channel -> ``offset_sd``, ``gain_sd``, ``delay_sd``: the
    config's ``diagnosis.sensors``) give each case's ``instruments`` and ``compared`` (the diagnosis channels) the
    channels an ``out_of_spec`` error may fall on.

    Each case is ``{"name": "<set>_01", "class", "scenario": {"overrides", "fault"?}, "truth",
    "noise_seed", "record"}`` (and ``instruments``, ``out_of_spec``); ``scenario`` goes to :func:`faults.scenario_values`, ``truth`` holds the drifted
    parameter and its value, or the effect's drawn parameters (every parameter of its range); ``record`` is
    :func:`draw_record`'s at sampling rate ``fs`` (of a machine set's case only the machine's angles).
    Classes (the set's own ``classes``, else ``classes``) come in equal shares (the remainder to
    classes picked by the seed), shuffled.  A draw that is not admissible on ``base_values`` is
    redrawn from the same stream.
    """
    if set_name not in hidden["sets"]:
        raise KeyError(f"no hidden set '{set_name}' (known: {', '.join(hidden['sets'])})")
    spec = hidden["sets"][set_name]
    n, seed = int(spec["cases"]), int(spec["seed"])
    ranges = default_ranges() if ranges is None else ranges
    chosen = list(spec.get("classes", faults.classes() if classes is None else classes))
    base = slots.complete(base_values)
    # One stream shuffles the classes, one per case draws it: a case's draw does not depend on how
    # often another case had to be redrawn.
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n + 1)]
    order = list(streams[0].permutation(chosen))
    labels = [str(c) for c in streams[0].permutation((order * (n // len(chosen) + 1))[:n])]
    cases = [
        {"name": name, "class": label, **_draw(label, hidden, ranges, base, rng), "noise_seed": int(rng.integers(0, 2**31 - 1))}
        for name, label, rng in zip(case_names(set_name, n), labels, streams[1:])
    ]
    if spec.get("instruments"):
        instrument_streams = [np.random.default_rng(s) for s in np.random.SeedSequence([seed, 1]).spawn(n + 1)]
        bad = set(instrument_streams[0].choice(n, int(spec.get("out_of_spec", 0)), replace=False).tolist())
        for i, (case, rng) in enumerate(zip(cases, instrument_streams[1:])):
            case.update(_draw_instruments(datasheets or {}, compared, rng, i in bad))
    for i, case in enumerate(cases):
        record = draw_record(seed, i, fs)
        case["record"] = {name: record[name] for name in model.IMBALANCE_ANGLES} if "recordings" in spec else record
    return cases


def draw_record(seed: int, case_index: int, fs: float, recording: int | None = None) -> dict[str, float]:
    """What a real machine leaves open, from the stream ``[seed, case_index, RECORD_STREAM]`` of its own: the case's
    :data:`newdyn.model.IMBALANCE_ANGLES` and its recording's :data:`RECORDING_ANGLES` (uniform in :data:`ANGLE_RANGE`), ``start`` (the
    model time of the first sample, uniform on the grid k/``fs`` in :data:`START_RANGE`) and ``speed_offset_rpm``
    (uniform in :data:`SPEED_OFFSET_RPM`); of a machine's ``recording`` (0, 1, …, stream tagged ``recording + 1``)
    only the recording's."""
    rng = np.random.default_rng([seed, case_index, RECORD_STREAM, *(() if recording is None else (recording + 1,))])
    names = RECORDING_ANGLES if recording is not None else model.IMBALANCE_ANGLES + RECORDING_ANGLES
    record = {name: float(rng.uniform(*ANGLE_RANGE)) for name in names}
    first, end = (math.ceil(t * fs - 1e-9) for t in START_RANGE)
    record["start"] = int(rng.integers(first, end)) / fs
    record["speed_offset_rpm"] = float(rng.uniform(*SPEED_OFFSET_RPM))
    return record


def _draw_instruments(datasheets: Mapping[str, Mapping[str, float]], compared: Sequence[str], rng: np.random.Generator,
                      out_of_spec: bool) -> dict:
    """One case's instrument errors: each from its datasheet's Normal prior; with ``out_of_spec`` one error on a
    ``compared`` channel :data:`OUT_OF_SPEC_SDS` datasheet sds off instead."""
    errors = {c: {q: sensors.NOMINAL[q] + float(rng.normal(0.0, sheet.get(f"{q}_sd", 0.0))) for q in sensors.QUANTITIES}
              for c, sheet in sorted(datasheets.items())}
    if not out_of_spec:
        return {"instruments": errors}
    candidates = [(c, q) for c in compared if c in datasheets for q in sensors.QUANTITIES if datasheets[c].get(f"{q}_sd", 0.0) > 0]
    if not candidates:
        raise ValueError("hidden out_of_spec: no compared channel has an instrument error with a datasheet (diagnosis.sensors)")
    channel, quantity = candidates[int(rng.integers(len(candidates)))]
    sds = float(rng.uniform(*OUT_OF_SPEC_SDS)) * (1.0 if rng.random() < 0.5 else -1.0)
    errors[channel][quantity] = sensors.NOMINAL[quantity] + sds * datasheets[channel][f"{quantity}_sd"]
    return {"instruments": errors, "out_of_spec": {"channel": channel, "quantity": quantity, "sds": sds}}


def _draw(label: str, hidden: Mapping, ranges: Mapping[str, Mapping[str, Sequence[float]]], base: Mapping[str, float],
          rng: np.random.Generator) -> dict:
    """Scenario and truth of one case of class ``label``, redrawn until admissible."""
    if label == HEALTHY:
        return {"scenario": {"overrides": {}}, "truth": {}}
    if label != PARAMETER_CHANGE and label not in ranges:
        known = ", ".join(ranges)
        raise ValueError(f"hidden {label}: no draw ranges for this class (ranges given for: {known or 'none'})")
    problems: list = []
    for _ in range(MAX_DRAWS):
        if label == PARAMETER_CHANGE:
            drift = hidden["parameter_change"]
            name = str(rng.choice(drift["parameters"]))
            relative = float(rng.uniform(*drift["relative"])) * (1.0 if rng.random() < 0.5 else -1.0)
            value = base[name] * (1.0 + relative)
            problem = model.PARAMETER_BY_NAME[name].problem(value)
            problems = [(name, problem)] if problem else []
            if not problems:
                return {"scenario": {"overrides": {}, "fault": {"kind": PARAMETER_CHANGE, "parameters": {name: value}}},
                        "truth": {name: value}}
        else:
            drawn = {name: float(rng.uniform(*ranges[label][name])) for name in sorted(ranges[label])}
            problems = faults.fault_problems(label, drawn, base)
            if not problems:
                return {"scenario": {"overrides": {}, "fault": {"kind": label, "parameters": drawn}}, "truth": drawn}
    raise ValueError(f"hidden {label}: no admissible draw in {MAX_DRAWS} tries, last problem: {problems[0]}")


def case_values(case: Mapping, base_values: Mapping[str, float]) -> dict[str, float]:
    """All model parameter values of a case."""
    return faults.scenario_values(case["scenario"], base_values)


def case_record(case: Mapping, recording: Mapping | None = None) -> dict[str, float]:
    """The record a case's file (or its machine's ``recording``'s) was simulated with."""
    return {**case["record"], **(recording["record"] if recording is not None else {})}


def recorded_values(case: Mapping, nameplate: Mapping[str, float], recording: Mapping | None = None) -> dict[str, float]:
    """All model values a case (or its machine's ``recording``) was simulated with: the case's at ``nameplate`` (the base
    values, with the recording's condition), with the record's angles and the running speed nameplate + offset."""
    record = case_record(case, recording)
    at = slots.complete({**nameplate, **(recording["condition"] if recording is not None else {})})
    at.update({name: record[name] for name in model.IMBALANCE_ANGLES + RECORDING_ANGLES})
    at["speed_rpm"] += record["speed_offset_rpm"]
    return case_values(case, at)


def _simulated_sampling(record: Mapping[str, float], sampling: model.Sampling) -> model.Sampling:
    """The model times of a record's samples: ``sampling``'s rate and length from the record's ``start``."""
    return model.Sampling(sampling.fs, record["start"], sampling.n_samples)


def _written_sampling(sampling: model.Sampling) -> model.Sampling:
    """A file's time stamps: the recorder's clock, from 0."""
    return model.Sampling(sampling.fs, 0.0, sampling.n_samples)


def _operating(values: Mapping[str, float], nameplate_rpm: float) -> dict[str, float]:
    """A file's operating condition: the simulated one, with the nameplate speed."""
    return {**{name: values[name] for name in model.OPERATING_PARAMETERS}, "speed_rpm": nameplate_rpm}


def draw_recordings(cases: Sequence[Mapping], set_name: str, spec: Mapping, operating_range: Mapping[str, Sequence[float]],
                    compared: Sequence[str], base_values: Mapping[str, float], sampling: model.Sampling, snr_db: float,
                    max_step: float = simulation.DEFAULT_MAX_STEP) -> list[dict]:
    """The cases of a machine set (``spec["recordings"]``), each with its ``recordings``: name, ``condition``,
    ``channels``, ``noise_seed`` and ``record`` (:func:`draw_record`, at ``sampling``'s rate); the conditions, channels
    and noise seeds redrawn from the machine's own stream until its finding shows in one of them."""
    names = recording_names(set_name, spec)
    seed = int(spec["seed"])
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence([seed, 3]).spawn(len(cases))]
    base = slots.complete(base_values)
    machines = []
    for i, (case, rng) in enumerate(zip(cases, streams)):
        case = {**case, "record": {name: case["record"][name] for name in model.IMBALANCE_ANGLES}}
        records = [draw_record(seed, i, sampling.fs, k) for k in range(len(names[case["name"]]))]
        for _ in range(MAX_DRAWS):
            recordings = [{**_draw_recording(name.split("/")[1], operating_range, compared, rng), "record": record}
                          for name, record in zip(names[case["name"]], records)]
            if case["class"] == HEALTHY or any(_visible(case, r, base, sampling, snr_db, max_step) for r in recordings):
                break
        else:
            raise ValueError(f"hidden {case['name']}: its finding shows in no recording of {MAX_DRAWS} draws of conditions")
        machines.append({**case, "recordings": recordings})
    return machines


def _draw_recording(name: str, operating_range: Mapping[str, Sequence[float]], compared: Sequence[str],
                    rng: np.random.Generator) -> dict:
    condition = {parameter: model.PARAMETER_BY_NAME[parameter].rounded(rng.uniform(low, high))
                 for parameter, (low, high) in sorted(operating_range.items())}
    channels = [c for c in compared if rng.random() < 0.5] or [str(rng.choice(list(compared)))]
    return {"name": name, "condition": condition, "channels": channels, "noise_seed": int(rng.integers(0, 2**31 - 1))}


def _visible(case: Mapping, recording: Mapping, base: Mapping[str, float], sampling: model.Sampling, snr_db: float,
             max_step: float) -> bool:
    """Whether the case's finding lifts the nominal model's reduced χ² to :data:`VISIBLE_CHI2` in ``recording`` (both
    with the recording's record)."""
    simulated = _simulated_sampling(case_record(case, recording), sampling)
    healthy = {**case, "scenario": {"overrides": {}}}
    truth, nominal = (simulation.simulate(recorded_values(c, base, recording), simulated, recording["channels"], max_step)
                      for c in (case, healthy))
    sigma = noise.noise_sigma(truth, snr_db)
    return 1.0 + float(np.mean(((truth - nominal) / sigma[:, None]) ** 2)) >= VISIBLE_CHI2


# ----------------------------------------------------------------------------------------- files


def write_truth(cases: Sequence[Mapping], path: str | os.PathLike, code_hash: str = "") -> None:
    """Write the cases with their truth (the only file that holds it) as JSON, atomically."""
    document = {"cases": list(cases), **provenance.attributes(code_hash)}
    io.write_json(path, document)


def read_truth(path: str | os.PathLike) -> list[dict]:
    """The cases written by :func:`write_truth`."""
    with open(path) as f:
        return json.load(f)["cases"]


def write_case_measurement(
    case: Mapping,
    base_values: Mapping[str, float],
    sampling: model.Sampling,
    snr_db: float,
    output: str | os.PathLike,
    code_hash: str = "",
    max_step: float = simulation.DEFAULT_MAX_STEP,
) -> None:
    """Simulate every channel of ``case`` with its record (:func:`recorded_values`, from its ``start`` at ``sampling``'s
    rate and length), add noise at ``snr_db`` from its noise seed, and write a measurement file that carries the signal
    (time stamps from 0), the operating condition (the nameplate speed) and provenance, nothing else: no scenario, class,
    parameter value, record or noise level (σ or SNR)."""
    values = recorded_values(case, base_values)
    simulated = _simulated_sampling(case_record(case), sampling)
    noisy, _ = noise.add_noise(_through_instruments(case, values, simulated, max_step), model.CHANNELS, snr_db, int(case["noise_seed"]))
    attrs = {"title": f"newdyn blind-test measurement {case['name']}", **provenance.attributes(code_hash)}
    operating = _operating(values, slots.complete(base_values)["speed_rpm"])
    io.write_netcdf(io.measurement_dataset(noisy, model.CHANNELS, _written_sampling(sampling), operating, attrs), output)


def write_recording_measurement(case: Mapping, recording: str, base_values: Mapping[str, float], sampling: model.Sampling,
                                snr_db: float, output: str | os.PathLike, code_hash: str = "",
                                max_step: float = simulation.DEFAULT_MAX_STEP) -> None:
    """One recording of a hidden machine as a measurement file: its channels at its condition with its noise, and
    nothing of the truth (as :func:`write_case_measurement`)."""
    drawn = next(r for r in case["recordings"] if r["name"] == recording)
    values = recorded_values(case, base_values, drawn)
    clean = simulation.simulate(values, _simulated_sampling(case_record(case, drawn), sampling), drawn["channels"], max_step)
    noisy, _ = noise.add_noise(clean, drawn["channels"], snr_db, int(drawn["noise_seed"]))
    attrs = {"title": f"newdyn blind-test recording {case['name']}/{recording}", **provenance.attributes(code_hash)}
    operating = _operating(values, slots.complete({**base_values, **drawn["condition"]})["speed_rpm"])
    io.write_netcdf(io.measurement_dataset(noisy, drawn["channels"], _written_sampling(sampling), operating, attrs), output)


def _through_instruments(case: Mapping, values: Mapping[str, float], sampling: model.Sampling, max_step: float) -> np.ndarray:
    """Every channel as the case's instruments read it, o + g·m(t − τ): the rig simulated at the times each
    delay shows (channels of one delay in one simulation); exact instruments read m."""
    errors = {c: case.get("instruments", {}).get(c, sensors.NOMINAL) for c in model.CHANNELS}
    reading = np.empty((len(model.CHANNELS), sampling.n_samples))
    for delay in sorted({e["delay"] for e in errors.values()}):
        rows = [i for i, c in enumerate(model.CHANNELS) if errors[c]["delay"] == delay]
        late = model.Sampling(sampling.fs, sampling.t_first - delay, sampling.n_samples)
        reading[rows] = simulation.simulate(values, late, [model.CHANNELS[i] for i in rows], max_step)
    offset, gain = (np.array([errors[c][q] for c in model.CHANNELS])[:, None] for q in ("offset", "gain"))
    return offset + gain * reading


# ----------------------------------------------------------------------------------------- scoring


def predicted_label(verdict: Mapping) -> str:
    """The class a verdict names: healthy (a sensor problem is a healthy machine), parameter_change, a fault
    kind, or unexplained."""
    kind = verdict.get("verdict")
    if kind in (HEALTHY, PARAMETER_CHANGE, UNEXPLAINED):
        return kind
    if kind == SENSOR_PROBLEM:
        return HEALTHY
    if kind == NEW_DYNAMICS:
        if verdict.get("effect") not in fault_classes():
            raise ValueError(f"verdict new_dynamics names no library fault kind (effect {verdict.get('effect')!r})")
        return verdict["effect"]
    raise ValueError(f"unknown verdict {kind!r} (known: {', '.join(VERDICTS)})")


def is_correct(case: Mapping, verdict: Mapping) -> bool:
    """Top-1 rule: the verdict names the case's class, and for a parameter change the drifted
    parameter or one the verdict declares equivalent (unidentifiable from the measured channels)."""
    label = predicted_label(verdict)
    if case["class"] != PARAMETER_CHANGE:
        return label == case["class"]
    named = {verdict.get("effect"), *(verdict.get("equivalent") or [])}
    return label == PARAMETER_CHANGE and _drifted(case) in named


def _drifted(case: Mapping) -> str:
    (name,) = case["truth"]
    return name


def score(cases: Sequence[Mapping], verdicts: Mapping[str, Mapping], chi2_max: float = CHI2_MAX) -> dict:
    """Score the verdicts (parsed ``verdict.json``, by case name) against the cases' truth.

    Returns the per-case ``rows``, the ``confusion`` matrix (truth class × predicted label), top-1
    ``accuracy`` overall and ``per_class``, the fitted-parameter errors of the correctly identified
    cases (``parameter_errors``: relative error of the posterior mean, truth inside the 94 % HDI),
    ``fault_fit``: how many correctly identified fault cases the fault's fit explains (χ²_red ≤ chi2_max) and
    ``instruments``: of the cases seen through instruments, how many out-of-spec errors the verdicts name
    (channel and quantity), how many only as an alternative that explains the data as well
    (``sensor_alternatives``), and how many instrument errors they name that were within spec.
    """
    missing = [case["name"] for case in cases if case["name"] not in verdicts]
    if missing:
        raise ValueError(f"no verdict for hidden case(s) {', '.join(missing)}: not diagnosed")
    labels = predicted_labels()
    truth_classes = [c for c in faults.classes() if any(case["class"] == c for case in cases)]
    counts = np.zeros((len(truth_classes), len(labels)), dtype=int)
    rows, errors = [], []
    for case in cases:
        verdict = verdicts[case["name"]]
        try:
            label = predicted_label(verdict)
        except ValueError as exc:
            raise ValueError(f"hidden case {case['name']}: {exc}") from None
        correct = is_correct(case, verdict)
        counts[truth_classes.index(case["class"]), labels.index(label)] += 1
        rows.append({
            "name": case["name"], "class": case["class"], "truth": dict(case["truth"]),
            "verdict": verdict["verdict"], "effect": verdict.get("effect"), "equivalent": list(verdict.get("equivalent") or []),
            "predicted": label, "correct": correct,
            "chi2_before": _worst(verdict.get("chi2_before")), "chi2_after": _worst(verdict.get("chi2_after")),
            "out_of_spec": _instrument(case["out_of_spec"]) if "out_of_spec" in case else None,
            "sensor_problems": [_instrument(p) for p in verdict.get("sensor_problems") or []],
            "sensor_alternatives": [_instrument(p) for a in verdict.get("sensor_alternatives") or [] for p in a["sensor_problems"]],
        })
        if correct:
            errors += _parameter_errors(case, verdict)
    per_class = {}
    for c in truth_classes:
        hits = [row["correct"] for row in rows if row["class"] == c]
        per_class[c] = {"cases": len(hits), "correct": sum(hits), "accuracy": sum(hits) / len(hits)}
    fault_rows = [row for row in rows if row["correct"] and row["class"] in fault_classes()]
    explained = sum(1 for row in fault_rows if row["chi2_after"] is not None and row["chi2_after"] <= chi2_max)
    covered = [e["in_hdi"] for e in errors if e["in_hdi"] is not None]
    n_correct = sum(row["correct"] for row in rows)
    seen = [row for row, case in zip(rows, cases) if "instruments" in case]
    bad = [row for row in seen if row["out_of_spec"]]
    return {
        "cases": len(rows),
        "correct": n_correct,
        "accuracy": n_correct / len(rows) if rows else None,
        "per_class": per_class,
        "confusion": {"truth": truth_classes, "predicted": list(labels), "counts": counts.tolist()},
        "rows": rows,
        "parameter_errors": errors,
        "hdi_coverage": sum(covered) / len(covered) if covered else None,
        "fault_fit": {"cases": len(fault_rows), "explained": explained, "chi2_max": chi2_max,
                      "fraction": explained / len(fault_rows) if fault_rows else None},
        "instruments": {"cases": len(seen), "out_of_spec": len(bad),
                        "named": sum(row["out_of_spec"] in row["sensor_problems"] for row in bad),
                        "named_as_alternative": sum(row["out_of_spec"] in row["sensor_alternatives"] for row in bad),
                        "false_alarms": sum(p != row["out_of_spec"] for row in seen for p in row["sensor_problems"])},
    }


def score_recordings(cases: Sequence[Mapping], verdicts: Mapping[str, Mapping]) -> dict:
    """How the recordings of a machine set fare diagnosed alone (``verdicts`` by ``<machine>/<recording>``), each
    scored against its machine's truth: what the machine's verdict is compared with."""
    rows = [{"recording": f"{case['name']}/{r['name']}", "class": case["class"],
             "predicted": predicted_label(verdicts[f"{case['name']}/{r['name']}"]),
             "correct": is_correct(case, verdicts[f"{case['name']}/{r['name']}"])}
            for case in cases for r in case["recordings"]]
    correct = sum(row["correct"] for row in rows)
    return {"recordings": len(rows), "correct": correct, "accuracy": correct / len(rows) if rows else None, "rows": rows}


def _worst(value) -> float | None:
    """A verdict's reduced χ²: a file's, or a machine's largest over its recordings."""
    return max((_float(v) for v in value), default=None) if isinstance(value, list) else _float(value)


def _instrument(entry: Mapping) -> str:
    """An instrument error as a score names it: "<channel> <quantity>"."""
    return f"{entry['channel']} {entry['quantity']}"


def _parameter_errors(case: Mapping, verdict: Mapping) -> list[dict]:
    """Fitted vs true value of each truth parameter the verdict's fit (or, for a parameter change,
    its ranking entry of the true parameter) estimated; truth parameters it did not fit are left out."""
    if not case["truth"]:  # healthy
        return []
    if case["class"] == PARAMETER_CHANGE:
        name = _drifted(case)
        entry = next((r for r in verdict.get("ranking") or [] if r.get("hypothesis") == f"{PARAMETER_CHANGE}:{name}"), None)
        fitted, source = (entry.get("parameters") or {}, f"ranking {PARAMETER_CHANGE}:{name}") if entry else (verdict.get("parameters") or {}, "verdict")
    else:  # the fit names the effect's parameters as the truth does
        fitted, source = verdict.get("parameters") or {}, "verdict"
    errors = []
    for name, truth in case["truth"].items():
        summary = fitted.get(name)
        if summary is None or _float(summary.get("mean")) is None:
            continue
        mean, low, high = _float(summary.get("mean")), _float(summary.get("hdi_low")), _float(summary.get("hdi_high"))
        angle = _is_shaft_angle(case["class"], name)
        if angle:
            found = turns.between(verdict.get("record") or {}, case["record"])
            if found is None:
                continue
            turn, turn_sd = found
            miss = mean - turn - truth
            turn -= model.wrap_angle(miss) - miss  # onto the truth's turn of the circle
            mean, low, high = (None if v is None else v - turn for v in (mean, low, high))
            sd = _float(summary.get("sd"))
            if low is not None and high is not None and sd:  # the interval widened by the turn's own error, in quadrature
                widen = math.hypot(1.0, turn_sd / sd)
                low, high = mean - widen * (mean - low), mean + widen * (high - mean)
        errors.append({
            "case": case["name"], "class": case["class"], "parameter": name, "truth": float(truth),
            "mean": mean, "sd": _float(summary.get("sd")), "hdi_low": low, "hdi_high": high,
            "relative_error": (mean - truth) / abs(truth) if truth != 0 and not angle else None,
            "in_hdi": None if low is None or high is None else bool(low <= truth <= high),
            "source": source,
        })
    return errors


def _is_shaft_angle(kind: str, name: str) -> bool:
    """Whether ``name`` is an effect's angle on a shaft (:func:`newdyn.effects.shaft_angle`)."""
    effect = effects.active().get(kind)
    return effect is not None and name in effect.shaft_angles()


def _float(value) -> float | None:
    """A number from a verdict, None when absent or not finite."""
    if value is None or isinstance(value, bool):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


CSV_COLUMNS = ("name", "class", "truth", "verdict", "effect", "equivalent", "predicted", "correct",
               "chi2_before", "chi2_after", "parameter_errors", "out_of_spec", "sensor_problems", "sensor_alternatives")


def write_score(result: Mapping, json_path: str | os.PathLike, csv_path: str | os.PathLike, code_hash: str = "") -> None:
    """Write the score as JSON (with provenance) and its per-case rows as CSV, each atomically."""
    io.write_json(json_path, {**result, **provenance.attributes(code_hash)})
    by_case: dict[str, list] = {}
    for e in result["parameter_errors"]:
        by_case.setdefault(e["case"], []).append(
            {k: e[k] for k in ("parameter", "truth", "mean", "relative_error", "in_hdi")})
    table = [
        {**row, "truth": json.dumps(row["truth"], sort_keys=True), "equivalent": ";".join(row["equivalent"]),
         "effect": row["effect"] or "", "chi2_before": _cell(row["chi2_before"]), "chi2_after": _cell(row["chi2_after"]),
         "parameter_errors": json.dumps(by_case.get(row["name"], [])), "out_of_spec": row["out_of_spec"] or "",
         "sensor_problems": ";".join(row["sensor_problems"]), "sensor_alternatives": ";".join(row["sensor_alternatives"])}
        for row in result["rows"]
    ]
    io.write_csv(csv_path, CSV_COLUMNS, table)


def _cell(value) -> str:
    return "" if value is None else repr(float(value))
