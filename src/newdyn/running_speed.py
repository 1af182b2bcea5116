"""The running speed a recording shows: a nameplate or attribute speed a few rpm off turns the imbalances' phase by
radians over a record, so the speed the model runs at is read from the data to the precision they allow.

A disk speed channel's mean is Ω in steady state (the motor delivers on average what the load takes): where a file
has one, the speed the file or the config states is kept where the data cannot tell it from theirs (within
:data:`AGREE_SDS` of the mean's standard error), else replaced by the data's.  A file of displacements alone shows
the speed in the shaft's once-per-revolution line, whatever the channels' unit or gain, but only to the load's lines
beside it: its stated speed is kept here and fitted with the angles (:mod:`newdyn.alignment`).  A stated speed that
the data put farther than :data:`FAR` from theirs is a bad file, not a speed to correct silently.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
from scipy import optimize

from . import model

FAR = 0.05  # a stated speed this far (relative) from the data's is an error in the file, not an offset to correct
AGREE_SDS = 3.0  # a stated speed within this many of the estimate's standard errors is kept
UNIT_LIKE = 2.0  # a disk speed this many times off the shaft's is in another unit (rpm, Hz), not another speed
DISPLACEMENTS = model.CHANNELS[:8]
SPEEDS = ("w1", "w4")
LINE_SPAN = 0.3  # the once-per-revolution line is looked for this far (relative) around the stated speed


def _line(y: np.ndarray, fs: float, frequency: float) -> complex:
    """The complex amplitude of ``y`` (mean removed) at ``frequency`` [Hz], by least squares on a cosine and a sine."""
    t = np.arange(y.size) / fs
    basis = np.stack([np.cos(2 * math.pi * frequency * t), np.sin(2 * math.pi * frequency * t), np.ones_like(t)], axis=1)
    coef = np.linalg.lstsq(basis, y, rcond=None)[0]
    return complex(coef[0], -coef[1])


def line_frequency(y: np.ndarray, fs: float, near: float, span: float = FAR) -> tuple[float, float]:
    """The frequency [Hz] of the strongest line of ``y`` within ``near`` ± ``span``·``near``, and its standard error
    (the Cramér-Rao bound of a sinusoid in white noise, the noise read from what the line leaves)."""
    n = y.size
    y = y - y.mean()
    padded = 8 * 2 ** math.ceil(math.log2(n))
    spectrum = np.abs(np.fft.rfft(y, padded))
    frequencies = np.fft.rfftfreq(padded, 1.0 / fs)
    inside = np.flatnonzero(np.abs(frequencies - near) <= span * near)
    if inside.size == 0:
        return math.nan, math.inf
    peak = frequencies[inside[np.argmax(spectrum[inside])]]
    step = fs / padded
    best = optimize.minimize_scalar(lambda f: -abs(_line(y, fs, f)), bounds=(peak - step, peak + step), method="bounded",
                                    options={"xatol": 1e-9 * near})
    frequency = float(best.x)
    amplitude = abs(_line(y, fs, frequency))
    t = np.arange(n) / fs
    residual = y - amplitude * np.cos(2 * math.pi * frequency * t + np.angle(_line(y, fs, frequency)))
    noise = float(np.std(residual))
    snr = amplitude**2 / (2.0 * max(noise, 1e-300) ** 2)
    sd = math.sqrt(6.0 / (n * (n**2 - 1.0) * snr)) * fs / (2.0 * math.pi)
    return frequency, sd


class Estimate(NamedTuple):
    rpm: float  # NaN where no channel shows the speed
    sd: float  # its standard error [rpm]
    channel: str | None
    how: str  # "mean" (a disk speed's) or "line" (a displacement's once-per-revolution line)

    @property
    def source(self) -> str:
        return f"the mean of {self.channel}" if self.how == "mean" else f"the once-per-revolution line of {self.channel}"


def estimate(channels: Sequence[str], y: np.ndarray, fs: float, stated_rpm: float, load_freq: float,
             speeds: Sequence[str] = SPEEDS) -> Estimate:
    """The speed as the data show it.  A disk speed's mean (of ``speeds``) over whole load cycles is Ω to the noise; a
    displacement's once-per-revolution line only to the lines beside it (the load's harmonics come within a fraction of
    a hertz of it), so it is the start of the speed's fit in :mod:`newdyn.alignment`, not its value."""
    rows = [i for i, c in enumerate(channels) if c in speeds]
    if rows:
        w = y[rows[0]]
        whole = max(2, int(math.floor(w.size / fs * load_freq + 1e-9) / load_freq * fs))  # whole load cycles
        noise = float(np.std(np.diff(w[:whole]))) / math.sqrt(2.0)
        scale = 60.0 / (2 * math.pi)
        return Estimate(float(np.mean(w[:whole])) * scale, noise / math.sqrt(whole) * scale, channels[rows[0]], "mean")
    rows = [i for i, c in enumerate(channels) if c in DISPLACEMENTS]
    if rows:
        found = [line_frequency(y[i], fs, stated_rpm / 60.0, LINE_SPAN) for i in rows]
        best = int(np.argmin([sd for _, sd in found]))
        frequency, sd = found[best]
        return Estimate(60.0 * frequency, 60.0 * sd, channels[rows[best]], "line")
    return Estimate(math.nan, math.inf, None, "none")


def measured(path, channels: Sequence[str], y: np.ndarray, fs: float, operating: Mapping[str, float]) -> float:
    """The speed [rpm] to model a recording at: the stated one where the data agree with it, else the data's; a stated
    speed farther than :data:`FAR` from the data's, or a disk speed and a displacement that disagree, is a
    :class:`newdyn.io.MeasurementError`."""
    from .io import MeasurementError

    stated, load_freq = float(operating["speed_rpm"]), float(operating["load_freq"])
    found = estimate(channels, y, fs, stated, load_freq)
    if not math.isfinite(found.rpm):
        return stated
    if abs(found.rpm - stated) > FAR * stated and found.how == "mean":
        line = estimate(channels, y, fs, stated, load_freq, speeds=())
        if abs(line.rpm - stated) <= FAR * stated:
            if abs(math.log(found.rpm / stated)) > math.log(UNIT_LIKE):  # a unit's factor: for the level checks to name
                return stated
            raise MeasurementError(path, f"{found.channel}'s mean says {found.rpm:.1f} rpm where {line.source} says "
                                         f"{line.rpm:.1f} rpm: one of them is not the shaft's speed")
    if abs(found.rpm - stated) > FAR * stated:
        raise MeasurementError(path, f"speed_rpm is {stated:g} rpm, but the data run at {found.rpm:.1f} rpm ({found.source}): "
                               "state the speed the machine ran at (or store w1 and w4 in rad/s)")
    if found.how != "mean" or abs(found.rpm - stated) <= AGREE_SDS * found.sd:
        return stated
    return found.rpm
