"""Discovery: the closed forms of Bayesian linear regression, the rig's linear response against statics and the
simulator, the catalogue's effect files, and the search on a measurement it must explain."""

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import integrate, stats

from newdyn import effects, faults, hypotheses, model, reference, sensors, simulation, slots
from newdyn import noise as measurement_noise
from newdyn.discovery import effect_file, force, search, verify
from newdyn.discovery.forms import FORMS, Peaks, Shape, Trajectory
from newdyn.discovery.linear import LinearRig
from newdyn.effects import Kinematics, RigValues
from newdyn.effects.check import effect_parameters_type

SIGMA = np.array([0.5, 2.0])


def smooth_sensitivity(rng, n_samples=120, n_basis=30, decay=8.0):
    """(2, n_samples, n_basis): each channel's decaying, oscillating response to pulses at the basis times."""
    t = np.arange(n_samples)[:, None] - np.linspace(0, n_samples - 10, n_basis)[None, :]
    channels = []
    for _ in SIGMA:
        frequency, gain = rng.uniform(0.1, 0.4), rng.uniform(0.5, 2.0)
        channels.append(np.where(t >= 0, gain * np.exp(-t / decay) * np.sin(frequency * t + 0.3), 0.0))
    return np.stack(channels)


def estimated(place, residual, sigma, sensitivity, times, scale_range):
    """The force behind ``residual`` on the columns of ``sensitivity``, as the search estimates it from their moments."""
    return force.estimate(place, force.Moments.of(residual, sigma, sensitivity), times, scale_range)


def noise(rng, n_samples=120):
    return rng.normal(size=(len(SIGMA), n_samples)) * SIGMA[:, None]


@pytest.mark.parametrize("n_basis", [30, 300])  # fewer pulses than data, and more
def test_evidence_and_posterior_at_one_scale_are_the_gaussian_closed_forms(n_basis):
    rng = np.random.default_rng(1)
    g = smooth_sensitivity(rng, n_basis=n_basis)
    residual = np.einsum("ctj,j->ct", g, rng.normal(0, 3.0, n_basis)) + noise(rng)
    s = 2.5
    result = estimated("here", residual, SIGMA, g, np.arange(n_basis), (s, s * (1 + 1e-10)))
    flat = g.reshape(residual.size, -1)
    noise_cov = np.diag(np.repeat(SIGMA**2, residual.shape[1]))
    expected = stats.multivariate_normal(np.zeros(residual.size), noise_cov + s**2 * flat @ flat.T).logpdf(residual.ravel())
    assert result.log_evidence == pytest.approx(expected, abs=1e-6)
    precision = flat.T @ np.linalg.solve(noise_cov, flat) + np.eye(n_basis) / s**2
    covariance = np.linalg.inv(precision)
    assert result.mean == pytest.approx(covariance @ flat.T @ np.linalg.solve(noise_cov, residual.ravel()), abs=1e-8)
    assert result.sd == pytest.approx(np.sqrt(np.diag(covariance)), rel=1e-7)
    without = stats.multivariate_normal(np.zeros(residual.size), noise_cov).logpdf(residual.ravel())
    assert result.log_bayes_factor == pytest.approx(expected - without, abs=1e-6)


def test_the_prior_scale_is_marginalized_over_its_log_uniform_prior():
    rng = np.random.default_rng(2)
    g = smooth_sensitivity(rng)
    residual = np.einsum("ctj,j->ct", g, rng.normal(0, 1.0, g.shape[2])) + noise(rng)
    low, high = 0.01, 100.0
    result = estimated("here", residual, SIGMA, g, np.arange(g.shape[2]), (low, high))

    def log_evidence_at(log_s):
        return estimated("here", residual, SIGMA, g, np.arange(g.shape[2]), (math.exp(log_s), math.exp(log_s) * (1 + 1e-10))).log_evidence

    peak = max(log_evidence_at(x) for x in np.linspace(math.log(low), math.log(high), 41))
    integral, _ = integrate.quad(lambda x: math.exp(log_evidence_at(x) - peak), math.log(low), math.log(high), limit=200)
    assert result.log_evidence == pytest.approx(peak + math.log(integral / (math.log(high) - math.log(low))), abs=1e-3)


