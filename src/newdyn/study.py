"""The study a checked config describes (:mod:`newdyn.config` loads and checks it): its variants, scenarios, model
values, record, the effects' parameter ranges of its diagnoses and blind tests, and a canonical text of any part.

:func:`base_values`, :func:`sampling`, :func:`scenario_values` and :func:`canonical_json` turn a checked config into
model values and a canonical text, so that the order of keys in the YAML or the spelling of a number (``3.25e+6`` or
``3250000``) changes nothing downstream; :func:`diagnosis_ranges`, :func:`hidden_ranges` and :func:`hidden_classes`
resolve the optional ``diagnosis.faults``, ``hidden.faults`` and ``hidden.classes`` against the active effects;
:func:`variant_config` is the whole study as one of its ``variants`` runs it.
"""

from __future__ import annotations

import copy
import json
import numbers
from collections.abc import Mapping, Sequence
from typing import Any

from . import effects, faults, model

#: ``calibration.joint`` of a config that has none.
NO_JOINT = {"parameters": [], "infer_sigma": False, "walkers": 0, "steps": 0}

def variant_names(config: Mapping) -> list[str]:
    """The study's variants in config order; a config without ``variants`` has one, ``default``."""
    return list(config.get("variants") or {"default": {}})


def variant_config(config: Mapping, name: str) -> dict:
    """The whole study as variant ``name`` runs it: a config without ``variants`` in which the variant's
    rig values and channels replace the study's, and its scenarios, parameters and SNRs select from them.

    The MCMC runs (1-D and joint) stay only where the variant keeps ``mcmc`` and calibrates their
    parameters; a joint calibration needs all of its parameters.
    """
    variants = config.get("variants") or {"default": {}}
    if name not in variants:
        raise KeyError(f"unknown variant {name!r} (known: {', '.join(variants)})")
    variant = variants[name] or {}
    derived = copy.deepcopy({key: value for key, value in config.items() if key != "variants"})
    derived["rig"].update(variant.get("rig", {}))
    calibration = derived["calibration"]
    calibration["channels"] = list(variant.get("channels", calibration["channels"]))
    keep = variant.get("parameters", list(calibration["parameters"]))
    calibration["parameters"] = {p: spec for p, spec in calibration["parameters"].items() if p in keep}
    if "scenarios" in variant:
        derived["scenarios"] = {s: spec for s, spec in derived["scenarios"].items() if s in variant["scenarios"]}
    if "snr_db" in variant:
        derived["noise"]["snr_db"] = [snr for snr in derived["noise"]["snr_db"] if snr in variant["snr_db"]]
    with_mcmc = variant.get("mcmc", True)
    mcmc = calibration["mcmc"]
    mcmc["parameters"] = [p for p in mcmc["parameters"] if with_mcmc and p in calibration["parameters"]]
    joint = calibration.setdefault("joint", copy.deepcopy(NO_JOINT))
    if not (with_mcmc and all(p in calibration["parameters"] for p in joint["parameters"])):
        joint["parameters"] = []
    return derived


def mcmc_runs(config: Mapping) -> list[str]:
    """The MCMC calibrations of each measurement of a variant (:func:`variant_config`): one per MCMC parameter, and
    "joint" where it has a joint calibration."""
    calibration = config["calibration"]
    return calibration["mcmc"]["parameters"] + (["joint"] if calibration.get("joint", NO_JOINT)["parameters"] else [])


def joint_dimension(config: Mapping) -> int:
    """Number of quantities the joint calibration samples: its parameters, and one σ per channel if inferred."""
    calibration = config["calibration"]
    joint = calibration.get("joint", NO_JOINT)
    if not joint["parameters"]:
        return 0
    return len(joint["parameters"]) + (len(calibration["channels"]) if joint.get("infer_sigma") else 0)


def base_values(config: Mapping) -> dict[str, float]:
    """Rig and operating values of the config merged into one mapping of model names to floats."""
    return {name: float(value) for section in ("rig", "operating") for name, value in config[section].items()}


