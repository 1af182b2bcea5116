"""Tests of the study configuration layer (newdyn.config, config/*.yaml, the config schema)."""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from jsonschema.validators import validator_for

from newdyn import config as cfg
from newdyn import effects, faults, model, slots, study

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "config" / "config.yaml"
CI = ROOT / ".test" / "config.yaml"
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"
README = ROOT / "config" / "README.md"
SOURCE = "config/config.yaml"


@pytest.fixture(scope="module")
def default_config() -> dict:
    return cfg.load(DEFAULT, SCHEMA)


@pytest.fixture(autouse=True)
def builtin_effects():
    """Every test starts and ends with the built-in effects only (a test may add its own)."""
    effects.use([])
    yield
    effects.use([])


def error_of(config: object, source: str = SOURCE) -> cfg.ConfigError:
    with pytest.raises(cfg.ConfigError) as info:
        cfg.check(config, source, SCHEMA)
    return info.value


def assert_one_line(err: cfg.ConfigError, source: str, field: str, *words: str) -> None:
    text = str(err)
    assert "\n" not in text and "\r" not in text, text
    assert text.startswith(f"{source}: {field}: "), text
    assert (err.source, err.field) == (source, field)
    for word in words:
        assert word in err.problem, text


# --------------------------------------------------------------------------------------------------
# the shipped configs


@pytest.mark.parametrize("path", [DEFAULT, CI], ids=["default", "ci"])
def test_shipped_configs_pass(path):
    config = cfg.load(path, SCHEMA)
    assert set(config) - {"variants"} == {
        "rig", "operating", "operating_range", "sampling", "simulation", "noise", "scenarios", "calibration", "diagnosis",
        "hidden"}
    for name in config["scenarios"]:
        values = study.scenario_values(config, name)
        assert set(values) == set(slots.slot_names())


@pytest.mark.parametrize("path", [DEFAULT, CI], ids=["default", "ci"])
def test_scenario_values_are_exactly_the_model_slots(path):
    config = cfg.load(path, SCHEMA)
    for name in config["scenarios"]:
        assert tuple(study.scenario_values(config, name)) == slots.slot_names(), name


def test_the_schema_with_the_effects_kinds_injected_is_a_valid_json_schema():
    schema = cfg.load_schema()
    validator_for(schema).check_schema(schema)


def test_checking_a_config_as_the_snakefile_does_leaves_numba_unimported(tmp_path):
    """The Snakefile's parse (every cluster job's too) imports these modules, checks the config, loads every effect
    file and takes the code hashes: none of it compiles, so none of it needs numba."""
    code = ("import sys, newdyn.catalog, newdyn.config, newdyn.effects, newdyn.provenance, newdyn.cli; "
            f"newdyn.config.load({str(ROOT / 'config' / 'config.yaml')!r}); "
            "[newdyn.provenance.command_hash(c, [e.source for e in newdyn.effects.active().values()]) for c in ('simulate', 'diagnose')]; "
            "print(sorted({'numba', 'scipy', 'xarray', 'matplotlib'} & set(sys.modules)))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "NEWDYN_CACHE": str(tmp_path)})
    assert run.stdout.split() == ["[]"]


def test_the_workflow_reads_the_schema_the_package_ships(default_config):
    assert SCHEMA.resolve() == cfg.SCHEMA_PATH
    assert cfg.SCHEMA_PATH.is_relative_to(Path(cfg.__file__).parent)
    cfg.check(copy.deepcopy(default_config), SOURCE)  # default schema_path


def test_an_installed_package_checks_a_config_without_the_source_tree(tmp_path):
    """A wheel of the package, installed away from the repository, checks a good config and names a bad one's field:
    the schema is package data, not a file of the source tree."""
    source = tmp_path / "source"
    shutil.copytree(ROOT / "src", source / "src", ignore=shutil.ignore_patterns("*.egg-info", "__pycache__"))
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, source / name)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", tmp_path / "dist", source], check=True)
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", tmp_path / "site",
                    *(tmp_path / "dist").glob("newdyn-*.whl")], check=True)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"sampling": {"fs": "fast"}}))

    def check(*paths):
        code = "import sys, newdyn, newdyn.cli; print(newdyn.__file__); sys.exit(newdyn.cli.main(['check-config', *sys.argv[1:]]))"
        return subprocess.run([sys.executable, "-c", code, *map(str, paths)], capture_output=True, text=True, cwd=tmp_path,
                              env={**os.environ, "PYTHONPATH": str(tmp_path / "site")}, check=False)

    good = check(DEFAULT)
    assert good.returncode == 0, good.stderr
    installed, verdict = good.stdout.splitlines()
    assert Path(installed).is_relative_to(tmp_path / "site")
    assert verdict == f"{DEFAULT}: OK"
    wrong = check(DEFAULT, bad)
    assert wrong.returncode != 0 and len(wrong.stderr.strip().splitlines()) == 1
    assert "sampling.fs" in wrong.stderr and str(bad) in wrong.stderr


def test_the_schema_names_no_channel_and_its_sensor_model_is_the_packages():
    """The channels come from model.CHANNELS wherever the schema names one (a channel added to the model is one the
    config may name); each instrument's quantities are the fields of sensors.Sensor."""
    from newdyn import sensors

    schema = yaml.safe_load(SCHEMA.read_text())
    assert not [listed for listed in _lists(schema) if set(model.CHANNELS) & {str(item) for item in listed}]
    channel_lists = [node["enum"] for _, node in _subschemas(cfg.load_schema(SCHEMA)) if model.CHANNELS[0] in node.get("enum", [])]
    assert len(channel_lists) == 5 and all(e == list(model.CHANNELS) for e in channel_lists)
    instrument = schema["properties"]["diagnosis"]["properties"]["sensors"]["additionalProperties"]
    assert list(instrument["properties"]) == [f.name for f in dataclasses.fields(sensors.Sensor)]


def test_default_config_is_rig_md(default_config):
    for name in model.RIG_PARAMETERS + model.OPERATING_PARAMETERS:
        assert study.base_values(default_config)[name] == pytest.approx(model.DEFAULTS[name], rel=1e-12), name
    assert default_config["simulation"]["channels"] == list(model.CHANNELS)
    assert default_config["simulation"]["max_step"] == 1.0e-4
    assert default_config["noise"] == {"snr_db": [40, 20], "seeds": [1]}
    assert list(default_config["scenarios"]) == [
        "healthy",
        "kT1_up",
        "kT3_down",
        "stick_slip",
        "breathing_crack",
        "cubic_coupling",
        "loose_bearing",
    ]
    s = study.sampling(default_config)
    assert (s.fs, s.t_first, s.n_samples) == (5000.0, 0.5, 5000)


def test_ci_config(default_config):
    ci = cfg.load(CI, SCHEMA)
    assert ci["rig"] == default_config["rig"] and ci["operating"] == default_config["operating"]
    assert study.sampling(ci).n_samples == 500
    assert ci["simulation"] == {"channels": ["b1_x", "w1", "torque_c"], "max_step": 1.0e-4}
    assert ci["noise"] == {"snr_db": [40], "seeds": [1]}
    assert list(ci["scenarios"]) == ["healthy", "kT1_up", "stick_slip"]
    assert "faults" not in ci["diagnosis"] and "faults" not in ci["hidden"]  # the effect files' ranges
    assert study.hidden_classes(ci) == ["breathing_crack"]


