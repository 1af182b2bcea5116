"""Diagnosis speed, the old pipeline against the new, over the blind sets (and the open-world set), verdicts compared.

Each revision runs from a git worktree of its own in a fresh folder, through Snakemake on 2 cores as a user runs it
(``snakemake --cores 2 results/<set>/score.json``, its own rules and command line), with the package of that
worktree (PYTHONPATH); the times are the workflow's own job times (``<root>/benchmarks/diagnose/<case>.tsv``, wall
seconds).  The old revision runs first, then the new, in one run of this script: the machine's speed drifts between
days, so only ratios measured side by side count.  The open-world cases are drawn by this checkout's generator
(``bench/open_world/run.py``), written into each revision's ``measurements/`` and diagnosed as a user's files.

A machine set (``--sets machines``) prints each recording's diagnosis and each machine's own job, and what a machine
costs in all (its recordings' diagnoses and its own job) per recording.

Run: python bench/bench_diagnosis.py [--before 4e27334] [--after HEAD] [--sets blind instruments] [--open-world]
                                     [--keep DIR]   (an hour and more: the old pipeline takes 1-10 min a diagnosis)
With ``--keep DIR`` the worktrees and their results stay in DIR, and a revision whose results are there already is
not run again (its times are those of that earlier run: say so when quoting them).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OPEN_WORLD = ROOT / "bench" / "open_world" / "run.py"
OPEN_WORLD_CASES, OPEN_WORLD_SEED = 12, 2026


def run(*command, cwd=None, env=None) -> None:
    subprocess.run([str(c) for c in command], cwd=cwd, env=env, check=True)


def revision_env(repo: Path) -> dict:
    return {**os.environ, "PYTHONPATH": str(repo / "src")}


def prepare(folder: Path, revision: str) -> Path:
    """A worktree of ``revision`` in ``folder``: one kept there is moved to ``revision`` (its results stay, and the
    workflow reruns what the code change touches)."""
    if not folder.exists():
        run("git", "-C", ROOT, "worktree", "add", "--detach", folder, revision)
    else:
        run("git", "-C", folder, "checkout", "--detach", subprocess.run(["git", "-C", ROOT, "rev-parse", revision], capture_output=True,
                                                                         text=True, check=True).stdout.strip())
    return folder


def study(repo: Path, sets: list[str], open_world: bool) -> None:
    """Diagnose the sets (and the open-world cases) in ``repo`` as its own workflow does."""
    targets = [f"results/{name}/score.json" for name in sets]
    if open_world:
        truth = repo / "open_world_truth.json"
        if not truth.exists():
            run(sys.executable, OPEN_WORLD, "draw", repo / "measurements", truth, "--cases", OPEN_WORLD_CASES, "--seed", OPEN_WORLD_SEED)
        targets += [f"results/diagnosis/{case['name']}/verdict.json" for case in json.loads(truth.read_text())]
    # the targets before --quiet, whose optional values would take them
    run(sys.executable, "-m", "snakemake", *targets, "--snakefile", repo / "Snakefile", "-d", repo, "--cores", "2",
        "--quiet", "progress", env=revision_env(repo))


def job_seconds(tsv: Path) -> float:
    with open(tsv) as f:
        return float(next(csv.DictReader(f, delimiter="\t"))["s"])


def cases(repo: Path, sets: list[str], open_world: bool) -> dict[str, dict]:
    """Per case: its set, class, job time and verdict.  A machine set's cases are its recordings
    (``<machine>/<recording>``, set ``<set> recordings``) and its machines, whose time is their own job's, on top of
    their recordings'."""
    found = {}

    def add(name, group, case_class, root, job):
        found[name] = {"set": group, "class": case_class, "seconds": job_seconds(root / f"benchmarks/{job}/{name}.tsv"),
                       "verdict": json.loads((root / f"diagnosis/{name}/verdict.json").read_text())}

    for name in sets:
        root = repo / f"results/{name}"
        for case in json.loads((root / "truth.json").read_text())["cases"]:
            for recording in case.get("recordings", []):
                add(f"{case['name']}/{recording['name']}", f"{name} recordings", case["class"], root, "diagnose")
            add(case["name"], name, case["class"], root, "diagnose_machine" if "recordings" in case else "diagnose")
    if open_world:
        for case in json.loads((repo / "open_world_truth.json").read_text()):
            add(case["name"], "open world", case["class"], repo / "results", "diagnose")
    return found


def label(verdict: dict) -> str:
    return f"{verdict['verdict']} {verdict.get('effect') or ''}".strip()


