"""The open-world blind test: measurements of effects that no library holds, diagnosed as a user's files.

The generator's effects live in ``bench/open_world/effects/`` (periodic torques and forces at free
frequencies, torques and forces at shaft orders, dry friction, a loose bearing where the library has
none); only this script loads them, the diagnosis never does.  Each case is drawn by the blind test's own
machinery (:func:`newdyn.hidden.draw_cases`, from the effects' ``hidden`` ranges) and written as a
measurement file with nothing of its truth.

    python bench/open_world/run.py draw <study>/measurements <truth.json> [--cases 12] [--seed 2026]
    (cd <study> && snakemake --cores 2 results/diagnosis/open_01/verdict.json ...)
    python bench/open_world/run.py score <truth.json> <study>/results/diagnosis

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

from newdyn import effects, hidden, model, slots

FOLDER = Path(__file__).resolve().parent / "effects"
SNR_DB = 40.0
FREQUENCY_TOLERANCE = 0.01
CHI2_MAX = 1.1


def generators() -> dict[str, type[effects.Effect]]:
    names = sorted(path.stem for path in FOLDER.glob("ow_*.py"))
    active = effects.use(names, FOLDER)
    return {name: active[name] for name in names}


def draw(measurements: Path, truth_path: Path, cases: int, seed: int) -> None:
    found = generators()
    section = {"sets": {"open": {"cases": cases, "seed": seed, "classes": list(found)}}}
    drawn = hidden.draw_cases(section, "open", model.DEFAULTS)
    base = slots.complete()
    speed_hz = base["speed_rpm"] / 60.0
    for case in drawn:
        effect = found[case["class"]]
        truth = case["truth"]
        case["expected"] = {
            "term": effect.family, "acts_on": effect.acts_on,
            "frequency_hz": truth.get("frequency", math.floor(truth["order"] + 0.5) * speed_hz if "order" in truth else None),
            "order": math.floor(truth["order"] + 0.5) if "order" in truth else None,
        }
        hidden.write_case_measurement(case, base, model.Sampling(), SNR_DB, measurements / f"{case['name']}.nc")
        print(case["name"], case["class"], json.dumps(case["truth"]))
    truth_path.write_text(json.dumps(drawn, indent=1) + "\n")


def score(truth_path: Path, diagnoses: Path) -> dict:
    rows = []
    for case in json.loads(truth_path.read_text()):
        verdict_path = diagnoses / case["name"] / "verdict.json"
        if not verdict_path.is_file():
            continue
        verdict = json.loads(verdict_path.read_text())
        expected = case["expected"]
        discovery = verdict.get("discovery") or {}
        top = (discovery.get("candidates") or [None])[0]
        family = top is not None and top["term"] == expected["term"]
        if top is None or not family:
            located = False
        elif expected["order"] is not None:
            located = top["order"] == expected["order"]
        elif expected["frequency_hz"] is not None:
            located = abs(top["frequency_hz"] - expected["frequency_hz"]) <= FREQUENCY_TOLERANCE * expected["frequency_hz"]
        else:
            located = True
        equivalent_places = {entry.rpartition(" on ")[2] for entry in discovery.get("equivalent", [])}
        fit = discovery.get("fit") or {}
        rows.append({
            "case": case["name"], "generator": case["class"], "truth": case["truth"], "expected": expected,
            "verdict": verdict["verdict"], "chi2_before": verdict["chi2_before"],
            "top": None if top is None else {k: top[k] for k in ("term", "acts_on", "frequency_hz", "order", "shape")},
            "right_family_and_frequency": bool(family and located and verdict["verdict"] == "unexplained"),
            "right_place": top is not None and top["acts_on"] == expected["acts_on"],
            "place_among_equivalent": expected["acts_on"] in equivalent_places,
            "chi2_after": fit.get("chi2_after"), "chi2_after_ok": fit.get("chi2_after") is not None and fit["chi2_after"] <= CHI2_MAX,
        })
    share = {key: sum(r[key] for r in rows) / len(rows) if rows else math.nan
             for key in ("right_family_and_frequency", "right_place", "place_among_equivalent", "chi2_after_ok")}
    return {"cases": len(rows), "share": share, "rows": rows}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    p = commands.add_parser("draw")
    p.add_argument("measurements", type=Path)
    p.add_argument("truth", type=Path)
    p.add_argument("--cases", type=int, default=12)
    p.add_argument("--seed", type=int, default=2026)
    p = commands.add_parser("score")
    p.add_argument("truth", type=Path)
    p.add_argument("diagnoses", type=Path)
    args = parser.parse_args(argv)
    if args.command == "draw":
        args.measurements.mkdir(parents=True, exist_ok=True)
        draw(args.measurements, args.truth, args.cases, args.seed)
    else:
        result = score(args.truth, args.diagnoses)
        for row in result["rows"]:
            print(json.dumps({k: row[k] for k in ("case", "generator", "expected", "top", "right_family_and_frequency",
                                                  "right_place", "place_among_equivalent", "chi2_before", "chi2_after")}))
        print(json.dumps({"cases": result["cases"], "share": result["share"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