# --------------------------------------------------------------------------------------------------
# bad configs: one ConfigError line naming the file and the field


def _set(path: str, value):
    """Mutation setting a dotted path (created if missing)."""

    def mutate(c):
        *parents, last = path.split(".")
        node = c
        for key in parents:
            node = node.setdefault(key, {})
        node[last] = value

    return mutate


def _del(path: str):
    def mutate(c):
        *parents, last = path.split(".")
        node = c
        for key in parents:
            node = node[key]
        del node[last]

    return mutate


def _rename(path: str, new: str):
    def mutate(c):
        *parents, last = path.split(".")
        node = c
        for key in parents:
            node = node[key]
        node[new] = node.pop(last)

    return mutate


def _fault(scenario: str, kind: str, **parameters):
    return _set(f"scenarios.{scenario}.fault", {"kind": kind, "parameters": parameters})


BAD = {
    # the study's own effects (files are tested below, with a folder of effects)
    "effects not a list": (_set("effects", "torque_ripple"), "effects", "must be a list"),
    "effect name not a name": (_set("effects", ["torque ripple"]), "effects[0]", "must match"),
    "effect listed twice": (_set("effects", ["a", "a"]), "effects[1]", "duplicate of effects[0]"),
    "effect named like a built-in": (_set("effects", ["stick_slip"]), "effects[0]", "stick_slip.py", "built-in effect"),
    "effect named like a class": (_set("effects", ["healthy"]), "effects[0]", "class of its own"),
    # diagnosis and hidden sets: optional overrides of the effect files' ranges
    "unknown diagnosis fault parameter": (
        _set("diagnosis.faults.breathing_crack", {"alpha": [0.0, 0.8], "beta": [0.0, 1.0]}),
        "diagnosis.faults.breathing_crack.beta", "unknown parameter of breathing_crack",
    ),
    "unknown diagnosis fault kind": (_set("diagnosis.faults.rust", {"depth": [0.0, 1.0]}), "diagnosis.faults.rust",
                                     "must be one of", "stick_slip"),
    "reversed diagnosis range": (_set("diagnosis.faults.cubic_coupling.gamma", [3.0, 0.0]),
                                 "diagnosis.faults.cubic_coupling.gamma", "reversed"),
    "unphysical diagnosis range": (_set("diagnosis.faults.breathing_crack.alpha", [0.0, 1.0]),
                                   "diagnosis.faults.breathing_crack.alpha", "[0, 1)"),
    "diagnosis range below an exclusive bound": (_set("diagnosis.faults.stick_slip.T_max", [-1.0, 2000.0]),
                                                 "diagnosis.faults.stick_slip.T_max", "(0, inf) N·m"),
    "empty diagnosis override": (_set("diagnosis.faults.stick_slip", {}), "diagnosis.faults.stick_slip", "at least 1"),
    "not a range": (_set("diagnosis.faults.cubic_coupling.gamma", [0.0, 1.0, 2.0]), "diagnosis.faults.cubic_coupling.gamma"),
    "operating range of a rig parameter": (_set("operating_range.kT1", [1.0e6, 2.0e6]), "operating_range.kT1",
                                           "must be one of", "speed_rpm"),
    "reversed operating range": (_set("operating_range.T0", [1800.0, 800.0]), "operating_range.T0", "low < high"),
    "unphysical operating range": (_set("operating_range.speed_rpm", [0.0, 1500.0]), "operating_range.speed_rpm", "(0, inf) rpm"),
    "machine set without an operating range": (lambda c: c.pop("operating_range"), "hidden.sets.machines.recordings",
                                                "operating_range, which is not set"),
    "reversed recordings": (_set("hidden.sets.fleet", {"cases": 2, "seed": 1, "recordings": [3, 2]}),
                            "hidden.sets.fleet.recordings", "low <= high"),
    "drift not calibrated": (_set("diagnosis.drift", ["k_s"]), "diagnosis.drift[0]", "not one of calibration.parameters"),
    "negative sensor spread": (_set("diagnosis.sensors.b1_x.offset_sd", -1e-8), "diagnosis.sensors.b1_x.offset_sd", "≥ 0"),
    "sensor of no channel": (_set("diagnosis.sensors.b9_x.gain_sd", 0.01), "diagnosis.sensors.b9_x", "unknown name"),
    "hidden instruments without datasheets": (lambda c: (c["diagnosis"].pop("sensors"), _set("hidden.sets.blind.instruments", True)(c)),
                                              "hidden.sets.blind.instruments", "diagnosis.sensors"),
    "more out of spec than cases": (lambda c: c["hidden"]["sets"]["blind"].update(instruments=True, out_of_spec=30),
                                    "hidden.sets.blind.out_of_spec", "more than the set's 24 cases"),
    "out of spec without instruments": (_set("hidden.sets.blind.out_of_spec", 2), "hidden.sets.blind.out_of_spec", "instruments: true"),
    # stick_slip, the largest effect, has 3 parameters; with the drift kT1 4: the KDE move needs 2·4 + 2
    "too few diagnosis walkers": (_set("diagnosis.mcmc.walkers", 8), "diagnosis.mcmc.walkers", "at least 10",
                                  "the 4 parameters"),
    "unphysical hidden share": (_set("hidden.faults.stick_slip.J2a_share", [0.2, 1.5]), "hidden.faults.stick_slip.J2a_share", "must lie"),
    "hidden set named like a variant": (_set("hidden.sets.paper", {"cases": 2, "seed": 1}), "hidden.sets.paper", "share results/paper/"),
    "unknown hidden fault parameter": (_set("hidden.faults.stick_slip.T_maks", [1800.0, 1900.0]),
                                       "hidden.faults.stick_slip.T_maks", "unknown parameter of stick_slip", "T_max"),
    "unknown hidden fault kind": (_set("hidden.faults.wobble", {"x": [0.0, 1.0]}), "hidden.faults.wobble", "must be one of"),
    "unknown hidden class": (_set("hidden.classes", ["healthy", "wobble"]), "hidden.classes[1]", "must be one of"),
    "empty hidden classes": (_set("hidden.classes", []), "hidden.classes", "at least 1"),
    "unknown class of a hidden set": (_set("hidden.sets.demo.classes", ["healthy", "wobble"]), "hidden.sets.demo.classes[1]"),
    "hidden parameter change of a non-rig parameter": (_set("hidden.parameter_change.parameters", ["kT1", "T0"]),
                                                       "hidden.parameter_change.parameters[1]", "unknown rig parameter"),
    "hidden relative change of 100 %": (_set("hidden.parameter_change.relative", [0.5, 1.0]),
                                        "hidden.parameter_change.relative", "0 <= low < high < 1"),
    # structure (schema)
    "missing sampling.fs": (_del("sampling.fs"), "sampling.fs", "missing required key"),
    "missing section": (_del("noise"), "noise", "missing required key"),
    "missing rig value": (_del("rig.k_bx"), "rig.k_bx", "missing required key"),
    "missing fault kind": (_del("scenarios.kT1_up.fault.kind"), "scenarios.kT1_up.fault.kind", "missing"),
    "extra rig key": (_set("rig.kT11", 3.0e6), "rig.kT11", "unknown key", "kT1"),
    "mistyped rig key": (_rename("rig.kT1", "kT11"), "rig.kT11", "unknown key", "did you mean 'kT1'"),
    "mistyped top-level key": (_rename("noise", "nosie"), "nosie", "unknown key", "noise"),
    "mistyped sampling key": (_rename("sampling.t_rec", "t_record"), "sampling.t_record", "unknown key"),
    "mistyped scenario key": (_rename("scenarios.kT1_up.fault", "falt"), "scenarios.kT1_up.falt", "unknown key"),
    "mistyped fault key": (
        _rename("scenarios.kT1_up.fault.parameters", "params"),
        "scenarios.kT1_up.fault.params",
        "unknown key",
    ),
    "string for a number": (_set("rig.J1", "heavy"), "rig.J1", "must be a number", "'heavy'"),
    "exponent without sign": (_set("rig.kT1", "3.0e6"), "rig.kT1", "must be a number", "3.0e+6"),
    "string for an operating value": (_set("operating.speed_rpm", "fast"), "operating.speed_rpm", "must be a number"),
    "bool for a number": (_set("sampling.fs", True), "sampling.fs", "must be a number"),
    "list for a mapping": (_set("rig", [1, 2]), "rig", "must be a mapping"),
    "string for a fault parameter": (
        _fault("stick_slip", "stick_slip", T_max="high"),
        "scenarios.stick_slip.fault.parameters.T_max",
        "number",
    ),
    "string for an override": (
        _set("scenarios.healthy.overrides", {"J1": "4"}),
        "scenarios.healthy.overrides.J1",
        "number",
    ),
    "text max_step": (_set("simulation.max_step", "1e-4"), "simulation.max_step", "number"),
    "zero max_step": (_set("simulation.max_step", 0), "simulation.max_step", "minimum"),
    "string seed": (_set("noise.seeds", ["a"]), "noise.seeds[0]", "whole number"),
    "negative seed": (_set("noise.seeds", [1, -1]), "noise.seeds[1]", "≥ 0"),
    "duplicate seed": (_set("noise.seeds", [1, 2, 1]), "noise.seeds[2]", "duplicate of noise.seeds[0]"),
    "duplicate snr": (_set("noise.snr_db", [40, 40.0]), "noise.snr_db[1]", "duplicate"),
    "empty snr list": (_set("noise.snr_db", []), "noise.snr_db", "at least 1"),
    "unknown channel": (
        _set("simulation.channels", ["b1_x", "b5_x"]),
        "simulation.channels[1]",
        "must be one of",
        "b5_x",
    ),
    "duplicate channel": (_set("simulation.channels", ["w1", "b1_x", "w1"]), "simulation.channels[2]", "duplicate"),
    "bad scenario name": (_set("scenarios.bad name", {}), "scenarios.bad name", "must match"),
    "scenario name with a slash": (_set("scenarios.a/b", {}), "scenarios.a/b", "must match"),
    "no scenarios": (_set("scenarios", {}), "scenarios", "at least 1"),
    "empty fault": (_set("scenarios.healthy.fault", None), "scenarios.healthy.fault", "must be a mapping"),
    "unknown fault kind": (
        _fault("kT1_up", "rust", depth=1.0),
        "scenarios.kT1_up.fault.kind",
        "must be one of",
        "stick_slip",
    ),
    # physics: rig, operating, sampling, noise
    "zero mass": (_set("rig.m1", 0.0), "rig.m1", "must lie in (0, inf) kg"),
    "negative bearing mass": (_set("rig.m_b", -50.0), "rig.m_b", "must lie in (0, inf) kg"),
    "zero inertia": (_set("rig.J2a", 0), "rig.J2a", "must lie in (0, inf) kg·m²"),
    "negative inertia": (_set("rig.J4", -6.0), "rig.J4", "(got -6)"),
    "zero torsional stiffness": (_set("rig.kT2", 0.0), "rig.kT2", "must lie in (0, inf) N·m/rad"),
    "negative lateral stiffness": (_set("rig.k_s", -2.0e8), "rig.k_s", "must lie in (0, inf) N/m"),
    "slip of one": (_set("rig.slip", 1.0), "rig.slip", "must lie in"),
    "negative damping": (_set("rig.beta", -1e-5), "rig.beta", "[0, inf)"),
    "non-finite rig value": (_set("rig.J1", math.inf), "rig.J1", "finite"),
    "fractional harmonics": (_set("operating.load_harm", 6.5), "operating.load_harm", "whole number"),
    "zero speed": (_set("operating.speed_rpm", 0), "operating.speed_rpm", "must lie in"),
    "zero fs": (_set("sampling.fs", 0), "sampling.fs", "> 0"),
    "infinite fs": (_set("sampling.fs", math.inf), "sampling.fs", "finite"),
    "negative warm-up": (_set("sampling.t_warm", -0.1), "sampling.t_warm", "≥ 0"),
    "fractional sample count": (_set("sampling.t_rec", 1.00001), "sampling.t_rec", "whole number of samples"),
    "t_rec shorter than one load cycle": (
        _set("sampling.t_rec", 0.05),
        "sampling.t_rec",
        "shorter than one load cycle",
    ),
    "infinite snr": (_set("noise.snr_db", [40, math.inf]), "noise.snr_db[1]", "finite", "inf"),
    "minus infinite snr": (_set("noise.snr_db", [-math.inf]), "noise.snr_db[0]", "finite"),
    "nan snr": (_set("noise.snr_db", [math.nan, 20]), "noise.snr_db[0]", "finite", "nan"),
    # physics: scenarios
    "zero mass override": (
        _set("scenarios.healthy.overrides", {"m4": 0.0}),
        "scenarios.healthy.overrides.m4",
        "(0, inf) kg",
    ),
    "negative inertia override": (
        _set("scenarios.stick_slip.overrides", {"J2b": -0.1}),
        "scenarios.stick_slip.overrides.J2b",
        "(0, inf)",
    ),
    "zero stiffness override": (
        _set("scenarios.kT1_up.overrides", {"kT3": 0}),
        "scenarios.kT1_up.overrides.kT3",
        "(0, inf)",
    ),
    "non-finite override": (
        _set("scenarios.healthy.overrides", {"T0": math.nan}),
        "scenarios.healthy.overrides.T0",
        "finite",
    ),
    "unknown override": (
        _set("scenarios.healthy.overrides", {"kT9": 1.0}),
        "scenarios.healthy.overrides.kT9",
        "unknown rig or operating",
    ),
    "effect parameter as override": (
        _set("scenarios.healthy.overrides", {"T_max": 100.0}),
        "scenarios.healthy.overrides.T_max",
        "unknown rig or operating parameter",
        "of the stick_slip effect: set it under fault.parameters",
    ),
    "effect model value as override": (
        _set("scenarios.healthy.overrides", {"breathing_crack.alpha": 0.2}),
        "scenarios.healthy.overrides.breathing_crack.alpha",
        "unknown rig or operating parameter",
        "breathing_crack effect",
    ),
    "effect presence as override": (
        _set("scenarios.healthy.overrides", {"stick_slip": 1.0}),
        "scenarios.healthy.overrides.stick_slip",
        "unknown rig or operating parameter",
    ),
    "override load cycle longer than the record": (
        _set("scenarios.healthy.overrides", {"load_freq": 0.5}),
        "scenarios.healthy.overrides.load_freq",
        "shorter than one load cycle",
    ),
    "parameter_change to negative stiffness": (
        _fault("kT1_up", "parameter_change", kT1=-1.0),
        "scenarios.kT1_up.fault.parameters.kT1",
        "(0, inf) N·m/rad",
    ),
    "parameter_change to zero mass": (
        _fault("kT1_up", "parameter_change", m2=0.0),
        "scenarios.kT1_up.fault.parameters.m2",
        "(0, inf) kg",
    ),
    "parameter_change to zero inertia": (
        _fault("kT1_up", "parameter_change", J3=0.0),
        "scenarios.kT1_up.fault.parameters.J3",
        "(0, inf) kg·m²",
    ),
    "parameter_change of an unknown parameter": (
        _fault("kT1_up", "parameter_change", kT11=3.0e6),
        "scenarios.kT1_up.fault.parameters.kT11",
        "unknown parameter",
    ),
    "parameter_change of an operating parameter": (
        _fault("kT1_up", "parameter_change", speed_rpm=1500.0),
        "scenarios.kT1_up.fault.parameters.speed_rpm",
        "unknown",
    ),
    "parameter_change of nothing": (
        _fault("kT1_up", "parameter_change"),
        "scenarios.kT1_up.fault.parameters",
        "at least one",
    ),
    "unknown fault parameter": (
        _fault("stick_slip", "stick_slip", T_maxx=1854.95),
        "scenarios.stick_slip.fault.parameters.T_maxx",
        "unknown parameter",
    ),
    "crack parameter on stick_slip": (
        _fault("stick_slip", "stick_slip", alpha=0.2),
        "scenarios.stick_slip.fault.parameters.alpha",
        "unknown parameter",
    ),
    "zero T_max": (
        _fault("stick_slip", "stick_slip", T_max=0.0),
        "scenarios.stick_slip.fault.parameters.T_max",
        "(0, inf) N·m",
    ),
    "negative T_max": (
        _fault("stick_slip", "stick_slip", T_max=-5.0),
        "scenarios.stick_slip.fault.parameters.T_max",
        "(got -5)",
    ),
    "infinite T_max": (
        _fault("stick_slip", "stick_slip", T_max=math.inf),
        "scenarios.stick_slip.fault.parameters.T_max",
        "finite",
    ),
    "zero r_k": (
        _fault("stick_slip", "stick_slip", r_k=0.0),
        "scenarios.stick_slip.fault.parameters.r_k",
        "must lie in",
    ),
    "J2a share of one": (
        _fault("stick_slip", "stick_slip", J2a_share=1.0),
        "scenarios.stick_slip.fault.parameters.J2a_share",
        "must lie in",
    ),
    "crack alpha of one": (
        _fault("breathing_crack", "breathing_crack", alpha=1.0),
        "scenarios.breathing_crack.fault.parameters.alpha",
        "[0, 1)",
    ),
    "negative gap": (
        _fault("loose_bearing", "loose_bearing", gap=-1e-7),
        "scenarios.loose_bearing.fault.parameters.gap",
        "[0, inf) m",
    ),
    "zero prior sd": (_set("calibration.parameters.kT1.prior.sd", 0.0), "calibration.parameters.kT1.prior.sd", "> 0"),
    "negative prior sd": (
        _set("calibration.parameters.kT1.prior.sd", -5.0e5),
        "calibration.parameters.kT1.prior.sd",
        "> 0",
    ),
    "grid bounds reversed": (_set("calibration.parameters.kT1.grid.low", 5.0e6), "calibration.parameters.kT1.grid", "reversed"),
    "grid below physical range": (
        _set("calibration.parameters.kT3.grid.low", -1.0e6),
        "calibration.parameters.kT3.grid.low",
        "physical only",
    ),
    "unknown calibration parameter": (
        _set("calibration.parameters.kT9", {"prior": {"mean": 1.0, "sd": 1.0}, "grid": {"low": 1.0, "high": 2.0, "points": 3}}),
        "calibration.parameters.kT9",
        "did you mean",
    ),
    "calibration channel not simulated": (_set("simulation.channels", ["b1_x"]), "calibration.channels[1]", "not simulated"),
    "chi2 threshold below 1": (_set("calibration.chi2_max", 0.9), "calibration.chi2_max", "must exceed 1"),
    "odd number of walkers": (_set("calibration.mcmc.walkers", 15), "calibration.mcmc.walkers", "even"),
    "mcmc of an uncalibrated parameter": (
        _set("calibration.mcmc.parameters", ["kT1", "J1"]),
        "calibration.mcmc.parameters[1]",
        "not one of calibration.parameters",
    ),
    "unknown mcmc move": (_set("calibration.mcmc.move", "hmc"), "calibration.mcmc.move", "hmc"),
    "too few grid points": (_set("calibration.parameters.kT1.grid.points", 2), "calibration.parameters.kT1.grid.points", "≥ 3"),
    "joint of an uncalibrated parameter": (
        _set("calibration.joint.parameters", ["kT1", "k_s"]),
        "calibration.joint.parameters[1]",
        "not one of calibration.parameters",
    ),
    # 2 parameters + σ of 2 channels sample 4 quantities: the KDE move needs 2·4 + 2 walkers
    "too few walkers for the joint dimension": (
        lambda c: (_set("calibration.joint.infer_sigma", True)(c), _set("calibration.joint.walkers", 8)(c)),
        "calibration.joint.walkers",
        "at least 10: twice the 4 sampled quantities plus 2 for the kde move",
    ),
    "too few walkers for one parameter": (_set("calibration.mcmc.walkers", 2), "calibration.mcmc.walkers", "at least 4"),
    "variant of an unknown scenario": (_set("variants.paper.scenarios", ["healthy", "cracked"]), "variants.paper.scenarios[1]", "cracked"),
    "variant of an unknown rig value": (_set("variants.paper.rig", {"betta": 0.0}), "variants.paper.rig.betta", "did you mean 'beta'"),
    "unphysical variant rig value": (_set("variants.paper.rig", {"beta": -1.0}), "variants.paper (as rig.beta)", "[0, inf)"),
    "variant channel not simulated": (
        lambda c: (_set("simulation.channels", ["b1_x", "w1"])(c), _set("variants.paper.channels", ["b1_x", "w4"])(c)),
        "variants.paper (as calibration.channels[1])",
        "'w4' is not simulated",
    ),
    "variant name unusable in paths": (_set("variants", {"my variant": {}}), "variants.my variant", "invalid name"),
}


