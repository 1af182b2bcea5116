"""The Snakemake study end to end on the small CI config (.test/config.yaml)."""

import os
import csv
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from newdyn import calibration, model
from newdyn.io import read_measurement

ROOT = Path(__file__).resolve().parents[1]
TEST_CONFIG = ROOT / ".test" / "config.yaml"


def snakemake(workdir, *args, config=TEST_CONFIG, pythonpath=None):
    """Run snakemake from this interpreter's environment; returns the completed process."""
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    if pythonpath:
        env["PYTHONPATH"] = str(pythonpath)
    return subprocess.run(
        [sys.executable, "-m", "snakemake", "-s", str(ROOT / "Snakefile"), "-d", str(workdir),
         "--configfile", str(config), "--cores", "2", *args],
        capture_output=True, text=True, env=env, timeout=600,
    )


def changed_config(tmp_path, change):
    """The CI config after ``change(config)``, written to a file."""
    config = yaml.safe_load(TEST_CONFIG.read_text())
    change(config)
    path = tmp_path / "changed.yaml"
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def planned_outputs(workdir, config=TEST_CONFIG, pythonpath=None):
    """Files a dry run would (re)create."""
    run = snakemake(workdir, "--dry-run", config=config, pythonpath=pythonpath)
    assert run.returncode == 0, run.stderr
    return sorted(set(re.findall(r"^\s+output: (\S+)", run.stdout, re.MULTILINE)))


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("study")
    run = snakemake(workdir)
    assert run.returncode == 0, run.stderr[-3000:]
    return workdir


def test_study_writes_every_scenario_clean_and_noisy_with_provenance(study):
    config = yaml.safe_load(TEST_CONFIG.read_text())
    channels = tuple(config["simulation"]["channels"])
    for scenario in config["scenarios"]:
        folder = study / "results" / "simulations" / scenario
        clean = read_measurement(folder / "clean.nc")
        assert clean.channels == channels and clean.sampling.n_samples == 500
        assert clean.attrs["scenario"] == scenario and clean.attrs["newdyn_version"]
        assert len(clean.attrs["code_hash"]) == 16
        assert (study / "results" / "logs" / "simulate" / f"{scenario}.log").stat().st_size > 0
        assert (study / "results" / "benchmarks" / "simulate" / f"{scenario}.tsv").exists()
        for snr in config["noise"]["snr_db"]:
            for seed in config["noise"]["seeds"]:
                noisy = read_measurement(folder / f"snr{snr:g}_seed{seed}.nc")
                assert noisy.attrs["snr_db"] == snr and noisy.attrs["seed"] == seed
                assert noisy.sigma is not None and noisy.attrs["scenario"] == scenario
                residual = noisy.y - clean.y
                assert 0.8 < residual.std(axis=1).mean() / noisy.sigma.mean() < 1.2
    kT1 = read_measurement(study / "results" / "simulations" / "kT1_up" / "clean.nc")
    assert '"kT1": 3250000.0' in kT1.attrs["parameters"]


