"""What integrating the instruments' offsets, gains and delays out of the likelihood costs (goal: at most 20 %
more diagnosis time), side by side with exact instruments on the stages that evaluate it most: a drift's grid
calibration, a fault's fit (breathing crack with the drift, least squares through the windows) and the
likelihood of an MCMC batch.  Default record (1 s at 40 dB, the config's diagnosis channels), a healthy rig whose
b1_x reads 0.2 of its std high; the sensor model is docs/validation.md's (b1_x offset sd 100 nm, gain sd 2 %; w1 0.01 rad/s,
0.1 %; other channels exact), then the same with a delay sd of 0.2 ms on both.  With ``--diagnosis``, whole
diagnoses of every scenario of the config and of that measurement, with exact instruments and with the config's
datasheets (half an hour).

Run: python bench/bench_sensors.py [--diagnosis]
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numba
import numpy as np
import yaml

from newdyn import calibration, diagnosis, faults, hypotheses, io, likelihood, model, noise, sensors, simulation, slots
from newdyn.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
GOAL = 1.2
SENSORS = {"b1_x": sensors.Sensor(offset_sd=1e-7, gain_sd=0.02), "w1": sensors.Sensor(offset_sd=0.01, gain_sd=0.001)}
DELAYED = {c: sensors.Sensor(s.offset_sd, s.gain_sd, delay_sd=2e-4) for c, s in SENSORS.items()}


def timed(stage, scale, repeat=3) -> float:
    """Best of ``repeat`` wall times of ``stage(scale)``."""
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        stage(scale)
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    numba.set_num_threads(2)
    settings = Settings.from_config(yaml.safe_load((ROOT / "config" / "config.yaml").read_text()))
    sampling, channels = model.Sampling(), settings.channels
    values = slots.complete(settings.rig)
    clean = simulation.simulate(values, sampling, channels)
    data, sigma = noise.add_noise(clean, channels, 40.0, 3)
    data[0] += 0.2 * np.std(clean[0])
    instruments = {"offset, gain": sensors.Instruments.of(SENSORS, channels, sampling.fs),
                   "+ delay": sensors.Instruments.of(DELAYED, channels, sampling.fs)}
    spec, prior = settings.grids["kT1"], settings.priors["kT1"]
    coarse = calibration.coarse_models(None, spec, values, sampling, channels, settings.max_step)
    crack = next(h for h in settings.hypotheses() if h.name == "breathing_crack")
    batch = simulation.simulate_batch(np.repeat(crack.parameter_rows(np.array([[0.1, 3.0e6]]), values), 16, axis=0),
                                      sampling, channels, settings.max_step)
    stages = {
        "grid calibration of kT1": lambda s: calibration.calibrate(data, sigma, spec, prior, coarse, values, sampling, channels,
                                                                   settings.refine_points, settings.chi2_max, settings.max_step, s),
        "fit of breathing_crack + kT1": lambda s: hypotheses.fit(crack, data, sigma, values, sampling, channels,
                                                                 [{"alpha": 0.1}], settings.max_step, search=False, instruments=s),
        "likelihood of 16 walkers": lambda s: likelihood.log_likelihood(data, batch, sigma, instruments=s),
    }
    print(f"healthy rig, b1_x offset by 0.2 std, 1-s record at 40 dB ({', '.join(channels)}), 2 cores; best of 3")
    print(f"{'stage':32s} {'exact':>10s}" + "".join(f" {name:>14s} {'ratio':>6s}" for name in instruments) + f"   goal <= {GOAL:.1f}x")
    for name, stage in stages.items():
        exact = timed(stage, None)
        row = "".join(f" {t * 1e3:12.1f}ms {t / exact:5.2f}x" for t in (timed(stage, s) for s in instruments.values()))
        print(f"{name:32s} {exact * 1e3:8.1f}ms" + row)


def whole_diagnoses() -> None:
    """Every scenario of the config, and a healthy rig whose b1_x reads 0.2 std high, diagnosed with exact
    instruments and with the config's datasheets; the total over the measurements whose two verdicts agree (where
    they differ, the datasheets change what the diagnosis does, not only its cost)."""
    config = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    settings = Settings.from_config(config)
    sampling, channels = model.Sampling(), settings.channels
    operating = {k: config["operating"][k] for k in model.OPERATING_PARAMETERS}
    base = {**settings.rig, **operating}
    cases = [(name, faults.scenario_values(spec, base), 0.0) for name, spec in config["scenarios"].items()]
    cases.append(("healthy + b1_x offset", slots.complete(base), 0.2))
    print(f"whole diagnoses, 1-s record at 40 dB ({', '.join(channels)}), 2 cores")
    print(f"{'measurement':24s} {'exact':>9s} {'datasheets':>11s} {'ratio':>6s}   verdicts")
    total = np.zeros(2)
    for name, values, offset in cases:
        clean = simulation.simulate(values, sampling, channels)
        data, sigma = noise.add_noise(clean, channels, 40.0, 3)
        data[0] += offset * np.std(clean[0])
        measurement = io.Measurement(name, tuple(channels), data, sampling, operating, sigma)
        times, verdicts = [], []
        for chosen in (replace(settings, sensors={}), settings):
            start = time.perf_counter()
            verdicts.append(diagnosis.diagnose(measurement, chosen).verdict["verdict"])
            times.append(time.perf_counter() - start)
        if verdicts[0] == verdicts[1]:
            total += times
        print(f"{name:24s} {times[0]:8.0f}s {times[1]:10.0f}s {times[1] / times[0]:5.2f}x   {' / '.join(verdicts)}", flush=True)
    print(f"{'same verdicts, total':24s} {total[0]:8.0f}s {total[1]:10.0f}s {total[1] / total[0]:5.2f}x   goal <= {GOAL:.1f}x")


if __name__ == "__main__":
    if "--diagnosis" in sys.argv[1:]:
        whole_diagnoses()
    else:
        main()