def test_instrument_errors_fitted_beside_the_force_are_the_gaussian_closed_forms():
    """r = G c + B b + e with b ~ N(0, I) (an offset and a gain-like column per channel, one of them far wider than the
    data say): the regression on the whitened r and G gives the Bayes factor and the posterior of c of the Normal model
    with covariance σ²I + BBᵀ + s²GGᵀ."""
    rng = np.random.default_rng(4)
    g = smooth_sensitivity(rng)
    n_samples = g.shape[1]
    design = np.stack([np.column_stack([np.full(n_samples, 0.3 * sd), 50.0 * sd * np.sin(0.05 * np.arange(n_samples) + c)])
                       for c, sd in enumerate(SIGMA)])
    residual = np.einsum("ctj,j->ct", g, rng.normal(0, 3.0, g.shape[2])) + np.einsum("ctk,ck->ct", design, rng.normal(size=(2, 2))) + noise(rng)
    nuisance = force.Nuisance.of(design, SIGMA)
    s = 2.5
    whitened = nuisance.whiten(residual)
    result = force.regress_records([whitened], [SIGMA], [nuisance.whiten(g)], (s, s * (1 + 1e-10)))
    # the same products from the columns as they are, the whitened columns never formed (as the search's pulses)
    products = nuisance.whitened_products(np.einsum("ctj,ctk->cjk", g, g), np.einsum("ctj,ct->cj", g, whitened),
                                          np.einsum("ctj,ctk->cjk", g, nuisance.basis), whitened)
    formed = force.Moments.of(whitened, SIGMA, nuisance.whiten(g))
    unformed = force.Moments.of_channels(*products, whitened, SIGMA)
    assert unformed.gram == pytest.approx(formed.gram, rel=1e-10, abs=1e-12 * np.abs(formed.gram).max())
    assert unformed.projection == pytest.approx(formed.projection, rel=1e-10, abs=1e-12 * np.abs(formed.projection).max())
    assert unformed.squares == pytest.approx(formed.squares, rel=1e-12)
    flat = g.reshape(residual.size, -1)
    errors = np.zeros((residual.size, residual.size))
    for c in range(2):
        rows = slice(c * n_samples, (c + 1) * n_samples)
        errors[rows, rows] = SIGMA[c] ** 2 * np.eye(n_samples) + design[c] @ design[c].T
    with_force = stats.multivariate_normal(np.zeros(residual.size), errors + s**2 * flat @ flat.T).logpdf(residual.ravel())
    without = stats.multivariate_normal(np.zeros(residual.size), errors).logpdf(residual.ravel())
    assert result.log_bayes_factor == pytest.approx(with_force - without, abs=1e-6)
    covariance = np.linalg.inv(flat.T @ np.linalg.solve(errors, flat) + np.eye(g.shape[2]) / s**2)
    assert result.mean == pytest.approx(covariance @ flat.T @ np.linalg.solve(errors, residual.ravel()), abs=1e-8)
    assert result.sd == pytest.approx(np.sqrt(np.diag(covariance)), rel=1e-7)


def test_the_place_the_force_acts_on_wins_and_the_force_is_recovered_within_its_uncertainty():
    rng = np.random.default_rng(3)
    at = smooth_sensitivity(rng)
    elsewhere = at * np.array([1.0, 3.0])[:, None, None]  # seen through the same channels, in another proportion
    times = np.arange(at.shape[2])
    truth = 4.0 * np.sin(times / 3.0)
    residual = np.einsum("ctj,j->ct", at, truth) + noise(rng)
    right = estimated("right", residual, SIGMA, at, times, (0.01, 100.0))
    wrong = estimated("wrong", residual, SIGMA, elsewhere, times, (0.01, 100.0))
    assert right.log_evidence - wrong.log_evidence > 50 and right.log_bayes_factor > 50
    assert right.chi2_before > 3 and right.chi2_after < 1.0  # the fitted force absorbs a little noise too
    inside = np.abs(right.mean - truth) <= 2 * right.sd
    assert inside.mean() >= 0.9


def test_noise_alone_is_not_read_as_a_force():
    """The Occam factor: with no force in the residual, adding one lowers the evidence."""
    g = smooth_sensitivity(np.random.default_rng(4))
    factors = [estimated("here", noise(np.random.default_rng(seed)), SIGMA, g, np.arange(g.shape[2]), (0.01, 100.0)).log_bayes_factor
               for seed in range(20)]
    assert max(factors) < 1.0 and np.median(factors) < 0


