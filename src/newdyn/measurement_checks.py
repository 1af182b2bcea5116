"""Whether a diagnosis can use a measurement, and its noise level: the checks the workflow makes on every file before
any long work (:func:`check_measurement`), and where each channel's σ comes from (:func:`noise_level`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from . import io, noise
from .discovery import search


def present_channels(measurement: io.Measurement, channels: Sequence[str]) -> tuple[str, ...]:
    """The ones of ``channels`` (``diagnosis.channels``, in its order) that ``measurement`` carries: what it is
    diagnosed on."""
    return tuple(c for c in channels if c in measurement.channels)


def check_measurement(measurement: io.Measurement, channels: Sequence[str], band_hz: float, path=None) -> None:
    """Refuse, in one line naming ``path`` (else the measurement's name), a measurement a diagnosis
    cannot use: it carries none of ``channels``, its first sample is not on the grid k/fs from t = 0 (where the
    search for a missing term simulates), or it states no noise level and its spectrum above ``band_hz`` is too
    thin to read σ from.  A measurement with some of ``channels`` is diagnosed on those."""
    where = path if path is not None else measurement.name
    if not present_channels(measurement, channels):
        raise io.MeasurementError(
            where, f"carries none of the channels diagnosis.channels uses ({', '.join(channels)}); it has "
                   f"{', '.join(measurement.channels)}: add one of those channels to diagnosis.channels in the config, "
                   f"or name the file's columns/variables after the channels (docs/measurements.md)")
    try:
        search.record_start(measurement.sampling)
    except ValueError as error:
        raise io.MeasurementError(where, f"{error}: put the stamps on the rig clock's grid k/fs (resample the record) "
                                         "(docs/measurements.md#time-the-rigs-clock)") from None
    if measurement.sigma is None and "snr_db" not in measurement.attrs:
        try:
            noise.floor_band(measurement.sampling.n_samples, measurement.sampling.fs, band_hz)
        except ValueError as error:
            raise io.MeasurementError(where, f"states no noise level (sigma or snr_db) and its {error}; state one in the file, "
                                             f"lower diagnosis.noise_band_hz or sample faster (docs/measurements.md)") from None


def noise_level(measurement: io.Measurement, rows: Sequence[int], band_hz: float) -> tuple[np.ndarray, str]:
    """Per-channel noise σ of the measurement's ``rows`` and where it came from."""
    if measurement.sigma is not None:
        return measurement.sigma[rows], "the file's sigma coordinate"
    y = measurement.y[rows]
    if "snr_db" in measurement.attrs:
        return noise.sigma_from_snr(y, float(measurement.attrs["snr_db"])), f"the file's snr_db = {measurement.attrs['snr_db']} dB"
    sigma, error = noise.noise_floor_sigma(y, measurement.sampling.fs, band_hz)
    return sigma, f"the noise floor above {band_hz:g} Hz (relative standard error {float(np.max(error / sigma)):.1%})"
