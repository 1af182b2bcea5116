"""Grid calibration on simulated measurements: the issue's expected results on a reduced record."""

import logging

import numpy as np
import pytest

from newdyn import calibration, comparison, faults, mcmc_calibration, model, noise
from newdyn.sampling import MCMCSettings
from newdyn.simulation import simulate

SAMPLING = model.Sampling(fs=5000.0, t_first=0.5, n_samples=2500)  # half the default record
CHANNELS = ["b1_x", "w1"]
GRIDS = {"kT1": calibration.GridSpec("kT1", 1.5e6, 4.5e6, 151), "kT3": calibration.GridSpec("kT3", 1.3e6, 3.7e6, 121)}
PRIORS = {"kT1": calibration.NormalPrior(3.0e6, 0.5e6), "kT3": calibration.NormalPrior(2.5e6, 0.4e6)}
STICK_SLIP = faults.scenario_values({"fault": {"kind": "stick_slip", "parameters": {"T_max": 1.15 * 1613.0}}}, model.DEFAULTS)


@pytest.fixture(scope="module")
def coarse_models():
    return {p: calibration.simulate_grid({}, p, g.axis, SAMPLING, CHANNELS) for p, g in GRIDS.items()}


def calibrate(coarse_models, truth, parameter, snr_db=40.0, seed=1):
    clean = simulate(truth, SAMPLING, CHANNELS)
    data, sigma = noise.add_noise(clean, CHANNELS, snr_db, seed)
    return calibration.calibrate(
        data, sigma, GRIDS[parameter], PRIORS[parameter], coarse_models[parameter], {}, SAMPLING, CHANNELS, 41, 1.1
    )


@pytest.mark.parametrize(
    "truth, parameter, value",
    [({}, "kT1", 3.0e6), ({}, "kT3", 2.5e6), ({"kT1": 3.25e6}, "kT1", 3.25e6), ({"kT3": 2.3e6}, "kT3", 2.3e6)],
    ids=["healthy-kT1", "healthy-kT3", "kT1_up", "kT3_down"],
)
def test_parameter_change_is_explained_by_its_parameter(coarse_models, truth, parameter, value):
    result = calibrate(coarse_models, truth, parameter)
    post = result.posterior
    assert post.mean == pytest.approx(value, rel=0.01)
    assert abs(post.mean - value) < 4 * post.sd  # and the truth lies inside the posterior
    assert result.n_peaks == 1 and result.verdict == "explained"
    n = SAMPLING.n_samples * len(CHANNELS)
    assert abs(result.chi2_red - 1) < 4 * np.sqrt(2 / n)  # the best fit reaches the noise
    # Refinement resolved the peak: several grid points within one posterior sd of the mean.
    assert np.sum(np.abs(post.grid - post.mean) < post.sd) >= 5


def test_the_best_fit_is_the_most_likely_model_of_every_pass(coarse_models):
    """The best fit comes from whichever pass holds the likelihood's maximum (a refined one, off the coarse grid)."""
    result = calibrate(coarse_models, {"kT1": 3.13e6}, "kT1")
    post = result.posterior
    best_value = post.grid[np.argmax(post.log_likelihood)]
    assert not np.any(np.isclose(GRIDS["kT1"].axis, best_value, rtol=0, atol=1.0))
    np.testing.assert_array_equal(result.best_fit, calibration.simulate_grid({}, "kT1", [best_value], SAMPLING, CHANNELS)[0])