def test_bad_shapes_and_scale_ranges_are_refused():
    g = smooth_sensitivity(np.random.default_rng(5))
    residual = np.zeros(g.shape[:2])
    with pytest.raises(ValueError, match="sensitivity must be"):
        estimated("here", residual, SIGMA, g[:, :-1], np.arange(g.shape[2]), (0.1, 1.0))
    with pytest.raises(ValueError, match="sigma must be"):
        estimated("here", residual, np.array([1.0, -1.0]), g, np.arange(g.shape[2]), (0.1, 1.0))
    with pytest.raises(ValueError, match="times must"):
        estimated("here", residual, SIGMA, g, np.arange(g.shape[2] - 1), (0.1, 1.0))
    with pytest.raises(ValueError, match="scale_range"):
        estimated("here", residual, SIGMA, g, np.arange(g.shape[2]), (1.0, 0.1))


# ------------------------------------------------------------------------- the rig's linear response, and the search

FS = 5000.0
RECORD = model.Sampling()  # rig.md's: 0.5 s of warm-up, 1 s recorded
BASE = slots.complete()


@pytest.fixture(scope="module")
def linear():
    return LinearRig.build(BASE, FS, 4 * 5000, ("w1", "w4", "torque_c", "b1_x", "b2_y"))


@pytest.mark.parametrize(("place", "w1_per_torque", "coupling_torque_per_torque"), [
    ("motor", "1/c_m", 0.0),  # a steady torque on the rotor: the motor's slope takes it, the shafts do not
    ("load", "1/c_m", -1.0),  # on the load: it travels back through the coupling to the motor
    ("coupling", 0.0, -1.0),  # across the coupling, like its own torque: the element relaxes by as much
    ("motor_shaft", 0.0, 0.0),  # across the motor shaft: balanced in the shaft, nothing moves on
])
def test_steady_torque_at_each_place_gives_the_static_closed_form(linear, place, w1_per_torque, coupling_torque_per_torque):
    response = linear.response(place, np.ones(4 * 5000))  # 4 s: every mode has decayed
    expected_w1 = 1.0 / model.motor_slope(BASE) if w1_per_torque == "1/c_m" else 0.0
    assert response[0, -1] == pytest.approx(expected_w1, abs=1e-9)
    assert response[1, -1] == pytest.approx(expected_w1, abs=1e-9)  # a rigid rotation: both disks alike
    assert response[2, -1] == pytest.approx(coupling_torque_per_torque, abs=1e-6)


@pytest.mark.parametrize("place", ["coupling", "b2_y"])
def test_the_pulses_products_are_those_of_each_hats_response_over_the_record(place):
    """The pulses' Gram matrices (from one response's lagged running sums) and their products with data (correlations
    with it) are those of the columns formed here from the linear model's response to each hat directly, seen on the
    record's samples first … first + n − 1, pulses before the record, in it and at its end alike."""
    first, n_record, spacing = 30, 120, 4
    rig = LinearRig.build(BASE, FS, first + n_record, ("w1", "b1_x", "b2_y"))
    pulses = rig.pulses(place, first, n_record, spacing)
    centres = pulses.centres
    assert centres[0] == spacing and centres[-1] < first + n_record
    k = np.arange(first + n_record)
    columns = np.stack([rig.response(place, np.clip(1.0 - np.abs(k - c) / spacing, 0.0, None))[:, first:] for c in centres], axis=2)
    scale = np.abs(columns).max(axis=(1, 2))
    products = np.einsum("ctj,ctk->cjk", columns, columns)
    assert np.all(np.abs(pulses.gram - products).max(axis=(1, 2)) <= 1e-12 * scale**2)
    x = np.random.default_rng(6).standard_normal((3, n_record, 2))
    assert np.all(np.abs(pulses.project(x) - np.einsum("ctj,ctm->cjm", columns, x)).max(axis=(1, 2)) <= 1e-12 * scale * n_record)


def test_steady_lateral_force_gives_the_static_deflection(linear):
    _, _, stiffness = model.linear_matrices(BASE)
    n = len(model.NODES)
    force = np.zeros(2 * n)
    force[model.NODES.index("b2") + n] = 1.0  # b2 in y
    static = np.linalg.solve(stiffness[4:, 4:], force)
    response = linear.response("b2_y", np.ones(4 * 5000))
    assert response[4, -1] == pytest.approx(static[model.NODES.index("b2") + n], rel=1e-6)
    assert response[3, -1] == pytest.approx(0.0, abs=1e-30)  # x does not see a force in y


