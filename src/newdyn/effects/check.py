"""What makes an effect declaration complete and sound; every problem is said in one line.

Checked without compiling anything, so that a bad file is named before any job runs: the
declarations (name, description, place, parameters with units, bounds, defaults and ranges, the
switching functions), then the functions themselves, called as plain Python on the rig's initial
state, on states around it and on the corners of the prior box, must return finite numbers.  A file whose
functions passed is remembered in the cache folder by its content (under the package's), so that the next
parse of the Snakefile does not call them again.
"""

from __future__ import annotations

import inspect
import itertools
import math
from collections.abc import Iterator

import numpy as np

from .. import cache, model, provenance
from .base import PLACES, Effect, Kinematics, Parameter, RigValues

_FUNCTIONS = ("force", "event", "switch")


def problems(effect: type[Effect], stem: str) -> Iterator[str]:
    """The problems of ``effect`` read from a file named ``<stem>.py``, the first one first."""
    declared = list(_declaration_problems(effect, stem))
    if declared:
        yield from declared
        return
    if not effect.content_hash:  # not read from a file: nothing to remember it by
        yield from _evaluation_problems(effect)
        return
    # Only a pass is remembered: a failure may come from a helper the file imports, which its content does not name.
    yield from cache.remembered(cache.folder() / "effects-checked" / f"{provenance.package_digest()}.json", effect.content_hash,
                                lambda: list(_evaluation_problems(effect)), keep=lambda found: not found)


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _declaration_problems(effect: type[Effect], stem: str) -> Iterator[str]:
    name = getattr(effect, "name", None)
    if not isinstance(name, str) or not name.isidentifier():
        yield f"{effect.__name__}.name must be the effect's name, letters, digits and _ (got {name!r})"
        return
    if name != stem:
        yield f"the effect is named '{name}' but its file '{stem}.py': name the file after the effect"
    description = getattr(effect, "description", None)
    if not isinstance(description, str) or not description.strip() or "\n" in description.strip():
        yield f"{name}: description must be one line of text saying what the effect is"
    place = getattr(effect, "acts_on", None)
    if place not in PLACES:
        yield f"{name}: acts_on must be one of {', '.join(PLACES)} (got {place!r})"
    parameters = getattr(effect, "parameters", None)
    if not isinstance(parameters, tuple) or not all(isinstance(p, Parameter) for p in parameters):
        yield f"{name}: parameters must be a tuple of newdyn.effects.Parameter"
        return
    seen = set()
    for p in parameters:
        yield from _parameter_problems(name, p, seen)
    if not callable(getattr(effect, "force", None)):
        yield f"{name}: declares no force(s, p, rig, mode) function"
    if effect.mode_name is None:
        for function in ("event", "switch"):
            if getattr(effect, function) is not None:
                yield f"{name}: has {function}() but no mode_name: name its mode variable to make it switch"
        if effect.locks_joint:
            yield f"{name}: locks_joint needs a mode (the joint is locked while the mode is 0)"
    else:
        if not (isinstance(effect.mode_name, str) and effect.mode_name.isidentifier()):
            yield f"{name}: mode_name must be a name, letters, digits and _ (got {effect.mode_name!r})"
        for function in ("event", "switch"):
            if not callable(getattr(effect, function)):
                yield f"{name}: switches (mode_name {effect.mode_name!r}) but declares no {function}(s, p, rig, mode) function"
    if effect.locks_joint and place != "slip_joint":
        yield f"{name}: locks_joint applies only to an effect acting on slip_joint (it acts on {place})"
    for function in _FUNCTIONS:
        f = getattr(effect, function, None)
        if callable(f):
            try:
                arguments = list(inspect.signature(f).parameters)
            except (TypeError, ValueError):
                continue
            if len(arguments) != 4:
                yield f"{name}: {function} must take (s, p, rig, mode), got ({', '.join(arguments)})"


