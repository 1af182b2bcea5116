"""Speed of diagnosing one measurement (goal: <= 3 minutes on 2 cores), against that goal, for
a measurement of each kind: healthy, a parameter change, new dynamics, and new dynamics without a
noise level in the file (σ from the noise floor).

Run: python bench/bench_diagnosis.py   (needs no study results: it simulates its own measurements)
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numba
import yaml

from newdyn import diagnosis, faults, io, model, noise, simulation

GOAL_SECONDS = 180.0
STICK_SLIP = {"fault": {"kind": "stick_slip", "parameters": {"T_max": 1854.95, "r_k": 1.0}}}
CASES = {  # name -> (scenario, the file states its noise level)
    "healthy": ({}, True),
    "kT1 +8 %": ({"overrides": {"kT1": 3.25e6}}, True),
    "stick-slip": (STICK_SLIP, True),
    "stick-slip, no σ in file": (STICK_SLIP, False),
}


def main() -> None:
    numba.set_num_threads(2)
    logging.basicConfig(level=logging.WARNING)
    config = yaml.safe_load((Path(__file__).resolve().parents[1] / "config" / "config.yaml").read_text())
    settings = diagnosis.Settings.from_config(config)
    sampling = model.Sampling()  # the default record: 1 s at 5 kHz after 0.5 s warm-up
    operating = {k: config["operating"][k] for k in model.OPERATING_PARAMETERS}
    print("one measurement at 40 dB (b1_x, w1), 2 cores; the study's grids are not reused here (simulated in the job)")
    print(f"{'measurement':26s} {'time':>8s} {'vs goal':>8s}   verdict")
    for name, (scenario, known_sigma) in CASES.items():
        clean = simulation.simulate(faults.scenario_values(scenario, model.DEFAULTS), sampling, settings.channels)
        y, sigma = noise.add_noise(clean, settings.channels, 40.0, 1)
        m = io.Measurement(name, settings.channels, y, sampling, operating, sigma if known_sigma else None)
        t0 = time.perf_counter()
        v = diagnosis.diagnose(m, settings).verdict
        seconds = time.perf_counter() - t0
        print(f"{name:26s} {seconds:7.1f}s {seconds / GOAL_SECONDS:7.2f}×   {v['verdict']} {v['effect']} "
              f"(chi2 {v['chi2_before']:.3g} -> {v['chi2_after']:.3g})")


if __name__ == "__main__":
    main()
