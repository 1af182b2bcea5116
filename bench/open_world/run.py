"""The open-world blind test: measurements of effects that no library holds, diagnosed as a user's files.

The generator's effects live in ``bench/open_world/effects/`` (periodic torques and forces at free
frequencies, torques and forces at shaft orders, dry friction, a loose bearing where the library has
none); only this script loads them, the diagnosis never does.  Each case is drawn by the blind test's own
machinery (:func:`newdyn.hidden.draw_cases`, from the effects' ``hidden`` ranges) and written as a
measurement file with nothing of its truth: like every hidden case, with the imbalances' angles, the load's phase,
the first sample's model time and the running speed's offset from the nameplate drawn (its ``record``,
:func:`newdyn.hidden.draw_record`; each recording of a machine its own but the angles), its time stamps from 0 and
the nameplate speed; a line at an order is expected at the order of the running speed.

    python bench/open_world/run.py draw <study>/measurements <truth.json> [--cases 12] [--seed 2026]
    (cd <study> && snakemake --cores 2 results/diagnosis/open_01/verdict.json ...)
    python bench/open_world/run.py score <truth.json> <study>/results/diagnosis

Machines: each drawn line (a periodic or an order generator) recorded twice, at the default speed and at a drawn lower
one, as ``<study>/measurements/<machine>/{a,b}.nc``; a machine counts as found when its verdict's search across the
recordings names the generator's family with its whole order, or its frequency in both recordings (within 1 %).

    python bench/open_world/run.py draw-machines <study>/measurements <truth.json> [--cases 8] [--seed 2027]
    (cd <study> && snakemake --cores 2 results/diagnosis/owm_01/verdict.json ...)
    python bench/open_world/run.py score-machines <truth.json> <study>/results/diagnosis

A case counts as found when its verdict is ``unexplained`` and discovery's top candidate has the
generator's family and its frequency (within 1 %) or whole order; placement is right when the top
candidate acts where the generator does, or that place is among those that explain the data equally;
χ² after is the discovered effect's fit on the full simulator.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from newdyn import effects, hidden, model, slots

FOLDER = Path(__file__).resolve().parent / "effects"
SNR_DB = 40.0
SAMPLING = model.Sampling()  # the rate and length of every file (the start is each record's)
FREQUENCY_TOLERANCE = 0.01
CHI2_MAX = 1.1


def generators() -> dict[str, type[effects.Effect]]:
    names = sorted(path.stem for path in FOLDER.glob("ow_*.py"))
    active = effects.use(names, FOLDER)
    return {name: active[name] for name in names}


def draw(measurements: Path, truth_path: Path, cases: int, seed: int) -> None:
    found = generators()
    section = {"sets": {"open": {"cases": cases, "seed": seed, "classes": list(found)}}}
    drawn = hidden.draw_cases(section, "open", model.DEFAULTS, fs=SAMPLING.fs)
    base = slots.complete()
    for case in drawn:
        effect = found[case["class"]]
        truth = case["truth"]
        speed_hz = (base["speed_rpm"] + case["record"]["speed_offset_rpm"]) / 60.0  # running, not nameplate
        case["expected"] = {
            "term": effect.family, "acts_on": effect.acts_on,
            "frequency_hz": truth.get("frequency", math.floor(truth["order"] + 0.5) * speed_hz if "order" in truth else None),
            "order": math.floor(truth["order"] + 0.5) if "order" in truth else None,
        }
        hidden.write_case_measurement(case, base, SAMPLING, SNR_DB, measurements / f"{case['name']}.nc")
        print(case["name"], case["class"], json.dumps(case["truth"]))
    truth_path.write_text(json.dumps(drawn, indent=1) + "\n")


def _top(verdict: dict) -> dict | None:
    """The best candidate of a verdict's discovery, None when it has none."""
    return ((verdict.get("discovery") or {}).get("candidates") or [None])[0]


def _names_the_line(candidate, expected) -> bool:
    """Whether a candidate of a search has the expected family with its whole order or its frequency (within 1 %): one
    frequency for a single file, one per recording for a machine's search."""
    if candidate is None or candidate["term"] != expected["term"]:
        return False
    if expected["order"] is not None:
        return candidate["order"] == expected["order"]
    if expected["frequency_hz"] is None:
        return True
    return all(abs(f - e) <= FREQUENCY_TOLERANCE * e
               for f, e in zip(np.atleast_1d(candidate["frequency_hz"]), np.atleast_1d(expected["frequency_hz"])))


def score(truth_path: Path, diagnoses: Path) -> dict:
    rows = []
    for case in json.loads(truth_path.read_text()):
        verdict_path = diagnoses / case["name"] / "verdict.json"
        if not verdict_path.is_file():
            continue
        verdict = json.loads(verdict_path.read_text())
        expected = case["expected"]
        discovery = verdict.get("discovery") or {}
        top = _top(verdict)
        equivalent_places = {entry.rpartition(" on ")[2] for entry in discovery.get("equivalent", [])}
        fit = discovery.get("fit") or {}
        rows.append({
            "case": case["name"], "generator": case["class"], "truth": case["truth"], "expected": expected,
            "verdict": verdict["verdict"], "chi2_before": verdict["chi2_before"],
            "top": None if top is None else {k: top[k] for k in ("term", "acts_on", "frequency_hz", "order", "shape")},
            "right_family_and_frequency": verdict["verdict"] == "unexplained" and _names_the_line(top, expected),
            "right_place": top is not None and top["acts_on"] == expected["acts_on"],
            "place_among_equivalent": expected["acts_on"] in equivalent_places,
            "chi2_after": fit.get("chi2_after"), "chi2_after_ok": fit.get("chi2_after") is not None and fit["chi2_after"] <= CHI2_MAX,
        })
    share = {key: sum(r[key] for r in rows) / len(rows) if rows else math.nan
             for key in ("right_family_and_frequency", "right_place", "place_among_equivalent", "chi2_after_ok")}
    return {"cases": len(rows), "share": share, "rows": rows}


