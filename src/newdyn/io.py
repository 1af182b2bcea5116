"""Measurement files (``docs/measurements.md``): write simulated ones, read and check users'.

A measurement is ``y`` (channel, time) with coordinates ``time`` [s] (the recorder's clock: only the spacing of the
stamps matters, the record may start anywhere) and ``channel``; optional operating-condition attributes, ``snr_db``
or a per-channel ``sigma``.  The model compares its steady state with it: sample k is the model's state at
``warm_up + k/fs`` (:func:`model_sampling`), and where on the shaft's turn and the load's cycle the record starts is
found from the data (:mod:`newdyn.alignment`).  Every problem with a file is one :class:`MeasurementError` line naming
the file.
"""

from __future__ import annotations

import csv
import json
import math
import os
import tempfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import xarray as xr

from . import model, running_speed
from .measurement_files import CONDITIONS

OPERATING_ATTRS = model.OPERATING_PARAMETERS  # speed_rpm, T0, load_amp, load_freq, load_harm
TIME_JITTER = 1e-2  # allowed deviation of a time stamp from the uniform grid, in sample intervals
FS_MAX = 1.0e6  # above this the fixed-step kernel would need too many steps to be useful
STEADY_WARM_UP = model.settling_time()  # [s] the reference rig's
NETCDF_SIGNATURES = (b"CDF", b"\x89HDF")  # the first bytes of a classic NetCDF file and of a NetCDF-4 (HDF5) one


class MeasurementError(ValueError):
    """A bad measurement file; its message is one line: ``<file>: <problem>``."""

    def __init__(self, path: str | os.PathLike, problem: str):
        super().__init__(f"{path}: {problem}")


@dataclass(frozen=True)
class Measurement:
    name: str
    channels: tuple[str, ...]
    y: np.ndarray  # (channel, time)
    sampling: model.Sampling
    operating: dict[str, float]
    sigma: np.ndarray | None = None  # known per-channel noise σ, else None (to be inferred)
    attrs: dict = field(default_factory=dict)


