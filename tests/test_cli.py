"""The command line a user runs by hand: --version, `newdyn check`, `newdyn check-config`, and one line for every
bad file, config or path given to any command (a bug keeps its traceback)."""

from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest

import newdyn
from newdyn import cli, io, model, noise
from newdyn.simulation import simulate

ROOT = Path(__file__).resolve().parents[1]
CONFIG = str(ROOT / "config" / "config.yaml")
CHANNELS = ["b1_x", "w1"]
SAMPLING = model.Sampling(5000.0, 0.5, 5000)
OPERATING = {name: model.DEFAULTS[name] for name in model.OPERATING_PARAMETERS}


def recorded(channels=CHANNELS, seed=1):
    """A healthy rig's record at the default condition with 40 dB noise: (signals, σ)."""
    return noise.add_noise(simulate({}, SAMPLING, channels), channels, 40.0, seed)


def write_csv(path, times=SAMPLING.times, separator=","):
    y, _ = recorded()
    rows = [separator.join(f"{v:.10g}" for v in row) for row in np.column_stack([times, y.T])]
    path.write_text("\n".join([separator.join(["time", *CHANNELS]), *rows]) + "\n")
    return path


def check(capsys, *paths, config=CONFIG):
    """(exit status, stdout lines, stderr lines) of `newdyn check --config <config> <paths>`."""
    status = cli.main(["check", "--config", str(config), *map(str, paths)])
    out, err = capsys.readouterr()
    return status, out.splitlines(), [line for line in err.splitlines() if line]


