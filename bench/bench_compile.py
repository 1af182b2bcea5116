"""The kernel's first compile at two revisions, side by side in one run, with what it compiles to: each revision cloned
fresh and its built-in kernel compiled into an empty cache folder (NEWDYN_CACHE) in a process of its own, then the
speed of the compiled code (the best of --repeat runs of a 64-simulation batch and of a lone simulation, one thread),
both in the process that compiled it (a study's first job) and in a new one that loads it from the cache (every other
job: what loading costs it too), and whether both revisions simulate every built-in effect to the same bits.

Run: python bench/bench_compile.py [--baseline REV] [--head REV] [--repeat 7]   (about 3 minutes)
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


def measure(folder: Path, cache: Path, outputs: Path, repeat: int) -> dict[str, float]:
    """Compile time [s] and the best batch and lone simulation times [s] of the clone ``folder``: in the process that
    compiled the kernel, and (``cached_load``, the kernel's rendering and loading, ``cached_batch``, ``cached_lone``) in a
    second one that loaded it."""
    environment = {**os.environ, "PYTHONPATH": str(folder / "src"), "NEWDYN_CACHE": str(cache), "NUMBA_NUM_THREADS": "1"}
    found = []
    for _ in range(2):
        run = subprocess.run([sys.executable, "-c", MEASURE, str(outputs), str(repeat)], env=environment,
                             capture_output=True, text=True, check=False)
        if run.returncode != 0:
            sys.exit(f"the measurement failed in {folder}:\n{run.stderr[-3000:]}")
        found.append(json.loads(run.stdout.strip().splitlines()[-1]))
    compiled, cached = found
    return {**compiled, "cached_load": cached["compile"], "cached_batch": cached["batch"], "cached_lone": cached["lone"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default="HEAD~1", help="the revision to compare with (default: HEAD~1)")
    parser.add_argument("--head", default="HEAD", help="the revision measured (default: HEAD)")
    parser.add_argument("--repeat", type=int, default=7, help="runs of each simulation, the best one counted")
    args = parser.parse_args()

    measured = {}
    with tempfile.TemporaryDirectory() as scratch:
        for label, revision in (("baseline", commit(args.baseline)), ("head", commit(args.head))):
            folder = Path(scratch) / label
            clone(revision, folder)
            outputs = Path(scratch) / f"{label}.npy"
            measured[label] = (revision, measure(folder, Path(scratch) / f"cache-{label}", outputs, args.repeat), np.load(outputs))
            print(f"{label} {revision}: compiled in {measured[label][1]['compile']:.1f} s", flush=True)
        (old_commit, old, old_out), (new_commit, new, new_out) = measured.values()

    print(f"\nthe built-in kernel, one thread, {time.strftime('%Y-%m-%d')}")
    print(f"{'':28s} {'baseline ' + old_commit:>18s} {'head ' + new_commit:>18s} {'head/baseline':>14s}")
    for key, label, unit, scale in (("compile", "first compile", "s", 1.0),
                                    ("batch", "64 simulations, compiling", "s", 1.0),
                                    ("lone", "one simulation, compiling", "ms", 1e3),
                                    ("cached_load", "loading it from the cache", "s", 1.0),
                                    ("cached_batch", "64 simulations, cached", "s", 1.0),
                                    ("cached_lone", "one simulation, cached", "ms", 1e3)):
        print(f"{label:28s} {old[key] * scale:16.3g}{unit:>2s} {new[key] * scale:16.3g}{unit:>2s} {new[key] / old[key]:13.2f}x")
    same = old_out.shape == new_out.shape and np.array_equal(old_out, new_out)
    print(f"every built-in effect simulated to the same bits: {'yes' if same else 'NO'}")


if __name__ == "__main__":
    main()
