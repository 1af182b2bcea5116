"""The kernel's parameter vector: the rig and operating values of :mod:`newdyn.model`, then, for each active effect
(:mod:`newdyn.effects`), its slots: ``<kind>`` (1 where the effect is present, else 0) and ``<kind>.<parameter>`` for
each parameter its functions read.  :func:`complete` fills a mapping of values with every slot,
:func:`parameter_vector` packs it for the compiled kernel."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from . import effects, model


def effect_slot(kind: str, parameter: str | None = None) -> str:
    """The model value name of an effect's presence flag (``parameter`` None) or of one of its parameters."""
    return kind if parameter is None else f"{kind}.{parameter}"


def slot_names() -> tuple[str, ...]:
    """The names of the kernel's parameter vector for the active effects: rig, operating, then per
    effect its presence flag and the parameters its functions read."""
    names = list(model.PARAMETER_NAMES)
    for kind, effect in effects.active().items():
        names += [effect_slot(kind)] + [effect_slot(kind, p.name) for p in effect.kernel_parameters()]
    return tuple(names)


def slot_index() -> dict[str, int]:
    return {name: i for i, name in enumerate(slot_names())}


def complete(values: Mapping[str, float] | None = None) -> dict[str, float]:
    """All model values: the rig.md defaults overridden by ``values``, then every active effect's
    slots (absent, its parameters at their defaults, unless ``values`` sets them); unknown names are an error."""
    values = dict(values or {})
    unknown = sorted(set(values) - set(slot_names()))
    if unknown:
        raise KeyError(f"unknown model parameter(s): {', '.join(unknown)}")
    full = {name: float(values.get(name, model.DEFAULTS[name])) for name in model.PARAMETER_NAMES}
    for kind, effect in effects.active().items():
        full[effect_slot(kind)] = float(values.get(effect_slot(kind), 0.0))
        for p in effect.kernel_parameters():
            default = p.default_value(full) if p.default is not None else p.prior[0]
            full[effect_slot(kind, p.name)] = float(values.get(effect_slot(kind, p.name), default))
    return full


def parameter_vector(values: Mapping[str, float] | None = None) -> np.ndarray:
    """The kernel's flat parameter vector for ``values`` (missing names take their defaults)."""
    return np.array(list(complete(values).values()), dtype=np.float64)


def without_effects(values: Mapping[str, float]) -> dict[str, float]:
    """The rig and operating values of ``values``, without any effect's slots: the same model where no effect is active
    (:func:`newdyn.effects.alone`).  An effect present in ``values`` cannot be dropped."""
    present = [name for name, value in values.items() if name not in model.PARAMETER_INDEX and "." not in name and value != 0.0]
    if present:
        raise ValueError(f"effect(s) {', '.join(present)} present: the model without effects is another one")
    return {name: float(values[name]) for name in model.PARAMETER_NAMES if name in values}