@pytest.mark.parametrize("case", list(BAD), ids=list(BAD))
def test_bad_config_gives_one_line_naming_file_and_field(default_config, case):
    mutate, field, *words = BAD[case]
    config = copy.deepcopy(default_config)
    mutate(config)
    assert_one_line(error_of(config), SOURCE, field, *words)


def test_resulting_values_are_checked(default_config, monkeypatch):
    """A value derived from the base (here a broken stick-slip default) is checked after combining."""
    effect = effects.active()["stick_slip"]
    broken = tuple(dataclasses.replace(p, default=lambda rig: 2.0) if p.name == "r_k" else p for p in effect.parameters)
    monkeypatch.setattr(effect, "parameters", broken)
    config = copy.deepcopy(default_config)
    del config["scenarios"]["stick_slip"]["fault"]["parameters"]["r_k"]
    assert_one_line(error_of(config), SOURCE, "scenarios.stick_slip.fault", "resulting r_k", "(got 2)")


def test_resulting_rig_values_of_an_effect_are_checked(default_config, monkeypatch):
    """Rig values an effect sets are checked against the rig's bounds, reported at the parameter that sets them."""
    config = copy.deepcopy(default_config)
    config["scenarios"]["stick_slip"]["fault"]["parameters"]["J2a_share"] = 0.3
    cfg.check(config, SOURCE, SCHEMA)
    values = study.scenario_values(config, "stick_slip")
    assert values["J2a"] == pytest.approx(0.3 * 0.15) and values["J2a"] + values["J2b"] == pytest.approx(0.15)
    effect = effects.active()["stick_slip"]
    monkeypatch.setattr(effect, "rig_values", classmethod(lambda cls, values, rig: {"J2a": -values["J2a_share"]}))
    assert_one_line(error_of(config), SOURCE, "scenarios.stick_slip.fault.parameters.J2a_share", "resulting J2a", "(0, inf)")
    del config["scenarios"]["stick_slip"]["fault"]["parameters"]["J2a_share"]  # set from its default: the fault as a whole
    assert_one_line(error_of(config), SOURCE, "scenarios.stick_slip.fault", "resulting J2a")


