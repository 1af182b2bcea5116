"""What running on a batch system costs: the CI study (.test/config.yaml) run locally and through Snakemake's
cluster-generic executor plugin with the stand-in batch system of the tests (.test/stand-in-submit: every job
a separate process with its own Snakemake start and parse), side by side (goal: at most 1.5 times the local
time).  Each run starts from an empty folder; the kernels' cache is shared, so no run compiles for the other.

Run: python bench/bench_cluster.py   (a few minutes; needs snakemake-executor-plugin-cluster-generic)
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GOAL = 1.5
CLUSTER = ["--executor", "cluster-generic", "--cluster-generic-submit-cmd", str(ROOT / ".test" / "stand-in-submit"),
           "--jobs", "2", "--seconds-between-status-checks", "1"]


def study_time(*args: str) -> float:
    """Wall time of the CI study in a fresh folder, run with ``args``."""
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", folder, "--configfile",
                        str(ROOT / ".test" / "config.yaml"), "--cores", "2", "--quiet", *args],
                       check=True, capture_output=True)
        return time.perf_counter() - start


def main() -> None:
    study_time()  # the kernels compiled once, for both
    local, cluster = study_time(), study_time(*CLUSTER)
    print("CI study, 2 cores")
    print(f"{'local (--cores 2)':34s} {local:7.0f} s")
    print(f"{'cluster-generic stand-in (--jobs 2)':34s} {cluster:7.0f} s   {cluster / local:.2f}x   goal <= {GOAL:.1f}x")


if __name__ == "__main__":
    main()
