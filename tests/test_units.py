"""A file with a channel in another unit than SI (µm, mm, mil, rpm, Hz, kN·m) is refused before any fit, in one line
naming the channel, the factor and the unit; a file in SI passes, whatever its imbalance angles or fault; and the
linear model's band (:func:`newdyn.measurement_checks.expected_levels`) holds the simulated rig's levels."""

import math

import numpy as np
import pytest

from newdyn import io, measurement_checks, model, simulation, slots

SAMPLING = model.Sampling()
# what the rig's simulation is run at: the default rig, other imbalance angles, the library's faults at their scenario
# values (config/config.yaml) and a second speed
CASES = {
    "healthy": {},
    "angles": {"phi1": 2.0, "phi4": -1.0},
    "stick_slip": {"stick_slip": 1.0, "stick_slip.T_max": 1854.95},
    "breathing_crack": {"breathing_crack": 1.0, "breathing_crack.alpha": 0.3},
    "cubic_coupling": {"cubic_coupling": 1.0, "cubic_coupling.gamma": 0.5},
    "loose_bearing": {"loose_bearing": 1.0, "loose_bearing.gap": 2e-8},
    "slow": {"speed_rpm": 1100.0},
}
FAULTS = ("stick_slip", "breathing_crack", "cubic_coupling", "loose_bearing")
# The linear model's 1× response is the simulated one to within 0.6 %; the load pulsation's sidebands add about 1 % of
# the RMS in quadrature, so a simulated RMS may leave the band by this much.
SLACK = 0.02


@pytest.fixture(scope="module")
def simulated():
    """Each case's values (what the check is given: the rig without its fault, at the case's condition) and its
    measurement, every channel, simulated in one batch."""
    values = {name: slots.complete(case) for name, case in CASES.items()}
    y = simulation.simulate_batch(list(values.values()), SAMPLING, model.CHANNELS)
    found = {}
    for (name, full), signals in zip(values.items(), y, strict=True):
        operating = {p: full[p] for p in model.OPERATING_PARAMETERS}
        nominal = slots.complete({p: full[p] for p in model.PARAMETER_NAMES})  # the check knows no fault
        found[name] = (nominal, io.Measurement(name, model.CHANNELS, signals, SAMPLING, operating))
    return found


def scaled(measurement: io.Measurement, channel: str, factor: float) -> io.Measurement:
    y = measurement.y.copy()
    y[measurement.channels.index(channel)] *= factor
    return io.Measurement(measurement.name, measurement.channels, y, measurement.sampling, measurement.operating)


def refusal(measurement: io.Measurement, values) -> str:
    with pytest.raises(io.MeasurementError) as error:
        measurement_checks.unit_problem(measurement, values, "measurements/run.nc")
    line = str(error.value)
    assert "\n" not in line and line.startswith("measurements/run.nc: ")
    return line


@pytest.mark.parametrize("case", ["healthy", "angles", "slow", *FAULTS])
def test_a_file_in_si_passes(simulated, case):
    values, measurement = simulated[case]
    measurement_checks.unit_problem(measurement, values)
    measurement_checks.check_measurement(measurement, ["b1_x", "b2_x", "w1"], 1000.0, values=values)


@pytest.mark.parametrize(("channel", "factor", "unit", "si"), [
    ("b1_x", 1e6, "micrometres", "metres"),
    ("b2_y", 1e3, "millimetres", "metres"),
    ("b3_x", 1 / 2.54e-5, "mils", "metres"),
    ("w1", 60 / (2 * math.pi), "rpm", "rad/s"),
    ("w4", 1 / (2 * math.pi), "Hz", "rad/s"),
    ("w1", 180 / math.pi, "deg/s", "rad/s"),
    ("torque_c", 1e-3, "kN·m", "N·m"),
])
def test_a_channel_in_another_unit_is_named_with_its_factor_and_unit(simulated, channel, factor, unit, si):
    values, measurement = simulated["healthy"]
    line = refusal(scaled(measurement, channel, factor), values)
    assert f": {channel}'s " in line and f"{unit}? store {si} (docs/measurements.md#units)" in line
    ratio = float(line.split(" is about ", 1)[1].split(" times ", 1)[0])
    assert ratio == pytest.approx(factor, rel=0.01)  # the rig's level itself is known to well within 1 %


