"""Whether a diagnosis can use a measurement, and its noise level: the checks the workflow makes on every file before
any long work (:func:`check_measurement`, with :func:`unit_problem` for channels not stored in SI), and where each
channel's σ comes from (:func:`noise_level`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from . import io, model, noise


def present_channels(measurement: io.Measurement, channels: Sequence[str]) -> tuple[str, ...]:
    """The ones of ``channels`` (``diagnosis.channels``, in its order) that ``measurement`` carries: what it is
    diagnosed on."""
    return tuple(c for c in channels if c in measurement.channels)


def check_measurement(measurement: io.Measurement, channels: Sequence[str], band_hz: float, path=None, *,
                      values: Mapping[str, float] | None = None) -> None:
    """Refuse, in one line naming ``path`` (else the measurement's name), a measurement a diagnosis
    cannot use: it carries none of ``channels``, or it states no noise level and its spectrum above ``band_hz`` is too
    thin to read σ from; given ``values`` (the rig and operating values at the file's condition), also a channel
    whose level is a unit's factor away from the rig's (:func:`unit_problem`).  A measurement with some of
    ``channels`` is diagnosed on those."""
    where = path if path is not None else measurement.name
    if not present_channels(measurement, channels):
        raise io.MeasurementError(
            where, f"carries none of the channels diagnosis.channels uses ({', '.join(channels)}); it has "
                   f"{', '.join(measurement.channels)}: add one of those channels to diagnosis.channels in the config, "
                   f"or name the file's columns/variables after the channels (docs/measurements.md)")
    if measurement.sigma is None and "snr_db" not in measurement.attrs:
        try:
            noise.floor_band(measurement.sampling.n_samples, measurement.sampling.fs, band_hz)
        except ValueError as error:
            raise io.MeasurementError(where, f"states no noise level (sigma or snr_db) and its {error}; state one in the file, "
                                             f"lower diagnosis.noise_band_hz or sample faster (docs/measurements.md)") from None
    if values is not None:
        unit_problem(measurement, values, where)


# A channel's level may differ from the linear model's band by this factor before it is called a unit mistake: the
# library's faults, the nonlinear coupling, noise and instruments out of spec move a displacement's RMS by far less,
# the displacement units below by 1000 at least.
TOLERANCE = 30.0
# The same for a mean (speed, torque), which the operating condition sets nearly exactly: no fault moves it by a
# factor, while the units' factors reach down to 2π (Hz) and 9.55 (rpm), inside TOLERANCE; a file at another speed or
# torque than its stated condition (the operating range's 1000 to 1500 rpm, 800 to 1800 N·m) stays inside.
MEAN_TOLERANCE = 3.0
UNIT_MATCH = 3.0  # a unit explains a ratio when its factor is within this factor of it
UNITS_DOC = "docs/measurements.md#units"
# Per channel kind: its SI unit as a message says it, and the units a recorder uses instead, with the factor by which
# each one's number exceeds the SI number.
KINDS = {
    "displacement": ("metres", {"millimetres": 1e3, "micrometres": 1e6, "mils": 1.0 / 2.54e-5}),
    "speed": ("rad/s", {"rpm": 60.0 / (2.0 * math.pi), "Hz": 1.0 / (2.0 * math.pi), "deg/s": 180.0 / math.pi}),
    "torque": ("N·m", {"kN·m": 1e-3}),
}
BEARING_CHANNELS = model.CHANNELS[:8]


def channel_kind(channel: str) -> str:
    return "displacement" if channel in BEARING_CHANNELS else "speed" if channel in ("w1", "w4") else "torque"


def expected_levels(values: Mapping[str, float]) -> dict[str, tuple[float, float]]:
    """(low, high) of each channel's level in SI at the condition of ``values`` (rig and operating, defaults for
    what it lacks), from the linear model's steady response to the two imbalances: a bearing channel's RMS over
    every pair of imbalance angles, ``w1``, ``w4`` and ``torque_c`` their means Ω and T0."""
    v = {**model.DEFAULTS, **values}
    M, C, K = model.linear_matrices(v)
    speed = model.omega(v)
    dynamic = K - speed**2 * M + 1j * speed * C
    n = len(model.NODES)
    amplitudes = []
    for name, node in (("u1", model.DISK_NODES["1"]), ("u4", model.DISK_NODES["4"])):
        # u Ω² (cos Ωt, sin Ωt) is the real part of u Ω² (1, −i) e^{iΩt}: y lags x by a quarter turn
        force = np.zeros(M.shape[0], dtype=complex)
        force[4 + node] = v[name] * speed**2
        force[4 + n + node] = -1j * v[name] * speed**2
        response = np.abs(np.linalg.solve(dynamic, force))
        amplitudes.append([response[4 + axis * n + node] for node in model.BEARING_NODES for axis in (0, 1)])
    a1, a4 = np.array(amplitudes)
    # the angles φ1, φ4 are unknown: the two 1× phasors add anywhere between opposed and aligned
    levels = {c: (abs(x - y) / math.sqrt(2.0), (x + y) / math.sqrt(2.0)) for c, x, y in zip(BEARING_CHANNELS, a1, a4, strict=True)}
    levels.update(w1=(speed, speed), w4=(speed, speed), torque_c=(float(v["T0"]), float(v["T0"])))
    return levels


def unit_problem(measurement: io.Measurement, values: Mapping[str, float], path=None) -> None:
    """Raise :class:`newdyn.io.MeasurementError` naming ``path`` (else the measurement's name) when a channel's level
    is outside what the rig at ``values`` can give by more than a fault could make it (:func:`expected_levels`), in
    one line with the ratio and the unit that likely explains it; the other channels off are named after it."""
    where = path if path is not None else measurement.name
    bands = expected_levels(values)
    v = {**model.DEFAULTS, **values}
    off = {}
    for row, channel in enumerate(measurement.channels):
        low, high = bands[channel]
        kind = channel_kind(channel)
        signal = measurement.y[row]
        # a displacement probe's static gap is a DC part the check must not read as level
        level = float(np.std(signal)) if kind == "displacement" else float(np.mean(signal))
        tolerance = TOLERANCE if kind == "displacement" else MEAN_TOLERANCE
        if high <= 0.0 or low / tolerance <= level <= high * tolerance:
            continue  # (without imbalance the linear rig predicts no displacement to compare with)
        off[channel] = _unit_line(channel, kind, level, low, high, v)
    if off:
        first, *others = off
        raise io.MeasurementError(where, off[first] + (f"; {', '.join(others)} too" if others else ""))


def _unit_line(channel: str, kind: str, level: float, low: float, high: float, values: Mapping[str, float]) -> str:
    """The problem of one channel off by ``level`` against its band [``low``, ``high``]: the ratio and the likely unit."""
    si, units = KINDS[kind]
    # the ratio to the band's nearer end: the least factor by which the level is off, whatever the imbalances' angles
    edge, end = (low, "least") if level < low else (high, "most")
    ratio = level / edge
    if kind == "displacement":
        what, reference = f"{channel}'s RMS", f"the {end} the rig's imbalances give ({edge:.2g} m at {values['speed_rpm']:g} rpm)"
    elif kind == "speed":
        what, reference = f"{channel}'s mean", f"the speed ({values['speed_rpm']:g} rpm = {edge:.3g} rad/s)"
    else:
        what, reference = f"{channel}'s mean", f"T0 ({edge:g} N·m)"

    def distance(factor: float) -> float:
        # how far level/factor, the number in SI were this the unit, lies from the band, in log
        si_level = level / factor
        return max(math.log(low / si_level) if low > 0 else 0.0, math.log(si_level / high), 0.0)

    if ratio > 0.0:
        unit = min(units, key=lambda name: (distance(units[name]), abs(math.log(ratio / units[name]))))
        if distance(units[unit]) <= math.log(UNIT_MATCH):
            return f"{what} is about {ratio:.3g} times {reference}: {unit}? store {si} ({UNITS_DOC})"
    return f"{what} is about {ratio:.3g} times {reference}, the factor of no unit newdyn knows: not the rig's level; " \
           f"store {si} ({UNITS_DOC})"


def noise_level(measurement: io.Measurement, rows: Sequence[int], band_hz: float) -> tuple[np.ndarray, str]:
    """Per-channel noise σ of the measurement's ``rows`` and where it came from."""
    if measurement.sigma is not None:
        return measurement.sigma[rows], "the file's sigma coordinate"
    y = measurement.y[rows]
    if "snr_db" in measurement.attrs:
        return noise.sigma_from_snr(y, float(measurement.attrs["snr_db"])), f"the file's snr_db = {measurement.attrs['snr_db']} dB"
    sigma, error = noise.noise_floor_sigma(y, measurement.sampling.fs, band_hz)
    return sigma, f"the noise floor above {band_hz:g} Hz (relative standard error {float(np.max(error / sigma)):.1%})"
