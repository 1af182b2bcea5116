"""Speed of the kernel with effects as files, side by side with the kernel before (a git revision).

Run: python bench/bench_effects.py [--before 4e27334] [--batch 64] [--rounds 15]

Prints, for the healthy rig and each built-in effect (stick-slip at several points, and 64 stick-slip rigs spread over
its prior in one batch, as a fit's search simulates them), the time per simulation batched on one core and alone, now
and at ``--before`` (run from a temporary git worktree), and each over the healthy rig's; then what a user's effect
costs against the built-in of the same arithmetic (a copy of cubic_coupling's force in a file of its own), and how long compiling
the kernel takes for a new effect and loading it from the cache afterwards.  docs/benchmarks.md quotes them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

from scipy.stats import qmc

from newdyn import effects, model

ROOT = Path(__file__).resolve().parents[1]

# A worker per revision (both read a scenario through faults.scenario_values): it prepares every case, then answers
# each line [case, "batched" | "alone"] on stdin with one timing in ms per simulation, so that the two revisions are
# timed in alternation, one simulation run apart (the machine's speed drifts within seconds).
MEASURE = textwrap.dedent("""
    import json, sys, time
    import numba
    from newdyn import faults, model
    from newdyn.simulation import simulate, simulate_batch
    cases, batch = json.loads(sys.argv[1]), int(sys.argv[2])
    simulate({})
    numba.set_num_threads(1)
    runs = {}
    for name, scenarios in cases.items():  # a case is one scenario, or a spread of them (batched in turn)
        spread = [faults.scenario_values(s, model.DEFAULTS) for s in (scenarios if isinstance(scenarios, list) else [scenarios])]
        rows = (spread * batch)[:batch]
        simulate(spread[0])  # compile or load outside the timing
        runs[name] = {"batched": (lambda rows=rows: simulate_batch(rows), batch), "alone": (lambda one=spread[0]: simulate(one), 1)}
    print("ready", flush=True)
    for line in sys.stdin:
        name, how = json.loads(line)
        run, count = runs[name][how]
        start = time.perf_counter(); run(); print(1e3 * (time.perf_counter() - start) / count, flush=True)
""")

USER_EFFECT = textwrap.dedent('''
    """A user's effect with the arithmetic of the built-in cubic_coupling, to compare their costs."""
    from newdyn.effects import Effect, Parameter


    class UserCubic(Effect):
        """The same force as cubic_coupling, written as a user would."""

        name = "user_cubic"
        description = "cubic hardening of the coupling element, as a user's effect"
        acts_on = "coupling"
        parameters = (Parameter("gamma", "-", "hardening coefficient", default=None, lower=0.0, lower_inclusive=True,
                                prior=(0.0, 3.0)),)

        @staticmethod
        def force(s, p, rig, mode):
            ratio = s.x * rig.kT2 / rig.T0
            return rig.kT2 * p.gamma * s.x * (ratio * ratio)
