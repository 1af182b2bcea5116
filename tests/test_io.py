"""Measurement files (docs/measurements.md): round trips, and one clear line for every bad file."""

import json
import os
import warnings

import numpy as np
import pytest
import xarray as xr

from newdyn import model
from newdyn.io import MeasurementError, measurement_dataset, read_measurement, write_csv, write_json, write_netcdf

SAMPLING = model.Sampling(fs=5000.0, t_first=0.5, n_samples=600)
CHANNELS = ["b1_x", "w1"]
OPERATING = {"speed_rpm": 1500.0, "T0": 1500.0, "load_amp": 0.2, "load_freq": 10.0, "load_harm": 4.0}


def make_dataset(sigma=None):
    rng = np.random.default_rng(0)
    speed = 2 * np.pi * OPERATING["speed_rpm"] / 60  # a disk speed's mean, and a displacement's 1x line, the running speed
    y = rng.standard_normal((2, SAMPLING.n_samples)) * np.array([[1e-7], [0.4]]) + np.array([[0.0], [speed]])
    y[0] += 1e-6 * np.cos(speed * SAMPLING.times)
    return measurement_dataset(y, CHANNELS, SAMPLING, OPERATING, {"scenario": "x", "parameters": {"kT1": 3e6}}, sigma)


def test_netcdf_round_trip(tmp_path):
    ds = make_dataset(sigma=np.array([1e-9, 4e-3]))
    write_netcdf(ds, tmp_path / "m.nc")
    m = read_measurement(tmp_path / "m.nc")
    assert m.name == "m" and m.channels == tuple(CHANNELS)
    np.testing.assert_array_equal(m.y, ds["y"].values)
    np.testing.assert_array_equal(m.sigma, [1e-9, 4e-3])
    assert m.sampling.n_samples == SAMPLING.n_samples and m.sampling.steady  # compared with the model's steady state
    assert m.sampling.fs == pytest.approx(SAMPLING.fs, rel=1e-12)
    assert m.operating == OPERATING  # attributes override the defaults
    assert m.attrs["parameters"] == '{"kT1": 3000000.0}'


def test_csv_takes_operating_condition_from_defaults(tmp_path):
    ds = make_dataset()
    rows = np.column_stack([SAMPLING.times, ds["y"].values.T])
    np.savetxt(tmp_path / "m.csv", rows, delimiter=",", header="time,b1_x,w1", comments="", fmt="%.17g")
    m = read_measurement(tmp_path / "m.csv", OPERATING)
    np.testing.assert_allclose(m.y, ds["y"].values, rtol=1e-15)
    assert m.operating == OPERATING and m.sigma is None


@pytest.mark.parametrize("start", [0.0, -2.5, 1234.5678])
def test_the_recorders_clock_may_start_anywhere_and_the_model_compares_from_its_warm_up(tmp_path, start):
    ds = _retime(make_dataset(), start + np.arange(SAMPLING.n_samples) / SAMPLING.fs)
    write_netcdf(ds, tmp_path / "m.nc")
    m = read_measurement(tmp_path / "m.nc", warm_up=0.3)
    assert m.sampling == model.Sampling(SAMPLING.fs, 0.3, SAMPLING.n_samples, steady=True)
    settled = read_measurement(tmp_path / "m.nc").sampling  # by default when the reference rig has settled
    assert settled.steady and settled.t_first == pytest.approx(model.settling_time(), abs=1 / SAMPLING.fs)


def test_a_speed_the_data_contradict_is_replaced_a_few_rpm_off_and_refused_far_off(tmp_path):
    def written(stated):
        write_netcdf(make_dataset().assign_attrs(speed_rpm=stated), tmp_path / "m.nc")
        return tmp_path / "m.nc"

    assert read_measurement(written(1503.0)).operating["speed_rpm"] == pytest.approx(1500.0, abs=0.5)  # noise: 0.17 rpm
    assert read_measurement(written(1500.02)).operating["speed_rpm"] == 1500.02  # within what the data tell
    with pytest.raises(MeasurementError, match=r"speed_rpm is 1400 rpm, but the data run at 1499.7 rpm \(the mean of w1\)"):
        read_measurement(written(1400.0))


def test_write_is_atomic(tmp_path, monkeypatch):
    """A failing write leaves neither a partial file nor a temporary behind."""
    def fail(self, path, **kwargs):
        with open(path, "w") as partial:
            partial.write("partial")
        raise OSError("disk full")

    monkeypatch.setattr(xr.Dataset, "to_netcdf", fail)
    with pytest.raises(OSError):
        write_netcdf(make_dataset(), tmp_path / "m.nc")
    assert list(tmp_path.iterdir()) == []


