"""A discovered term written out as an effect file of :mod:`newdyn.effects`, ready to add to a study.

The file declares the form's fitted parameters with their units, the discovered values as defaults
and a prior range around them for the next diagnosis to fit over; the shape's discrete values (an
order, a disk) are written into its force as numbers.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping

from .forms import FORMS

#: Prior range of a fitted parameter around its discovered value, by parameter name:
#: (low, high, lower bound, lower inclusive, upper bound, upper inclusive) from the value v.
_PRIORS = {
    "frequency": lambda v: (0.99 * v, 1.01 * v, 0.0, False, math.inf, False),
    "phase": lambda v: (v - math.pi, v + math.pi, -4 * math.pi, True, 4 * math.pi, True),
    "share": lambda v: (0.0, 1.0, 0.0, True, 1.0, True),
    "clearance": lambda v: (0.0, 4.0 * v, 0.0, True, math.inf, False),
}


def _magnitude(v: float) -> tuple:
    """A coefficient keeps the sign it was found with; its prior runs from zero to three times it."""
    return (0.0, 3.0 * v, 0.0, True, math.inf, False) if v >= 0 else (3.0 * v, 0.0, -math.inf, False, 0.0, True)


def effect_name(term: str, place: str, measurement: str) -> str:
    """A valid effect name saying what was found where and in which measurement."""
    return re.sub(r"\W", "_", f"discovered_{term}_{place}_{measurement}")


def render(candidate, measurement: str) -> tuple[str, str]:
    """(effect name, file content) of ``candidate`` (a :class:`.search.Candidate`) found in ``measurement``."""
    form = FORMS[candidate.term]
    name = effect_name(candidate.term, candidate.acts_on, measurement)
    expression, fitted = form.effect_body(candidate.acts_on, candidate.shape)
    declared = []
    for parameter in fitted:
        row: Mapping = candidate.parameters[parameter]
        value = float(row["value"])
        low, high, lower, lower_inclusive, upper, upper_inclusive = _PRIORS.get(parameter, _magnitude)(value)
        if low == high:  # a coefficient found at zero: a range from zero to the posterior's reach
            high = max(abs(row["hdi_low"]), abs(row["hdi_high"]), 1e-12)
        declared.append(
            f"        Parameter({parameter!r}, {row['unit']!r}, {_description(parameter, candidate)!r}, default={value!r},\n"
            f"                  lower={_literal(lower)}, lower_inclusive={lower_inclusive}, upper={_literal(upper)}, "
            f"upper_inclusive={upper_inclusive},\n"
            f"                  prior=({low!r}, {high!r})),"
        )
    found = ", ".join(f"{key} = {row['value']:.6g} {row['unit']} (sd {row['sd']:.3g})" for key, row in candidate.parameters.items())
    class_name = "".join(part.title() for part in name.split("_"))
    return name, f'''"""{form.description[0].upper() + form.description[1:]}, on {candidate.acts_on}.

Found by newdyn's discovery in the measurement {measurement}: {found};
log-evidence {candidate.log_evidence:.6g} on the linearized model.  Add it to a study by copying this file
into its effects folder and naming it in the config (``effects: [{name}]``).
"""

from __future__ import annotations

import math

from newdyn.effects import Effect, Parameter, sincos


class {class_name}(Effect):
    """{candidate.term} on {candidate.acts_on}: {expression}"""

    name = "{name}"
    description = "{candidate.term} on {candidate.acts_on} ({candidate.shape.label}), discovered in {measurement}"
    acts_on = "{candidate.acts_on}"
    parameters = (
{chr(10).join(declared)}
    )

    @staticmethod
    def force(s, p, rig, mode):
        return {expression}
'''


def _literal(x: float) -> str:
    return repr(x) if math.isfinite(x) else ("math.inf" if x > 0 else "-math.inf")


def _description(parameter: str, candidate) -> str:
    return f"{parameter} of the {candidate.term} term on {candidate.acts_on}"