def grid_channels(config: Mapping) -> list[str]:
    """Channels a study's coarse grids simulate: its calibrations', and its diagnoses', which reuse the grids."""
    return list(dict.fromkeys([*config["calibration"]["channels"], *config["diagnosis"]["channels"]]))


def sampling(config: Mapping) -> model.Sampling:
    """The recorded samples of the study."""
    s = config["sampling"]
    return model.Sampling.from_window(s["fs"], s["t_warm"], s["t_rec"])


def scenario_names(config: Mapping) -> list[str]:
    """Scenario names in config order."""
    return list(config["scenarios"])


def scenario_values(config: Mapping, name: str) -> dict[str, float]:
    """All model parameter values of scenario ``name``: rig and operating, its overrides, its fault."""
    scenarios = config["scenarios"]
    if name not in scenarios:
        raise KeyError(f"unknown scenario {name!r} (known: {', '.join(scenarios)})")
    return faults.scenario_values(scenarios[name], base_values(config))


def diagnosis_ranges(config: Mapping) -> dict[str, dict[str, tuple[float, float]]]:
    """The parameter ranges a diagnosis fits over of every effect it offers (``diagnosis.effects``, else
    every active one), by kind and parameter (declaration order): ``diagnosis.faults`` where it gives
    one, else the effect file's ``prior``.  ``config`` is a
    checked config or a spec holding its ``diagnosis`` section."""
    ranges = _effect_ranges(config["diagnosis"].get("faults") or {}, "diagnosis.faults", lambda p: p.prior)
    offered = config["diagnosis"].get("effects")
    return ranges if offered is None else {kind: ranges[kind] for kind in offered}


def hidden_ranges(config: Mapping) -> dict[str, dict[str, tuple[float, float]]]:
    """Every active effect's parameter ranges a blind test draws from, by kind and parameter
    (declaration order): ``hidden.faults`` where it gives one, else the effect file's ``hidden`` range
    (:attr:`newdyn.effects.Parameter.draw_range`).  ``config`` is a checked config or a spec holding
    its ``hidden`` section."""
    return _effect_ranges(config["hidden"].get("faults") or {}, "hidden.faults", lambda p: p.draw_range)


def hidden_classes(config: Mapping) -> list[str]:
    """The classes a hidden set draws from unless the set names its own: ``hidden.classes``, or when
    omitted healthy, parameter_change and every active effect."""
    classes = config["hidden"].get("classes")
    return list(classes) if classes else list(faults.classes())


def _effect_ranges(given: Mapping[str, Mapping[str, Sequence[float]]], where: str, default) -> dict[str, dict[str, tuple[float, float]]]:
    active = effects.active()
    unknown = [kind for kind in given if kind not in active]
    if unknown:
        raise KeyError(f"{where} names '{unknown[0]}', which is not an active effect (active: {', '.join(active)}); "
                       "call newdyn.config.use_effects(config) first")
    ranges = {}
    for kind, effect in active.items():
        overrides = given.get(kind, {})
        ranges[kind] = {p.name: tuple(float(v) for v in overrides.get(p.name, default(p))) for p in effect.parameters}
    return ranges


def canonical_json(obj: Any) -> str:
    """Canonical JSON text of ``obj``: sorted keys, no spaces, every number as a float.

    ``{"b": 3.25e6, "a": 1}`` and ``{"a": 1.0, "b": 3250000}`` give the same text, so reordering YAML
    keys or respelling a number changes nothing downstream (hashes, file attributes).  Non-finite
    floats come out as ``Infinity`` / ``NaN`` (as Python's json writes and reads them).
    """
    return json.dumps(_normalise(obj), sort_keys=True, separators=(",", ":"), ensure_ascii=True)


def _normalise(obj: Any) -> Any:
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, numbers.Real):
        value = float(obj)
        return 0.0 if value == 0.0 else value  # -0.0 and 0 -> 0.0
    if isinstance(obj, Mapping):
        return {str(k): _normalise(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_normalise(v) for v in obj]
    if hasattr(obj, "tolist"):  # numpy arrays, numpy bools
        return _normalise(obj.tolist())
    raise TypeError(f"canonical_json cannot encode {type(obj).__name__}")