def test_linear_response_to_a_crack_is_the_simulators_to_first_order():
    # A breathing crack adds -α/2 (1 - cos θ4) kT3 (x + β v) across the load shaft: along the healthy motion
    # that force, through the linear model, is the simulator's change to first order in α.
    channels = ("w1", "w4", "torque_c")
    grid = model.Sampling(FS, 0.0, 2500 + RECORD.n_samples)
    healthy = simulation.simulate(BASE, grid, channels)[:, 2500:]
    motion = Trajectory.simulate(BASE, FS, grid.n_samples, simulation.DEFAULT_MAX_STEP)
    x, v, theta4 = motion.x["load_shaft"], motion.v["load_shaft"], motion.theta["4"]
    linear = LinearRig.build(BASE, FS, grid.n_samples, channels)
    sigma = np.std(healthy, axis=1) * 0.01  # 40 dB
    sizes, errors = [], []
    for alpha in (0.02, 0.04):
        crack = faults.scenario_values({"fault": {"kind": "breathing_crack", "parameters": {"alpha": alpha}}}, model.DEFAULTS)
        change = simulation.simulate(slots.complete(crack), RECORD, channels) - healthy
        force_history = -0.5 * alpha * (1 - np.cos(theta4)) * BASE["kT3"] * (x + BASE["beta"] * v)
        predicted = linear.response("load_shaft", force_history)[:, 2500:]
        sizes.append(np.sqrt(np.mean((change / sigma[:, None]) ** 2)))
        errors.append(np.sqrt(np.mean(((change - predicted) / sigma[:, None]) ** 2)))
    assert errors[0] < 0.03 * sizes[0]
    assert sizes[1] / sizes[0] == pytest.approx(2.0, rel=0.05) and errors[1] / errors[0] == pytest.approx(4.0, rel=0.15)


def test_spectral_peaks_find_a_line_within_the_resolution_and_none_in_noise():
    rng = np.random.default_rng(4)
    t = RECORD.times
    noise_only = rng.normal(size=(2, t.size)) * SIGMA[:, None]
    assert search.spectral_peaks(noise_only, SIGMA, FS).frequencies == ()
    line = noise_only + np.array([[0.0], [1.0]]) * np.sin(2 * np.pi * 37.3 * t)  # its whitened power ~ 300
    peaks = search.spectral_peaks(line, SIGMA, FS)
    assert peaks.resolution == pytest.approx(1.0) and abs(peaks.frequencies[0] - 37.3) <= peaks.resolution / 4


@pytest.fixture(scope="module")
def motion():
    return Trajectory.simulate(BASE, FS, 2500 + RECORD.n_samples, simulation.DEFAULT_MAX_STEP)


@pytest.mark.parametrize("term", list(FORMS))
def test_each_forms_effect_file_loads_and_its_force_is_the_forms_basis(term, motion, tmp_path):
    form = FORMS[term]
    place, shape = next((p, s[0]) for p in form.places() if (s := form.shapes(motion, p, Peaks((49.4, 74.0), 1.0))))
    basis = form.basis(motion, place, shape)
    coefficients = np.linspace(0.4, 0.7, len(basis)) * np.where(term == "dead_zone", 1.0, 1e-3)
    candidate = search.Candidate(term, place, 0.0, shape, None, None, {
        name: {"value": value, "sd": 0.1 * abs(value), "hdi_low": 0.8 * value, "hdi_high": 1.2 * value, "unit": unit}
        for name, (value, unit) in form.parameters(coefficients, shape, place).items()}, 1.0, coefficients @ basis)
    generic, generic_content = effect_file.render_generic(term, place, shape)
    (tmp_path / f"{generic}.py").write_text(generic_content)
    assert effects.load_file(tmp_path / f"{generic}.py").parameter_names() == tuple(candidate.parameters)
    name, content = effect_file.render(candidate, "a measurement-1")
    assert name.startswith(generic) and name.isidentifier() and "measurement" not in generic_content
    (tmp_path / f"{name}.py").write_text(content)
    effect = effects.load_file(tmp_path / f"{name}.py")  # checked: declarations, units, ranges, finite forces
    assert effect.acts_on == place
    p = effect_parameters_type(effect)(**effect.defaults(BASE))
    rig = RigValues(**{name: BASE[name] for name in model.PARAMETER_NAMES}, Omega=model.omega(BASE))
    samples = range(2500, 2500 + RECORD.n_samples, 97)
    forces = [effect.force(Kinematics(motion.t[k], motion.x[place][k], motion.v[place][k], motion.theta["1"][k],
                                      motion.theta["4"][k], 0.0, 0.0, 0.0), p, rig, 0.0) for k in samples]
    assert forces == pytest.approx(list(coefficients @ basis[:, list(samples)]), rel=1e-9, abs=1e-12 * np.max(np.abs(forces)))


