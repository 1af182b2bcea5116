"""The study configuration: load it and check it, each problem in one line.

A study config (``config/config.yaml``; every key is documented in ``config/README.md``) has the
sections ``rig`` and ``operating`` (model parameter values, :mod:`newdyn.model` names), ``sampling``,
``simulation``, ``noise``, ``scenarios`` (name -> optional ``description``, ``overrides`` of rig or
operating parameters and a ``fault`` from :mod:`newdyn.faults`), ``calibration``, ``diagnosis``,
``hidden`` and, optionally, ``effects`` (the study's own effects, files ``effects/<name>.py``) and
``variants`` (the study rerun with other rig values or channels: :func:`newdyn.study.variant_config`).

Fault kinds are never listed by hand: they are the effect registry's (:func:`newdyn.effects.active`,
the built-ins plus the config's ``effects``), injected into the schema by :func:`load_schema`.

:func:`check` validates in three stages and raises :class:`ConfigError` for the first problem, as one line
``<file>: <dotted.field>: <problem>``:

1. the config's ``effects``: each file is loaded and checked (:func:`newdyn.effects.use`), which makes
   them the active effects of this process;
2. structure, against the JSON schema ``newdyn/schemas/config.schema.yaml``, shipped in the package (the single
   source of the keys and types; the workflow's ``workflow/schemas/`` links to it) with the active kinds injected;
3. physics: every rig and operating value, every override and every fault against the bounds in
   :mod:`newdyn.model` and the effect files; the sampling window; finite SNRs; the resulting model
   values of every scenario (after overrides and fault); the calibration; the diagnosis and hidden-set
   ranges; then each variant's study.

What a checked config describes (its variants, scenarios, model values, ranges) is derived by :mod:`newdyn.study`.

Note on YAML numbers: YAML 1.1 (PyYAML, and so Snakemake) reads ``3.25e6`` as *text*; write exponents
with a sign, ``3.25e+6``.  The check says so when it meets such a string.
"""

from __future__ import annotations

import difflib
import math
import re
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from . import effects, faults, model, slots, study

#: The config schema, package data: an installed package checks a config without the workflow's source tree.
SCHEMA_PATH = Path(__file__).resolve().parent / "schemas" / "config.schema.yaml"

#: Parameters a scenario may override (an effect's parameters are set through ``fault:`` only).
OVERRIDABLE: tuple[str, ...] = model.RIG_PARAMETERS + model.OPERATING_PARAMETERS



_TYPE_NAMES = {
    "number": "a number",
    "integer": "a whole number",
    "object": "a mapping",
    "array": "a list",
    "string": "text",
    "boolean": "true or false",
    "null": "empty",
}


#: The problem of a config that lacks a required key (what follows names the others missing).
MISSING_KEY = "missing required key"


class ConfigError(ValueError):
    """A config problem, reported as one line ``<file>: <dotted.field>: <problem>``."""

    def __init__(self, source: str, field: str, problem: str):
        self.source = str(source)
        self.field = field or "(top level)"
        self.problem = " ".join(str(problem).split())  # one line, whatever the message held
        super().__init__(f"{self.source}: {self.field}: {self.problem}")


# ----------------------------------------------------------------------------------------------------
# loading and checking


def load(path: str | Path, schema_path: str | Path | None = None) -> dict:
    """Read a YAML config file, :func:`check` it and return it (a plain dict)."""
    config = read(path)
    check(config, str(path), schema_path)
    return config


def load_merged(paths: Sequence[str | Path], schema_path: str | Path | None = None) -> dict:
    """The config files ``paths`` merged in that order as Snakemake merges a workflow's ``configfile:`` and each
    ``--configfile`` (:func:`snakemake.utils.update_config`: a mapping key by key, anything else, a list too, replaced
    whole), then :func:`check`-ed as one config whose problems name every file: ``a.yaml, b.yaml: field: problem``."""
    from snakemake.utils import update_config

    parts = [read(path) for path in paths]
    if len(parts) == 1:
        config = parts[0]
    else:
        config = {}
        for path, part in zip(paths, parts):
            if not isinstance(part, Mapping):
                raise ConfigError(path, "(top level)", f"must be a mapping of sections (rig:, noise:, …) to merge with the "
                                                       f"other files (got {_show(part)})")
            update_config(config, part)
    check(config, ", ".join(map(str, paths)), schema_path)
    return config


