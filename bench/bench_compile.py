"""The kernel's first compile at two revisions, side by side in one run, with what it compiles to: each revision cloned
fresh and its built-in kernel compiled into an empty cache folder (NEWDYN_CACHE) in a process of its own, then the
speed of the compiled code (the best of --repeat runs of a 64-simulation batch and of a lone simulation, one thread),
both in the process that compiled it (a study's first job) and in a new one that loads it from the cache (every other
job: what loading costs it too), then the compile's wall time where a second core can share it: a process with two
threads (a lone diagnosis) and two one-thread processes started together (a study's first two jobs).  The revisions
take turns for --rounds rounds, the best of each row counted; printed is also whether both revisions simulate every
built-in effect to the same bits.

Run: python bench/bench_compile.py [--baseline REV] [--head REV] [--repeat 7] [--rounds 2]   (about 10 minutes)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_study import clone, commit

# Run in each clone's own process: compile, time, and write every built-in effect's simulations (batched, and lone
# with the search's step) to the file named by argv[1].
MEASURE = """
import json, sys, time
import numpy as np
from newdyn import effects, faults, kernels, model, simulation

start = time.perf_counter()
kernels.module()
simulation.simulate_batch([model.DEFAULTS], model.Sampling(n_samples=1))
compile_s = time.perf_counter() - start

def best(values, repeat):
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        simulation.simulate_batch(values, model.Sampling())
        times.append(time.perf_counter() - start)
    return min(times)

batch = [{**model.DEFAULTS, "kT1": 3e6 * (0.8 + 0.4 * i / 63)} for i in range(64)]
repeat = int(sys.argv[2])
outputs = []
for kind, effect in effects.active().items():
    drawn = {p.name: 0.5 * sum(p.draw_range) for p in effect.parameters if p.default is None}
    values = faults.scenario_values({"fault": {"kind": kind, "parameters": drawn}}, model.DEFAULTS)
    outputs.append(simulation.simulate_batch([values, {**values, "kT1": 3.3e6}], model.Sampling()).ravel())
    outputs.append(simulation.simulate_batch([values], model.Sampling(), search=True).ravel())
np.save(sys.argv[1], np.concatenate(outputs))
print(json.dumps({"compile": compile_s, "batch": best(batch, repeat), "lone": best(batch[:1], repeat)}))
"""


def environment(folder: Path, cache: Path, threads: int) -> dict[str, str]:
    """The environment of a process that runs the clone ``folder``'s newdyn on ``threads`` threads and the cache folder
    ``cache``."""
    return {**os.environ, "PYTHONPATH": str(folder / "src"), "NEWDYN_CACHE": str(cache), "NUMBA_NUM_THREADS": str(threads)}


def measure(folder: Path, cache: Path, outputs: Path, repeat: int) -> dict[str, float]:
    """The kernel's compile or load time [s] (``compile``) and the best batch and lone simulation times [s] of the
    clone ``folder``, measured in a new process on the cache folder ``cache``."""
    run = subprocess.run([sys.executable, "-c", MEASURE, str(outputs), str(repeat)], env=environment(folder, cache, 1),
                         capture_output=True, text=True, check=False)
    if run.returncode != 0:
        sys.exit(f"the measurement failed in {folder}:\n{run.stderr[-3000:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


# Run in each of the processes started together: the kernel compiled (or loaded, once another has compiled it).
COMPILE = "from newdyn import kernels; kernels.module()"


def compile_together(folder: Path, cache: Path, processes: int, threads: int) -> float:
    """Wall time [s] until ``processes`` processes of ``threads`` threads each, started together on the empty cache
    folder ``cache``, all have the clone ``folder``'s built-in kernel."""
    start = time.perf_counter()
    runs = [subprocess.Popen([sys.executable, "-c", COMPILE], env=environment(folder, cache, threads), stderr=subprocess.PIPE,
                             text=True)
            for _ in range(processes)]
    for run in runs:
        _, errors = run.communicate()
        if run.returncode != 0:
            sys.exit(f"the compile failed in {folder}:\n{errors[-3000:]}")
    return time.perf_counter() - start