def test_calibrations_run_together_give_each_its_result_alone_to_the_bit(coarse_models, monkeypatch):
    """Several measurements on both grids, their refinements simulated in shared batches (small ones here, so that
    cells of different tasks share a batch and a task's cells span two), give what each gets alone; a task whose
    cells another's already holds (here the same measurement twice) adds no simulation."""
    measurements = [noise.add_noise(simulate(truth, SAMPLING, CHANNELS), CHANNELS, 40.0, seed)
                    for seed, truth in enumerate([{}, {"kT1": 3.13e6}, STICK_SLIP], start=1)]
    sigma = measurements[0][1]
    tasks = [calibration.Task(data, GRIDS[p], PRIORS[p], coarse_models[p]) for data, _ in measurements for p in GRIDS]
    alone = [calibration.calibrate(t.data, sigma, t.spec, t.prior, t.coarse_models, {}, SAMPLING, CHANNELS, 41, 1.1)
             for t in tasks]
    monkeypatch.setattr(calibration, "REFINE_BATCH", 100)
    simulated = []
    batch = calibration.simulation.simulate_batch
    monkeypatch.setattr(calibration.simulation, "simulate_batch", lambda rows, *args: simulated.append(len(rows)) or batch(rows, *args))
    calibration.calibrate_many(tasks, sigma, {}, SAMPLING, CHANNELS, 41, 1.1)
    once, simulated[:] = sum(simulated), []
    together = calibration.calibrate_many(tasks + tasks[:2], sigma, {}, SAMPLING, CHANNELS, 41, 1.1)
    assert sum(simulated) == once
    for one, many in zip(alone + alone[:2], together, strict=True):
        for name in ("grid", "log_likelihood", "density"):
            np.testing.assert_array_equal(getattr(one.posterior, name), getattr(many.posterior, name))
        np.testing.assert_array_equal(one.best_fit, many.best_fit)
        np.testing.assert_array_equal(one.channel_log_likelihood, many.channel_log_likelihood)
        assert one.chi2_red == many.chi2_red


@pytest.mark.parametrize("parameter", ["kT1", "kT3"])
def test_stick_slip_is_not_explained_by_a_stiffness(coarse_models, parameter):
    """The paper's Fig. 4: calibrating kT1 or kT3 cannot absorb the stick-slip's new dynamics."""
    result = calibrate(coarse_models, STICK_SLIP, parameter)
    assert result.chi2_red > 10
    assert result.verdict == "not explained"


def test_summary_rows_carry_hellinger_distance_to_healthy():
    grid = np.linspace(0.0, 10.0, 1001)

    def result(scenario, mu):
        density = np.exp(-0.5 * (grid - mu) ** 2) / np.sqrt(2 * np.pi)
        return {"scenario": scenario, "parameter": "kT1", "snr_db": 40.0, "seed": 1, "method": "grid",
                "grid": grid, "posterior": density}

    rows = calibration.summary_rows([result("shifted", 6.0), result("healthy", 5.0), result("alone", 5.0) | {"seed": 2}])
    by_scenario = {(r["scenario"], r["seed"]): r for r in rows}
    assert by_scenario[("healthy", 1)]["hellinger_to_healthy"] == pytest.approx(0.0, abs=1e-6)
    closed_form = np.sqrt(1 - np.exp(-1 / 8))  # two unit Gaussians one sd apart
    assert by_scenario[("shifted", 1)]["hellinger_to_healthy"] == pytest.approx(closed_form, abs=1e-4)
    assert np.isnan(by_scenario[("alone", 2)]["hellinger_to_healthy"])
    assert list(rows[0]) == list(calibration.SUMMARY_COLUMNS)


def test_grid_posterior_resolves_a_narrow_peak(coarse_models):
    """At 40 dB the kT1 likelihood is ~100x narrower than the coarse grid spacing; refinement must
    still give a posterior that quadrature integrates correctly: it matches its Gaussian fit."""
    post = calibrate(coarse_models, {"kT1": 3.25e6}, "kT1").posterior
    assert post.sd < 0.5 * (GRIDS["kT1"].axis[1] - GRIDS["kT1"].axis[0])  # narrower than a coarse cell
    fine = np.linspace(post.mean - 6 * post.sd, post.mean + 6 * post.sd, 2001)
    gaussian = np.exp(-0.5 * ((fine - post.mean) / post.sd) ** 2)
    assert comparison.hellinger_densities(post.grid, post.density, fine, gaussian) < 0.01


