"""Faults of a scenario: a drift of rig parameters, or one physical effect of :mod:`newdyn.effects`.

A fault spec ``{"kind", "parameters"}`` turns into model values (:mod:`newdyn.model` names), so a
scenario is fully described by one value mapping and every fault runs through the same kernel.
``parameter_change`` is no new dynamics: it only gives rig parameters other values.  Every other
kind is an active effect: its presence flag is set, its parameters take the given values or their
defaults, and the rig values it sets (:meth:`~newdyn.effects.Effect.rig_values`) replace the rig's.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Mapping

import numpy as np

from . import effects, model, slots

HEALTHY = "healthy"  # the class of a rig without any change: a hypothesis, a hidden case and a verdict of that name
PARAMETER_CHANGE = "parameter_change"


def kinds() -> tuple[str, ...]:
    """Every fault kind: ``parameter_change``, then the active effects."""
    return (PARAMETER_CHANGE, *effects.active())


def classes() -> tuple[str, ...]:
    """Every class a rig can be in: healthy, then every fault kind (:func:`kinds`)."""
    return (HEALTHY, *kinds())


def effect_values(kind: str, parameters: Mapping[str, float], base: Mapping[str, float]) -> dict[str, float]:
    """An effect's parameter values: the given ones, the others at their defaults on ``base``."""
    effect = effects.active()[kind]
    values = {p.name: p.default_value(base) for p in effect.parameters if p.default is not None}
    values.update({name: float(value) for name, value in parameters.items()})
    return values


def model_values(kind: str, parameters: Mapping[str, float], base: Mapping[str, float]) -> dict[str, float]:
    """Model values a fault sets, given its parameters and the base model values."""
    if kind == PARAMETER_CHANGE:
        return {name: float(value) for name, value in parameters.items()}
    effect = effects.active()[kind]
    values = effect_values(kind, parameters, base)
    out = {slots.effect_slot(kind): 1.0}
    out.update({slots.effect_slot(kind, p.name): values[p.name] for p in effect.kernel_parameters()})
    out.update(effect.rig_values(values, base))
    return out


def fault_problems(
    kind: str, parameters: Mapping[str, object], base: Mapping[str, float] | None = None
) -> list[tuple[str, str]]:
    """(field, problem) pairs for a fault spec on the ``base`` model values; empty when it is admissible."""
    if kind == PARAMETER_CHANGE:
        if not parameters:
            return [("parameters", "parameter_change needs at least one rig parameter")]
        problems = []
        for name, value in parameters.items():
            if name not in model.RIG_PARAMETERS:
                problems.append((f"parameters.{name}", f"unknown parameter of {kind} (known: {', '.join(model.RIG_PARAMETERS)})"))
            elif (problem := model.PARAMETER_BY_NAME[name].problem(value)) is not None:
                problems.append((f"parameters.{name}", problem))
        return problems
    if kind not in effects.active():
        return [("kind", f"unknown fault kind '{kind}' (known: {', '.join(kinds())})")]
    effect = effects.active()[kind]
    known = effect.parameter_names()
    missing = [p.name for p in effect.parameters if p.default is None and p.name not in parameters]
    if missing:
        return [(f"parameters.{missing[0]}", f"{kind} needs its parameter {missing[0]}")]
    problems = []
    for name, value in parameters.items():
        if name not in known:
            problems.append((f"parameters.{name}", f"unknown parameter of {kind} (known: {', '.join(known)})"))
        elif (problem := effect.parameter(name).problem(value)) is not None:
            problems.append((f"parameters.{name}", problem))
    if base is not None and not problems:
        values = effect_values(kind, parameters, base)
        for name, value in values.items():  # defaults derived from the base must be physical too
            if (problem := effect.parameter(name).problem(value)) is not None:
                problems.append(("", f"resulting {name} {problem}"))
        problems += [(f"parameters.{name}", problem) for name, problem in effect.problems(values, base)]
    return problems


def prior_grid(kind: str, points: int) -> Iterator[dict[str, float]]:
    """The parameter sets of effect ``kind`` admissible on the default rig, on a grid of ``points`` an axis spanning its
    prior box, corners included (for checks of the simulator over the range a diagnosis fits it over)."""
    effect = effects.active()[kind]
    for point in itertools.product(*[np.linspace(*p.prior, points) for p in effect.parameters]):
        parameters = dict(zip(effect.parameter_names(), map(float, point)))
        if not fault_problems(kind, parameters, model.DEFAULTS):
            yield parameters


def scenario_values(scenario: Mapping[str, object], base: Mapping[str, float]) -> dict[str, float]:
    """All model values of a scenario: base, then its overrides, then its fault."""
    values = slots.complete({**base, **scenario.get("overrides", {})})
    fault = scenario.get("fault")
    if fault:
        values.update(model_values(fault["kind"], fault.get("parameters", {}), values))
    return values