def scores(repo: Path, sets: list[str], open_world: bool) -> dict[str, str]:
    """Each set's score in one line: the hidden-score's, the open-world script's."""
    found = {}
    for name in sets:
        s = json.loads((repo / f"results/{name}/score.json").read_text())
        inst = s["instruments"]
        found[name] = (f"{s['correct']}/{s['cases']} right, truth in 94 % HDI {s['hdi_coverage']:.0%}, "
                       f"fault fits explaining {s['fault_fit']['explained']}/{s['fault_fit']['cases']}"
                       + (f", out of spec named {inst['named']}/{inst['out_of_spec']}, false alarms {inst['false_alarms']}"
                          if inst["cases"] else "")
                       + (f"; the recordings alone {s['single_recordings']['correct']}/{s['single_recordings']['recordings']} right"
                          if "single_recordings" in s else ""))
    if open_world:
        out = subprocess.run([sys.executable, OPEN_WORLD, "score", repo / "open_world_truth.json", repo / "results" / "diagnosis"],
                             capture_output=True, text=True, check=True).stdout.strip().splitlines()
        share = json.loads(out[-1])["share"]
        rows = [json.loads(line) for line in out[:-1]]
        found["open world"] = (f"right family and frequency {share['right_family_and_frequency']:.0%}, chi2 <= 1.1 after adding "
                               f"{share['chi2_after_ok']:.0%}, place among equivalent {share['place_among_equivalent']:.0%} "
                               f"({len(rows)} cases)")
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default="4e27334", help="the old pipeline's revision")
    parser.add_argument("--after", default="HEAD", help="the new pipeline's revision")
    parser.add_argument("--sets", nargs="*", default=["blind", "instruments"], help="hidden sets of config.yaml")
    parser.add_argument("--open-world", action="store_true", help="also the 12 open-world cases")
    parser.add_argument("--keep", type=Path, help="keep the worktrees here, and reuse a revision's results found there")
    args = parser.parse_args()
    base = args.keep or Path(tempfile.mkdtemp(prefix="bench_diagnosis_"))
    base.mkdir(parents=True, exist_ok=True)
    runs = {}
    for name, revision in (("old", args.before), ("new", args.after)):
        repo = prepare(base / name, revision)
        study(repo, args.sets, args.open_world)
        runs[name] = (repo, cases(repo, args.sets, args.open_world))
    (old_repo, old), (new_repo, new) = runs["old"], runs["new"]
    print(f"diagnoses on 2 cores (Snakemake job times), {args.before} -> {args.after}")
    print(f"{'case':16s} {'class':22s} {'old s':>7s} {'new s':>7s} {'ratio':>6s}   old verdict -> new verdict")
    agree = 0
    for case, row in new.items():
        before = old[case]
        same = label(before["verdict"]) == label(row["verdict"])
        agree += same
        print(f"{case:16s} {row['class']:22s} {before['seconds']:7.1f} {row['seconds']:7.1f} {before['seconds'] / row['seconds']:5.1f}x   "
              f"{label(before['verdict'])} -> {label(row['verdict'])}{'' if same else '   DIFFERS'}")
    for group in dict.fromkeys(row["set"] for row in new.values()):
        o = [old[c]["seconds"] for c, row in new.items() if row["set"] == group]
        n = [row["seconds"] for row in new.values() if row["set"] == group]
        print(f"{group}: median {statistics.median(o):.1f} s -> {statistics.median(n):.1f} s, worst {max(o):.1f} s -> {max(n):.1f} s, "
              f"total {sum(o):.0f} s -> {sum(n):.0f} s ({sum(o) / sum(n):.1f}x)")
    for name in args.sets:  # a machine's whole cost: its recordings' diagnoses and its own
        machines = [c for c, row in new.items() if row["set"] == name and any(r.startswith(f"{c}/") for r in new)]
        for revision, times in ((args.before, old), (args.after, new)):
            whole = [sum(row["seconds"] for r, row in times.items() if r == m or r.startswith(f"{m}/")) for m in machines]
            per = [w / sum(r.startswith(f"{m}/") for r in times) for m, w in zip(machines, whole)]
            if machines:
                print(f"{name} at {revision}: a machine with its recordings median {statistics.median(whole):.1f} s, worst "
                      f"{max(whole):.1f} s; per recording median {statistics.median(per):.1f} s, worst {max(per):.1f} s")
    print(f"verdicts (class and effect) the same in {agree} of {len(new)} cases")
    for name, repo in (("old", old_repo), ("new", new_repo)):
        for group, line in scores(repo, args.sets, args.open_world).items():
            print(f"{name} {group}: {line}")


if __name__ == "__main__":
    main()
