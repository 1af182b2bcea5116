"""Speed of the kernel with effects as files, side by side with the kernel before (a git revision).

Run: python bench/bench_effects.py [--before 4e27334] [--batch 64] [--repeat 5] [--rounds 2]

Prints, for the healthy rig and each built-in effect (stick-slip at several points, and 64 stick-slip rigs spread over
its prior in one batch, as a fit's search simulates them), the time per simulation batched on one core and alone, now
and at ``--before`` (run from a temporary git worktree), and each over the healthy rig's; then what a user's effect
costs against the built-in of the same arithmetic (a copy of cubic_coupling's force in a file of its own), and how long compiling
the kernel takes for a new effect and loading it from the cache afterwards.  docs/benchmarks.md quotes them.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

from scipy.stats import qmc

from newdyn import effects, model

ROOT = Path(__file__).resolve().parents[1]

# Runs in a subprocess against either revision (both read a scenario through faults.scenario_values):
# prints {case: [batched ms per simulation, lone ms]}.
MEASURE = textwrap.dedent("""
    import json, sys, time
    import numba
    from newdyn import faults, model
    from newdyn.simulation import simulate, simulate_batch
    cases, batch, repeat = json.loads(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
    def best(run):
        times = []
        for _ in range(repeat):
            start = time.perf_counter(); run(); times.append(time.perf_counter() - start)
        return min(times)
    simulate({})
    numba.set_num_threads(1)
    out = {}
    for name, scenarios in cases.items():  # a case is one scenario, or a spread of them (batched in turn)
        spread = [faults.scenario_values(s, model.DEFAULTS) for s in (scenarios if isinstance(scenarios, list) else [scenarios])]
        rows = (spread * batch)[:batch]
        simulate(spread[0])  # compile or load outside the timing
        out[name] = [1e3 * best(lambda: simulate_batch(rows)) / batch, 1e3 * best(lambda: simulate(spread[0]))]
    print(json.dumps(out))
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

# Runs in a subprocess with a fresh cache: compile time of a kernel with a new effect, then its cost.
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default="4e27334", help="git revision to compare with (4e27334: a slipping joint's whole "
                        "record rerun at the fine step; b893f81: effects written into the kernel by hand)")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=2, help="measure each revision this many times, in turns, the "
                        "order reversed each round; every figure is the best of all (the machine's speed drifts)")
    args = parser.parse_args()
    common = (json.dumps(CASES), str(args.batch), str(args.repeat))

    with tempfile.TemporaryDirectory() as tree:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", tree, args.before], check=True, capture_output=True)
        try:
            revisions = {"now": (ROOT / "src", None), "before": (Path(tree) / "src", {"NUMBA_CACHE_DIR": str(Path(tree) / ".numba")})}
            measured = {which: [] for which in revisions}
            for round_ in range(args.rounds):
                for which in list(revisions)[:: 1 if round_ % 2 == 0 else -1]:
                    src, env = revisions[which]
                    measured[which].append(run(MEASURE, *common, src=src, env=env))
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", tree], check=True, capture_output=True)
    now, before = ({name: [min(rounds[name][i] for rounds in measured[which]) for i in (0, 1)] for name in CASES}
                   for which in ("now", "before"))

    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "user_cubic.py").write_text(USER_EFFECT)
        fresh = {"NEWDYN_CACHE": str(Path(folder) / "cache")}
        user = run(USER, folder, str(args.batch), str(args.repeat), src=ROOT / "src", env=fresh)
        cached = run(USER, folder, str(args.batch), str(args.repeat), src=ROOT / "src", env=fresh)

    print(f"1.5-s simulation, 11 channels, one core; batch of {args.batch}; best of {args.repeat} in each of {args.rounds} "
          f"rounds, the revisions in turns; before = {args.before}")
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