def _parameter_problems(effect: str, p: Parameter, seen: set) -> Iterator[str]:
    where = f"{effect}: parameter {p.name!r}"
    if not isinstance(p.name, str) or not p.name.isidentifier() or p.name in seen:
        yield f"{where}: a parameter needs a unique name of letters, digits and _"
    seen.add(p.name)
    if not isinstance(p.unit, str) or not p.unit.strip():
        yield f"{where} has no unit (write '-' for a dimensionless one)"
    if not isinstance(p.description, str) or not p.description.strip():
        yield f"{where} has no description"
    if not (_number(p.lower) and _number(p.upper) and p.lower < p.upper and not math.isnan(p.lower + p.upper)):
        yield f"{where} needs physical bounds lower < upper (got {p.lower!r}, {p.upper!r})"
        return
    for label, interval in (("prior", p.prior), ("hidden", p.hidden)):
        if interval is None and label == "hidden":
            continue
        if not (isinstance(interval, tuple) and len(interval) == 2 and all(_number(v) and math.isfinite(v) for v in interval)):
            yield f"{where}: {label} must be a range (low, high) of finite numbers (got {interval!r})"
            continue
        low, high = interval
        if not low < high:
            yield f"{where}: {label} range reversed or empty ({low:g}, {high:g})"
        for value in interval:
            problem = p.problem(value)
            if problem is not None and not (value == p.lower == low):  # a range may start at an exclusive bound
                yield f"{where}: {label} range {problem}"
    if p.default is not None and not callable(p.default):
        problem = p.problem(p.default)
        if problem is not None:
            yield f"{where}: default {problem}"


def trial_points(effect: type[Effect], rig: dict) -> list[dict[str, float]]:
    """Parameter values a check calls the functions at: the defaults and every corner of the prior box."""
    corners = itertools.product(*[p.prior for p in effect.kernel_parameters()])
    names = [p.name for p in effect.kernel_parameters()]
    middle = {p.name: (p.default_value(rig) if p.default is not None else 0.5 * sum(p.prior)) for p in effect.parameters}
    return [middle] + [{**middle, **dict(zip(names, corner))} for corner in corners]


def trial_states(rig: dict) -> list[Kinematics]:
    """Kinematics around the rig's initial state: at rest in its frame, twisted and moving both ways."""
    omega = model.omega(rig)
    twist = rig["T0"] / rig["kT2"]
    states = []
    for t, x, v in ((0.0, 0.0, 0.0), (0.013, twist, 0.5), (0.27, -2 * twist, -3.0), (0.5, 1e-7, 1e-4), (0.9, -1e-6, -1e-3)):
        states.append(Kinematics(t, x, v, omega * t, omega * t - 0.3, omega + v, omega - v, rig["T0"] * (1 + x / max(twist, 1e-300))))
    return states


def _evaluation_problems(effect: type[Effect]) -> Iterator[str]:
    rig = dict(model.DEFAULTS)
    rig_values = RigValues(**rig, Omega=model.omega(rig))
    kernel_names = [p.name for p in effect.kernel_parameters()]
    Params = effect_parameters_type(effect)
    modes = (0.0, 1.0, -1.0) if effect.switching() else (0.0,)
    for values in trial_points(effect, rig):
        p = Params(*[float(values[name]) for name in kernel_names])
        for s, mode in itertools.product(trial_states(rig), modes):
            for function in _FUNCTIONS:
                f = getattr(effect, function)
                if f is None:
                    continue
                try:
                    result = f(s, p, rig_values, mode)
                except Exception as error:  # noqa: BLE001 - a user's function may fail in any way; say how, in one line
                    yield f"{effect.name}: {function}() failed at {_where(values, s, mode)}: {type(error).__name__}: {error}"
                    return
                if not _number(result) and not isinstance(result, np.floating):
                    yield f"{effect.name}: {function}() must return a number, got {type(result).__name__}"
                    return
                if math.isnan(result) or (function != "event" and math.isinf(result)):
                    yield f"{effect.name}: {function}() returned {result} at {_where(values, s, mode)}"
                    return


def _where(values, s, mode) -> str:
    shown = ", ".join(f"{k}={v:g}" for k, v in values.items())
    return f"{shown}{', ' if shown else ''}x={s.x:g}, v={s.v:g}, mode={mode:g}"


_TYPES: dict = {}


def effect_parameters_type(effect: type[Effect]):
    """The named tuple an effect's functions receive as ``p`` (one type per effect, made once)."""
    from collections import namedtuple

    key = (effect.name, tuple(p.name for p in effect.kernel_parameters()))
    if key not in _TYPES:
        _TYPES[key] = namedtuple(f"{effect.name}_parameters", key[1] or ("unused",), defaults=(0.0,) if not key[1] else None)
    return _TYPES[key]