def measure_round(folder: Path, scratch: Path, repeat: int) -> dict[str, float]:
    """One round's times [s] of the clone ``folder``, each on an empty cache folder of its own under ``scratch`` but
    the cached simulations: the one-thread compile and the simulations in its process, then in a new one that loads
    the kernel, then the compile shared by a process's two threads and by two processes."""
    cache = Path(tempfile.mkdtemp(dir=scratch))
    compiled = measure(folder, cache, scratch / "outputs.npy", repeat)
    cached = measure(folder, cache, scratch / "cached.npy", repeat)
    return {**compiled, "cached_load": cached["compile"], "cached_batch": cached["batch"], "cached_lone": cached["lone"],
            "two_threads": compile_together(folder, Path(tempfile.mkdtemp(dir=scratch)), 1, 2),
            "two_processes": compile_together(folder, Path(tempfile.mkdtemp(dir=scratch)), 2, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default="HEAD~1", help="the revision to compare with (default: HEAD~1)")
    parser.add_argument("--head", default="HEAD", help="the revision measured (default: HEAD)")
    parser.add_argument("--repeat", type=int, default=7, help="runs of each simulation, the best one counted")
    parser.add_argument("--rounds", type=int, default=2, help="rounds, the revisions in turns, the best one counted")
    args = parser.parse_args()

    revisions = {"baseline": commit(args.baseline), "head": commit(args.head)}
    best: dict[str, dict[str, float]] = {label: {} for label in revisions}
    outputs = {}
    with tempfile.TemporaryDirectory() as scratch:
        for label, revision in revisions.items():
            clone(revision, Path(scratch) / label)
            (Path(scratch) / f"{label}-work").mkdir()
        for round_ in range(args.rounds):
            for label in list(revisions)[:: 1 if round_ % 2 == 0 else -1]:  # each first in every other round
                work = Path(scratch) / f"{label}-work"
                times = measure_round(Path(scratch) / label, work, args.repeat)
                best[label] = {key: min(value, best[label].get(key, float("inf"))) for key, value in times.items()}
                outputs[label] = np.load(work / "outputs.npy")
                print(f"round {round_ + 1}, {label} {revisions[label]}: compiled in {times['compile']:.1f} s (one thread), "
                      f"{times['two_threads']:.1f} s (two threads), {times['two_processes']:.1f} s (two processes)",
                      flush=True)
    old, new = best["baseline"], best["head"]

    print(f"\nthe built-in kernel, {time.strftime('%Y-%m-%d')}, the best of {args.rounds} rounds (simulations on one thread)")
    print(f"{'':28s} {'baseline ' + revisions['baseline']:>18s} {'head ' + revisions['head']:>18s} {'head/baseline':>14s}")
    for key, label, unit, scale in (("compile", "first compile, 1 thread", "s", 1.0),
                                    ("two_threads", "first compile, 2 threads", "s", 1.0),
                                    ("two_processes", "first compile, 2 processes", "s", 1.0),
                                    ("batch", "64 simulations, compiling", "s", 1.0),
                                    ("lone", "one simulation, compiling", "ms", 1e3),
                                    ("cached_load", "loading it from the cache", "s", 1.0),
                                    ("cached_batch", "64 simulations, cached", "s", 1.0),
                                    ("cached_lone", "one simulation, cached", "ms", 1e3)):
        print(f"{label:28s} {old[key] * scale:16.3g}{unit:>2s} {new[key] * scale:16.3g}{unit:>2s} {new[key] / old[key]:13.2f}x")
    same = outputs["baseline"].shape == outputs["head"].shape and np.array_equal(outputs["baseline"], outputs["head"])
    print(f"every built-in effect simulated to the same bits: {'yes' if same else 'NO'}")


if __name__ == "__main__":
    main()
