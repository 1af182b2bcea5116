"""How far a record's start turned the shaft: a recording starts at any moment, and the shaft's angle at its first
sample is folded into the imbalances' angles ``phi1`` and ``phi4`` that its diagnosis finds (:mod:`newdyn.alignment`),
so two records of one machine, or a record and the angles a simulation drew, differ by that turn in both; an angle
on a shaft (:func:`newdyn.effects.shaft_angle`) turns with them."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from . import model


def between(found: Mapping[str, Mapping[str, float]], reference: Mapping[str, float],
         reference_sd: Mapping[str, float] | None = None) -> tuple[float, float] | None:
    """How far a record's start turned the shaft from a ``reference`` (another record's found angles, or the angles a
    simulation drew, with ``reference_sd`` None: exact), and that turn's standard error: each imbalance's angle in
    ``found`` (a record's ``values`` and ``sd``) less the reference's, averaged on the circle with the weights their
    standard errors give.  An imbalance on a disk no probe is near leaves its angle free and its turn unknown while the
    other's holds it; None where neither has a standard error."""
    values, sd = found.get("values") or {}, found.get("sd") or {}
    reference_sd = reference_sd or {}
    shifts = [(values[n] - reference[n], math.hypot(sd[n], reference_sd.get(n, 0.0))) for n in model.IMBALANCE_ANGLES
              if n in values and n in reference and sd.get(n, 0.0) > 0]
    if not shifts:
        return None
    weights = np.array([1.0 / s**2 for _, s in shifts])
    return float(np.angle(np.sum(weights * np.exp(1j * np.array([d for d, _ in shifts]))))), float(1.0 / math.sqrt(weights.sum()))


def precision(found: Mapping[str, Mapping[str, float]]) -> float:
    """How well a record's found imbalance angles hold where its start turned the shaft: the sum of their precisions
    (0 without standard errors)."""
    sd = found.get("sd") or {}
    return float(sum(1.0 / sd[n] ** 2 for n in model.IMBALANCE_ANGLES if sd.get(n, 0.0) > 0))