def read(path: str | Path) -> Any:
    """The YAML of a config file, not checked; a file that cannot be read, bad YAML or a duplicate key raises
    :class:`ConfigError`."""
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(source, "(file)", f"cannot read: {exc.strerror or exc}") from None
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        for parts, line in _duplicate_keys(node, []):
            raise ConfigError(
                source, _field(parts), f"duplicate key on line {line} (YAML would keep only the last one)"
            )
        config = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        what = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(source, "(file)", f"not valid YAML: {what}{where}") from None
    return config


def check(config: Any, source: str, schema_path: str | Path | None = None) -> None:
    """Raise :class:`ConfigError` for the first problem of ``config`` (read from ``source``).

    ``schema_path`` defaults to :data:`SCHEMA_PATH`.  Structure is checked first (JSON schema), then
    physics, so the physical checks can rely on every key being present with the right type.

    Checking makes the config's ``effects`` (and the built-ins) the active effects of this process
    (:func:`newdyn.effects.use`); a config without ``effects`` resets them to the built-ins.
    """
    for parts, key in _non_text_keys(config, []):
        raise ConfigError(source, _field(parts), f"key {key!r} must be text, not {type(key).__name__} (quote it)")
    raw = _read_schema(schema_path)
    if isinstance(config, Mapping) and "effects" in config:  # the list's structure first: it is loaded before the rest
        only_effects = {"type": "object", "properties": {"effects": raw["properties"]["effects"]}}
        error = _schema_error({"effects": config["effects"]}, only_effects)
        if error is not None:
            raise ConfigError(source, *error)
    _use_effects(config, source)
    error = _schema_error(config, _inject_kinds(raw))
    if error is not None:
        raise ConfigError(source, *error)
    for field, problem in _physical_problems(config):
        raise ConfigError(source, field, problem)


def effect_names(config: Mapping) -> list[str]:
    """The study's own effects (``effects``; none when omitted), in config order."""
    return list(config.get("effects") or [])


def use_effects(config: Mapping) -> Mapping[str, type[effects.Effect]]:
    """Make the built-ins and the config's ``effects`` the active effects of this process (as
    :func:`check` does); a job that reads a checked config calls this before it needs the kinds.
    Raises :class:`newdyn.effects.EffectError` for a bad effect file."""
    return effects.use(effect_names(config))


def _use_effects(config: Any, source: str) -> None:
    """:func:`use_effects`, with a bad effect reported as ``<file>: effects[i]: <effect file>: <problem>``."""
    names = effect_names(config) if isinstance(config, Mapping) else []
    for i, name in enumerate(names):
        if name in (faults.HEALTHY, faults.PARAMETER_CHANGE):
            raise ConfigError(source, f"effects[{i}]", f"'{name}' is a class of its own (healthy, parameter_change); "
                                                       "give your effect another name")
    try:
        effects.use(names)
    except effects.EffectError as error:
        stem = Path(error.source).stem
        field = next((f"effects[{i}]" for i, name in enumerate(names) if name == stem), "effects")
        raise ConfigError(source, field, str(error)) from None


#: What an ``x-kinds`` marker of the schema stands for: the list its node's ``enum`` becomes.
_KIND_LISTS = {
    "faults": lambda: list(faults.kinds()),
    "effects": lambda: list(effects.active()),
    "hidden_classes": lambda: list(faults.classes()),
    "operating": lambda: list(model.OPERATING_PARAMETERS),
    "channels": lambda: list(model.CHANNELS),
}


def _read_schema(schema_path: str | Path | None) -> dict:
    with open(schema_path or SCHEMA_PATH, encoding="utf-8") as f:
        return yaml.safe_load(f)


def _inject_kinds(node: Any) -> Any:
    """A copy of the schema ``node`` in which every ``x-kinds: <list>`` marker is replaced by
    ``enum: [...]``, that list of the active effect registry."""
    if isinstance(node, list):
        return [_inject_kinds(item) for item in node]
    if not isinstance(node, Mapping):
        return node
    out = {key: _inject_kinds(value) for key, value in node.items() if key != "x-kinds"}
    if "x-kinds" in node:
        which = node["x-kinds"]
        if which not in _KIND_LISTS:
            raise ValueError(f"config schema: unknown x-kinds {which!r} (known: {', '.join(_KIND_LISTS)})")
        out["enum"] = _KIND_LISTS[which]()
    return out