def test_resulting_values_after_overrides_and_fault(default_config):
    """A parameter_change to a value that is physical, of a parameter an override also sets, wins; the
    stick-slip default T_max = 1.15·T0 follows an overridden T0 and must still carry it."""
    config = copy.deepcopy(default_config)
    config["scenarios"]["low_T0"] = {"overrides": {"T0": 1000.0}, "fault": {"kind": "stick_slip", "parameters": {"r_k": 0.8}}}
    assert_one_line(error_of(config), SOURCE, "scenarios.low_T0.fault.parameters.T_max", "must exceed T0 = 1000")
    config["scenarios"]["low_T0"]["fault"]["parameters"]["r_k"] = 0.9
    cfg.check(config, SOURCE, SCHEMA)


def test_config_error_is_a_value_error():
    err = cfg.ConfigError("a.yaml", "rig.J1", "bad\nthing")
    assert isinstance(err, ValueError)
    assert str(err) == "a.yaml: rig.J1: bad thing"


def test_not_a_mapping():
    assert_one_line(error_of([1, 2]), SOURCE, "(top level)", "must be a mapping")
    assert_one_line(error_of(None), SOURCE, "(top level)", "must be a mapping")


def test_non_text_key(default_config):
    config = copy.deepcopy(default_config)
    config["scenarios"][1] = {}
    assert_one_line(error_of(config), SOURCE, "scenarios", "key 1 must be text")


