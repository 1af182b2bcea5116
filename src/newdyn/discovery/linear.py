"""The rig's response to a small added force at a place, from its linearization.

A missing effect is, to first order, a force history f(t) at a place added to a model that otherwise
fits; the channels answer with y = h * f, h the place's impulse response in the model linearized about
its motion (:func:`newdyn.model.linear_matrices`: torsional and lateral, the slip joint locked, no
imbalance).  Leaving out the imbalance drops the cross-domain responses, a torque's trace in the
bearing displacements and a lateral force's in the speeds: on the default rig at 40 dB these are
about 2 % of the same-domain response (tests/test_discovery.py measures it on the library's effects).

The force is taken as piecewise linear between the samples of the simulation's grid (t = k/fs from
t = 0, where the model starts), so the first-order-hold discretization is exact for it and the impulse
response is that of a unit hat at one sample.  Across the locked slip joint a force does nothing.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import signal

from .. import model
from ..effects import PLACES, TORSIONAL_BODIES

#: The linear model's torsional degree of freedom of each body: θ1 θ2 θ3 θ4, the locked joint's halves 2a and 2b one.
_DOF = {"theta1": 0, "theta2a": 1, "theta2b": 1, "theta3": 2, "theta4": 3}
#: Torsional places -> (DOF, sign) pairs: an element's force acts like its own spring torque, −τ on the motor-side
#: body, +τ on the other (see newdyn.effects.PLACES); the slip joint's two cancel, as it is internal to the locked joint.
TORSIONAL_INPUTS: Mapping[str, tuple[tuple[int, float], ...]] = {
    place: ((_DOF[a], 1.0),) if b is None else ((_DOF[a], -1.0), (_DOF[b], 1.0)) for place, (a, b) in TORSIONAL_BODIES.items()
}
N_TORSIONAL = 4
N_DOF = N_TORSIONAL + 2 * len(model.NODES)


def _input_vector(place: str) -> np.ndarray:
    b = np.zeros(N_DOF)
    if place in TORSIONAL_INPUTS:
        for dof, sign in TORSIONAL_INPUTS[place]:
            b[dof] += sign
        return b
    node, _, axis = place.rpartition("_")
    b[N_TORSIONAL + (0 if axis == "x" else len(model.NODES)) + model.NODES.index(node)] = 1.0
    return b


def _output_rows(channel: str, values: Mapping[str, float]) -> np.ndarray:
    """The channel as a row on the state (positions, then velocities)."""
    row = np.zeros(2 * N_DOF)
    if channel in ("w1", "w4"):
        row[N_DOF + (0 if channel == "w1" else 3)] = 1.0
    elif channel == "torque_c":
        row[[1, 2]] = values["kT2"] * np.array([1.0, -1.0])
        row[[N_DOF + 1, N_DOF + 2]] = values["beta"] * values["kT2"] * np.array([1.0, -1.0])
    else:
        node, _, axis = channel.partition("_")
        row[N_TORSIONAL + (0 if axis == "x" else len(model.NODES)) + model.NODES.index(node)] = 1.0
    return row


@dataclass(frozen=True)
class LinearRig:
    """Impulse responses of ``channels`` to a unit force at every place, on a grid of ``n_samples``
    samples at ``fs`` from t = 0: ``responses[place]`` is (channel, lag), ``spectra[place]`` its real
    FFT zero-padded to ``fft_size`` (≥ 2 n_samples − 1, so that products are linear convolutions)."""

    fs: float
    channels: tuple[str, ...]
    responses: Mapping[str, np.ndarray]
    spectra: Mapping[str, np.ndarray]
    fft_size: int

    @classmethod
    def build(cls, values: Mapping[str, float], fs: float, n_samples: int, channels: Sequence[str]) -> LinearRig:
        mass, damping, stiffness = model.linear_matrices(values)
        inverse_mass = np.linalg.inv(mass)
        a = np.block([[np.zeros((N_DOF, N_DOF)), np.eye(N_DOF)], [-inverse_mass @ stiffness, -inverse_mass @ damping]])
        places = list(PLACES)
        b = np.vstack([np.zeros((N_DOF, len(places))), inverse_mass @ np.column_stack([_input_vector(p) for p in places])])
        c = np.vstack([_output_rows(channel, values) for channel in channels])
        ad, bd, cd, dd, _ = signal.cont2discrete((a, b, c, np.zeros((len(channels), len(places)))), 1.0 / fs, method="foh")
        # A unit sample at k = 0 through the discrete system, for every place at once.
        responses = np.empty((n_samples, len(channels), len(places)))
        state = bd.copy()
        responses[0] = dd
        for k in range(1, n_samples):
            responses[k] = cd @ state
            state = ad @ state
        by_place = {p: np.ascontiguousarray(responses[:, :, i].T) for i, p in enumerate(places)}
        size = 1 << (2 * n_samples - 1).bit_length()
        return cls(float(fs), tuple(channels), by_place, {p: np.fft.rfft(r, size) for p, r in by_place.items()}, size)

    def response(self, place: str, force: np.ndarray) -> np.ndarray:
        """Each channel's response (channel, ..., time) to force histories (..., time) at ``place``,
        sampled on the grid from t = 0."""
        force = np.asarray(force, dtype=float)
        n = force.shape[-1]
        if n > self.responses[place].shape[1]:
            raise ValueError(f"a force of {n} samples is longer than the grid's {self.responses[place].shape[1]}")
        spectrum = self.spectra[place]
        out = np.fft.irfft(spectrum.reshape(spectrum.shape[:1] + (1,) * (force.ndim - 1) + spectrum.shape[1:])
                           * np.fft.rfft(force, self.fft_size), self.fft_size)
        return out[..., :n]

    def pulses(self, place: str, first: int, n_record: int, spacing: int) -> Pulses:
        """Unit hats of force at ``place`` of half-width ``spacing`` samples, centred every ``spacing`` samples from
        t = spacing/fs (the first hat whole) to the record's end, seen on the record (samples first … first + n_record − 1
        of the grid)."""
        centres = np.arange(spacing, first + n_record, spacing)
        lags = np.arange(-spacing + 1, spacing)
        unit = np.zeros(first + n_record)
        unit[lags + spacing] = 1.0 - np.abs(lags) / spacing  # the hat centred at sample `spacing`
        return Pulses(self.response(place, unit), centres, first, n_record, spacing)


@dataclass(frozen=True)
class Pulses:
    """The channels' responses to unit force pulses on a record: column j of their sensitivity G (channel, record sample,
    pulse) is the response ``one`` to the first hat shifted by a_j = centres[j] − spacing (time invariance), zero
    before the grid's start.  G is never formed: its Gram matrices come from running sums of ``one``'s lagged products
    and its products with data from correlations with ``one``."""

    one: np.ndarray  # (channel, grid) the response to the hat centred at sample `spacing`
    centres: np.ndarray  # the pulses' centres, in samples of the grid
    first: int  # the record's first sample on the grid
    n_record: int
    spacing: int

    @property
    def gram(self) -> np.ndarray:
        """Each channel's GᵀG (channel, pulse, pulse)."""
        return _shifted_gram(self.one, self.centres - self.spacing, self.first, self.spacing)

    def project(self, x: np.ndarray) -> np.ndarray:
        """Gᵀx of each channel for ``x`` (channel, record sample, ...), (channel, pulse, ...): Σ_t one(first + t − a_j)·x(t),
        the correlation of ``one`` with x by FFT (long enough that nothing wraps)."""
        x = np.asarray(x, dtype=float)
        size = 1 << (self.one.shape[1] + self.n_record - 1).bit_length()
        one = np.fft.rfft(self.one, size).reshape(self.one.shape[:1] + (-1,) + (1,) * (x.ndim - 2))
        correlation = np.fft.irfft(one * np.conj(np.fft.rfft(x, size, axis=1)), size, axis=1)
        return correlation[:, (self.first - (self.centres - self.spacing)) % size]


@njit(cache=True, error_model="numpy")
def _shifted_gram(one: np.ndarray, shifts: np.ndarray, first: int, spacing: int) -> np.ndarray:
    """Each channel's Σ_t one(t − a_i)·one(t − a_j) over the record t = first … n_grid − 1, shifts a_i = i·spacing and
    one(u < 0) = 0: for j = i + k, the sum of q(v) = one(v + k·spacing)·one(v) over v = t − a_j, the difference of
    q's running sum at the window's two ends (one pass over the grid for each k, not one product of two columns per
    pair)."""
    n_channels, n_grid = one.shape
    n_pulses = shifts.size
    gram = np.empty((n_channels, n_pulses, n_pulses))
    running = np.zeros(n_grid + 1)
    for c in range(n_channels):
        for k in range(n_pulses):
            lag = k * spacing
            total = 0.0
            for v in range(n_grid - lag):
                total += one[c, v + lag] * one[c, v]
                running[v + 1] = total
            for i in range(n_pulses - k):
                end = n_grid - shifts[i + k]
                start = min(max(first - shifts[i + k], 0), end)
                gram[c, i, i + k] = gram[c, i + k, i] = running[end] - running[start]
    return gram