def load_schema(schema_path: str | Path | None = None) -> dict:
    """The config schema (default :data:`SCHEMA_PATH`) with the active fault kinds injected: the
    schema :func:`check` validates against (call :func:`use_effects` first for a study's own effects)."""
    return _inject_kinds(_read_schema(schema_path))


def _schema_error(config: Any, schema: Mapping) -> tuple[str, str] | None:
    """(field, problem) of the most relevant violation of ``schema``, or None."""
    from jsonschema.exceptions import best_match, by_relevance
    from jsonschema.validators import validator_for

    cls = validator_for(schema)  # the schema itself is held to its metaschema by the tests, not on every parse
    # Among errors on the same object prefer an unexpected (e.g. mistyped) key over the key it lacks.
    error = best_match(cls(schema).iter_errors(config), key=by_relevance(strong=frozenset({"additionalProperties"})))
    if error is None:
        return None
    parts, problem = _describe(error)
    return _field(parts), problem


def _describe(error) -> tuple[list, str]:
    """Path parts and a one-line problem for a jsonschema ValidationError."""
    parts = list(error.absolute_path)
    kind, value, instance, schema = error.validator, error.validator_value, error.instance, error.schema

    if kind == "additionalProperties" and value is False and isinstance(instance, Mapping):
        known = list(schema.get("properties", {}))
        patterns = list(schema.get("patternProperties", {}))
        extras = [k for k in instance if k not in known and not any(re.search(p, str(k)) for p in patterns)]
        key = extras[0] if extras else "?"
        problem = f"unknown key{_did_you_mean(key, known)} (allowed: {', '.join(known)})"
        return parts + [key], problem

    if kind == "required" and isinstance(instance, Mapping):
        missing = [k for k in value if k not in instance]
        problem = MISSING_KEY
        if len(missing) > 1:
            problem += f" (also missing: {', '.join(missing[1:])})"
        return parts + [missing[0] if missing else "?"], problem

    if kind == "type":
        expected = " or ".join(_TYPE_NAMES.get(t, t) for t in ([value] if isinstance(value, str) else value))
        return parts, f"must be {expected} (got {_show(instance)}){_number_text_hint(instance)}"

    in_names = "propertyNames" in error.relative_schema_path or "propertyNames" in error.schema_path
    if kind == "enum":
        allowed = ", ".join(str(v) for v in value)
        if in_names:  # a key that is not one of the allowed names: point at it
            return parts + [instance], f"unknown name: must be one of {allowed}{_did_you_mean(instance, value)}"
        return parts, f"must be one of {allowed} (got {_show(instance)}){_did_you_mean(instance, value)}"

    if in_names:
        # The name itself is wrong: point at it.
        what = schema.get("description", "") if isinstance(schema, Mapping) else ""
        problem = f"invalid name: must match {schema.get('pattern', value)}"
        if what:
            problem += f"; {what.rstrip('.')}"
        return parts + [instance], problem

    if kind == "uniqueItems" and isinstance(instance, list):
        for j, item in enumerate(instance):
            for i in range(j):
                if _same(instance[i], item):
                    return parts + [j], f"duplicate of {_field(parts + [i])} ({_show(item)})"

    if kind == "pattern":
        return parts, f"must match {value} (got {_show(instance)})"
    if kind == "minItems":
        return parts, f"must list at least {value} item{'s' if value != 1 else ''}"
    if kind == "minProperties":
        return parts, f"must have at least {value} entr{'ies' if value != 1 else 'y'}"
    if kind == "minimum":
        return parts, f"must be ≥ {value} (got {_show(instance)})"
    return parts, error.message


def _physical_problems(config: Mapping) -> Iterator[tuple[str, str]]:
    """(field, problem) pairs for a config that already matches the schema.

    Stages run in order and stop after the first stage with problems, so every later stage can
    rely on what the earlier ones checked (e.g. load_freq > 0 before the load-cycle check).
    """
    for stage in (_value_problems, _sampling_problems, _noise_problems, _all_scenario_problems, _calibration_problems,
                  _diagnosis_problems, _hidden_problems):
        problems = list(stage(config))
        if problems:
            yield from problems
            return
    yield from _variant_problems(config)