# --------------------------------------------------------------------------------------------------
# errors in YAML text, through load()


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "my.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def _default_text_with(old: str, new: str) -> str:
    text = DEFAULT.read_text(encoding="utf-8")
    assert text.count(old) == 1, old
    return text.replace(old, new)


@pytest.mark.parametrize(
    "old, new, field, words",
    [
        ("snr_db: [40, 20]", "snr_db: [40, .inf]", "noise.snr_db[1]", ["finite", "inf"]),
        ("snr_db: [40, 20]", "snr_db: [.nan]", "noise.snr_db[0]", ["finite", "nan"]),
        ("snr_db: [40, 20]", "snr_db: [-.inf]", "noise.snr_db[0]", ["finite"]),
        ("kT1: 3.25e+6", "kT1: 3.25e6", "scenarios.kT1_up.fault.parameters.kT1", ["must be a number", "3.25e+6"]),
        ("  fs: 5000.0 ", "  fs: .inf ", "sampling.fs", ["finite"]),
        ("  J3: 0.15 ", "  J3: 0.15\n  J3: 0.25 ", "rig.J3", ["duplicate key"]),
        ("  kT3_down:\n", "  kT1_up:\n", "scenarios.kT1_up", ["duplicate key"]),
        ("  t_rec: 1.0 ", "  t_rec: 0.05 ", "sampling.t_rec", ["load cycle"]),
        ("    - w4 ", "    - w5 ", "simulation.channels[9]", ["must be one of"]),
    ],
)
def test_yaml_file_errors(tmp_path, old, new, field, words):
    path = _write(tmp_path, _default_text_with(old, new))
    with pytest.raises(cfg.ConfigError) as info:
        cfg.load(path, SCHEMA)
    assert_one_line(info.value, str(path), field, *words)


def test_invalid_yaml_and_missing_file(tmp_path):
    path = _write(tmp_path, "rig: {J1: 4.0\nsampling: [")
    with pytest.raises(cfg.ConfigError) as info:
        cfg.load(path, SCHEMA)
    assert_one_line(info.value, str(path), "(file)", "not valid YAML", "line")
    missing = tmp_path / "nope.yaml"
    with pytest.raises(cfg.ConfigError) as info:
        cfg.load(missing, SCHEMA)
    assert_one_line(info.value, str(missing), "(file)", "cannot read")


# --------------------------------------------------------------------------------------------------
# helpers


def test_scenario_values(default_config):
    c = copy.deepcopy(default_config)
    assert study.scenario_values(c, "kT1_up")["kT1"] == 3.25e6
    assert study.scenario_values(c, "healthy") == slots.complete(study.base_values(c))
    crack = study.scenario_values(c, "breathing_crack")
    assert (crack["breathing_crack"], crack["breathing_crack.alpha"]) == (1.0, 0.3)
    assert study.scenario_values(c, "loose_bearing")["loose_bearing.gap"] == 2e-8
    healthy = study.scenario_values(c, "healthy")
    assert all(healthy[kind] == 0.0 for kind in effects.active())  # no effect present
    # overrides come before the fault; the stick-slip default T_max = 1.15 T0 uses the overridden T0
    c["scenarios"]["slow"] = {"overrides": {"T0": 1000.0, "speed_rpm": 990.0}, "fault": {"kind": "stick_slip"}}
    cfg.check(c, SOURCE, SCHEMA)
    values = study.scenario_values(c, "slow")
    assert (values["T0"], values["speed_rpm"], values["stick_slip"], values["stick_slip.T_max"], values["stick_slip.r_k"]) == (
        1000.0,
        990.0,
        1.0,
        pytest.approx(1150.0),
        1.0,
    )
    # a parameter_change wins over an override of the same parameter
    c["scenarios"]["both"] = {
        "overrides": {"kT1": 2.0e6},
        "fault": {"kind": "parameter_change", "parameters": {"kT1": 4.0e6}},
    }
    assert study.scenario_values(c, "both")["kT1"] == 4.0e6
    with pytest.raises(KeyError, match="unknown scenario"):
        study.scenario_values(c, "nope")


def test_variant_config_replaces_and_selects(default_config):
    paper = study.variant_config(default_config, "paper")
    assert "variants" not in paper and paper["rig"]["beta"] == 0.0 and default_config["rig"]["beta"] == 3.0e-5
    assert paper["calibration"]["channels"] == ["b1_x"]
    assert list(paper["scenarios"]) == ["healthy", "kT1_up", "stick_slip"]
    assert list(paper["calibration"]["parameters"]) == ["kT1", "kT3"]
    assert paper["calibration"]["mcmc"]["parameters"] == [] and paper["calibration"]["joint"]["parameters"] == []
    assert study.mcmc_runs(paper) == []
    assert study.scenario_values(paper, "kT1_up")["beta"] == 0.0  # the variant's rig under every scenario
    default = study.variant_config(default_config, "default")
    assert default == {k: v for k, v in default_config.items() if k != "variants"}
    assert study.mcmc_runs(default) == ["kT1", "joint"]  # each MCMC parameter's run, then the joint one
    without = {k: v for k, v in default_config.items() if k != "variants"}
    assert study.variant_names(without) == ["default"] and study.variant_config(without, "default") == without
    with pytest.raises(KeyError, match="unknown variant"):
        study.variant_config(default_config, "nope")