def _nc(mutate):
    def build(path):
        ds = make_dataset()
        ds = mutate(ds)
        ds.to_netcdf(path)
        return path
    return build


def _csv(text):
    def build(path):
        path = path.with_suffix(".csv")
        path.write_text(text)
        return path
    return build


def _cycle_csv(n, fs=5000.0, columns="time,b1_x"):
    lines = [columns] + [f"{0.5 + k / fs!r},{float(np.sin(k))!r}" for k in range(n)]
    return "\n".join(lines) + "\n"


def _truncated(path):
    make_dataset().to_netcdf(path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def _retime(ds, times):
    return ds.assign_coords(time=times)


BAD_FILES = {
    "missing file": (lambda p: p, "file not found"),
    "truncated NetCDF": (_truncated, "unreadable or truncated"),
    "not NetCDF at all": (lambda p: (p.write_text("hello"), p)[1], "is not a NetCDF file"),
    "no y": (_nc(lambda ds: ds.rename({"y": "z"})), "no variable 'y'"),
    "no channel columns": (_csv("time\n0.5\n0.5002\n"), "no channel columns"),
    "unknown channel": (_nc(lambda ds: ds.assign_coords(channel=["b1_x", "w9"])), "unknown channel 'w9'"),
    "NaN": (_nc(lambda ds: ds.copy(data={"y": np.where(np.arange(600) == 7, np.nan, ds["y"].values)})), "non-finite"),
    "infinity in CSV": (_csv("time,w1\n0.5,1\n0.5002,inf\n"), "non-finite"),
    "non-increasing time": (_nc(lambda ds: _retime(ds, SAMPLING.times[::-1])), "not increasing"),
    "non-uniform time": (_nc(lambda ds: _retime(ds, SAMPLING.times ** 1.01)), "not uniform"),
    "shorter than a load cycle": (_csv(_cycle_csv(300)), "less than one load cycle"),
    "sampling rate out of reach": (_csv(_cycle_csv(200000, fs=2e6)), "sampling rate"),
    "operating attribute not a number": (_nc(lambda ds: ds.assign_attrs(T0="fast")), "attribute T0"),
    "operating attribute infinite": (_nc(lambda ds: ds.assign_attrs(speed_rpm=np.inf)), "attribute speed_rpm"),
    "ragged CSV": (_csv("time,b1_x,w1\n0.5,1,2\n0.5002,1\n0.5004,1,2\n"), "line 3 has 2 values where the header names 3 columns"),
    "CSV without data": (_csv("time,b1_x,w1\n"), "has a header but no data rows"),
    "unsupported type": (lambda p: (p.with_suffix(".mat").write_text("x"), p.with_suffix(".mat"))[1], "unsupported file type"),
}


@pytest.mark.parametrize("case", BAD_FILES)
def test_bad_file_gets_one_line_naming_it(tmp_path, case):
    build, problem = BAD_FILES[case]
    path = build(tmp_path / "bad.nc")
    with pytest.raises(MeasurementError) as error, warnings.catch_warnings():
        warnings.simplefilter("error")  # newdyn's line alone: no numpy warning printed before it
        read_measurement(path)
    message = str(error.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: ")
    assert problem in message


def _csv_rows(times, header="time,b1_x,w1", separator=",", decimal="."):
    """A CSV of ``times`` and two plausible channels, its numbers written with ``separator`` and ``decimal``."""
    rows = [separator.join(f"{v:.10g}".replace(".", decimal) for v in (t, 1e-7 * np.cos(155 * t), 155.0)) for t in times]
    return "\n".join([header.replace(",", separator), *rows]) + "\n"


# Bad files a user meets, each with the whole line it gets after "<file>: ".
USERS_BAD_FILES = {
    "garbage bytes named .nc": (
        lambda p: (p.write_bytes(b"\x13\x37\xfe\x00" * 500), p)[1],
        ("is not a NetCDF file: it starts with b'\\x137\\xfe\\x00' where a NetCDF file starts with b'CDF' or b'\\x89HDF'; "
        "write it with xarray's to_netcdf (docs/measurements.md#netcdf)")),
    "a CSV named .nc": (
        lambda p: (p.write_text(_csv_rows(SAMPLING.times)), p)[1],
        ("is not a NetCDF file: it starts with b'time' where a NetCDF file starts with b'CDF' or b'\\x89HDF' (text: a CSV "
        "file is named .csv); write it with xarray's to_netcdf (docs/measurements.md#netcdf)")),
    "semicolons between columns": (
        _csv(_csv_rows(SAMPLING.times, separator=";")),
        ("columns are separated by ';', the format needs commas, with a dot as the decimal mark (time,b1_x,w1 / "
        "0.5,1.2e-07,155.0; docs/measurements.md#csv)")),
    "semicolons and decimal commas": (
        _csv(_csv_rows(SAMPLING.times, separator=";", decimal=",")),
        ("columns are separated by ';', the format needs commas, with a dot as the decimal mark (time,b1_x,w1 / "
        "0.5,1.2e-07,155.0; docs/measurements.md#csv)")),
    "tabs between columns": (
        _csv(_csv_rows(SAMPLING.times, separator="\t")),
        ("columns are separated by '\\t', the format needs commas, with a dot as the decimal mark (time,b1_x,w1 / "
        "0.5,1.2e-07,155.0; docs/measurements.md#csv)")),
    "last row cut short": (
        _csv(_csv_rows(SAMPLING.times) + "0.62,1.1e-"),
        (f"line {SAMPLING.n_samples + 2}, the last, has 2 values where the header names 3 columns: the file looks cut short; "
        "write it again")),
    "time in milliseconds": (
        _csv(_csv_rows(1000.0 * SAMPLING.times)),
        ("sampling rate 5 Hz is below twice the shaft's rotation frequency (25 Hz): time looks like milliseconds (read as "
        "such, the rate is 5000 Hz); the time column must be in seconds: divide it by 1000")),
    "far too slow": (
        _csv(_csv_rows(0.5 + np.arange(50) / 0.01)),
        ("sampling rate 0.01 Hz is below twice the shaft's rotation frequency (25 Hz), too slow to show the rig's "
        "vibration: sample faster")),
    "empty CSV": (_csv(""), "is empty (0 bytes)"),
    "empty NetCDF": (lambda p: (p.write_bytes(b""), p)[1], "is empty (0 bytes)"),
    "CSV without a header": (
        _csv(_csv_rows(SAMPLING.times).split("\n", 1)[1]),
        ("has no header: its first line holds numbers; the first line must name the columns, time and then the channels "
        "(time,b1_x,w1; docs/measurements.md#csv)")),
    "CSV with another header": (
        _csv(_csv_rows(SAMPLING.times, header="t,b1_x,w1")),
        ("header starts with 't'; the first line must name the columns, time and then the channels (time,b1_x,w1; "
        "docs/measurements.md#csv)")),
    "text in a value": (_csv("time,b1_x,w1\n0.5,1e-7,155\n0.5002,1e-7,n/a\n"), "line 3, column w1: 'n/a' is not a number"),
    "sigma as a data variable": (
        _nc(lambda ds: ds.assign(sigma=("channel", [1e-9, 4e-3]))),
        ("sigma is a data variable, but the noise level is read from a coordinate sigma along channel: write it with "
        "ds.assign_coords(sigma=('channel', values)) (docs/measurements.md#the-noise-level)")),
}


@pytest.mark.parametrize("case", USERS_BAD_FILES)
def test_a_users_bad_file_gets_the_line_that_names_its_problem_and_fix(tmp_path, case):
    build, problem = USERS_BAD_FILES[case]
    path = build(tmp_path / "bad.nc")
    with pytest.raises(MeasurementError) as error, warnings.catch_warnings():
        warnings.simplefilter("error")
        read_measurement(path, OPERATING)
    assert str(error.value) == f"{path}: {problem}"


def test_comment_and_empty_lines_of_a_csv_are_skipped(tmp_path):
    text = _csv_rows(SAMPLING.times).replace("\n", "\n# acquisition paused? no\n\n", 1)
    (tmp_path / "m.csv").write_text(text)
    assert read_measurement(tmp_path / "m.csv", OPERATING).sampling.n_samples == SAMPLING.n_samples


def test_written_files_get_ordinary_permissions(tmp_path):
    write_netcdf(make_dataset(), tmp_path / "m.nc")
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "m.nc").stat().st_mode & 0o777 == 0o666 & ~umask


def test_json_is_strict_with_numpy_scalars_and_non_finite_numbers_as_null(tmp_path):
    write_json(tmp_path / "v.json", {"chi2": np.float64(1.02), "ok": np.bool_(True), "rhat": float("nan"),
                                     "rows": [{"z": -np.inf, "n": np.int64(3)}]})
    text = (tmp_path / "v.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"chi2": 1.02, "ok": True, "rhat": None, "rows": [{"z": None, "n": 3}]}


def test_csv_rows_by_column_name(tmp_path):
    write_csv(tmp_path / "t.csv", ["a", "b"], [{"a": 1, "b": "x"}, {"b": "y", "a": 2.5}])
    assert (tmp_path / "t.csv").read_text().splitlines() == ["a,b", "1,x", "2.5,y"]