def test_mcmc_on_the_simulator_agrees_with_the_grid(coarse_models):
    """The built-in cross-check: the 1-D MCMC posterior matches the grid posterior (Hellinger < 0.05)."""
    truth = {"kT1": 3.25e6}
    clean = simulate(truth, SAMPLING, CHANNELS)
    data, sigma = noise.add_noise(clean, CHANNELS, 40.0, 1)
    grid = calibration.calibrate(data, sigma, GRIDS["kT1"], PRIORS["kT1"], coarse_models["kT1"], {}, SAMPLING, CHANNELS, 41, 1.1)
    settings = MCMCSettings(n_walkers=16, n_steps=300, n_burn=30, seed=1)
    idata = mcmc_calibration.calibrate_mcmc(data, sigma, GRIDS["kT1"], PRIORS["kT1"], grid.posterior, {}, SAMPLING, CHANNELS, settings)
    row = mcmc_calibration.mcmc_summary(idata, "kT1", PRIORS["kT1"], grid.posterior, sigma, 1.1)
    assert row["converged"] and row["verdict"] == "explained"
    assert row["hellinger_to_grid"] < 0.05
    assert abs(row["mean"] - grid.posterior.mean) < 0.2 * grid.posterior.sd
    assert row["chi2_red"] == pytest.approx(grid.chi2_red, abs=0.01)


def test_grid_proposal_samples_the_simulators_posterior_with_few_simulations(coarse_models):
    """proposal="grid": walkers propose from the grid posterior and the simulator decides; nearly every move is
    accepted, so 8 walkers x 80 steps (680 simulations) give the convergence thresholds in one round, and the
    posterior agrees with the grid's and with the KDE sampler's (600 simulations per 100 steps more)."""
    truth = {"kT1": 3.25e6}
    clean = simulate(truth, SAMPLING, CHANNELS)
    data, sigma = noise.add_noise(clean, CHANNELS, 40.0, 1)
    grid = calibration.calibrate(data, sigma, GRIDS["kT1"], PRIORS["kT1"], coarse_models["kT1"], {}, SAMPLING, CHANNELS, 41, 1.1)
    settings = MCMCSettings(n_walkers=8, n_steps=80, n_burn=5, seed=1)
    idata = mcmc_calibration.calibrate_mcmc(data, sigma, GRIDS["kT1"], PRIORS["kT1"], grid.posterior, {}, SAMPLING, CHANNELS,
                                            settings, proposal="grid")
    row = mcmc_calibration.mcmc_summary(idata, "kT1", PRIORS["kT1"], grid.posterior, sigma, 1.1)
    assert row["converged"] and row["verdict"] == "explained"
    assert int(idata.attrs["rounds"]) == 1
    assert float(idata.sample_stats["acceptance_fraction"].mean()) > 0.8
    assert "grid posterior" in idata.attrs["sampler"]
    assert row["hellinger_to_grid"] < 0.08
    assert abs(row["mean"] - grid.posterior.mean) < 0.2 * grid.posterior.sd
    assert row["sd"] == pytest.approx(grid.posterior.sd, rel=0.15)
    with pytest.raises(ValueError, match="proposal must be one of"):
        mcmc_calibration.calibrate_mcmc(data, sigma, GRIDS["kT1"], PRIORS["kT1"], grid.posterior, {}, SAMPLING, CHANNELS,
                                        settings, proposal="nearest")


def test_posterior_cut_by_the_grid_bound_is_resolved_there(coarse_models):
    """Stick-slip pushes kT1 against the grid's upper bound: the posterior is the exponential tail the
    bound cuts, and the refinement must still put many points within its decay length."""
    post = calibrate(coarse_models, STICK_SLIP, "kT1").posterior
    assert post.map == GRIDS["kT1"].high
    assert np.sum(post.grid > post.map - post.sd) >= 5


def test_mcmc_of_a_posterior_cut_by_the_grid_bound_folds_back_into_the_range():
    """Stick-slip piles kT1 against the grid's upper bound (an exponential tail): the mirrored sampler
    keeps every draw in the range, centres on the grid posterior, and a run that calls itself
    converged also has its spread.  On a quarter-second record: every walker's step is a simulation of
    the rig with its kT1, three runs of 16 × 300."""
    record = model.Sampling(fs=5000.0, t_first=0.25, n_samples=1250)
    clean = simulate(STICK_SLIP, record, CHANNELS)
    data, sigma = noise.add_noise(clean, CHANNELS, 40.0, 1)
    spec = GRIDS["kT1"]
    models = calibration.simulate_grid({}, "kT1", spec.axis, record, CHANNELS)
    grid = calibration.calibrate(data, sigma, spec, PRIORS["kT1"], models, {}, record, CHANNELS, 41, 1.1)
    assert grid.posterior.map == spec.high
    converged = 0
    for seed in (1, 2, 3):
        settings = MCMCSettings(n_walkers=16, n_steps=300, n_burn=30, seed=seed)
        idata = mcmc_calibration.calibrate_mcmc(data, sigma, spec, PRIORS["kT1"], grid.posterior, {}, record, CHANNELS, settings)
        draws = idata.posterior["kT1"].values
        assert spec.low <= draws.min() and draws.max() <= spec.high
        row = mcmc_calibration.mcmc_summary(idata, "kT1", PRIORS["kT1"], grid.posterior, sigma, 1.1)
        assert abs(row["mean"] - grid.posterior.mean) < 0.2 * grid.posterior.sd
        if row["converged"]:
            converged += 1
            assert row["sd"] == pytest.approx(grid.posterior.sd, rel=0.1)
    assert converged >= 1  # R-hat ≤ 1.01 at a bound is reached in some runs of this length, not all