def test_joint_dimension_counts_inferred_sigmas(default_config):
    config = copy.deepcopy(default_config)
    config["calibration"]["joint"]["infer_sigma"] = True
    assert study.joint_dimension(config) == 2 + 2  # kT1, kT3 and σ of b1_x, w1
    config["calibration"]["joint"]["infer_sigma"] = False
    assert study.joint_dimension(config) == 2
    config["calibration"]["joint"]["parameters"] = []
    assert study.joint_dimension(config) == 0


def test_sampling_helper(default_config):
    c = copy.deepcopy(default_config)
    c["sampling"].update(fs=2000, t_warm=0.25, t_rec=0.5)
    cfg.check(c, SOURCE, SCHEMA)
    s = study.sampling(c)
    assert (s.fs, s.t_first, s.n_samples) == (2000.0, 0.25, 1000)
    assert s.times[1] == pytest.approx(0.25 + 1 / 2000)


@pytest.mark.parametrize(
    "a, b",
    [
        ({"b": 3.25e6, "a": 1}, {"a": 1.0, "b": 3250000}),
        ({"kT1": 3.25e6}, {"kT1": 3250000.0}),
        ({"x": {"z": [1, 2.0], "y": 0}, "w": -0.0}, {"w": 0, "x": {"y": 0.0, "z": [1.0, 2]}}),
    ],
)
def test_canonical_json_same_text(a, b):
    assert study.canonical_json(a) == study.canonical_json(b)


def test_canonical_json_form():
    assert study.canonical_json({"b": 3.25e6, "a": [1, True, None, "s"]}) == '{"a":[1.0,true,null,"s"],"b":3250000.0}'
    assert study.canonical_json({"a": 1}) != study.canonical_json({"a": 1.5})


def test_reordered_yaml_changes_nothing_downstream(tmp_path, default_config):
    reordered = {key: default_config[key] for key in reversed(list(default_config))}
    reordered["rig"] = {
        k: (int(v) if float(v).is_integer() else v) for k, v in reversed(list(default_config["rig"].items()))
    }
    reordered["scenarios"] = {k: default_config["scenarios"][k] for k in reversed(list(default_config["scenarios"]))}
    path = tmp_path / "reordered.yaml"
    path.write_text(yaml.safe_dump(reordered, sort_keys=False, allow_unicode=True), encoding="utf-8")
    loaded = cfg.load(path, SCHEMA)
    for name in default_config["scenarios"]:
        assert study.canonical_json(study.scenario_values(loaded, name)) == study.canonical_json(
            study.scenario_values(default_config, name)
        )
    assert study.canonical_json(loaded) == study.canonical_json(default_config)


# --------------------------------------------------------------------------------------------------
# schema and documentation stay in sync with the model


def _schema() -> dict:
    return yaml.safe_load(SCHEMA.read_text(encoding="utf-8"))


def test_schema_matches_model():
    schema = _schema()
    props = schema["properties"]
    assert list(props["rig"]["properties"]) == list(model.RIG_PARAMETERS)
    assert props["rig"]["required"] == list(model.RIG_PARAMETERS)
    assert list(props["operating"]["properties"]) == list(model.OPERATING_PARAMETERS)
    assert props["operating"]["required"] == list(model.OPERATING_PARAMETERS)
    assert cfg.load_schema(SCHEMA)["properties"]["simulation"]["properties"]["channels"]["items"]["enum"] == list(model.CHANNELS)


def _lists(node):
    if isinstance(node, dict):
        for value in node.values():
            yield from _lists(value)
    elif isinstance(node, list):
        yield node
        for value in node:
            yield from _lists(value)


def test_schema_holds_no_kinds_and_gets_the_registry_injected():
    schema = _schema()
    classes = {faults.HEALTHY, *faults.kinds()}
    for path, node in _subschemas(schema):  # no enum of the YAML names a kind or class
        assert not classes & {str(item) for item in node.get("enum", [])}, path
    for listed in _lists(schema):  # nor does any other list name an effect (hidden.parameter_change is a key)
        assert not set(effects.active()) & {str(item) for item in listed}, listed
    markers = [path for path, node in _subschemas(schema) if "x-kinds" in node]
    assert len(markers) == 11, markers
    injected = cfg.load_schema(SCHEMA)
    assert injected["$defs"]["fault"]["properties"]["kind"]["enum"] == list(faults.kinds())
    assert list(faults.kinds()) == [faults.PARAMETER_CHANGE, *effects.active()]
    assert injected["$defs"]["hidden_classes"]["items"]["enum"] == [faults.HEALTHY, faults.PARAMETER_CHANGE, *effects.active()]
    for section in ("diagnosis", "hidden"):
        assert injected["properties"][section]["properties"]["faults"]["propertyNames"]["enum"] == list(effects.active())
    assert injected["properties"]["diagnosis"]["properties"]["effects"]["items"]["enum"] == list(effects.active())
    assert injected["properties"]["operating_range"]["propertyNames"]["enum"] == list(model.OPERATING_PARAMETERS)
    assert not [path for path, node in _subschemas(injected) if "x-kinds" in node]
    assert cfg.load_schema() == injected  # the default schema path


def _subschemas(node, path="#"):
    if isinstance(node, dict):
        yield path, node
        for key, value in node.items():
            yield from _subschemas(value, f"{path}/{key}")
    elif isinstance(node, list):
        for i, value in enumerate(node):
            yield from _subschemas(value, f"{path}/{i}")


def test_schema_is_closed_and_described():
    for path, node in _subschemas(_schema()):
        if path.endswith(("/properties", "/$defs")):
            continue  # maps of names, not schemas
        if node.get("type") == "object":
            assert "additionalProperties" in node, path
            if "properties" in node:
                assert node["additionalProperties"] is False, path
        if path != "#" and ("type" in node or "enum" in node or "$ref" in node):
            assert "description" in node or "$ref" in node, path
    for path, node in _subschemas(_schema()):
        if path.endswith("/properties"):
            for key, sub in node.items():
                assert "description" in sub or "$ref" in sub, f"{path}/{key}"


def _leaf_keys(node, prefix=""):
    for key, value in node.items():
        yield key
        if isinstance(value, dict) and prefix != "scenarios":
            yield from _leaf_keys(value, key)


def _optional_keys(node, path=""):
    """The dotted paths of the keys the schema leaves optional (a mapping's entries as ``<name>``), a scenario's aside."""
    required = set(node.get("required", []))
    for key, sub in node.get("properties", {}).items():
        if key == "scenarios":
            continue
        dotted = f"{path}.{key}" if path else key
        if key not in required:
            yield dotted
        yield from _optional_keys(sub, dotted)
    if isinstance(node.get("additionalProperties"), dict):
        yield from _optional_keys(node["additionalProperties"], f"{path}.<name>")


