"""Where a recording sits on the shaft's turn and the load's cycle, and the speed it runs at, found from its data."""

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from newdyn import alignment, diagnosis, faults, hypotheses, io, likelihood, model, noise, reference, running_speed, slots
from newdyn.settings import Settings
from newdyn.simulation import DEFAULT_MAX_STEP, simulate, simulate_batch

ROOT = Path(__file__).resolve().parents[1]

CHANNELS = ["b1_x", "b2_x", "w1"]
SAMPLING = model.Sampling()  # the model's record: from the warm-up on
# A machine's recording: its imbalances at angles nobody measured, the load at its own phase, started 0.8 s after
# the model's start (so its shaft is turned on as well), running 3 rpm above its nameplate.
RECORD = {"phi1": 2.3, "phi4": -1.9, "load_phase": 0.7}
START, OFFSET_RPM = 0.8134, 3.0


@pytest.fixture(scope="module")
def recording():
    truth = slots.complete({**RECORD, "speed_rpm": model.DEFAULTS["speed_rpm"] + OFFSET_RPM})
    clean = simulate(truth, model.Sampling(SAMPLING.fs, START, SAMPLING.n_samples), CHANNELS)
    noisy, sigma = noise.add_noise(clean, CHANNELS, 40.0, 5)
    return clean, noisy, np.asarray(sigma)


def test_the_running_speed_is_a_disk_speeds_mean_to_its_noise_and_the_once_per_revolution_line_near_it(recording):
    _, noisy, _ = recording
    true_rpm = model.DEFAULTS["speed_rpm"] + OFFSET_RPM
    mean = running_speed.estimate(CHANNELS, noisy, SAMPLING.fs, 1480.0, 12.0)
    assert (mean.channel, mean.how) == ("w1", "mean") and abs(mean.rpm - true_rpm) < 3 * mean.sd < 0.01
    line = running_speed.estimate(["b1_x"], noisy[:1], SAMPLING.fs, 1480.0, 12.0)
    assert line.how == "line" and abs(line.rpm - true_rpm) < 0.3  # the load's lines beside it: a start, not the value


def test_a_record_is_aligned_to_the_noise_whatever_its_start_angles_and_speed(recording):
    clean, noisy, sigma = recording
    nameplate = slots.complete({})
    speed = running_speed.measured("m.nc", CHANNELS, noisy, SAMPLING.fs, nameplate)
    assert speed == pytest.approx(1483.0, abs=0.01)
    found = alignment.align(noisy, sigma, CHANNELS, {**nameplate, "speed_rpm": speed}, SAMPLING, DEFAULT_MAX_STEP)
    assert found.compared == "lines" and found.chi2_stated > 1e3 and found.chi2_found < 2.0  # noise: (24 - 3) / 24 ± 0.3
    model_record = simulate({**nameplate, "speed_rpm": speed, **found.values}, SAMPLING, CHANNELS)
    shown = model_record - model_record.mean(axis=1, keepdims=True) + clean.mean(axis=1, keepdims=True)
    assert np.all(reference.relative_rms(shown, clean) < 0.1 * 10 ** (-40 / 20))  # a tenth of the noise
    # The load's phase at the model's record start is the truth's, turned by the 0.3134 s between the two starts.
    turned = RECORD["load_phase"] + 2 * math.pi * 12.0 * (START - SAMPLING.t_first)
    assert abs(model.wrap_angle(found.values["load_phase"] - turned)) < 0.01


def test_a_record_of_displacements_alone_gets_its_speed_fitted_with_the_angles(recording):
    _, noisy, sigma = recording
    found = alignment.align(noisy[:2], sigma[:2], CHANNELS[:2], slots.complete({}), SAMPLING, DEFAULT_MAX_STEP,
                            fit_speed=True)
    assert found.values["speed_rpm"] == pytest.approx(1483.0, abs=0.01)
    assert found.chi2_found < 2.0