def measurement_dataset(
    y: np.ndarray,
    channels: Sequence[str],
    sampling: model.Sampling,
    operating: Mapping[str, float],
    attrs: Mapping[str, object] | None = None,
    sigma: np.ndarray | None = None,
) -> xr.Dataset:
    """A measurement as an xarray Dataset; dict/list attributes are stored as JSON text."""
    data = xr.DataArray(
        np.asarray(y, dtype=np.float64),
        dims=("channel", "time"),
        coords={"channel": list(channels), "time": sampling.times},
        attrs={"long_name": "measured signal", "units": json.dumps({c: model.CHANNEL_UNITS[c] for c in channels})},
    )
    ds = xr.Dataset({"y": data})
    ds["time"].attrs.update(units="s", long_name="time")
    if sigma is not None:
        ds = ds.assign_coords(sigma=("channel", np.asarray(sigma, dtype=np.float64)))
        ds["sigma"].attrs.update(long_name="noise standard deviation", units="channel units")
    ds.attrs.update({name: float(operating[name]) for name in OPERATING_ATTRS})
    ds.attrs.update(
        {k: json.dumps(v, sort_keys=True) if isinstance(v, (dict, list, tuple)) else v for k, v in (attrs or {}).items()}
    )
    return ds


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> None:
    """Call ``write(temporary_path)`` and move the result onto ``path``: a crash leaves the old file
    or none, never half a file.  The file gets the permissions a plain ``open`` would give it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        write(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_netcdf(ds: xr.Dataset, path: str | os.PathLike) -> None:
    atomic_write(path, lambda tmp: ds.to_netcdf(tmp, engine="netcdf4"))


def netcdf_attribute(value):
    """A value as a netCDF attribute, which is text or a number: bools become 1/0, dicts and lists JSON text."""
    if isinstance(value, (bool, np.bool_)):
        return int(value)
    if isinstance(value, (str, int, float, np.integer, np.floating)):
        return value
    return json.dumps(value)


def write_csv(path: str | os.PathLike, columns: Sequence[str], rows: Sequence[Mapping]) -> None:
    """Rows (mappings by column name) as CSV with a header, atomically."""

    def write(tmp):
        with open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(columns))
            writer.writeheader()
            writer.writerows(rows)

    atomic_write(path, write)


def write_json(path: str | os.PathLike, document) -> None:
    """``document`` as strict JSON, atomically: NumPy scalars become numbers, non-finite numbers null."""

    def write(tmp):
        with open(tmp, "w") as f:
            json.dump(_finite_json(document), f, indent=1, allow_nan=False)
            f.write("\n")

    atomic_write(path, write)


def _finite_json(value):
    if isinstance(value, Mapping):
        return {str(k): _finite_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_json(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def read_measurement(path: str | os.PathLike, operating_defaults: Mapping[str, float] | None = None,
                     warm_up: float | None = STEADY_WARM_UP) -> Measurement:
    """Read and check a ``.nc`` or ``.csv`` measurement; operating values missing from it take the defaults.  Its
    sampling is the model's: the first sample ``warm_up`` (rounded up to the grid k/fs) after the model's start in its
    steady state (by default when the reference rig has settled there, :func:`newdyn.model.settling_time`); its
    running speed is the one its data show (:func:`newdyn.running_speed.measured`).  With ``warm_up`` None the file is
    one of the study's own simulations, on the model's clock at its stated condition (the study's calibrations)."""
    path = Path(path)
    if not path.is_file():
        raise MeasurementError(path, "file not found")
    if path.stat().st_size == 0:
        raise MeasurementError(path, "is empty (0 bytes)")
    suffix = path.suffix.lower()
    if suffix == ".nc":
        channels, times, y, attrs, sigma = _read_netcdf(path)
    elif suffix == ".csv":
        channels, times, y = _read_csv(path)
        attrs, sigma = {}, None
    else:
        raise MeasurementError(path, f"unsupported file type '{suffix}' (expected .nc or .csv)")

    unknown = [c for c in channels if c not in model.CHANNELS]
    if unknown:
        raise MeasurementError(path, f"unknown channel '{unknown[0]}' (known: {', '.join(model.CHANNELS)})")
    if len(set(channels)) != len(channels):
        raise MeasurementError(path, "a channel appears twice")
    if not np.all(np.isfinite(y)):
        c, k = np.argwhere(~np.isfinite(y))[0]
        raise MeasurementError(path, f"non-finite value {y[c, k]} in channel '{channels[c]}' at sample {k}")

    operating = dict(operating_defaults or {name: model.DEFAULTS[name] for name in OPERATING_ATTRS})
    operating.update(recorded_condition(path))
    for name in OPERATING_ATTRS:
        if name in attrs:
            value = attrs[name]
            problem = model.PARAMETER_BY_NAME[name].problem(value.item() if isinstance(value, np.generic) else value)
            if problem:
                raise MeasurementError(path, f"attribute {name} {problem}")
            operating[name] = float(value)

    sampling = _check_time(path, times, operating, warm_up)
    if warm_up is not None:
        stated = operating["speed_rpm"]
        operating["speed_rpm"] = running_speed.measured(path, channels, y, sampling.fs, operating)
        if operating["speed_rpm"] != stated:
            attrs["stated_speed_rpm"] = stated
    snr = attrs.get("snr_db")
    if sigma is None and snr is not None and (isinstance(snr, str) or not math.isfinite(float(snr))):
        raise MeasurementError(path, f"attribute snr_db must be a finite number (got {snr!r})")
    if sigma is not None and not (np.all(np.isfinite(sigma)) and np.all(sigma > 0)):
        raise MeasurementError(path, "coordinate sigma must be finite and positive")
    return Measurement(path.stem, tuple(channels), y, sampling, operating, sigma, dict(attrs))


def recorded_condition(path: str | os.PathLike) -> dict[str, float]:
    """The operating values that the ``conditions.csv`` beside a recording gives it: the row whose ``recording`` column
    is the file's name without suffix; columns of operating values (``speed_rpm``, ``T0``, ...), an empty cell for
    none.  A file's own attributes override these; the config's operating condition fills what neither gives."""
    path = Path(path)
    table = path.parent / CONDITIONS
    if not table.is_file():
        return {}
    with open(table, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    unknown = [c for c in (rows[0] if rows else {}) if c not in ("recording", *OPERATING_ATTRS)]
    if unknown:
        raise MeasurementError(table, f"unknown column '{unknown[0]}' (columns: recording, {', '.join(OPERATING_ATTRS)})")
    found = {}
    for number, row in enumerate(rows, start=2):
        if row.get("recording") != path.stem:
            continue
        for name in OPERATING_ATTRS:
            if row.get(name) not in (None, ""):
                try:
                    value = float(row[name])
                except ValueError:
                    raise MeasurementError(table, f"line {number}, column {name}: '{row[name]}' is not a number") from None
                problem = model.PARAMETER_BY_NAME[name].problem(value)
                if problem:
                    raise MeasurementError(table, f"line {number}, column {name} {problem}")
                found[name] = value
    return found


def _read_netcdf(path: Path):
    try:
        with xr.open_dataset(path, engine="netcdf4") as ds:
            ds.load()
    except Exception as exc:  # noqa: BLE001 - netCDF4 raises OSError, ValueError, RuntimeError, ... for damaged files
        with open(path, "rb") as f:
            start = f.read(4)
        if not start.startswith(NETCDF_SIGNATURES):
            text = all(32 <= byte < 127 or byte in b"\t\r\n" for byte in start)
            raise MeasurementError(path, f"is not a NetCDF file: it starts with {start!r} where a NetCDF file starts with "
                                         f"b'CDF' or b'\\x89HDF'{' (text: a CSV file is named .csv)' if text else ''}; "
                                         "write it with xarray's to_netcdf (docs/measurements.md#netcdf)") from None
        raise MeasurementError(path, f"unreadable or truncated NetCDF ({type(exc).__name__}: {exc})") from None
    if "y" not in ds:
        raise MeasurementError(path, "no variable 'y'")
    y = ds["y"]
    if set(y.dims) != {"channel", "time"}:
        raise MeasurementError(path, f"variable 'y' must have dims (channel, time), has {y.dims}")
    y = y.transpose("channel", "time")
    if "channel" not in y.coords or "time" not in y.coords:
        raise MeasurementError(path, "variable 'y' needs coordinates 'channel' and 'time'")
    channels = [str(c) for c in y["channel"].values]
    times = np.asarray(y["time"].values)
    if not np.issubdtype(times.dtype, np.number):
        raise MeasurementError(path, f"coordinate 'time' must be numeric seconds (is {times.dtype})")
    if "sigma" in ds.data_vars:
        raise MeasurementError(path, "sigma is a data variable, but the noise level is read from a coordinate sigma along "
                                     "channel: write it with ds.assign_coords(sigma=('channel', values)) "
                                     "(docs/measurements.md#the-noise-level)")
    sigma = np.asarray(ds["sigma"].values, dtype=float) if "sigma" in y.coords else None
    return channels, times.astype(float), np.asarray(y.values, dtype=float), dict(ds.attrs), sigma


def _read_csv(path: Path):
    try:
        with open(path, newline="") as f:
            header = f.readline().strip()
            lines = [(number, line) for number, line in enumerate(f.read().splitlines(), start=2)
                     if line.strip() and not line.lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as exc:
        raise MeasurementError(path, f"unreadable CSV ({exc})") from None
    names = [name.strip() for name in header.split(",")]
    separator = next((s for s in (";", "\t") if len(names) == 1 and s in header), None)
    if separator is not None:
        raise MeasurementError(path, f"columns are separated by {separator!r}, the format needs commas, with a dot as the "
                                     "decimal mark (time,b1_x,w1 / 0.5,1.2e-07,155.0; docs/measurements.md#csv)")
    if names[:1] != ["time"]:
        first = "has no header: its first line holds numbers" if _numbers(names) else f"header starts with {names[0]!r}"
        raise MeasurementError(path, f"{first}; the first line must name the columns, time and then the channels "
                                     "(time,b1_x,w1; docs/measurements.md#csv)")
    if len(names) < 2:
        raise MeasurementError(path, "no channel columns")
    if not lines:
        raise MeasurementError(path, "has a header but no data rows")
    for number, line in lines:
        if line.count(",") != len(names) - 1:
            where, cut = (f"line {number}, the last,", ": the file looks cut short; write it again") if number == lines[-1][0] \
                else (f"line {number}", "")
            raise MeasurementError(path, f"{where} has {line.count(',') + 1} values where the header names {len(names)} "
                                         f"columns{cut}")
    try:
        data = np.loadtxt([line for _, line in lines], delimiter=",", ndmin=2)
    except ValueError as exc:
        found = next(((number, name, text) for number, line in lines
                      for name, text in zip(names, line.split(",")) if not _numbers([text])), None)
        if found is None:
            raise MeasurementError(path, f"unreadable CSV ({exc})") from None
        number, column, text = found
        raise MeasurementError(path, f"line {number}, column {column}: {text.strip()!r} is not a number") from None
    return names[1:], data[:, 0], data[:, 1:].T.copy()


def _numbers(texts: Sequence[str]) -> bool:
    """Whether every one of ``texts`` reads as a number."""
    try:
        [float(text) for text in texts]
    except ValueError:
        return False
    return True


def _recorder_rate(times: np.ndarray) -> float:
    """The sampling rate the recorder was set to: the one of fewest significant digits whose grid holds every stamp
    within half the time check's tolerance (the stamps' last bits, or their rounding to microseconds, are not the rate)."""
    dt = (times[-1] - times[0]) / (times.size - 1)
    steps = np.arange(times.size)
    for digits in range(1, 16):
        fs = float(f"{1.0 / dt:.{digits}g}")
        if np.max(np.abs(times - times[0] - steps / fs)) <= 0.5 * TIME_JITTER / fs:
            return fs
    return 1.0 / dt


def model_sampling(fs: float, n_samples: int, warm_up: float) -> model.Sampling:
    """Where the model, started in its steady state, takes a record of ``n_samples`` at ``fs``: from the first instant
    k/fs at or after ``warm_up``, when what the linear steady state left out has died out (the kernel and discovery's
    search step on that grid)."""
    return model.Sampling(fs=fs, t_first=math.ceil(warm_up * fs - 1e-9) / fs, n_samples=n_samples, steady=True)


def _check_time(path: Path, times: np.ndarray, operating: Mapping[str, float], warm_up: float | None) -> model.Sampling:
    if times.size < 2:
        raise MeasurementError(path, f"only {times.size} sample(s)")
    if not np.all(np.isfinite(times)):
        raise MeasurementError(path, "non-finite time stamp")
    steps = np.diff(times)
    if np.any(steps <= 0):
        raise MeasurementError(path, f"time is not increasing (at sample {int(np.argmax(steps <= 0)) + 1})")
    dt = (times[-1] - times[0]) / (times.size - 1)
    worst = np.max(np.abs(times - (times[0] + dt * np.arange(times.size))))
    if worst > TIME_JITTER * dt:
        raise MeasurementError(path, f"time is not uniform (a stamp is {worst / dt:.3g} sample intervals off the grid)")
    fs = _recorder_rate(times)
    rotation_hz = operating["speed_rpm"] / 60.0
    if fs < 2.0 * rotation_hz:
        slow = f"sampling rate {fs:.4g} Hz is below twice the shaft's rotation frequency ({rotation_hz:.4g} Hz)"
        if 2.0 * rotation_hz <= 1000.0 * fs <= FS_MAX:
            raise MeasurementError(path, f"{slow}: time looks like milliseconds (read as such, the rate is {1000.0 * fs:.4g} "
                                         "Hz); the time column must be in seconds: divide it by 1000")
        raise MeasurementError(path, f"{slow}, too slow to show the rig's vibration: sample faster")
    load_freq = operating["load_freq"]
    if times.size * dt < 1.0 / load_freq:
        raise MeasurementError(
            path, f"{times.size} samples span {times.size * dt:.4g} s, less than one load cycle (1/{load_freq:g} Hz)"
        )
    if fs > FS_MAX:
        raise MeasurementError(path, f"sampling rate {fs:.6g} Hz is above the {FS_MAX:.0e} Hz the simulator reproduces")
    if warm_up is None:  # the model's own clock
        if times[0] < 0:
            raise MeasurementError(path, f"time starts at {times[0]:g} s, before the model's start at t = 0")
        return model.Sampling(fs=fs, t_first=float(times[0]), n_samples=int(times.size))
    return model_sampling(fs, int(times.size), warm_up)