def test_readme_names_every_key_that_may_be_left_out():
    """config/README.md says every key is required but those it lists: the list is the schema's optional keys."""
    paragraph = re.search(r"Every section and every key in it is \*\*required\*\*, except these(.*?)Unknown keys",
                          README.read_text(encoding="utf-8"), re.DOTALL).group(1)
    named = set(re.findall(r"`([^`]+)`", paragraph))
    optional = sorted(_optional_keys(_schema()))
    missing = [key for key in optional if key not in named and key.rsplit(".", 1)[-1] not in named]
    assert optional and not missing, f"config/README.md does not say these keys may be left out: {missing}"


def test_readme_documents_every_key(default_config):
    readme = README.read_text(encoding="utf-8")
    keys = set(_leaf_keys(default_config)) - set(default_config["scenarios"]) | {
        "overrides",
        "description",
        "fault",
        "kind",
        "parameters",
        "effects",
        "faults",
        "classes",
    }
    keys |= set(faults.kinds())
    for effect in effects.active().values():
        keys |= set(effect.parameter_names())
    missing = sorted(k for k in keys if not re.search(rf"`{re.escape(k)}`", readme))
    assert not missing, f"config/README.md does not document: {missing}"
    assert "--configfile" in readme


@pytest.mark.parametrize(
    "kind, parameter",
    [(kind, p.name) for kind, effect in effects.active().items() for p in effect.parameters if p.default is None],
)
def test_effect_parameter_without_default_is_required(default_config, kind, parameter):
    config = copy.deepcopy(default_config)
    config["scenarios"]["x"] = {"fault": {"kind": kind, "parameters": {}}}
    assert_one_line(error_of(config), SOURCE, f"scenarios.x.fault.parameters.{parameter}", f"needs its parameter {parameter}")


@pytest.mark.parametrize(
    "kind, parameters, field, problem",
    [
        ("stick_slip", {"T_max": 1500.0}, "parameters.T_max", "must exceed T0"),
        ("stick_slip", {"T_max": 2000.0, "r_k": 0.5}, "parameters.T_max", "stalls"),
        ("stick_slip", {"r_k": 1.5}, "parameters.r_k", "(0, 1]"),
    ],
)
def test_fault_without_severity_or_unable_to_carry_the_load_is_rejected(default_config, kind, parameters, field, problem):
    config = copy.deepcopy(default_config)
    config["scenarios"]["x"] = {"fault": {"kind": kind, "parameters": parameters}}
    assert_one_line(error_of(config), SOURCE, f"scenarios.x.fault.{field}", problem)



# --------------------------------------------------------------------------------------------------
# effect ranges and hidden classes: the effect files' defaults, the config's optional overrides


def test_ranges_default_to_the_effect_files(default_config):
    assert "faults" not in default_config["diagnosis"] and "faults" not in default_config["hidden"]
    diagnosis, hidden = study.diagnosis_ranges(default_config), study.hidden_ranges(default_config)
    assert list(diagnosis) == list(hidden) == list(effects.active())
    for kind, effect in effects.active().items():
        assert list(diagnosis[kind]) == list(hidden[kind]) == list(effect.parameter_names())  # declaration order
        for p in effect.parameters:
            assert diagnosis[kind][p.name] == tuple(p.prior)
            assert hidden[kind][p.name] == tuple(p.draw_range)


def test_range_overrides_replace_only_what_they_name(default_config):
    config = copy.deepcopy(default_config)
    config["diagnosis"]["faults"] = {"stick_slip": {"T_max": [1700, 2400]}}
    config["hidden"]["faults"] = {"breathing_crack": {"alpha": [0.2, 0.4]}}
    cfg.check(config, SOURCE, SCHEMA)
    diagnosis, hidden = study.diagnosis_ranges(config), study.hidden_ranges(config)
    assert diagnosis["stick_slip"]["T_max"] == (1700.0, 2400.0)
    assert hidden["breathing_crack"]["alpha"] == (0.2, 0.4)
    expected = study.diagnosis_ranges(default_config)
    expected["stick_slip"]["T_max"] = (1700.0, 2400.0)
    assert diagnosis == expected
    # a range may start at an exclusive lower bound (T_max > 0), as the effect files' may
    config["diagnosis"]["faults"]["stick_slip"]["T_max"] = [0.0, 2400.0]
    cfg.check(config, SOURCE, SCHEMA)
    # a spec holding just the section works too; a kind that is not active is an error
    assert study.hidden_ranges({"hidden": config["hidden"]}) == hidden
    with pytest.raises(KeyError, match="not an active effect"):
        study.diagnosis_ranges({"diagnosis": {"faults": {"torque_ripple": {"amplitude": [0, 1]}}}})


def test_a_diagnosis_offers_the_effects_it_names(default_config):
    config = copy.deepcopy(default_config)
    config["diagnosis"]["effects"] = ["loose_bearing", "stick_slip"]
    cfg.check(config, SOURCE, SCHEMA)
    assert list(study.diagnosis_ranges(config)) == ["loose_bearing", "stick_slip"]
    assert list(study.hidden_ranges(config)) == list(effects.active())  # the blind draw is not narrowed
    config["diagnosis"]["effects"] = ["stick_slip", "rust"]
    assert_one_line(error_of(config), SOURCE, "diagnosis.effects[1]", "must be one of", "stick_slip")


def test_hidden_classes(default_config):
    assert "classes" not in default_config["hidden"]
    assert study.hidden_classes(default_config) == [faults.HEALTHY, *faults.kinds()]
    config = copy.deepcopy(default_config)
    config["hidden"]["classes"] = ["healthy", "loose_bearing"]
    cfg.check(config, SOURCE, SCHEMA)
    assert study.hidden_classes(config) == ["healthy", "loose_bearing"]
    assert set(default_config["hidden"]["sets"]["demo"]["classes"]) <= set(effects.active())  # the demo keeps its own list


# --------------------------------------------------------------------------------------------------
# the study's own effects: files effects/<name>.py beside config/

RIPPLE = (Path(__file__).parent / "effects" / "torque_ripple.py").read_text(encoding="utf-8")  # a test effect


@pytest.fixture
def effect_folder(tmp_path, monkeypatch, request):
    """Run in a fresh folder with an ``effects/`` beside where the config would be; write(name, text)
    writes ``effects/<name>.py``.  Afterwards the built-in effects only are active again."""
    request.addfinalizer(lambda: effects.use([]))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "effects").mkdir()

    def write(text: str, name: str = "torque_ripple") -> Path:
        path = tmp_path / "effects" / f"{name}.py"
        path.write_text(text, encoding="utf-8")
        return path

    return write


def _with_ripple(default_config) -> dict:
    config = copy.deepcopy(default_config)
    config["effects"] = ["torque_ripple"]
    config["scenarios"]["ripple"] = {"fault": {"kind": "torque_ripple", "parameters": {"amplitude": 10.0}}}
    return config