def test_a_disk_speed_read_through_its_sensors_gain_is_corrected_by_the_shafts_line(recording):
    """A tachometer within its datasheet's 0.1 % still reads 1.5 rpm off: from its mean, a speed fitted with the angles
    and a prior of the datasheet's spread about that mean ends at the truth on a 1-s record; on a tenth of it, whose
    lines alone may not hold the speed, the prior keeps it within the tachometer's spread."""
    _, noisy, sigma = recording
    read = noisy * np.array([1.0, 1.0, 1.001])[:, None]
    start = running_speed.measured("m.nc", CHANNELS, read, SAMPLING.fs, slots.complete({}))
    assert start == pytest.approx(1483.0 * 1.001, abs=0.01)
    stated, spread = {**slots.complete({}), "speed_rpm": start}, 0.001 * start
    found = alignment.align(read, sigma, CHANNELS, stated, SAMPLING, DEFAULT_MAX_STEP, speed_sd=spread)
    assert found.values["speed_rpm"] == pytest.approx(1483.0, abs=0.01) and found.speed_sd == spread
    short = model.Sampling(SAMPLING.fs, SAMPLING.t_first, SAMPLING.n_samples // 10)
    found = alignment.align(read[:, : short.n_samples], sigma, CHANNELS, stated, short, DEFAULT_MAX_STEP, speed_sd=spread)
    assert abs(found.values["speed_rpm"] - start) < 3 * spread


def test_a_record_on_the_models_own_clock_keeps_its_stated_angles():
    clean = simulate(slots.complete({}), SAMPLING, CHANNELS)
    noisy, sigma = noise.add_noise(clean, CHANNELS, 40.0, 2)
    for compared in ("lines", "waveform"):
        found = alignment.align(noisy, np.asarray(sigma), CHANNELS, slots.complete({}), SAMPLING, DEFAULT_MAX_STEP,
                                compared=compared)
        assert found.values == {"phi1": 0.0, "phi4": 0.0, "load_phase": 0.0} and found.chi2_found == found.chi2_stated


def test_the_lines_hold_the_angles_where_a_fault_the_nominal_model_lacks_pulls_the_whole_waveform():
    """A hardening coupling reshapes the speed's waveform: the nominal model's best waveform turns the load's phase to
    cover it, the lines leave it almost where it is (a slipping joint moves even the load's fundamental: the
    diagnosis finds the angles again under its fit)."""
    truth = slots.complete({**RECORD, "cubic_coupling": 1.0, "cubic_coupling.gamma": 0.5})
    noisy, sigma = noise.add_noise(simulate(truth, SAMPLING, CHANNELS), CHANNELS, 40.0, 3)
    errors = {}
    for compared in ("lines", "waveform"):
        found = alignment.align(noisy, np.asarray(sigma), CHANNELS, slots.complete({}), SAMPLING, DEFAULT_MAX_STEP,
                                compared=compared)
        errors[compared] = abs(model.wrap_angle(found.values["load_phase"] - RECORD["load_phase"]))
    assert errors["lines"] < 0.25 * errors["waveform"]


@pytest.mark.parametrize(("stated", "problem"), [
    (1400.0, "speed_rpm is 1400 rpm, but the data run at 1483.0 rpm (the mean of w1)"),
])
def test_a_stated_speed_far_from_the_datas_is_one_line(recording, stated, problem):
    _, noisy, _ = recording
    with pytest.raises(io.MeasurementError, match=problem.replace("(", r"\(").replace(")", r"\)")):
        running_speed.measured("m.nc", CHANNELS, noisy, SAMPLING.fs, {**slots.complete({}), "speed_rpm": stated})


def test_a_disk_speed_and_a_displacement_that_disagree_are_one_line(recording):
    _, noisy, _ = recording
    slow = noisy.copy()
    slow[2] *= 1300.0 / 1483.0
    with pytest.raises(io.MeasurementError, match="w1's mean says 1300.0 rpm where the once-per-revolution line of b1_x"):
        running_speed.measured("m.nc", CHANNELS, slow, SAMPLING.fs, slots.complete({}))
    in_rpm = noisy.copy()
    in_rpm[2] *= 60 / (2 * math.pi)  # a unit, for the level checks to name
    assert running_speed.measured("m.nc", CHANNELS, in_rpm, SAMPLING.fs, slots.complete({})) == 1480.0


def test_the_standard_errors_are_the_spread_of_least_squares_estimates_and_an_unseen_angle_is_anywhere():
    """Linear least squares of a speed and an angle the residuals see, beside one they do not: over many noise draws
    the estimates spread as the standard errors say; the unseen angle reads π/√3, a uniform angle's sd."""
    rng = np.random.default_rng(3)
    jacobian = np.column_stack([rng.normal(size=(200, 2)), np.zeros(200)])
    truth = np.array([0.4, -1.2])
    estimates = np.array([np.linalg.lstsq(jacobian[:, :2], jacobian[:, :2] @ truth + rng.standard_normal(200), rcond=None)[0]
                          for _ in range(4000)])
    sd = alignment.standard_errors(jacobian, ["speed_rpm", "phi1", "phi4"])
    assert np.allclose(estimates.std(axis=0), [sd["speed_rpm"], sd["phi1"]], rtol=0.05)
    assert sd["phi4"] == pytest.approx(math.pi / math.sqrt(3))


def test_the_found_load_phase_is_the_truths_within_its_standard_error(recording):
    """The truth's load phase at the model's record start (the record started 0.3134 s later) lies within a few of its
    standard errors of the found one, which the lines give to milliradians, as they give both imbalances'."""
    _, noisy, sigma = recording
    found = alignment.align(noisy, sigma, CHANNELS, {**slots.complete({}), "speed_rpm": 1483.0}, SAMPLING, DEFAULT_MAX_STEP)
    turned = RECORD["load_phase"] + 2 * math.pi * 12.0 * (START - SAMPLING.t_first)
    assert abs(model.wrap_angle(found.values["load_phase"] - turned)) < 4 * found.sd["load_phase"]
    assert all(found.sd[name] < 0.01 for name in ("phi1", "phi4", "load_phase"))
    assert found.summary()["sd"] == found.sd


def test_the_load_phase_integrated_out_beside_a_faults_values_is_the_integral_over_the_phase():
    """A breathing crack's fit with the load's phase (and a kT1 drift) free: at rows of its values out to twice their
    posterior's spread, the profiled likelihood (one Gauss–Newton step from the phase's conditional mean, along the
    residual's derivative at the fit) plus what the phase's integral adds is log ∫ L dφ by quadrature over the phase."""
    settings = Settings.from_config(yaml.safe_load((ROOT / "config" / "config.yaml").read_text()))
    channels, sampling = ("b1_x", "w1"), model.Sampling(fs=5000.0, t_first=0.5, n_samples=1000)
    crack = {"alpha": 0.343, "angle": -1.67}
    truth = faults.scenario_values({"fault": {"kind": "breathing_crack", "parameters": crack}}, model.DEFAULTS)
    data, sigma = noise.add_noise(simulate(slots.complete({**truth, **RECORD}), sampling, channels), channels, 40.0, 3)
    sigma = np.asarray(sigma)
    values = slots.complete({**settings.rig, **{k: model.DEFAULTS[k] for k in model.OPERATING_PARAMETERS}, **RECORD})
    hypothesis = diagnosis._with_load_phase({h.name: h for h in settings.hypotheses()}["breathing_crack"], RECORD["load_phase"])
    fit = hypotheses.fit(hypothesis, data, sigma, values, sampling, channels,
                         [{**crack, "load_phase": RECORD["load_phase"], "kT1": values["kT1"]}], settings.max_step, search=False)
    names, profiled = alignment.phase_profiled(hypothesis, fit.theta, fit.covariance, data, sigma, channels, sampling,
                                               settings.max_step, values)
    own, phase = [hypothesis.parameters.index(n) for n in names], hypothesis.parameters.index("load_phase")
    rows = np.random.default_rng(1).multivariate_normal(fit.theta[own], 4 * fit.covariance[np.ix_(own, own)], 4)
    found = profiled(rows)
    for row, log_likelihood, log_integral, mean, sd in zip(rows, found.log_likelihood, found.log_integral, found.mean[:, 0],
                                                            found.sd[:, 0]):
        phases = mean + sd * np.linspace(-7.0, 7.0, 57)
        at = np.insert(np.repeat(row[None], len(phases), axis=0), phase, phases, axis=1)
        along = likelihood.log_likelihood(data, simulate_batch(hypothesis.parameter_rows(at, values), sampling, channels,
                                                               settings.max_step), sigma)
        exact = along.max() + math.log(np.trapezoid(np.exp(along - along.max()), phases))
        assert log_likelihood + log_integral == pytest.approx(exact, abs=0.01)