''')

# Runs in a subprocess with a fresh cache: compile time of a kernel with a new effect, then its cost and the built-in's
# (best of REPEAT runs each, in one process).
REPEAT = 5
USER = textwrap.dedent("""
    import json, sys, time
    import numba
    from newdyn import effects, faults, model
    from newdyn.simulation import simulate, simulate_batch
    folder, batch, repeat = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    effects.use(["user_cubic"], folder)
    start = time.perf_counter(); simulate({}); first = time.perf_counter() - start
    numba.set_num_threads(1)
    out = {"first_simulation_s": first}
    for kind in ("cubic_coupling", "user_cubic"):
        values = faults.scenario_values({"fault": {"kind": kind, "parameters": {"gamma": 0.5}}}, model.DEFAULTS)
        times = []
        for _ in range(repeat):
            start = time.perf_counter(); simulate_batch([values] * batch); times.append(time.perf_counter() - start)
        out[kind] = 1e3 * min(times) / batch
    print(json.dumps(out))
""")

def prior_spread(n: int = 64, seed: int = 1) -> list[dict]:
    """Stick-slip rigs spread over its prior box (quasi-random), as a fit's search simulates them in one batch, each
    made admissible by the effect itself (r_k raised where the stall rule needs it)."""
    stick_slip = effects.active()["stick_slip"]
    low, high = zip(*(p.prior for p in stick_slip.parameters))
    spread = []
    for point in qmc.scale(qmc.Sobol(len(low), seed=seed).random(n), low, high):
        drawn = dict(zip(stick_slip.parameter_names(), map(float, point)))
        parameters = {name: float(value) for name, value in stick_slip.admissible(drawn, model.DEFAULTS).items()}
        spread.append({"fault": {"kind": "stick_slip", "parameters": parameters}})
    return spread


CASES = {  # the default study's scenarios: healthy, and each built-in effect at its study severity;
    # stick-slip also with kinetic friction below static, and above its peak torque (never slips)
    "healthy": {},
    "stick_slip": {"fault": {"kind": "stick_slip", "parameters": {"T_max": 1854.95}}},
    "stick_slip_rk0.85": {"fault": {"kind": "stick_slip", "parameters": {"T_max": 2000.0, "r_k": 0.85}}},
    "stick_slip_locked": {"fault": {"kind": "stick_slip", "parameters": {"T_max": 2300.0}}},
    # two stick-slip cases of the blind set: kinetic friction a little and a tenth below static, the joint off its default split
    "stick_slip_blind06": {"fault": {"kind": "stick_slip", "parameters": {"T_max": 1990.80, "r_k": 0.97679, "J2a_share": 0.45312}}},
    "stick_slip_blind16": {"fault": {"kind": "stick_slip", "parameters": {"T_max": 2024.19, "r_k": 0.90154, "J2a_share": 0.45985}}},
    "stick_slip_spread": prior_spread(),  # 64 rigs across the prior box in one batch (alone: its first)
    "breathing_crack": {"fault": {"kind": "breathing_crack", "parameters": {"alpha": 0.3}}},
    "cubic_coupling": {"fault": {"kind": "cubic_coupling", "parameters": {"gamma": 0.5}}},
    "loose_bearing": {"fault": {"kind": "loose_bearing", "parameters": {"gap": 2e-8}}},
}


def run(code: str, *args: str, src: Path, env: dict | None = None) -> dict:
    environment = {**os.environ, "PYTHONPATH": str(src), **(env or {})}
    done = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=environment, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def start_worker(src: Path, env: dict | None, batch: int) -> subprocess.Popen:
    worker = subprocess.Popen([sys.executable, "-c", MEASURE, json.dumps(CASES), str(batch)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(src), **(env or {})})
    if worker.stdout.readline().strip() != "ready":
        raise RuntimeError(f"the worker for {src} failed to start")
    return worker


def timed(worker: subprocess.Popen, name: str, how: str) -> float:
    worker.stdin.write(json.dumps([name, how]) + "\n")
    worker.stdin.flush()
    return float(worker.stdout.readline())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default="4e27334", help="git revision to compare with (4e27334: a slipping joint's whole "
                        "record rerun at the fine step; b893f81: effects written into the kernel by hand)")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--rounds", type=int, default=15, help="times each case is run, batched and alone, by each revision "
                        "in alternation, the order reversed each round; every figure is the best of them")
    args = parser.parse_args()

    best: dict[tuple[str, str, str], float] = {}
    with tempfile.TemporaryDirectory() as tree:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", tree, args.before], check=True, capture_output=True)
        workers = {}
        try:
            workers = {"now": start_worker(ROOT / "src", None, args.batch),
                       "before": start_worker(Path(tree) / "src", {"NUMBA_CACHE_DIR": str(Path(tree) / ".numba")}, args.batch)}
            for round_ in range(args.rounds):
                for name in CASES:
                    for how in ("batched", "alone"):
                        for which in list(workers)[:: 1 if round_ % 2 == 0 else -1]:
                            key = (which, name, how)
                            best[key] = min(best.get(key, math.inf), timed(workers[which], name, how))
        finally:
            for worker in workers.values():
                worker.stdin.close()
                worker.wait()
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", tree], check=True, capture_output=True)
    now, before = ({name: [best[which, name, how] for how in ("batched", "alone")] for name in CASES} for which in ("now", "before"))

    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "user_cubic.py").write_text(USER_EFFECT)
        fresh = {"NEWDYN_CACHE": str(Path(folder) / "cache")}
        user = run(USER, folder, str(args.batch), str(REPEAT), src=ROOT / "src", env=fresh)
        cached = run(USER, folder, str(args.batch), str(REPEAT), src=ROOT / "src", env=fresh)

    print(f"1.5-s simulation, 11 channels, one core; batch of {args.batch}; best of {args.rounds} runs, the revisions in "
          f"alternation; before = {args.before}")
    print(f"{'':19s} {'batched now':>12s} {'before':>9s} {'ratio':>6s} {'x healthy':>13s}   {'alone now':>10s} {'before':>9s} "
          f"{'ratio':>6s} {'x healthy':>13s}")
    for name in CASES:
        (b_now, l_now), (b_old, l_old) = now[name], before[name]
        healthy = f"{b_now / now['healthy'][0]:5.2f} / {b_old / before['healthy'][0]:5.2f}"
        healthy_alone = f"{l_now / now['healthy'][1]:5.2f} / {l_old / before['healthy'][1]:5.2f}"
        print(f"{name:19s} {b_now:9.2f} ms {b_old:6.2f} ms {b_now / b_old:6.2f} {healthy:>13s}   {l_now:7.2f} ms {l_old:6.2f} ms "
              f"{l_now / l_old:6.2f} {healthy_alone:>13s}")
    print("x healthy: the case's time over the healthy rig's, now / before (goal for a slipping joint: at most 2)")
    print(f"a user's effect against the built-in of the same arithmetic, batched: user_cubic {user['user_cubic']:.2f} ms, "
          f"cubic_coupling {user['cubic_coupling']:.2f} ms (ratio {user['user_cubic'] / user['cubic_coupling']:.2f})")
    print(f"kernel with a new effect: compiled in {user['first_simulation_s']:.0f} s on first use, "
          f"loaded from the cache in {cached['first_simulation_s']:.1f} s afterwards")


if __name__ == "__main__":
    main()
