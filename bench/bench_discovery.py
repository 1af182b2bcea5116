"""Speed of discovery on one unexplained measurement (goal: it adds <= 2 minutes on 2 cores), against that
goal: the search on the linearized rig, then the full-simulator fits of its leading forms, on the default
record (1 s at 40 dB).  The measurement holds a ripple at three times the motor speed (the test effect
tests/effects/torque_ripple.py, which the search does not know); its residual is taken against the
nominal model, as the diagnosis takes it against the calibrated one.  The forms' generic kernels compile
once per machine: the first run pays that (printed), the timing is of the second.

Run: python bench/bench_discovery.py
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numba
import yaml

from newdyn import effects, hypotheses, io, model, noise, simulation, slots
from newdyn.discovery import verify
from newdyn.settings import Settings

GOAL_SECONDS = 120.0
ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    numba.set_num_threads(2)
    logging.basicConfig(level=logging.WARNING)
    config = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    settings = Settings.from_config(config)
    sampling = model.Sampling()
    effects.use(["torque_ripple"], ROOT / "tests" / "effects")
    truth = slots.complete({"torque_ripple": 1.0, "torque_ripple.amplitude": 10.0, "torque_ripple.order": 3.0})
    clean = simulation.simulate(truth, sampling, settings.channels)
    effects.use([])
    y, sigma = noise.add_noise(clean, settings.channels, 40.0, 1)
    measurement = io.Measurement("ripple", tuple(settings.channels), y, sampling,
                                 {k: config["operating"][k] for k in model.OPERATING_PARAMETERS}, sigma)
    values = slots.complete({**settings.rig, **measurement.operating})
    nominal = hypotheses.fit(hypotheses.Hypothesis("healthy", "healthy"), y, sigma, values, sampling, settings.channels,
                             max_step=settings.max_step)
    print(f"a 10 N·m ripple at 3x the motor speed, 1-s record at 40 dB ({', '.join(settings.channels)}), 2 cores")
    print(f"{'run':10s} {'time':>8s} {'vs goal':>8s}   best form")
    for run in ("first", "second"):
        start = time.perf_counter()
        found = verify.discover(measurement.name, nominal, y, sigma, values, sampling, settings)
        seconds = time.perf_counter() - start
        best = found.section["candidates"][0]
        print(f"{run:10s} {seconds:7.1f}s {seconds / GOAL_SECONDS:7.2f}x   {best['term']} on {best['acts_on']} ({best['shape']}), "
              f"chi2 {found.section['chi2_before']:.3g} -> {found.fit.chi2_red:.3g}")


if __name__ == "__main__":
    main()