def test_a_loose_seat_seen_through_a_probe_reading_high_is_found_with_the_probes_errors_fitted_beside_it():
    # A loose b1 housing changes how much b1_x swings, as a probe's gain error does: the instruments read off the nominal
    # model first would take that part of it (and the search then names a line at 3x disk 4 on m4_x); fitted jointly
    # with every form, they leave the dead zone its own.
    channels, gap = ("b1_x", "w1"), 1e-8
    loose = faults.scenario_values({"fault": {"kind": "loose_bearing", "parameters": {"gap": gap}}}, model.DEFAULTS)
    seen = simulation.simulate(slots.complete(loose), RECORD, channels) * np.array([[1.03], [1.0]])  # b1_x reads 3 % high
    data, sigma = measurement_noise.add_noise(seen, channels, 40.0, 3)
    instruments = sensors.Instruments.of({"b1_x": sensors.Sensor(1e-6, 0.01, 2e-4), "w1": sensors.Sensor(0.01, 0.001, 2e-4)},
                                         channels, RECORD.fs)
    residual, design = sensors.linearized(data, simulation.simulate(BASE, RECORD, channels), sigma, instruments)
    found = search.discover(residual, sigma, BASE, RECORD, channels, simulation.DEFAULT_MAX_STEP, force.Nuisance.of(design, sigma))
    best = found.candidates[0]
    assert (best.term, best.acts_on) == ("dead_zone", "b1_x")
    assert best.parameters["clearance"]["value"] == pytest.approx(gap, rel=0.3)  # the clearance tried nearest the gap
    assert best.chi2_after < 0.3 * found.chi2_before


def test_a_small_breathing_crack_is_found_as_a_stiffness_turning_with_the_load(motion):
    # The crack is the library's, but the search knows only the catalogue: its top form must be a
    # stiffness modulated once per revolution of disk 4, and its frequency that speed.
    channels = ("b1_x", "w1")
    crack = faults.scenario_values({"fault": {"kind": "breathing_crack", "parameters": {"alpha": 0.02}}}, model.DEFAULTS)
    data, sigma = measurement_noise.add_noise(simulation.simulate(slots.complete(crack), RECORD, channels), channels, 40.0, 3)
    residual = data - simulation.simulate(BASE, RECORD, channels)
    found = search.discover(residual, sigma, BASE, RECORD, channels, simulation.DEFAULT_MAX_STEP)
    best = found.candidates[0]
    assert (best.term, best.shape.label) == ("angle_stiffness", "1x disk 4")
    assert best.frequency_hz == pytest.approx(BASE["speed_rpm"] / 60, rel=0.01)
    assert best.chi2_after < found.chi2_before and search.log_bayes_factor(best, found) > 10
    equal = search.equivalent(found, 3.0)
    assert ("angle_stiffness", "load_shaft") in equal and len(equal) > 1  # w1 alone cannot tell the shafts apart
    # ... the coupling's torque tells them apart (each one's fitted force through the linearized rig), a bearing not at all
    separable = [c for c in found.candidates if (c.term, c.acts_on) in equal]
    separating = search.separating_channels(separable, found, {"b2_x": 1e-9, "torque_c": 0.2})
    assert [row["channel"] for row in separating] == ["torque_c", "b2_x"]
    assert separating[0]["expected_log_bayes_factor"] > 10 and separating[1]["expected_log_bayes_factor"] == 0.0
    assert found.forces["load_shaft"].log_bayes_factor > 0 > found.forces["b1_x"].log_bayes_factor


TEST_EFFECTS = Path(__file__).parent / "effects"
SHORT = model.Sampling(5000.0, 0.2, 1000)  # 0.2 s warm-up, 0.2 s recorded: lines known to 5 Hz


TWO_SPEEDS = ({"speed_rpm": 1480.0}, {"speed_rpm": 1200.0})


