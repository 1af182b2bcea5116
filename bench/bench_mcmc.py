"""Speed of a 1-parameter MCMC calibration on the real simulator (goal: ESS >= 1000 in <= 30 s
on one core), for each emcee move.

Run: python bench/bench_mcmc.py
"""

from __future__ import annotations

import time

import numba

from newdyn import calibration, mcmc_calibration, model, noise
from newdyn.sampling import MOVES, MCMCSettings
from newdyn.simulation import simulate

SAMPLING = model.Sampling()  # the default record: 1 s at 5 kHz after 0.5 s warm-up
CHANNELS = ["b1_x", "w1"]


def main() -> None:
    numba.set_num_threads(1)
    grid = calibration.GridSpec("kT1", 1.5e6, 4.5e6, 301)
    prior = calibration.NormalPrior(3.0e6, 0.5e6)
    data, sigma = noise.add_noise(simulate({"kT1": 3.25e6}, SAMPLING, CHANNELS), CHANNELS, 40.0, 1)
    coarse = calibration.simulate_grid({}, "kT1", grid.axis, SAMPLING, CHANNELS)
    start = calibration.calibrate(data, sigma, grid, prior, coarse, {}, SAMPLING, CHANNELS, 41, 1.1).posterior
    print("kT1_up at 40 dB, 16 walkers, 1 core; walkers start from the grid posterior")
    print(f"{'move':8s} {'steps':>6s} {'time':>8s} {'ESS bulk':>9s} {'R-hat':>7s} {'ESS/s':>7s}   goal: ESS >= 1000 in <= 30 s")
    for move in MOVES:
        for steps in (150, 400):
            settings = MCMCSettings(n_walkers=16, n_steps=steps, n_burn=30, seed=1, move=move)
            t0 = time.perf_counter()
            idata = mcmc_calibration.calibrate_mcmc(data, sigma, grid, prior, start, {}, SAMPLING, CHANNELS, settings)
            seconds = time.perf_counter() - t0
            ess, rhat = idata.attrs["ess_bulk"], idata.attrs["rhat"]
            print(f"{move:8s} {steps:6d} {seconds:7.1f}s {ess:9.0f} {rhat:7.4f} {ess / seconds:7.0f}")


if __name__ == "__main__":
    main()
