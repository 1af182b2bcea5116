"""The fault library: each kind is an element with named, documented, bounded parameters.

A fault turns into model parameter values (:mod:`newdyn.model` names), so a scenario is fully
described by one parameter mapping and every fault runs through the same compiled kernel.
``parameter_change`` is no new dynamics: it only gives rig parameters other values.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping

from . import model

# Not a model parameter: where a stick-slip joint splits the motor-side inertia, J2a / (J2a + J2b),
# which a diagnosis fits and a hidden case draws (the total J2a + J2b is kept).
J2A_SHARE = "J2a_share"


@dataclass(frozen=True)
class FaultKind:
    name: str
    description: str
    slots: Mapping[str, str] = field(default_factory=dict)  # fault parameter -> model parameter
    # Parameters without a default must be given: a missing severity would silently mean "healthy".
    defaults: Mapping[str, Callable[[Mapping[str, float]], float]] = field(default_factory=dict)

    def allowed(self) -> dict[str, model.Parameter]:
        """The fault's parameters, with the bounds of the model parameter each one sets."""
        return {name: model.PARAMETER_BY_NAME[slot] for name, slot in self.slots.items()}

    def model_values(self, parameters: Mapping[str, float], base: Mapping[str, float]) -> dict[str, float]:
        """Model parameter values set by this fault, given its parameters and the base model values."""
        values = {self.slots[name]: default(base) for name, default in self.defaults.items()}
        values.update({self.slots[name]: float(value) for name, value in parameters.items()})
        return values


FAULT_KINDS: dict[str, FaultKind] = {
    kind.name: kind
    for kind in (
        FaultKind(
            "parameter_change",
            "rig parameters drift to other values (not new dynamics)",
            {name: name for name in model.RIG_PARAMETERS},
        ),
        FaultKind(
            "stick_slip",
            "Karnopp stick-slip between motor shaft end (J2a) and motor-side hub (J2b), paper Eqs. 2-3",
            {"T_max": "T_max", "r_k": "r_k"},
            {"T_max": lambda base: 1.15 * base["T0"], "r_k": lambda base: 1.0},
        ),
        FaultKind(
            "breathing_crack",
            "breathing crack on the load shaft: kT3 -> kT3 (1 - alpha (1 - cos θ4) / 2)",
            {"alpha": "crack_alpha"},
        ),
        FaultKind(
            "cubic_coupling",
            "cubic hardening of the coupling element: kT2 δ -> kT2 (δ + gamma δ³/δ0²), δ0 = T0/kT2",
            {"gamma": "cubic_gamma"},
        ),
        FaultKind(
            "loose_bearing",
            "loose motor non-drive-end bearing housing in x: b1's ground spring and damper act only beyond ±gap",
            {"gap": "bearing_gap"},
        ),
    )
}


def fault_problems(
    kind: str, parameters: Mapping[str, object], base: Mapping[str, float] | None = None
) -> list[tuple[str, str]]:
    """(field, problem) pairs for a fault spec on the ``base`` model values; empty when it is admissible."""
    if kind not in FAULT_KINDS:
        return [("kind", f"unknown fault kind '{kind}' (known: {', '.join(FAULT_KINDS)})")]
    fault = FAULT_KINDS[kind]
    allowed = fault.allowed()
    if kind == "parameter_change":
        if not parameters:
            return [("parameters", "parameter_change needs at least one rig parameter")]
    else:
        missing = [name for name in allowed if name not in fault.defaults and name not in parameters]
        if missing:
            return [(f"parameters.{missing[0]}", f"{kind} needs its parameter {missing[0]}")]
    problems = []
    for name, value in parameters.items():
        if name not in allowed:
            known = ", ".join(allowed)
            problems.append((f"parameters.{name}", f"unknown parameter of {kind} (known: {known})"))
        elif (problem := allowed[name].problem(value)) is not None:
            problems.append((f"parameters.{name}", problem))
    if kind == "stick_slip" and base is not None and not problems:
        values = fault.model_values(parameters, base)
        if values["r_k"] * values["T_max"] <= base["T0"]:
            problems.append(
                ("parameters.T_max", f"r_k·T_max must exceed T0 = {base['T0']:g} N·m, or the slipping joint cannot carry the mean load and the rig stalls")
            )
    return problems


def scenario_values(scenario: Mapping[str, object], base: Mapping[str, float]) -> dict[str, float]:
    """All model parameter values of a scenario: base, then its overrides, then its fault."""
    values = model.complete({**base, **scenario.get("overrides", {})})
    fault = scenario.get("fault")
    if fault:
        values.update(FAULT_KINDS[fault["kind"]].model_values(fault.get("parameters", {}), values))
    return values