def test_version_is_the_packages(capsys):
    with pytest.raises(SystemExit) as done:
        cli.main(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out == f"newdyn {version('newdyn')}\n" == f"newdyn {newdyn.__version__}\n"


def test_a_good_csv_is_ok_with_what_the_diagnosis_will_use(tmp_path, capsys):
    path = write_csv(tmp_path / "run_0413.csv")
    status, out, err = check(capsys, path)
    assert status == 0 and err == []
    assert out == [(f"{path}: OK: channels b1_x, w1, diagnosed on b1_x, w1 (without b2_x of diagnosis.channels); 5000 Hz, "
                   "5000 samples, 1 s; noise level from the noise floor above 1000 Hz (relative standard "
                   "error 1.3%); operating condition speed_rpm 1480, T0 1613, load_amp 0.3, load_freq 12, load_harm 6")]


def test_a_machine_folder_is_checked_as_the_workflow_lists_it_each_recording_at_its_condition(tmp_path, capsys):
    machine = tmp_path / "measurements" / "pump7"
    machine.mkdir(parents=True)
    y, sigma = recorded()
    recording = io.measurement_dataset(y, CHANNELS, SAMPLING, OPERATING, sigma=sigma)
    del recording.attrs["T0"]  # its condition from conditions.csv
    io.write_netcdf(recording, machine / "full_load.nc")
    write_csv(machine / "part_load.csv", separator=";")
    (machine / "conditions.csv").write_text("recording,T0\nfull_load,1100\n")
    status, out, _ = check(capsys, tmp_path / "measurements")
    assert status == 1 and len(out) == 2
    assert out[0].startswith(f"{machine / 'full_load.nc'}: OK: ") and "the file's sigma coordinate" in out[0]
    assert out[0].endswith("speed_rpm 1480, T0 1100, load_amp 0.3, load_freq 12, load_harm 6")
    assert out[1].startswith(f"{machine / 'part_load.csv'}: columns are separated by ';'")


def test_a_folder_without_measurements_says_so(tmp_path, capsys):
    assert check(capsys, tmp_path)[:2] == (1, [f"{tmp_path}: holds no measurement file (.nc or .csv), nor a machine's folder of them"])


def test_the_check_uses_the_configs_merged_in_order(tmp_path, capsys):
    """diagnosis.channels of an override file decide what the file is diagnosed on, the rest is the default's."""
    path = write_csv(tmp_path / "m.csv")
    override = tmp_path / "w1_only.yaml"
    override.write_text("diagnosis:\n  channels: [w1]\n")
    status = cli.main(["check", "--config", CONFIG, "--config", str(override), str(path)])
    out = capsys.readouterr().out
    assert status == 0 and ", diagnosed on w1; 5000 Hz" in out


# Each bad file a user meets, and the line `newdyn check` prints for it after "<file>: ".
BAD_FILES = {
    "not NetCDF": (lambda p: (p.with_suffix(".nc").write_bytes(b"\x00\x01garbage" * 100), p.with_suffix(".nc"))[1],
                   ("is not a NetCDF file: it starts with b'\\x00\\x01ga' where a NetCDF file starts with b'CDF' or "
                   "b'\\x89HDF'; write it with xarray's to_netcdf (docs/measurements.md#netcdf)")),
    "semicolons": (lambda p: write_csv(p, separator=";"),
                   ("columns are separated by ';', the format needs commas, with a dot as the decimal mark (time,b1_x,w1 / "
                   "0.5,1.2e-07,155.0; docs/measurements.md#csv)")),
    "truncated": (lambda p: (write_csv(p), p.write_text(p.read_text()[:-20]), p)[2],
                  ("line 5001, the last, has 2 values where the header names 3 columns: the file looks cut short; write it "
                  "again")),
    "milliseconds": (lambda p: write_csv(p, times=1000.0 * SAMPLING.times),
                     ("sampling rate 5 Hz is below twice the shaft's rotation frequency (24.67 Hz): time looks like "
                     "milliseconds (read as such, the rate is 5000 Hz); the time column must be in seconds: divide it by "
                     "1000")),
    "missing": (lambda p: p, "file not found"),
    "empty": (lambda p: (p.write_text(""), p)[1], "is empty (0 bytes)"),
    "no header": (lambda p: (write_csv(p), p.write_text(p.read_text().split("\n", 1)[1]), p)[2],
                  ("has no header: its first line holds numbers; the first line must name the columns, time and then the "
                  "channels (time,b1_x,w1; docs/measurements.md#csv)")),
    "speed far from the stated": (lambda p: (p.with_name("conditions.csv").write_text(f"recording,speed_rpm\n{p.stem},1300\n"),
                                             write_csv(p))[1],
                                  ("speed_rpm is 1300 rpm, but the data run at 1480.0 rpm (the mean of w1): state the speed "
                                   "the machine ran at (or store w1 and w4 in rad/s)")),
    "a name the workflow refuses": (lambda p: write_csv(p.with_name("run 1.csv")),
                                    "names of files and folders may hold letters, digits, '_', '-' and '.' only"),
}


@pytest.mark.parametrize("case", BAD_FILES)
def test_a_bad_file_gets_one_line_naming_it_and_the_problem(tmp_path, capsys, case):
    build, problem = BAD_FILES[case]
    path = build(tmp_path / "m.csv")
    status, out, err = check(capsys, path)
    assert (status, out, err) == (1, [f"{path}: {problem}"], [])


def test_every_file_gets_its_line_and_one_bad_file_fails_the_check(tmp_path, capsys):
    good, bad = write_csv(tmp_path / "good.csv"), tmp_path / "gone.csv"
    status, out, _ = check(capsys, good, bad)
    assert status == 1 and [line.split(": ")[:2] for line in out] == [[str(good), "OK"], [str(bad), "file not found"]]


def test_a_config_that_is_good_is_ok(capsys):
    assert cli.main(["check-config", CONFIG]) == 0
    assert capsys.readouterr().out == f"{CONFIG}: OK\n"


def test_a_three_line_override_is_checked_merged_over_the_default(tmp_path, capsys):
    override = tmp_path / "my.yaml"
    override.write_text("# another noise stream\nnoise:\n  seeds: [7]\n")
    assert cli.main(["check-config", CONFIG, str(override)]) == 0
    assert capsys.readouterr().out == f"{CONFIG}, {override}: OK\n"
    override.write_text("noise:\n  seeds: [-7]\n")
    assert cli.main(["check-config", CONFIG, str(override)]) == 1
    assert capsys.readouterr().err == f"newdyn check-config: {CONFIG}, {override}: noise.seeds[0]: must be ≥ 0 (got -7)\n"


@pytest.mark.parametrize("text, problem", [
    (None, "(file): cannot read: No such file or directory"),
    ("noise: [1, 2\n", "(file): not valid YAML: expected ',' or ']', but got '<stream end>' at line 2, column 1"),
    ("rig:\n  J1: 4.0\n", ("operating: missing required key (also missing: sampling, simulation, noise, scenarios, "
                          "calibration, diagnosis, hidden)")),
])
def test_a_bad_config_gets_one_line_naming_the_file_and_field(tmp_path, capsys, monkeypatch, text, problem):
    path = tmp_path / "my.yaml"
    if text is not None:
        path.write_text(text)
    monkeypatch.chdir(tmp_path)  # no config/config.yaml beside it, so the line gives no hint to merge over it
    assert cli.main(["check-config", str(path)]) == 1
    assert capsys.readouterr().err == f"newdyn check-config: {path}: {problem}\n"


@pytest.mark.parametrize("command", [["check-config"], ["check", str(ROOT / "measurements"), "--config"]])
def test_an_override_checked_alone_is_told_to_give_the_default_first(tmp_path, capsys, monkeypatch, command):
    """As snakemake --configfile takes it, an override is merged over config/config.yaml; checked alone it lacks what
    the default has, and the line says so."""
    monkeypatch.chdir(ROOT)
    override = tmp_path / "my.yaml"
    override.write_text("noise:\n  seeds: [7]\n")
    assert cli.main([*command, str(override)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"newdyn {command[0]}: {override}: rig: missing required key (also missing: operating, ")
    assert err.endswith("; to check an override as snakemake --configfile takes it, merged over the default, give "
                        "config/config.yaml first\n")


def test_a_config_that_is_no_mapping_is_not_merged(tmp_path, capsys):
    path = tmp_path / "list.yaml"
    path.write_text("- noise\n")
    assert cli.main(["check-config", CONFIG, str(path)]) == 1
    assert capsys.readouterr().err == (f"newdyn check-config: {path}: (top level): must be a mapping of sections (rig:, "
                                       "noise:, …) to merge with the other files (got a list)\n")


def test_check_with_a_bad_config_says_so_in_one_line(tmp_path, capsys):
    path = write_csv(tmp_path / "m.csv")
    status, out, err = check(capsys, path, config=tmp_path / "none.yaml")
    assert (status, out) == (1, [])
    assert err == [f"newdyn check: {tmp_path / 'none.yaml'}: (file): cannot read: No such file or directory"]


def test_a_workflow_command_given_a_bad_measurement_ends_in_one_line(tmp_path, capsys):
    path = write_csv(tmp_path / "m.csv", separator=";")
    spec = '{"parameters": [{}], "values": {"speed_rpm": 1480, "T0": 1613, "load_amp": 0.3, "load_freq": 12, ' \
           '"load_harm": 6}, "channels": ["b1_x"]}'
    status = cli.main(["calibrate-grid", "--measurement", str(path), "--spec", spec, "--grids", "g.nc", "--outputs", "o.nc"])
    assert status == 1
    assert capsys.readouterr().err == (f"newdyn calibrate-grid: {path}: columns are separated by ';', the format needs "
                                       "commas, with a dot as the decimal mark (time,b1_x,w1 / 0.5,1.2e-07,155.0; "
                                       "docs/measurements.md#csv)\n")


def test_a_workflow_command_given_a_missing_file_ends_in_one_line(tmp_path, capsys):
    missing = tmp_path / "clean.nc"
    status = cli.main(["add-noise", "--input", str(missing), "--output", str(tmp_path / "noisy.nc"), "--snr-db", "40",
                       "--seed", "1"])
    assert status == 1
    assert capsys.readouterr().err == f"newdyn add-noise: {missing}: No such file or directory\n"


def test_a_bug_keeps_its_traceback(tmp_path, monkeypatch):
    """Only errors in what the user gave become one line: newdyn's own failures stay visible as they are."""
    def broken(*args):
        raise ValueError("an internal inconsistency")

    monkeypatch.setattr(cli, "check_config", broken)
    with pytest.raises(ValueError, match="an internal inconsistency"):
        cli.main(["check-config", CONFIG])