def test_the_messages_read_as_documented(simulated):
    values, measurement = simulated["healthy"]
    assert refusal(scaled(measurement, "w1", 60 / (2 * math.pi)), values) == (
        "measurements/run.nc: w1's mean is about 9.55 times the speed (1480 rpm = 155 rad/s): rpm? store rad/s "
        "(docs/measurements.md#units)")
    line = refusal(scaled(measurement, "b1_x", 1e6), values)
    assert line.startswith("measurements/run.nc: b1_x's RMS is about 1e+06 times the most the rig's imbalances give (8.4e-08 m "
                           "at 1480 rpm): micrometres? store metres")


def test_at_another_speed_the_speed_is_held_against_that_condition(simulated):
    values, measurement = simulated["slow"]
    assert "(1100 rpm = 115 rad/s): rpm?" in refusal(scaled(measurement, "w1", 60 / (2 * math.pi)), values)


def test_every_channel_off_is_named_in_the_one_line(simulated):
    values, measurement = simulated["healthy"]
    micrometres = scaled(scaled(measurement, "b1_x", 1e6), "b2_x", 1e6)
    line = refusal(scaled(micrometres, "w1", 60 / (2 * math.pi)), values)
    assert "b1_x's RMS" in line and line.endswith("; b2_x, w1 too")


def test_a_factor_of_no_unit_says_the_level_is_not_the_rigs(simulated):
    values, measurement = simulated["healthy"]
    line = refusal(scaled(measurement, "b1_x", 300.0), values)
    assert "about 300 times the most the rig's imbalances give" in line and "not the rig's level; store metres" in line and "?" not in line
    assert "not the rig's level; store rad/s" in refusal(scaled(measurement, "w1", -1.0), values)


def test_a_probes_static_gap_is_not_read_as_level(simulated):
    """A 1-mm gap is ten thousand times the vibration: the RMS about the mean ignores it."""
    values, measurement = simulated["healthy"]
    y = measurement.y.copy()
    y[measurement.channels.index("b1_x")] += 1e-3
    measurement_checks.unit_problem(io.Measurement("gap", measurement.channels, y, SAMPLING, measurement.operating), values)


def test_check_measurement_checks_units_only_when_given_the_values(simulated):
    values, measurement = simulated["healthy"]
    micrometres = scaled(measurement, "b1_x", 1e6)
    measurement_checks.check_measurement(micrometres, ["b1_x", "b2_x", "w1"], 1000.0)  # unchanged without values
    with pytest.raises(io.MeasurementError, match=r"^measurements/run\.nc: b1_x's RMS .* micrometres\?"):
        measurement_checks.check_measurement(micrometres, ["b1_x", "b2_x", "w1"], 1000.0, "measurements/run.nc", values=values)


@pytest.mark.parametrize("case", ["healthy", "angles", "slow"])
def test_the_linear_band_holds_the_simulated_levels(simulated, case):
    """The steady response of the linear rig to the two imbalances, over their angles, is the simulated RMS of every
    bearing channel, and the means are Ω and T0: at the default rig, other angles and another speed."""
    values, measurement = simulated[case]
    bands = measurement_checks.expected_levels(values)
    for row, channel in enumerate(measurement.channels):
        signal = measurement.y[row]
        level = np.std(signal) if channel in measurement_checks.BEARING_CHANNELS else np.mean(signal)
        low, high = bands[channel]
        assert low * (1 - SLACK) <= level <= high * (1 + SLACK), (channel, level, low, high)
    assert bands["w1"][0] == pytest.approx(2 * math.pi * values["speed_rpm"] / 60)


def test_the_band_follows_the_imbalances():
    """Twice the imbalances, twice the level; each imbalance alone gives one level, and the two together lie between
    their difference and their sum."""
    base = measurement_checks.expected_levels(model.DEFAULTS)
    doubled = measurement_checks.expected_levels({"u1": 2 * model.DEFAULTS["u1"], "u4": 2 * model.DEFAULTS["u4"]})
    motor, load = (measurement_checks.expected_levels({name: 0.0}) for name in ("u4", "u1"))
    for channel in measurement_checks.BEARING_CHANNELS:
        assert doubled[channel] == pytest.approx(tuple(2 * x for x in base[channel]))
        assert motor[channel][0] == pytest.approx(motor[channel][1]) and load[channel][0] == pytest.approx(load[channel][1])
        one, other = motor[channel][1], load[channel][1]
        assert base[channel] == pytest.approx((abs(one - other), one + other))
