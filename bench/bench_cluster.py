"""What running on a batch system costs: the CI study (.test/config.yaml) run locally and through Snakemake's
cluster-generic executor plugin with the stand-in batch system of the tests (.test/stand-in-submit: every job
a separate process with its own Snakemake start and parse, the scenarios grouped as the repository's SLURM profile
groups them), side by side (goal: at most 1.5 times the local time).  Each run starts from an empty folder; the
kernels' cache is shared, so no run compiles for the other.  With --baseline REV the same two runs of a fresh clone
of that revision (its newdyn first on PYTHONPATH, its own profile's groups) go beside those of the working tree, in
turns, so that the machine's drift touches both alike.

Run: python bench/bench_cluster.py [--baseline REV] [--status-checks SECONDS]   (a few minutes, twice that with a
baseline; needs snakemake-executor-plugin-cluster-generic).  --status-checks is how often Snakemake asks the batch
system whether a job ended: 1 s by default here, Snakemake's own default is 10 s, which a job's end may wait for.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
GOAL = 1.5
PROFILE = Path("workflow") / "profiles" / "slurm" / "config.yaml"


def cluster(root: Path, status_checks: float) -> list[str]:
    """The stand-in batch system's command line, with the groups the repository's SLURM profile submits together."""
    profile = yaml.safe_load((root / PROFILE).read_text()) if (root / PROFILE).exists() else {}
    groups = ["--group-components", *profile["group-components"]] if "group-components" in profile else []
    return ["--executor", "cluster-generic", "--cluster-generic-submit-cmd", str(root / ".test" / "stand-in-submit"),
            "--jobs", "2", "--seconds-between-status-checks", f"{status_checks:g}", *groups]


def study_time(root: Path, *args: str) -> float:
    """Wall time of the CI study of the repository ``root`` in a fresh folder, run with ``args``."""
    environment = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    if root != ROOT:
        environment["PYTHONPATH"] = str(root / "src")
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "snakemake", "-s", str(root / "Snakefile"), "-d", folder, "--configfile",
                        str(root / ".test" / "config.yaml"), "--cores", "2", "--quiet", *args],
                       check=True, capture_output=True, env=environment)
        return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", help="a revision to measure beside the working tree")
    parser.add_argument("--status-checks", type=float, default=1.0, help="seconds between Snakemake's job status checks")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        roots = {"working tree": ROOT}
        if args.baseline:
            clone = Path(scratch) / "baseline"
            subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True)
            subprocess.run(["git", "-C", str(clone), "checkout", "--quiet", args.baseline], check=True)
            roots = {f"baseline {args.baseline}": clone, **roots}
        for root in roots.values():
            study_time(root)  # the kernels compiled once, for both of its runs
        local = {label: study_time(root) for label, root in roots.items()}
        remote = {label: study_time(root, *cluster(root, args.status_checks)) for label, root in roots.items()}
    print(f"CI study, 2 cores, {time.strftime('%Y-%m-%d')}, status checks every {args.status_checks:g} s")
    print(f"{'':36s}" + "".join(f"{label:>22s}" for label in roots))
    print(f"{'local (--cores 2)':36s}" + "".join(f"{local[label]:21.0f}s" for label in roots))
    print(f"{'cluster-generic stand-in (--jobs 2)':36s}" + "".join(f"{remote[label]:21.0f}s" for label in roots))
    print(f"{'cluster / local':36s}" + "".join(f"{remote[label] / local[label]:21.2f}x" for label in roots)
          + f"   goal <= {GOAL:.1f}x")


if __name__ == "__main__":
    main()
