"""The index of measurement files: each file is read once per size, time stamp and settings."""

import os

import numpy as np
import pytest

from newdyn import catalog, model, noise
from newdyn.simulation import simulate

OPERATING = {name: model.DEFAULTS[name] for name in model.OPERATING_PARAMETERS}
CHANNELS = ["b1_x", "w1"]


def write_good(path):
    sampling = model.Sampling(5000.0, 0.5, 500)
    y, _ = noise.add_noise(simulate({}, sampling, CHANNELS), CHANNELS, 40.0, 1)
    np.savetxt(path, np.column_stack([sampling.times, y.T]), delimiter=",", header="time,b1_x,w1", comments="")


@pytest.fixture
def folder(tmp_path):
    measurements = tmp_path / "measurements"
    measurements.mkdir()
    write_good(measurements / "good.csv")
    (measurements / "empty.csv").write_text("time,b1_x,w1\n")
    (measurements / "twin.csv").write_text("time,b1_x,w1\n")
    (measurements / "twin.nc").write_text("")
    (measurements / "notes.txt").write_text("not a measurement")
    return measurements


def test_good_files_are_kept_and_each_bad_one_gets_one_line(folder, tmp_path):
    good, problems = catalog.good_measurements(folder, OPERATING, CHANNELS, 1000.0, tmp_path / "index.json")
    assert good == {"good": str(folder / "good.csv")}
    assert len(problems) == 2 and all("\n" not in line for line in problems)
    assert any(line.startswith(f"{folder / 'empty.csv'}: ") and "no data rows" in line for line in problems)
    assert any("share the name 'twin'" in line for line in problems)


def test_a_file_is_read_again_only_when_it_or_the_settings_change(folder, tmp_path, monkeypatch):
    index = tmp_path / "index.json"
    first = catalog.good_measurements(folder, OPERATING, CHANNELS, 1000.0, index)
    read = []
    original = catalog._problem
    monkeypatch.setattr(catalog, "_problem", lambda path, *args: read.append(path.name) or original(path, *args))
    assert catalog.good_measurements(folder, OPERATING, CHANNELS, 1000.0, index) == first and read == []
    stat = (folder / "good.csv").stat()
    os.utime(folder / "good.csv", ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))  # rewritten, same size
    catalog.good_measurements(folder, OPERATING, CHANNELS, 1000.0, index)
    assert read == ["good.csv"]
    read.clear()
    catalog.good_measurements(folder, OPERATING, ["b1_x"], 1000.0, index)  # other channels: every file again
    assert sorted(read) == ["empty.csv", "good.csv"]