def test_user_effect_is_a_kind_like_the_builtins(default_config, effect_folder):
    effect_folder(RIPPLE)
    config = _with_ripple(default_config)
    cfg.check(config, SOURCE, SCHEMA)
    assert list(effects.active())[-1] == "torque_ripple" and "torque_ripple" in faults.kinds()
    schema = cfg.load_schema(SCHEMA)
    assert "torque_ripple" in schema["$defs"]["fault"]["properties"]["kind"]["enum"]
    assert "torque_ripple" in schema["$defs"]["hidden_classes"]["items"]["enum"]
    assert "torque_ripple" in schema["properties"]["diagnosis"]["properties"]["faults"]["propertyNames"]["enum"]
    assert study.diagnosis_ranges(config)["torque_ripple"] == {"amplitude": (0.0, 50.0), "order": (1.0, 12.0)}
    assert study.hidden_ranges(config)["torque_ripple"] == {"amplitude": (5.0, 20.0), "order": (1.0, 12.0)}
    assert study.hidden_classes(config)[-1] == "torque_ripple"  # drawn in the blind test with no other edit
    values = study.scenario_values(config, "ripple")
    assert tuple(values) == slots.slot_names()
    assert (values["torque_ripple"], values["torque_ripple.amplitude"], values["torque_ripple.order"]) == (1.0, 10.0, 6.0)
    assert study.scenario_values(config, "healthy")["torque_ripple"] == 0.0
    # its ranges can be overridden and checked like a built-in's
    config["diagnosis"]["faults"] = {"torque_ripple": {"amplitude": [0.0, 20.0]}}
    cfg.check(config, SOURCE, SCHEMA)
    assert study.diagnosis_ranges(config)["torque_ripple"]["amplitude"] == (0.0, 20.0)
    config["hidden"]["faults"] = {"torque_ripple": {"order": [-1.0, 3.0]}}
    assert_one_line(error_of(config), SOURCE, "hidden.faults.torque_ripple.order", "(0, inf)")
    del config["hidden"]["faults"]
    config["scenarios"]["ripple"]["fault"]["parameters"] = {}
    assert_one_line(error_of(config), SOURCE, "scenarios.ripple.fault.parameters.amplitude", "needs its parameter amplitude")
    # checking a config without effects resets to the built-ins: the kind is unknown again
    without = _with_ripple(default_config)
    del without["effects"]
    assert_one_line(error_of(without), SOURCE, "scenarios.ripple.fault.kind", "must be one of")
    assert "torque_ripple" not in effects.active()
    # `effects: []` is the built-ins only, as omitting it is
    cfg.check({**copy.deepcopy(default_config), "effects": []}, SOURCE, SCHEMA)
    assert list(effects.active()) == list(effects.builtin())


def test_user_effect_through_load(default_config, effect_folder, tmp_path):
    effect_folder(RIPPLE)
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(_with_ripple(default_config), sort_keys=False, allow_unicode=True), encoding="utf-8")
    loaded = cfg.load(path, SCHEMA)
    assert loaded["effects"] == ["torque_ripple"] and "torque_ripple" in study.hidden_ranges(loaded)
    cfg.use_effects({})  # as a job would, for a config without effects
    assert "torque_ripple" not in effects.active()
    cfg.use_effects(loaded)
    assert "torque_ripple" in effects.active()


@pytest.mark.parametrize(
    "old, new, words",
    [
        ("    def force(s, p, rig, mode):", "    def force(s, p, rig, mode)", ["syntax error on line"]),
        ('Parameter("order", "-",', 'Parameter("order", "",', ["parameter 'order' has no unit"]),
        ("return p.amplitude * math.sin(p.order * s.theta1)", "return p.amplitude * math.sin(p.order * s.theta1) + math.nan",
         ["force() returned nan"]),
        ('name = "torque_ripple"', 'name = "ripple"', ["name the file after the effect"]),
        ("import math\n", "import math\nimport no_such_module_here\n", ["cannot be imported", "ModuleNotFoundError"]),
    ],
    ids=["syntax error", "missing unit", "NaN force", "misnamed", "import error"],
)
def test_bad_user_effect_gives_one_line_naming_config_field_and_file(default_config, effect_folder, old, new, words):
    assert RIPPLE.count(old) == 1, old
    effect_folder(RIPPLE.replace(old, new))
    err = error_of(_with_ripple(default_config))
    assert_one_line(err, SOURCE, "effects[0]", str(Path("effects") / "torque_ripple.py"), *words)
    assert "torque_ripple" not in effects.active()  # the active set stays as it was


def test_an_effect_files_functions_are_called_once_for_its_content(effect_folder, tmp_path, monkeypatch):
    """That a file's functions return numbers is remembered by the file's content in the cache folder: loading it
    again (the next parse of the Snakefile) calls none of them, while a file with other content, or one that failed,
    is called."""
    from newdyn.effects import check

    monkeypatch.setenv("NEWDYN_CACHE", str(tmp_path / "cache"))
    path = effect_folder(RIPPLE)
    effects.load_file(path)
    calls = []
    monkeypatch.setattr(check, "_evaluation_problems", lambda effect: calls.append(effect.name) or iter(()))
    path.write_text(RIPPLE + "\n", encoding="utf-8")
    effects.load_file(path)
    assert calls == ["torque_ripple"]
    path.write_text(RIPPLE, encoding="utf-8")
    effects.load_file(path)
    assert calls == ["torque_ripple"]
    # A failure is not remembered: it may come from a helper the file imports, which its content does not name.
    monkeypatch.setattr(check, "_evaluation_problems", lambda effect: calls.append(effect.name) or iter(["force() returned nan"]))
    path.write_text(RIPPLE + "\n\n", encoding="utf-8")
    for _ in range(2):
        with pytest.raises(effects.EffectError, match="returned nan"):
            effects.load_file(path)
    assert calls == ["torque_ripple"] * 3


def test_missing_user_effect_file(default_config, effect_folder):
    effect_folder(RIPPLE)
    config = copy.deepcopy(default_config)
    config["effects"] = ["torque_ripple", "wobble"]
    assert_one_line(error_of(config), SOURCE, "effects[1]", str(Path("effects") / "wobble.py"), "no such file")


def test_user_effect_counts_in_the_diagnosis_walkers(default_config, effect_folder):
    """The walkers must cover the largest effect's parameters plus the drift, a study's own effect too."""
    order = '        Parameter("order", "-", "ripple periods per revolution", default=6.0, prior=(1.0, 12.0)),\n'
    extra = "".join(f'        Parameter("c{i}", "-", "an unused coefficient", default=1.0, prior=(0.5, 1.5)),\n' for i in range(5))
    effect_folder(RIPPLE.replace(order, order + extra))
    config = _with_ripple(default_config)  # 7 parameters and the drift kT1: the KDE move needs 2·8 + 2 walkers
    assert_one_line(error_of(config), SOURCE, "diagnosis.mcmc.walkers", "at least 18", "the 8 parameters")
    config["diagnosis"]["mcmc"]["walkers"] = 18
    cfg.check(config, SOURCE, SCHEMA)


@pytest.mark.parametrize("environment", ["environment.yml", "workflow/envs/newdyn.yaml"])
def test_conda_environments_hold_every_runtime_dependency_of_the_package(environment):
    """pyproject.toml lists the dependencies once; conda cannot read it, so its files must agree with it."""
    import tomllib

    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    wanted = {re.match(r"[A-Za-z0-9_.-]+", d).group(0).lower(): d for d in declared}
    listed = {}
    for entry in yaml.safe_load((ROOT / environment).read_text())["dependencies"]:
        if isinstance(entry, str):
            name = re.match(r"[A-Za-z0-9_.-]+", entry).group(0).lower()
            listed[name] = entry[len(name):].replace(" ", "")
    for name, requirement in wanted.items():
        assert name in listed, f"{environment} lacks {name}"
        assert listed[name] == requirement[len(name):].replace(" ", ""), f"{environment}: {name}{listed[name]} vs pyproject {requirement}"