def _variant_problems(config: Mapping) -> Iterator[tuple[str, str]]:
    """A variant's references must exist; then its derived study must pass the same physical checks."""
    for name, variant in (config.get("variants") or {}).items():
        where = f"variants.{name}"
        variant = variant or {}
        references = list(_variant_reference_problems(where, variant, config))
        if references:
            yield from references
            return
        for field, problem in _physical_problems(study.variant_config(config, name)):
            yield f"{where} (as {field})", problem
            return


def _variant_reference_problems(where: str, variant: Mapping, config: Mapping) -> Iterator[tuple[str, str]]:
    for key in variant.get("rig", {}):
        if key not in model.RIG_PARAMETERS:
            yield f"{where}.rig.{key}", f"unknown rig parameter{_did_you_mean(key, model.RIG_PARAMETERS)} (known: {', '.join(model.RIG_PARAMETERS)})"
    for key, known in (
        ("scenarios", list(config["scenarios"])),
        ("parameters", list(config["calibration"]["parameters"])),
        ("snr_db", list(config["noise"]["snr_db"])),
    ):
        for i, item in enumerate(variant.get(key, [])):
            if item not in known:
                yield f"{where}.{key}[{i}]", f"{item!r} is not in the study's {key} ({', '.join(map(str, known))})"


def _value_problems(config: Mapping) -> Iterator[tuple[str, str]]:
    for section, names in (("rig", model.RIG_PARAMETERS), ("operating", model.OPERATING_PARAMETERS)):
        for name in names:
            problem = model.PARAMETER_BY_NAME[name].problem(config[section][name])
            if problem is not None:
                yield f"{section}.{name}", problem
    for name, (low, high) in config.get("operating_range", {}).items():
        problem = model.PARAMETER_BY_NAME[name].problem(low) or model.PARAMETER_BY_NAME[name].problem(high)
        if problem is None and not low < high:
            problem = f"must be [low, high] with low < high (got [{low:g}, {high:g}])"
        if problem is not None:
            yield f"operating_range.{name}", problem


def _sampling_problems(config: Mapping) -> Iterator[tuple[str, str]]:
    s = config["sampling"]
    fs, t_warm, t_rec = s["fs"], s["t_warm"], s["t_rec"]
    bad = False
    for key, value, positive, unit in (
        ("fs", fs, True, "Hz"),
        ("t_warm", t_warm, False, "s"),
        ("t_rec", t_rec, True, "s"),
    ):
        if not math.isfinite(value) or value < 0 or (positive and value == 0):
            bad = True
            yield f"sampling.{key}", f"must be a finite number {'>' if positive else '≥'} 0 {unit} (got {value})"
    if bad:
        return
    n = fs * t_rec
    if abs(n - round(n)) > 1e-6 * max(1.0, n):
        yield "sampling.t_rec", f"fs·t_rec = {n:.10g} must be a whole number of samples (fs = {fs:g} Hz, t_rec = {t_rec:g} s)"
    yield from _load_cycle_problem("sampling.t_rec", fs, t_rec, config["operating"]["load_freq"])


def _noise_problems(config: Mapping) -> Iterator[tuple[str, str]]:
    for i, snr in enumerate(config["noise"]["snr_db"]):
        if not math.isfinite(snr):
            yield f"noise.snr_db[{i}]", f"must be a finite number of dB (got {snr})"


