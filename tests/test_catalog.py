"""The index of measurement files: each file is read once per size, time stamp and settings."""

import math
import os
import re
from pathlib import Path

import numpy as np
import pytest

from newdyn import catalog, io, model, noise
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


def test_a_conditions_table_is_not_taken_for_a_recording(tmp_path):
    machine = tmp_path / "pump7"
    machine.mkdir()
    write_good(machine / "full_load.csv")
    (machine / "conditions.csv").write_text("recording,T0\nfull_load,1100\n")
    (tmp_path / "conditions.csv").write_text("recording,T0\n")
    assert catalog.good_measurements(tmp_path, OPERATING, CHANNELS, 1000.0, tmp_path / "index.json") == (
        {"pump7/full_load": str(machine / "full_load.csv")}, [])


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


def test_a_record_starting_between_the_model_grids_instants_is_taken_onto_its_grid(tmp_path):
    """Discovery's search simulates on the grid k/fs from t = 0: whatever the recorder's first stamp, and stamps
    rounded to microseconds, the model takes the record from the first instant of that grid after its warm-up."""
    fs = 3000.0
    times = 0.5 + np.arange(500) / fs
    y, _ = noise.add_noise(simulate({}, model.Sampling(fs, 0.5, 500), CHANNELS), CHANNELS, 40.0, 1)
    np.savetxt(tmp_path / "rounded.csv", np.column_stack([times, y.T]), delimiter=",", header="time,b1_x,w1", comments="",
               fmt=["%.6f", "%.10g", "%.10g"])
    np.savetxt(tmp_path / "off_grid.csv", np.column_stack([times + 0.4 / fs, y.T]), delimiter=",", header="time,b1_x,w1",
               comments="", fmt="%.10g")
    good, problems = catalog.good_measurements(tmp_path, OPERATING, CHANNELS, 1000.0, tmp_path / "index.json")
    assert sorted(good) == ["off_grid", "rounded"] and problems == []
    for path in good.values():
        sampling = catalog.checked_measurement(path, OPERATING, CHANNELS, 1000.0).sampling
        first = sampling.t_first * fs
        assert sampling.fs == fs and first == pytest.approx(round(first), abs=1e-9)
        assert round(first) == math.ceil(io.STEADY_WARM_UP * fs)  # the first instant of the grid after the warm-up


@pytest.mark.parametrize("reserved", catalog.MACHINE_FOLDERS)
def test_a_recording_named_like_its_machines_own_results_folder_is_refused_in_one_line(tmp_path, reserved):
    machine = tmp_path / "pump7"
    machine.mkdir()
    write_good(machine / "full_load.csv")
    write_good(machine / f"{reserved}.csv")
    write_good(tmp_path / f"{reserved}.csv")  # a lone file of that name has no machine's folder beside it
    good, problems = catalog.good_measurements(tmp_path, OPERATING, CHANNELS, 1000.0, tmp_path / "index.json")
    assert good == {"pump7/full_load": str(machine / "full_load.csv"), reserved: str(tmp_path / f"{reserved}.csv")}
    assert problems == [(f"{machine / reserved}.csv: a machine's recording may not be named '{reserved}', the name of the "
                         f"machine's own results folder results/diagnosis/pump7/{reserved}; rename the file")]


def test_the_reserved_names_are_the_folders_of_a_machines_results_in_the_workflow():
    rules = (Path(__file__).parents[1] / "workflow" / "rules" / "diagnose.smk").read_text()
    folders = {path.split("/")[0] for path in re.findall(r'"\{root\}/diagnosis/\{machine\}/([^"]+)"', rules) if "/" in path
               or "." not in path}
    assert folders == set(catalog.MACHINE_FOLDERS)
