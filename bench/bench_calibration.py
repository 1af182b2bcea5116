"""Speed of the grid calibrations, side by side with a git revision: a diagnosis's four and a condition's signature
library (what every diagnosis at a new operating condition builds, and the study's bank job).

Run: python bench/bench_calibration.py [--before 3bcfb2d] [--threads 2] [--rounds 3]

Two worker processes, this checkout's package and the revision's (from a temporary git worktree), each prepare both
cases at the study's condition (config/config.yaml), then run them one at a time, the revisions in alternation, the
order reversed each round (the machine's speed drifts within seconds); every figure is the best of --rounds.  Each
worker calls the calibrations as its revision's diagnosis does.  docs/benchmarks.md quotes it.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

WORKER = textwrap.dedent("""
    import sys, time
    import numba
    from newdyn import calibration, config, noise, signatures, slots, study
    from newdyn.settings import Settings
    from newdyn.simulation import simulate
    numba.set_num_threads(int(sys.argv[2]))
    cfg = config.load(sys.argv[1])
    sampling = study.sampling(cfg)
    settings = Settings.from_config({
        "rig": cfg["rig"], "operating": cfg["operating"], "diagnosis": cfg["diagnosis"],
        "sampling": {"fs": sampling.fs, "t_first": sampling.t_first, "n_samples": sampling.n_samples},
        "calibration": {k: cfg["calibration"][k] for k in ("parameters", "chi2_max", "refine_points", "mcmc")},
        "simulation": {"max_step": cfg["simulation"]["max_step"]}, "effects": config.effect_names(cfg)})
    values = slots.complete({**cfg["rig"], **cfg["operating"]})
    hyps = {h.name: h for h in settings.hypotheses()}
    coarse = {p: calibration.simulate_grid(values, p, g.axis, sampling, settings.channels, settings.max_step)
              for p, g in settings.grids.items()}
    instruments = settings.instruments(sampling.fs)
    entries = signatures.entries(hyps, list(settings.grids), settings.drift_sizes, settings.fault_ranges, settings.severities, values)
    data, sigma = noise.add_noise(simulate({**values, "kT1": 1.03 * values["kT1"]}, sampling, settings.channels),
                                  settings.channels, 40.0, 3)

    def library():
        signatures.build(hyps, entries, values, sampling, settings.channels, settings.grids, settings.priors, coarse,
                         instruments, settings.max_step)

    def four_grids():
        shared = (sigma, values, sampling, settings.channels, settings.refine_points, settings.chi2_max, settings.max_step, instruments)
        if hasattr(calibration, "calibrate_many"):
            calibration.calibrate_many([calibration.Task(data, g, settings.priors[p], coarse[p]) for p, g in settings.grids.items()],
                                       *shared)
        else:
            for p, g in settings.grids.items():
                calibration.calibrate(data, shared[0], g, settings.priors[p], coarse[p], *shared[1:])

    cases = {"signature library": library, "four grid calibrations": four_grids}
    for run in cases.values():
        run()  # compiled or loaded outside the timing
    print("ready", flush=True)
    for line in sys.stdin:
        start = time.perf_counter(); cases[line.strip()](); print(time.perf_counter() - start, flush=True)
""")
CASES = ("signature library", "four grid calibrations")


def start_worker(src: Path, threads: int) -> subprocess.Popen:
    worker = subprocess.Popen([sys.executable, "-c", WORKER, str(ROOT / "config" / "config.yaml"), str(threads)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": str(src), "OPENBLAS_NUM_THREADS": str(threads)})
    if worker.stdout.readline().strip() != "ready":
        raise RuntimeError(f"the worker for {src} failed to start")
    return worker


def timed(worker: subprocess.Popen, case: str) -> float:
    worker.stdin.write(case + "\n")
    worker.stdin.flush()
    return float(worker.stdout.readline())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default="3bcfb2d", help="git revision to compare with (3bcfb2d: each calibration's "
                        "cells simulated one at a time, the likelihood's sums without SIMD)")
    parser.add_argument("--threads", type=int, default=2, help="threads of each worker (a diagnosis 2, the study's bank job 1)")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    best = {}
    with tempfile.TemporaryDirectory() as tree:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", tree, args.before], check=True, capture_output=True)
        workers = {}
        try:
            workers = {"now": start_worker(ROOT / "src", args.threads), "before": start_worker(Path(tree) / "src", args.threads)}
            for round_ in range(args.rounds):
                for case in CASES:
                    for which in list(workers)[:: 1 if round_ % 2 == 0 else -1]:
                        best[which, case] = min(best.get((which, case), math.inf), timed(workers[which], case))
        finally:
            for worker in workers.values():
                worker.stdin.close()
                worker.wait()
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", tree], check=True, capture_output=True)
    print(f"at the study's condition, {args.threads} thread(s), best of {args.rounds} runs in alternation; before = {args.before}")
    for case in CASES:
        now, before = best["now", case], best["before", case]
        print(f"{case:24s} now {now:6.2f} s   before {before:6.2f} s   ratio {now / before:.2f}")


if __name__ == "__main__":
    main()