def _calibration_problems(config: Mapping) -> Iterator[tuple[str, str]]:
    calibration = config["calibration"]
    simulated = config["simulation"]["channels"]
    for i, channel in enumerate(calibration["channels"]):
        if channel not in simulated:
            yield f"calibration.channels[{i}]", f"'{channel}' is not simulated (simulation.channels: {', '.join(simulated)})"
    if not calibration["chi2_max"] > 1.0:
        yield "calibration.chi2_max", f"must exceed 1, the reduced χ² of a model that explains the data (got {calibration['chi2_max']})"
    mcmc = calibration["mcmc"]
    for i, name in enumerate(mcmc["parameters"]):
        if name not in calibration["parameters"]:
            yield f"calibration.mcmc.parameters[{i}]", f"'{name}' is not one of calibration.parameters ({', '.join(calibration['parameters'])})"
    joint = calibration.get("joint", study.NO_JOINT)
    for i, name in enumerate(joint["parameters"]):
        if name not in calibration["parameters"]:
            yield f"calibration.joint.parameters[{i}]", f"'{name}' is not one of calibration.parameters ({', '.join(calibration['parameters'])})"
    # emcee needs 2·ndim walkers; the KDE move also a nonsingular KDE of half the ensemble (> ndim)
    kde = 2 if mcmc["move"] == "kde" else 0
    runs = [("calibration.mcmc.walkers", mcmc["walkers"], 1)]
    if joint["parameters"]:
        runs.append(("calibration.joint.walkers", joint["walkers"], study.joint_dimension(config)))
    for field, walkers, dimension in runs:
        if walkers < 2 * dimension + kde or walkers % 2:
            yield field, (
                f"must be even and at least {2 * dimension + kde}: twice the {dimension} sampled quantit"
                f"{'ies' if dimension > 1 else 'y'}{' plus 2 for the kde move' if kde else ''}, got {walkers}"
            )
    if not mcmc["rhat_max"] > 1.0:
        yield "calibration.mcmc.rhat_max", f"must exceed 1 (got {mcmc['rhat_max']})"
    for name, spec in calibration["parameters"].items():
        where = f"calibration.parameters.{name}"
        if name not in model.RIG_PARAMETERS:
            yield where, f"unknown rig parameter{_did_you_mean(name, model.RIG_PARAMETERS)} (known: {', '.join(model.RIG_PARAMETERS)})"
            continue
        bounds = model.PARAMETER_BY_NAME[name]
        prior, grid = spec["prior"], spec["grid"]
        if not (math.isfinite(prior["sd"]) and prior["sd"] > 0):
            yield f"{where}.prior.sd", f"must be a finite number > 0 (got {prior['sd']})"
        for field, value in (("prior.mean", prior["mean"]), ("grid.low", grid["low"]), ("grid.high", grid["high"])):
            if (problem := bounds.problem(value)) is not None:
                yield f"{where}.{field}", f"{problem}: {name} is physical only there"
        if not grid["low"] < grid["high"]:
            yield f"{where}.grid", f"bounds reversed or equal (low {grid['low']:g} ≥ high {grid['high']:g})"


def _range_problems(where: str, kind: str, ranges: Mapping[str, Sequence[float]]) -> Iterator[tuple[str, str]]:
    """Given ranges of an effect's parameters: known parameters, physical (a range may start at an
    exclusive lower bound), low < high."""
    effect = effects.active()[kind]
    known = effect.parameter_names()
    for name, (low, high) in ranges.items():
        if name not in known:
            yield f"{where}.{name}", f"unknown parameter of {kind}{_did_you_mean(name, known)} (known: {', '.join(known)})"
            continue
        parameter = effect.parameter(name)
        for value in (low, high):
            if (problem := parameter.problem(value)) is not None and not (value == parameter.lower and value == low):
                yield f"{where}.{name}", f"{problem}"
        if not low < high:
            yield f"{where}.{name}", f"bounds reversed or equal (low {low:g} ≥ high {high:g})"


def _diagnosis_problems(config: Mapping) -> Iterator[tuple[str, str]]:
    diagnosis, calibration = config["diagnosis"], config["calibration"]
    for i, name in enumerate(diagnosis["drift"]):
        if name not in calibration["parameters"]:
            yield f"diagnosis.drift[{i}]", f"'{name}' is not one of calibration.parameters ({', '.join(calibration['parameters'])})"
    for kind, ranges in (diagnosis.get("faults") or {}).items():
        yield from _range_problems(f"diagnosis.faults.{kind}", kind, ranges)
    # every active effect is a hypothesis, all its parameters fitted jointly with the drift
    offered = diagnosis.get("effects") or list(effects.active())
    largest = max((len(effects.active()[kind].parameters) for kind in offered), default=0) + len(diagnosis["drift"])
    walkers, kde = diagnosis["mcmc"]["walkers"], 2 if calibration["mcmc"]["move"] == "kde" else 0
    if walkers < 2 * largest + kde or walkers % 2:
        yield "diagnosis.mcmc.walkers", (f"must be even and at least {2 * largest + kde}: twice the {largest} parameters of the "
                                         f"largest fault model{' plus 2 for the kde move' if kde else ''}, got {walkers}")


