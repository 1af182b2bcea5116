"""What a whole study costs at two revisions, side by side in one run: each revision cloned fresh into a temporary
folder and its study run from an empty results folder, as a user's first `snakemake --cores 2`; printed are the
wall time, the number of jobs and each rule's jobs and summed job time (its results/benchmarks/ files, and each
hidden set's results/<set>/benchmarks/).  Both runs use this interpreter's packages, each with its own clone's
newdyn first on PYTHONPATH.  The kernels' cache folder (NEWDYN_CACHE) is shared, so that neither run compiles for
the other, unless --empty-cache gives each run an empty one of its own.

Run: python bench/bench_study.py [--baseline REV] [--head REV] [--configfile PATH] [--cores 2] [--keep FOLDER]
(the default study: about 25 minutes for the two runs; --configfile .test/config.yaml, the CI study: a few).
With --keep, the clones and their results stay in FOLDER/<revision> for a comparison of the results.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def commit(revision: str) -> str:
    """The short hash of ``revision`` in this repository."""
    return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", revision], check=True, capture_output=True,
                          text=True).stdout.strip()


def clone(commit: str, folder: Path) -> None:
    """A fresh clone of this repository at ``commit`` in ``folder``."""
    subprocess.run(["git", "clone", "--quiet", str(ROOT), str(folder)], check=True)
    subprocess.run(["git", "-C", str(folder), "checkout", "--quiet", commit], check=True)


def run_study(folder: Path, configfile: str, cores: int, cache: Path | None) -> tuple[float, int]:
    """Wall time [s] and number of jobs of the study in the clone ``folder``."""
    environment = {**os.environ, "PYTHONPATH": str(folder / "src"),
                   "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    if cache is not None:
        environment["NEWDYN_CACHE"] = str(cache)
    # the study is the file alone, not merged over the clone's config/config.yaml
    command = [sys.executable, "-m", "snakemake", "--cores", str(cores), "--configfile", configfile, "--replace-workflow-config"]
    start = time.perf_counter()
    run = subprocess.run(command, cwd=folder, env=environment, capture_output=True, text=True, check=False)
    elapsed = time.perf_counter() - start
    if run.returncode != 0:
        sys.exit(f"the study failed in {folder}:\n{run.stderr[-3000:]}")
    done = re.findall(r"^(\d+) of \1 steps \(100%\) done$", run.stderr, re.MULTILINE)
    return elapsed, int(done[-1]) - 1  # the target rule `all` counts as a step, but runs nothing


def job_times(folder: Path) -> dict[str, tuple[int, float]]:
    """rule -> (jobs, summed wall time [s]) from the study's benchmark files (a rule made in a loop, one per variant,
    by the folder its benchmarks share)."""
    found: dict[str, list] = defaultdict(lambda: [0, 0.0])
    for path in (folder / "results").rglob("benchmarks/**/*.tsv"):
        rule = Path(path.as_posix().split("/benchmarks/", 1)[1]).parts[0].removesuffix(".tsv")
        with path.open() as f:
            for row in csv.DictReader(f, delimiter="\t"):
                found[rule][0] += 1
                found[rule][1] += float(row["s"])
    return {rule: (jobs, seconds) for rule, (jobs, seconds) in found.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default="main", help="the revision to compare with (default: main)")
    parser.add_argument("--head", default="HEAD", help="the revision measured (default: HEAD)")
    parser.add_argument("--configfile", default="config/config.yaml", help="the study, relative to the repository")
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--empty-cache", action="store_true", help="each run with an empty cache folder: kernels compiled")
    parser.add_argument("--keep", type=Path, help="keep the clones and their results in this folder")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as scratch:
        base = args.keep or Path(scratch)
        measured = {}
        for label, revision in (("baseline", commit(args.baseline)), ("head", commit(args.head))):
            folder = base / label
            clone(revision, folder)
            cache = Path(scratch) / f"cache-{label}" if args.empty_cache else None
            wall, jobs = run_study(folder, args.configfile, args.cores, cache)
            measured[label] = (revision, wall, jobs, job_times(folder))
            print(f"{label} {revision}: {wall:.0f} s, {jobs} jobs", flush=True)

    (old_commit, old_wall, old_jobs, old_rules), (new_commit, new_wall, new_jobs, new_rules) = measured.values()
    print(f"\n{args.configfile}, --cores {args.cores}, {time.strftime('%Y-%m-%d')}, "
          f"{'empty' if args.empty_cache else 'shared'} kernel cache")
    print(f"{'':24s} {'baseline ' + old_commit:>22s} {'head ' + new_commit:>22s} {'head/baseline':>14s}")
    print(f"{'wall time':24s} {old_wall:21.0f}s {new_wall:21.0f}s {new_wall / old_wall:13.2f}x")
    print(f"{'jobs':24s} {old_jobs:22d} {new_jobs:22d}")
    old_total, new_total = (sum(seconds for _, seconds in rules.values()) for rules in (old_rules, new_rules))
    print(f"{'job time, all rules':24s} {old_total:21.0f}s {new_total:21.0f}s {new_total / old_total:13.2f}x")
    print(f"\n{'rule':24s} {'jobs':>6s} {'job time':>15s} {'jobs':>6s} {'job time':>15s}")
    for rule in sorted(old_rules.keys() | new_rules.keys()):
        (old_n, old_s), (new_n, new_s) = old_rules.get(rule, (0, 0.0)), new_rules.get(rule, (0, 0.0))
        print(f"{rule:24s} {old_n:6d} {old_s:14.1f}s {new_n:6d} {new_s:14.1f}s")


if __name__ == "__main__":
    main()