def test_the_studys_grid_files_are_found_by_their_parameter_and_reused(tmp_path, caplog):
    """A diagnosis is handed the study's grid files in the config's order, its settings hold the parameters in another:
    each file is matched by the parameter it says it holds, and reused for it."""
    from newdyn import cli

    sampling = model.Sampling(fs=5000.0, t_first=0.5, n_samples=50)
    window = {"fs": sampling.fs, "t_first": sampling.t_first, "n_samples": sampling.n_samples}
    grids = {"kT3": calibration.GridSpec("kT3", 2.0e6, 3.0e6, 3), "kT1": calibration.GridSpec("kT1", 2.5e6, 3.5e6, 3)}
    paths = []
    for name, grid in grids.items():
        paths.append(str(tmp_path / f"{name}.nc"))
        cli.simulate_grid_models({"parameter": name, "grid": {"low": grid.low, "high": grid.high, "points": grid.points},
                                  "values": dict(model.DEFAULTS), "sampling": window, "channels": CHANNELS, "max_step": 1e-4},
                                 paths[-1], "test")
    found = calibration.grid_files(paths)
    assert found == {"kT3": paths[0], "kT1": paths[1]}
    with caplog.at_level("INFO", logger="newdyn"):
        for name, grid in grids.items():
            reused = calibration.coarse_models(found[name], grid, model.DEFAULTS, sampling, CHANNELS)
            np.testing.assert_array_equal(reused, calibration.simulate_grid(model.DEFAULTS, name, grid.axis, sampling, CHANNELS))
        assert "simulating its grid" not in caplog.text
        calibration.coarse_models(found["kT3"], grids["kT1"], model.DEFAULTS, sampling, CHANNELS)
        assert "simulating its grid" in caplog.text


def test_a_study_grid_is_reused_for_a_record_at_its_condition_and_angles_and_simulated_again_at_others(tmp_path, caplog):
    """The workflow's coarse grid (written by the grid-models command) stands for a record at the study's condition;
    a record whose imbalances or load the diagnosis found at other angles gets its grid simulated at those."""
    from newdyn import cli, slots

    caplog.set_level(logging.INFO, logger="newdyn")
    grid = calibration.GridSpec("kT1", 2.5e6, 3.5e6, 5)
    spec = {"parameter": "kT1", "grid": {"low": grid.low, "high": grid.high, "points": grid.points},
            "sampling": {"fs": SAMPLING.fs, "t_first": SAMPLING.t_first, "n_samples": 500}, "channels": CHANNELS,
            "values": slots.complete({}), "max_step": 1e-4}
    cli.simulate_grid_models(spec, str(tmp_path / "kT1.nc"), "h")
    window = model.Sampling(SAMPLING.fs, SAMPLING.t_first, 500)
    stored = calibration.coarse_models(str(tmp_path / "kT1.nc"), grid, slots.complete({}), window, CHANNELS)
    assert "simulating its grid" not in caplog.text
    turned = calibration.coarse_models(str(tmp_path / "kT1.nc"), grid, slots.complete({"load_phase": 1.0}), window, CHANNELS)
    assert "simulating its grid" in caplog.text
    np.testing.assert_array_equal(stored, calibration.simulate_grid({}, "kT1", grid.axis, window, CHANNELS))
    from newdyn.reference import relative_rms

    assert np.all(relative_rms(turned, stored)[:, CHANNELS.index("w1")] > 0.1)  # the load's phase turned: w1 another