def recorded_at(effect, parameters, conditions=TWO_SPEEDS, channels=("b1_x", "w1")):
    """The rig with the test ``effect`` (a file of tests/effects) at each of ``conditions``, simulated by newdyn.reference
    (SciPy, not the kernel) at 40 dB: each recording's residual against the nominal model at its condition, as
    discover_across takes them."""
    runs = []
    with effects.including(TEST_EFFECTS / f"{effect}.py"):
        for seed, changed in enumerate(conditions):
            condition = {**model.DEFAULTS, **changed}
            truth = faults.scenario_values({"fault": {"kind": effect, "parameters": parameters}}, condition)
            runs.append((condition, *measurement_noise.add_noise(reference.simulate_reference(truth, SHORT, channels), channels, 40.0, seed)))
    # the nominal model after the block: the kernel compiled for the built-in effects serves it
    return [(y - simulation.simulate(slots.complete(condition), SHORT, channels), sigma, slots.complete(condition), SHORT, channels, None)
            for condition, y, sigma in runs]


@pytest.mark.parametrize("effect, parameters, term, lines_hz", [
    ("torque_ripple", {"amplitude": 15.0, "order": 6.0}, "order", (148.0, 120.0)),  # 6 per revolution: moves with the speed
    ("motor_hum", {"amplitude": 15.0, "frequency": 148.0}, "periodic", (148.0, 148.0)),  # stays where it is
])
def test_two_speeds_tell_an_order_of_the_shaft_from_a_fixed_frequency_where_one_cannot(effect, parameters, term, lines_hz):
    across = search.discover_across(recorded_at(effect, parameters), simulation.DEFAULT_MAX_STEP)
    best = across.scores[0]
    assert best["term"] == term and best["log_bayes_factor"] > 100
    assert best["frequency_hz"] == pytest.approx(lines_hz, abs=SHORT.fs / SHORT.n_samples)
    rival = next(row for row in across.scores if row["term"] == {"order": "periodic", "periodic": "order"}[term])
    assert best["log_evidence"] - rival["log_evidence"] > 100  # one shape for both recordings: only the right form has one
    # At 1480 rpm the line lies at 6 orders of the shaft either way: that recording alone ranks the order a few nats
    # ahead whichever is true (its one shape against a frequency's many), so only the second speed decides.
    alone = {}
    for found_term, _, log_evidence in across.alone[0].scores:
        alone.setdefault(found_term, log_evidence)
    assert 0 < alone["order"] - alone["periodic"] < 15


def test_a_form_without_a_phase_is_one_physical_term_for_recordings_at_two_loads():
    """A cubic stiffening of fixed k3 (tests/effects/coupling_cubic.py) recorded at T0 1613 and 1100 N·m, where its basis
    δ³ has RMS about three times apart: scored across both, the cubic's one coefficient is one k3 for both recordings,
    and it explains them as well as each recording's own k3 does, with one coefficient fewer (a coefficient per unit
    of each recording's own basis RMS would be three different k3s, and nats worse).  Which torsional element holds it is
    not told, as every element's twist follows the transmitted torque; the place compared is the one found."""
    loads = ({"T0": 1613.0}, {"T0": 1100.0})
    across = search.discover_across(recorded_at("coupling_cubic", {"k3": 5e8}, loads, ("b1_x", "w1", "torque_c")), simulation.DEFAULT_MAX_STEP)
    best = across.scores[0]
    assert best["term"] == "cubic" and best["chi2_after"] < 1.0
    assert best["parameters"][0]["k3"] == best["parameters"][1]["k3"]
    alone = [next(log_z for term, place, log_z in found.scores if (term, place) == ("cubic", best["acts_on"])) for found in across.alone]
    assert 0 < best["log_evidence"] - sum(alone) < 10


def test_including_an_effect_file_adds_it_for_the_block_only(tmp_path):
    source = (Path(__file__).parent / "effects" / "torque_ripple.py").read_text()
    (tmp_path / "torque_ripple.py").write_text(source)
    before = list(effects.active())
    with effects.including(tmp_path / "torque_ripple.py") as effect:
        assert list(effects.active()) == [*before, "torque_ripple"] and effect.name == "torque_ripple"
        assert "torque_ripple.amplitude" in slots.slot_names()
        with pytest.raises(effects.EffectError, match="already active"), effects.including(tmp_path / "torque_ripple.py"):
            pass
    assert list(effects.active()) == before


