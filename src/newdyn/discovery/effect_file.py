"""A discovered term written out as an effect file of :mod:`newdyn.effects`.

Two kinds of file, one force: the *found* file hands the term to the user, ready to add to a study,
with the discovered values as defaults and prior ranges around them for the next diagnosis to fit
over; the *generic* file of a form at a place holds no number of any measurement, so its simulation
kernel compiles once per machine and serves every full-simulator fit of that form there (a fit takes
its ranges from :func:`prior_range`, not from the file).
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

from .. import io
from .forms import FORMS, Shape

#: A fitted parameter's range around its discovered value v, by name: (low, high, lower bound, lower
#: inclusive, upper bound, upper inclusive).  Any other parameter is a coefficient (:func:`_coefficient`).
_AROUND = {
    "frequency": lambda v: (0.99 * v, 1.01 * v, 0.0, False, math.inf, False),
    "order": lambda v: (0.995 * v, 1.005 * v, 0.0, False, math.inf, False),
    "phase": lambda v: (v - math.pi, v + math.pi, -4 * math.pi, True, 4 * math.pi, True),
    "share": lambda v: (0.0, 1.0, 0.0, True, 1.0, True),
    "clearance": lambda v: (0.0, 4.0 * v, 0.0, True, math.inf, False),
    "v_smooth": lambda v: (0.1 * v, 10.0 * v, 0.0, False, math.inf, False),
}
#: The generic file's ranges: wide and finite, the same for every measurement.
_GENERIC = {
    "frequency": (1e-3, 1e5, 0.0, False, math.inf, False),
    "order": (0.1, 100.0, 0.0, False, math.inf, False),
    "phase": (-math.pi, math.pi, -4 * math.pi, True, 4 * math.pi, True),
    "share": (0.0, 1.0, 0.0, True, 1.0, True),
    "clearance": (0.0, 1.0, 0.0, True, math.inf, False),
    "v_smooth": (1e-9, 1e3, 0.0, False, math.inf, False),
}
_GENERIC_COEFFICIENT = (-1e30, 1e30, -1e31, True, 1e31, True)


def _coefficient(v: float) -> tuple:
    """A coefficient keeps the sign it was found with; its range runs from zero to three times it."""
    return (0.0, 3.0 * v, 0.0, True, math.inf, False) if v >= 0 else (3.0 * v, 0.0, -math.inf, False, 0.0, True)


def prior_range(name: str, row: Mapping) -> tuple:
    """(low, high, lower, lower inclusive, upper, upper inclusive) of a discovered parameter (``row``: its
    value and 94 % HDI) for fitting it again."""
    value = float(row["value"])
    bounds = _AROUND.get(name, _coefficient)(value)
    if bounds[0] == bounds[1]:  # found at zero: up to the posterior's reach
        bounds = (0.0, max(abs(row["hdi_low"]), abs(row["hdi_high"]), 1e-12), *bounds[2:])
    return bounds


def _disk(shape: Shape) -> str:
    return f"_disk{int(shape.values['disk'])}" if "disk" in shape.values else ""


def effect_name(term: str, place: str, shape: Shape, measurement: str | None = None) -> str:
    """The found file's effect name (what, where, in which measurement), or the generic one's (no measurement)."""
    return re.sub(r"\W", "_", f"discovered_{term}_{place}{_disk(shape)}" + (f"_{measurement}" if measurement else "")).lower()


def render(candidate, measurement: str) -> tuple[str, str]:
    """(effect name, content) of the found file of ``candidate`` (a :class:`.search.Candidate`) in ``measurement``."""
    name = effect_name(candidate.term, candidate.acts_on, candidate.shape, measurement)
    found = ", ".join(f"{key} = {_valued(row)}" for key, row in candidate.parameters.items())
    return name, _content(name, candidate.term, candidate.acts_on, candidate.shape, _declared(candidate.parameters),
                          _found_where(f"Found by newdyn's discovery in the measurement {measurement}: {found}", name),
                          f"discovered in {measurement}")


def render_across(term: str, place: str, shape: Shape, shared: Mapping[str, Mapping], own: Sequence[Mapping[str, Mapping]],
                  machine: str, recordings: Sequence[str]) -> tuple[str, str]:
    """(effect name, content) of the found file of a term found across a machine's ``recordings``: the form ``term`` at
    ``place`` with ``shape``, its ``shared`` parameters' rows (value, sd, 94 % HDI, unit) one for all recordings and its
    ``own`` rows one mapping per recording (a phased form's amplitude and phase).  A shared parameter's default is its
    value; an own one has none, as it is each recording's (a scenario gives it), and its range covers every
    recording's."""
    name = effect_name(term, place, shape, machine)
    declared = _declared(shared)
    for key in own[0]:
        ranges = [prior_range(key, rows[key]) for rows in own]
        declared[key] = (None, own[0][key]["unit"], (min(r[0] for r in ranges), max(r[1] for r in ranges), *ranges[0][2:]))
    found = "; ".join([*(f"{key} = {_valued(row)}" for key, row in shared.items()),
                       *(f"{key} {', '.join(f'{_valued(rows[key])} in {r}' for r, rows in zip(recordings, own))}" for key in own[0])])
    return name, _content(name, term, place, shape, declared,
                          _found_where(f"Found by newdyn's discovery across the recordings of the machine {machine}: {found}", name,
                                       f"; a scenario gives its {', '.join(own[0])}" if own[0] else ""),
                          f"discovered across the recordings of {machine}")


def _declared(rows: Mapping[str, Mapping]) -> dict:
    """Each parameter's (default, unit, range) from its found row: its value and :func:`prior_range` around it."""
    return {key: (float(row["value"]), row["unit"], prior_range(key, row)) for key, row in rows.items()}


def _found_where(found: str, name: str, note: str = "") -> str:
    """The found file's account of itself: what was found where, and how a study takes it."""
    return (f"{found}.  Add it to a study by\ncopying this file into its effects folder and naming it in the config "
            f"(``effects: [{name}]``){note}.")


def _valued(row: Mapping) -> str:
    return f"{row['value']:.6g}{'' if row['unit'] == '-' else ' ' + row['unit']} (sd {row['sd']:.3g})"


def write(folder: str | os.PathLike, found: tuple[str, str] | None) -> None:
    """The folder ``folder`` with the found effect file ``found`` (name, content) in it, written atomically; the folder
    alone (empty) where nothing was found."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if found is not None:
        name, content = found
        io.atomic_write(folder / f"{name}.py", lambda tmp: Path(tmp).write_text(content, encoding="utf-8"))


def render_generic(term: str, place: str, shape: Shape) -> tuple[str, str]:
    """(effect name, content) of the generic file of the form ``term`` at ``place`` (turning with ``shape``'s disk)."""
    name = effect_name(term, place, shape)
    units = {key: unit for key, (_, unit) in FORMS[term].parameters(_unit_coefficients(term), shape, place).items()}
    declared = {key: (None, unit, _GENERIC.get(key, _GENERIC_COEFFICIENT)) for key, unit in units.items()}
    return name, _content(name, term, place, shape, declared, "The generic form newdyn's discovery fits on the full simulator.",
                          "newdyn discovery's generic form")


def _unit_coefficients(term: str):
    import numpy as np

    return np.ones(len(FORMS[term].coefficients))


def _content(name: str, term: str, place: str, shape: Shape, declared: Mapping, provenance: str, origin: str) -> str:
    form = FORMS[term]
    expression = form.effect_body(place, shape)
    parameters = []
    for key, (value, unit, (low, high, lower, lower_inclusive, upper, upper_inclusive)) in declared.items():
        parameters.append(
            f"        Parameter({key!r}, {unit!r}, {f'{key} of the {term} term on {place}'!r}, default={value!r},\n"
            f"                  lower={_literal(lower)}, lower_inclusive={lower_inclusive}, upper={_literal(upper)}, "
            f"upper_inclusive={upper_inclusive},\n"
            f"                  prior=({low!r}, {high!r})),"
        )
    class_name = "".join(part.title() for part in name.split("_"))
    return f'''"""{form.description[0].upper() + form.description[1:]}, on {place}.

{provenance}
"""

from __future__ import annotations

import math

from newdyn.effects import Effect, Parameter, sincos


class {class_name}(Effect):
    """{term} on {place}: {expression}"""

    name = "{name}"
    description = "{term} on {place}{_disk(shape).replace('_', ' ')}, {origin}"
    acts_on = "{place}"
    parameters = (
{chr(10).join(parameters)}
    )

    @staticmethod
    def force(s, p, rig, mode):
        return {expression}
'''


def _literal(x: float) -> str:
    return repr(x) if math.isfinite(x) else ("math.inf" if x > 0 else "-math.inf")