def test_summary_table_has_a_row_per_calibration_and_the_expected_verdicts(study):
    config = yaml.safe_load(TEST_CONFIG.read_text())
    with open(study / "results" / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert set(calibration.SUMMARY_COLUMNS) <= set(rows[0])
    calibrations = len(config["calibration"]["parameters"]) + len(config["calibration"]["mcmc"]["parameters"])
    assert len(rows) == len(config["scenarios"]) * calibrations * len(config["noise"]["snr_db"])
    verdict = {(r["scenario"], r["parameter"]): r["verdict"] for r in rows if r["method"] == "grid"}
    assert verdict["healthy", "kT1"] == verdict["kT1_up", "kT1"] == "explained"
    assert verdict["stick_slip", "kT1"] == verdict["stick_slip", "kT3"] == "not explained"
    for method in ("grid", "mcmc"):
        kT1_up = next(r for r in rows if (r["scenario"], r["parameter"], r["method"]) == ("kT1_up", "kT1", method))
        assert float(kT1_up["mean"]) == pytest.approx(3.25e6, rel=0.01)
        assert float(kT1_up["hellinger_to_healthy"]) > 0.9
    mcmc = [r for r in rows if r["method"] == "mcmc"]
    assert mcmc and all(r["rhat"] and r["ess_bulk"] and r["converged"] in ("0", "1") for r in mcmc)
    # The built-in cross-check, for converged runs whose posterior lies inside the grid. Stick-slip
    # piles kT1 against the grid bound, where MCMC and grid differ slightly more (H ~ 0.07, sd 194
    # vs 212; exact draws of the grid posterior score 0.02): an open item of issue #3.
    def inside(r):
        grid = config["calibration"]["parameters"][r["parameter"]]["grid"]
        return grid["low"] + 1e-3 * (grid["high"] - grid["low"]) < float(r["map"]) < grid["high"] - 1e-3 * (grid["high"] - grid["low"])

    checked = [r for r in mcmc if r["converged"] == "1" and inside(r)]
    assert checked and all(float(r["hellinger_to_grid"]) < 0.05 for r in checked)


def test_changing_one_prior_reruns_only_its_calibrations(study, tmp_path):
    path = changed_config(tmp_path, lambda c: c["calibration"]["parameters"]["kT1"]["prior"].update(sd=4.0e5))
    planned = planned_outputs(study, path)
    calibrations = [p for p in planned if p != "results/summary.csv"]
    assert "results/summary.csv" in planned and calibrations
    assert all(p.startswith("results/calibration/") and "/kT1/" in p for p in calibrations)


def test_immediate_rerun_has_nothing_to_do(study):
    run = snakemake(study, "--dry-run")
    assert "Nothing to be done" in run.stdout + run.stderr


def test_reordering_config_keys_reruns_nothing(study, tmp_path):
    config = yaml.safe_load(TEST_CONFIG.read_text())
    reordered = {key: config[key] for key in reversed(list(config))}
    reordered["rig"] = dict(reversed(list(config["rig"].items())))
    reordered["scenarios"] = dict(reversed(list(config["scenarios"].items())))
    path = tmp_path / "reordered.yaml"
    path.write_text(yaml.safe_dump(reordered, sort_keys=False))
    assert planned_outputs(study, path) == []


def test_changing_one_scenario_reruns_only_that_scenario(study, tmp_path):
    path = changed_config(tmp_path, lambda c: c["scenarios"]["kT1_up"]["fault"]["parameters"].update(kT1=3.3e6))
    planned = planned_outputs(study, path)
    own = ("results/simulations/kT1_up/", "results/calibration/kT1_up/", "results/summary.csv")
    assert planned and all(p.startswith(own) for p in planned)
    assert "results/simulations/kT1_up/clean.nc" in planned


def test_changing_a_rig_value_reruns_every_scenario(study, tmp_path):
    path = changed_config(tmp_path, lambda c: c["rig"].update(beta=2.0e-5))
    planned = planned_outputs(study, path)
    scenarios = set(yaml.safe_load(TEST_CONFIG.read_text())["scenarios"])
    assert {p.split("/")[2] for p in planned if p.startswith("results/simulations/")} == scenarios


@pytest.mark.parametrize(
    "module, rules",
    [
        ("kernels.py", {"clean.nc", "snr40_seed1.nc", "snr40_seed1_grid.nc", "snr40_seed1_mcmc.nc", "kT1.nc", "kT3.nc", "summary.csv"}),
        ("noise.py", {"snr40_seed1.nc", "snr40_seed1_grid.nc", "snr40_seed1_mcmc.nc", "summary.csv"}),
        ("likelihood.py", {"snr40_seed1_grid.nc", "snr40_seed1_mcmc.nc", "kT1.nc", "kT3.nc", "summary.csv"}),
        ("sampling.py", {"snr40_seed1_mcmc.nc", "summary.csv"}),
        ("plots_unused.py", set()),
    ],
)
def test_editing_science_code_reruns_exactly_the_jobs_that_use_it(study, tmp_path, module, rules):
    """A copy of the package with one module edited, first on PYTHONPATH, is what the workflow imports."""
    package = tmp_path / "newdyn"
    shutil.copytree(ROOT / "src" / "newdyn", package, ignore=shutil.ignore_patterns("__pycache__"))
    with open(package / module, "a") as source:
        source.write("\n# an edit\n")
    planned = planned_outputs(study, pythonpath=tmp_path)
    assert {p.split("/")[-1] for p in planned} == rules
    scenarios = set(yaml.safe_load(TEST_CONFIG.read_text())["scenarios"])
    if "snr40_seed1.nc" in rules:
        assert {p.split("/")[2] for p in planned if p.startswith("results/simulations/")} == scenarios


def test_bad_config_fails_in_one_line_before_any_job(tmp_path):
    path = changed_config(tmp_path, lambda c: c["scenarios"]["stick_slip"]["fault"]["parameters"].update(T_max=-5.0))
    run = snakemake(tmp_path / "work", config=path)
    assert run.returncode != 0
    lines = [line for line in run.stderr.splitlines() if "bad config" in line]
    assert lines == [f"newdyn: bad config: {path}: scenarios.stick_slip.fault.parameters.T_max: "
                     "must lie in (0, inf) N·m (got -5)"]
    assert not (tmp_path / "work" / "results").exists()


def test_workflow_is_lint_clean_and_snakefmt_formatted():
    lint = subprocess.run([sys.executable, "-m", "snakemake", "--lint"], cwd=ROOT, capture_output=True, text=True)
    assert lint.returncode == 0 and "Lints for" not in lint.stdout + lint.stderr, lint.stdout + lint.stderr
    files = [ROOT / "Snakefile", *sorted((ROOT / "workflow" / "rules").glob("*.smk"))]
    fmt = subprocess.run([Path(sys.executable).parent / "snakefmt", "--check", *map(str, files)],
                         capture_output=True, text=True)
    assert fmt.returncode == 0, fmt.stderr


def test_every_default_channel_is_a_model_channel():
    config = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    assert set(config["simulation"]["channels"]) <= set(model.CHANNELS)