def test_alone_makes_the_active_set_those_files_for_the_block_only(tmp_path):
    (tmp_path / "torque_ripple.py").write_text((TEST_EFFECTS / "torque_ripple.py").read_text())
    before = list(effects.active())
    with effects.alone([tmp_path / "torque_ripple.py"]) as (effect,):
        assert list(effects.active()) == ["torque_ripple"] and effect.name == "torque_ripple"
        assert [name for name in slots.slot_names() if name not in model.PARAMETER_INDEX] == [
            "torque_ripple", "torque_ripple.amplitude", "torque_ripple.order"]
    assert list(effects.active()) == before
    with pytest.raises(ValueError, match="at least one"), effects.alone([]):
        pass


def test_a_models_values_without_effects_are_its_rig_and_a_present_effect_is_refused():
    values = slots.complete({"kT1": 3.1e6})
    assert slots.without_effects(values) == {name: values[name] for name in model.PARAMETER_NAMES}
    with pytest.raises(ValueError, match="stick_slip"):
        slots.without_effects({**values, "stick_slip": 1.0})


def test_a_model_of_no_library_effect_gets_the_same_bits_in_a_kernel_of_its_own_effects_alone():
    """A found term's full fit runs in a kernel of its generic file alone: an absent effect adds nothing to the forces
    nor to the steps, so a model on a drifted rig gets the same bits there as in the kernel that also holds the library."""
    values = {"torque_ripple": 1.0, "torque_ripple.amplitude": 15.0, "kT1": 3.2e6}
    with effects.including(TEST_EFFECTS / "torque_ripple.py"):
        beside = simulation.simulate(values, SHORT)
    with effects.alone([TEST_EFFECTS / "torque_ripple.py"]):
        alone = simulation.simulate(values, SHORT)
    np.testing.assert_array_equal(alone, beside)
    assert np.ptp(alone[model.CHANNELS.index("w1")]) > 0


@pytest.mark.parametrize(("drift", "expected"), [
    ({"kT1": 4.5e6}, [{"friction": 16.0, "v_smooth": 6e-4, "kT1": 4.5e6}, {"friction": 16.0, "v_smooth": 6e-4}]),  # and at kT1's prior mean
    ({}, [{"friction": 16.0, "v_smooth": 6e-4}]),  # found beside the healthy model: one start
])
def test_a_found_terms_full_fit_starts_beside_its_drift_and_at_the_drifts_prior_mean(monkeypatch, drift, expected):
    """A drift can absorb part of the missing term (a friction across the coupling pushed kT1 to its grid's edge), so
    the term's full fit starts from the drift it was found beside and from the drift's prior mean, the best kept."""
    shape = Shape({"v_smooth": 6e-4}, "v_s 0.0006")
    rows = {"friction": {"value": 16.0, "sd": 1.0, "hdi_low": 14.0, "hdi_high": 18.0, "unit": "N·m"},
            "v_smooth": {"value": 6e-4, "sd": 0.0, "hdi_low": 6e-4, "hdi_high": 6e-4, "unit": "rad/s"}}
    candidate = search.Candidate("friction", "coupling", 0.0, shape, None, None, rows, 1.0, None)
    origin = hypotheses.Fit(hypotheses.Hypothesis("origin", "parameter_change", ()), drift, np.zeros((1, 1)), 0.0, 9.0, 0.0, 1)
    settings = SimpleNamespace(calibration_priors=lambda: {"kT1": hypotheses.Prior("kT1", 1.5e6, 4.5e6, 3.0e6, 5.0e5)},
                               drift=["kT1"], channels=("w1",), max_step=1e-4, instruments=lambda fs, colour: None)
    seen = []
    monkeypatch.setattr(hypotheses, "fit", lambda hypothesis, data, sigma, values, sampling, channels, starts, *_, **__: seen.append(starts))
    with effects.including(verify._generic_file("friction", "coupling", shape)) as effect:
        verify._full_fit(candidate, effect, None, None, {}, origin, model.Sampling(), settings)
    assert seen == [expected]