LINE_FAMILIES = ("order", "periodic")
SECOND_SPEED_RPM = (1000.0, 1350.0)  # the second recording's speed, drawn; the first at the default 1480 rpm
RECORDINGS = ("a", "b")


def draw_machines(measurements: Path, truth_path: Path, cases: int, seed: int) -> None:
    found = {name: effect for name, effect in generators().items() if effect.family in LINE_FAMILIES}
    section = {"sets": {"open_machines": {"cases": cases, "seed": seed, "classes": list(found)}}}
    drawn = hidden.draw_cases(section, "open_machines", model.DEFAULTS, fs=SAMPLING.fs)
    base = slots.complete()
    rng = np.random.default_rng([seed, 1])
    machines = []
    for index, case in enumerate(drawn):
        name = f"owm_{index + 1:02d}"
        speeds = (base["speed_rpm"], model.PARAMETER_BY_NAME["speed_rpm"].rounded(rng.uniform(*SECOND_SPEED_RPM)))
        records = [hidden.draw_record(seed, index, SAMPLING.fs, k) for k in range(len(RECORDINGS))]
        case = {**case, "name": name, "record": {n: case["record"][n] for n in model.IMBALANCE_ANGLES}, "recordings": [
            {"name": recording, "condition": {"speed_rpm": speed}, "channels": list(model.CHANNELS),
             "noise_seed": int(rng.integers(0, 2**31 - 1)), "record": record}
            for recording, speed, record in zip(RECORDINGS, speeds, records)]}
        truth = case["truth"]
        order = math.floor(truth["order"] + 0.5) if "order" in truth else None
        running = [speed + record["speed_offset_rpm"] for speed, record in zip(speeds, records)]
        case["expected"] = {"term": found[case["class"]].family, "acts_on": found[case["class"]].acts_on, "order": order,
                            "frequency_hz": [truth["frequency"] if order is None else order * rpm / 60.0 for rpm in running]}
        (measurements / name).mkdir(parents=True, exist_ok=True)
        for recording in RECORDINGS:
            hidden.write_recording_measurement(case, recording, base, SAMPLING, SNR_DB, measurements / name / f"{recording}.nc")
        print(name, case["class"], json.dumps(truth), speeds)
        machines.append(case)
    truth_path.write_text(json.dumps(machines, indent=1) + "\n")


def score_machines(truth_path: Path, diagnoses: Path) -> dict:
    rows = []
    for case in json.loads(truth_path.read_text()):
        path = diagnoses / case["name"] / "verdict.json"
        if not path.is_file():
            continue
        verdict, expected = json.loads(path.read_text()), case["expected"]
        top = _top(verdict)
        alone = []
        for i, recording in enumerate(RECORDINGS):
            own = json.loads((diagnoses / case["name"] / recording / "verdict.json").read_text())
            alone.append(_names_the_line(_top(own), {**expected, "frequency_hz": expected["frequency_hz"][i]}))
        rows.append({"machine": case["name"], "generator": case["class"], "expected": expected, "verdict": verdict["verdict"],
                     "top": None if top is None else {k: top[k] for k in ("term", "acts_on", "shape", "frequency_hz", "log_bayes_factor")},
                     "runner_up": [(c["term"], round(top["log_evidence"] - c["log_evidence"], 1))
                                   for c in (verdict.get("discovery") or {}).get("candidates", [])[1:2]],
                     "found": verdict["verdict"] == "unexplained" and _names_the_line(top, expected),
                     "found_alone": alone})
    share = {"machines": sum(r["found"] for r in rows) / len(rows) if rows else math.nan,
             "recordings_alone": (sum(sum(r["found_alone"]) for r in rows) / sum(len(r["found_alone"]) for r in rows)
                                  if rows else math.nan)}
    return {"cases": len(rows), "share": share, "rows": rows}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    for command, cases, seed in (("draw", 12, 2026), ("draw-machines", 8, 2027)):
        p = commands.add_parser(command)
        p.add_argument("measurements", type=Path)
        p.add_argument("truth", type=Path)
        p.add_argument("--cases", type=int, default=cases)
        p.add_argument("--seed", type=int, default=seed)
    for command in ("score", "score-machines"):
        p = commands.add_parser(command)
        p.add_argument("truth", type=Path)
        p.add_argument("diagnoses", type=Path)
    args = parser.parse_args(argv)
    if args.command == "draw":
        args.measurements.mkdir(parents=True, exist_ok=True)
        draw(args.measurements, args.truth, args.cases, args.seed)
    elif args.command == "draw-machines":
        draw_machines(args.measurements, args.truth, args.cases, args.seed)
    elif args.command == "score-machines":
        result = score_machines(args.truth, args.diagnoses)
        for row in result["rows"]:
            print(json.dumps(row))
        print(json.dumps({"cases": result["cases"], "share": result["share"]}))
    else:
        result = score(args.truth, args.diagnoses)
        for row in result["rows"]:
            print(json.dumps({k: row[k] for k in ("case", "generator", "expected", "top", "right_family_and_frequency",
                                                  "right_place", "place_among_equivalent", "chi2_before", "chi2_after")}))
        print(json.dumps({"cases": result["cases"], "share": result["share"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