def _hidden_problems(config: Mapping) -> Iterator[tuple[str, str]]:
    hidden = config["hidden"]
    for i, name in enumerate(hidden["parameter_change"]["parameters"]):
        if name not in model.RIG_PARAMETERS:
            yield f"hidden.parameter_change.parameters[{i}]", f"unknown rig parameter{_did_you_mean(name, model.RIG_PARAMETERS)}"
    low, high = hidden["parameter_change"]["relative"]
    if not 0 <= low < high < 1:
        yield "hidden.parameter_change.relative", f"must be 0 <= low < high < 1 (got [{low:g}, {high:g}])"
    for kind, ranges in (hidden.get("faults") or {}).items():
        yield from _range_problems(f"hidden.faults.{kind}", kind, ranges)
    for name, spec in hidden["sets"].items():
        if name in study.variant_names(config) or name in ("diagnosis", "figures", "logs", "benchmarks"):
            yield f"hidden.sets.{name}", f"'{name}' would share results/{name}/ with the study; choose another name"
        if spec.get("instruments") and not config["diagnosis"].get("sensors"):
            yield f"hidden.sets.{name}.instruments", "draws instrument errors from diagnosis.sensors, which names none"
        if spec.get("out_of_spec", 0) > 0 and not spec.get("instruments"):
            yield f"hidden.sets.{name}.out_of_spec", "needs instruments: true (out-of-spec errors are drawn on top of them)"
        if spec.get("out_of_spec", 0) > spec["cases"]:
            yield f"hidden.sets.{name}.out_of_spec", f"more than the set's {spec['cases']} cases"
        if "recordings" in spec:
            low, high = spec["recordings"]
            if low > high:
                yield f"hidden.sets.{name}.recordings", f"must be [low, high] with low <= high (got [{low}, {high}])"
            if not config.get("operating_range"):
                yield f"hidden.sets.{name}.recordings", "draws each recording's condition in operating_range, which is not set"
            if spec.get("instruments"):
                yield f"hidden.sets.{name}.recordings", "a set of machines is drawn with exact instruments (drop instruments)"


def _all_scenario_problems(config: Mapping) -> Iterator[tuple[str, str]]:
    base = study.base_values(config)
    s = config["sampling"]
    for name, scenario in config["scenarios"].items():
        yield from _scenario_problems(f"scenarios.{name}", scenario, base, s["fs"], s["t_rec"])


def _scenario_problems(
    where: str, scenario: Mapping, base: Mapping[str, float], fs: float, t_rec: float
) -> Iterator[tuple[str, str]]:
    spec = list(_scenario_spec_problems(where, scenario, base))
    if spec:
        yield from spec
        return  # the resulting values cannot be computed from a broken spec

    # The resulting rig and operating values (overrides, then the fault's rig values, its defaults
    # derived from them); an effect's own values were checked by faults.fault_problems.
    overrides = scenario.get("overrides", {})
    fault = scenario.get("fault")
    values = faults.scenario_values(scenario, base)
    set_by_fault = _rig_values_set_by_fault(where, fault, slots.complete({**base, **overrides})) if fault else {}
    for name in model.PARAMETER_NAMES:
        problem = model.PARAMETER_BY_NAME[name].problem(values[name])
        if problem is None:
            continue
        if name in set_by_fault:
            field = set_by_fault[name]
        elif name in overrides:
            field = f"{where}.overrides.{name}"
        else:
            field = f"{'rig' if name in model.RIG_PARAMETERS else 'operating'}.{name}"
        yield field, f"resulting {name} {problem}"

    if "load_freq" in overrides:
        yield from _load_cycle_problem(f"{where}.overrides.load_freq", fs, t_rec, values["load_freq"])


def _rig_values_set_by_fault(where: str, fault: Mapping, values: Mapping[str, float]) -> dict[str, str]:
    """Rig or operating parameter the fault sets -> the field a problem of its value is reported at:
    the fault parameter that sets it when one given parameter does, else the fault as a whole."""
    kind, parameters = fault["kind"], fault.get("parameters", {})
    set_values = faults.model_values(kind, parameters, values)
    if kind == faults.PARAMETER_CHANGE:
        return {name: f"{where}.fault.parameters.{name}" for name in set_values if name in model.PARAMETER_NAMES}
    setters = [p.name for p in effects.active()[kind].parameters if p.sets_rig and p.name in parameters]
    field = f"{where}.fault.parameters.{setters[0]}" if len(setters) == 1 else f"{where}.fault"
    return {name: field for name in set_values if name in model.PARAMETER_NAMES}