@pytest.mark.parametrize(("uncompiled", "together"), [({"coupling", "b1_x"}, ["b1_x", "coupling"]), ({"coupling"}, [])])
def test_full_fits_whose_kernels_are_not_compiled_share_one_kernel(monkeypatch, uncompiled, together):
    """Candidates whose kernels are not compiled yet are fitted with all their generic files active and no library
    effect, one kernel to compile; one whose kernel is compiled, or a lone one that is not, with its own file alone."""
    shape = Shape({"frequency": 50.0}, "50 Hz")
    candidates = [search.Candidate("periodic", place, 0.0, shape, 50.0, None, {}, 1.0, None) for place in ("coupling", "load", "b1_x")]
    monkeypatch.setattr(verify, "_compiled", lambda path: path.stem.removeprefix("discovered_periodic_") not in uncompiled)
    fitted = []

    def fit(candidate, effect, *_):
        assert all(name.startswith("discovered") for name in effects.active())  # no library effect compiled in
        fitted.append((candidate.acts_on, [name.removeprefix("discovered_periodic_") for name in effects.active()]))
        assert effect.name == f"discovered_periodic_{candidate.acts_on}"
        return candidate.acts_on

    monkeypatch.setattr(verify, "_full_fit", fit)
    fits, kernel_files = verify._full_fits(candidates, None, None, {}, None, None, None)
    assert [fits[id(c)] for c in candidates] == ["coupling", "load", "b1_x"]
    assert [active for place, active in fitted if place in together] == [together] * len(together)
    assert all(active == [place] for place, active in fitted if place not in together)
    assert not any(name.startswith("discovered") for name in effects.active())
    for c in candidates[:2]:  # what a fit's model is simulated with later: the kernel it was fitted in
        with verify.Discovered({}, None, kernel_files=tuple(kernel_files[id(c)])).as_fitted():
            beside = [name.removeprefix("discovered_periodic_") for name in effects.active()]
        assert beside == (together if c.acts_on in together else [c.acts_on])


def test_equivalent_placements_rest_on_the_full_fits_and_on_the_best_forms_linearized_scores():
    scores = (("dead_zone", "b3_x", 100.0), ("periodic", "b2_x", 99.0), ("dead_zone", "b2_x", 95.0),
              ("dead_zone", "b4_x", 90.0), ("dead_zone", "m2_x", 80.0), ("periodic", "m2_x", 94.0))
    found = search.Discovery([], scores, {}, 0.0, 1.0, None)
    # Fitted on the full simulator, b3_x falls far behind b2_x; b4_x was not fitted, but on the linearized model
    # it scores within the margin of b2_x; a line at m2_x does too, but another form's score there says nothing.
    fitted = {("dead_zone", "b3_x"): 50.0, ("dead_zone", "b2_x"): 70.0, ("periodic", "b2_x"): 66.0}
    assert verify._equivalent(found, fitted, 6.9) == [("dead_zone", "b2_x"), ("periodic", "b2_x"), ("dead_zone", "b4_x")]
    assert verify._equivalent(found, {}, 6.9) == []


def test_the_search_starts_from_healthy_or_a_drift_its_terms_full_fit_fits_not_from_another_calibration():
    """A calibration of a parameter outside ``drift`` that does not explain the data may have absorbed part of the
    missing term (a bearing stiffness moved toward its line), so the search starts from the best fit among healthy,
    the drifts that the found term's full fit fits jointly and the drifts that explain the data, whatever the others'
    evidence."""
    def fit(name, kind, log_evidence, parameters=()):
        priors = tuple(hypotheses.Prior(p, 0.0, 1.0) for p in parameters)
        return hypotheses.Fit(hypotheses.Hypothesis(name, kind, priors), {}, np.zeros((1, 1)), 0.0, 9.0, log_evidence, 1)

    fits = {"healthy": fit("healthy", "healthy", -900.0),
            "parameter_change:k_bx": fit("parameter_change:k_bx", "parameter_change", -100.0, ["k_bx"]),
            "parameter_change:kT1": fit("parameter_change:kT1", "parameter_change", -500.0, ["kT1"]),
            "stick_slip": fit("stick_slip", "stick_slip", -50.0, ["T_max", "r_k", "kT1"])}
    assert verify.search_base(fits, ["kT1"]).hypothesis.name == "parameter_change:kT1"
    assert verify.search_base(fits, []).hypothesis.name == "healthy"
    assert verify.search_base(fits, ["kT1", "k_bx"]).hypothesis.name == "parameter_change:k_bx"
    worse = {**fits, "parameter_change:kT1": fit("parameter_change:kT1", "parameter_change", -950.0, ["kT1"])}
    assert verify.search_base(worse, ["kT1"]).hypothesis.name == "healthy"
    # Run on request where a drift explains the data, the search looks beyond that drift.
    assert verify.search_base(fits, ["kT1"], explaining=["parameter_change:k_bx"]).hypothesis.name == "parameter_change:k_bx"
    assert verify.search_base(fits, ["kT1"], explaining=["stick_slip"]).hypothesis.name == "parameter_change:kT1"