def _scenario_spec_problems(where: str, scenario: Mapping, base: Mapping[str, float]) -> Iterator[tuple[str, str]]:
    """Problems of a scenario's overrides and fault taken one by one."""
    overrides = scenario.get("overrides", {})
    for key, value in overrides.items():
        field = f"{where}.overrides.{key}"
        if key not in OVERRIDABLE:
            owner = _effect_owning(key)
            hint = f"; {key} is a parameter of the {owner} effect: set it under fault.parameters" if owner else ""
            yield field, f"unknown rig or operating parameter{_did_you_mean(key, OVERRIDABLE)}{hint} (known: {', '.join(OVERRIDABLE)})"
        elif (problem := model.PARAMETER_BY_NAME[key].problem(value)) is not None:
            yield field, problem

    fault = scenario.get("fault")
    if fault:
        with_overrides = {**base, **overrides}  # override problems, if any, were reported first
        for sub, problem in faults.fault_problems(fault["kind"], fault.get("parameters", {}), with_overrides):
            yield (f"{where}.fault.{sub}" if sub else f"{where}.fault"), problem


def _effect_owning(name: str) -> str | None:
    """The active effect that has a parameter ``name`` (or model value ``<kind>.<parameter>``), if any."""
    for kind, effect in effects.active().items():
        if name in effect.parameter_names() or name in (slots.effect_slot(kind, p) for p in effect.parameter_names()):
            return kind
    return None


def _load_cycle_problem(field: str, fs: float, t_rec: float, load_freq: float) -> Iterator[tuple[str, str]]:
    """The recorded window must hold at least one load cycle, i.e. fs·t_rec ≥ fs/load_freq samples."""
    cycle = 1.0 / load_freq
    if t_rec * fs < fs * cycle * (1.0 - 1e-9):
        yield field, (
            f"the record of {t_rec:g} s ({round(t_rec * fs)} samples) is shorter than one load cycle "
            f"1/load_freq = {cycle:.6g} s ({fs * cycle:.6g} samples at fs = {fs:g} Hz)"
        )


# ----------------------------------------------------------------------------------------------------
# helpers for the workflow


# ----------------------------------------------------------------------------------------------------
# small formatting helpers


def _field(parts: list) -> str:
    """Dotted field path; list indices in brackets: ``noise.snr_db[1]``."""
    text = ""
    for part in parts:
        if isinstance(part, int) and not isinstance(part, bool):
            text += f"[{part}]"
        else:
            text += ("." if text else "") + str(part)
    return text


def _show(value: Any) -> str:
    if value is None:
        return "an empty value"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f"the text {_short(repr(value))}"
    if isinstance(value, Mapping):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    return _short(repr(value))


def _short(text: str, limit: int = 60) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _number_text_hint(value: Any) -> str:
    if not isinstance(value, str):
        return ""
    try:
        float(value)
    except ValueError:
        return ""
    if re.fullmatch(r"\s*[+-]?(\d+\.?\d*|\.\d+)[eE]\d+\s*", value):
        return f"; YAML reads an exponent without a sign as text: write {value.strip().replace('e', 'e+').replace('E', 'E+')}"
    return "; remove the quotes to make it a number"


def _did_you_mean(value: Any, choices) -> str:
    if not isinstance(value, str):
        return ""
    close = difflib.get_close_matches(value, [str(c) for c in choices], n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else ""


def _same(a: Any, b: Any) -> bool:
    """Equality as JSON Schema's uniqueItems sees it (1 == 1.0, but True != 1)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    return a == b


def _non_text_keys(obj: Any, parts: list) -> Iterator[tuple[list, Any]]:
    """(path of the mapping, key) for every key that is not a string (YAML reads ``1:`` as a number)."""
    if isinstance(obj, Mapping):
        for key, value in obj.items():
            if not isinstance(key, str):
                yield parts, key
            else:
                yield from _non_text_keys(value, parts + [key])
    elif isinstance(obj, list):
        for i, value in enumerate(obj):
            yield from _non_text_keys(value, parts + [i])


def _duplicate_keys(node: yaml.Node | None, parts: list) -> Iterator[tuple[list, int]]:
    """(path, line) of every key that appears twice in the same YAML mapping."""
    if isinstance(node, yaml.MappingNode):
        seen = set()
        for key_node, value_node in node.value:
            key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
            if key is not None and key in seen:
                yield parts + [key], key_node.start_mark.line + 1
            seen.add(key)
            yield from _duplicate_keys(value_node, parts + [key])
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            yield from _duplicate_keys(item, parts + [i])
