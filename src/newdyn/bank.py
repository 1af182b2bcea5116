"""What every diagnosis at one operating condition and record reuses, computed once per study and condition: the
signature library (:mod:`newdyn.signatures`) and the members of each hypothesis with parameters.  The library is a
property of the condition, not of where on the shaft's turn and the load's cycle a record starts, nor of a few rpm
the data correct the nameplate's speed by, and is reused for any; members are compared with the record itself, so a
record that starts elsewhere gets its own (:func:`with_members`), at the load's phase the record's lines give (the
fits free the phase from the best member: a box dimension for it would thin every axis of the others).

Members are quasi-random points (a scrambled Sobol sequence) of a hypothesis's prior box, simulated over the fits'
first search windows at a search's precision (:func:`newdyn.simulation.simulate_batch`): they only choose where least
squares on the exact simulator starts.  A fit of a hypothesis with at most :data:`MAX_PARAMETERS` fitted parameters starts its least
squares on each of those windows from the member that fits it best, instead of from a differential evolution there:
:data:`MEMBERS` points put 32 on each axis of a two-parameter box, as dense as the search's own population, and 10 on
each of a three-parameter one (a crack's depth and where it sits, and a drift: smooth in each, the test suite's
fit from members ends where a search's does).  A four-parameter box (stick-slip) gets fewer than six an axis, too few to find the truth's narrow basin (seeding the
search with its best members led it astray): its fit starts from members only where another hypothesis already
explains the data to the noise, its evidence then a lower bound (:func:`needs_search`), and searches everywhere else.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np
import xarray as xr
from scipy.stats import qmc

from . import calibration, hypotheses, model, sensors, signatures

MAX_PARAMETERS = 3
MEMBERS = 1024  # a power of two, as Sobol points balance best
MEMBER_SEED = 1


def banked(hyps: Mapping[str, hypotheses.Hypothesis], kinds: Sequence[str]) -> list[str]:
    """The hypotheses of ``kinds`` with members: those with parameters."""
    return [kind for kind in kinds if hyps[kind].priors]


def needs_search(hypothesis: hypotheses.Hypothesis) -> bool:
    """Whether a fit of ``hypothesis`` needs the global search wherever its result may decide the verdict: it has more
    than :data:`MAX_PARAMETERS` parameters, too many for the members to find its best fit's basin."""
    return len(hypothesis.priors) > MAX_PARAMETERS


def spec(hyps: Mapping[str, hypotheses.Hypothesis], signature_entries, kinds: Sequence[str], values: Mapping[str, float],
         sampling: model.Sampling, channels: Sequence[str], grids: Mapping[str, calibration.GridSpec],
         priors: Mapping[str, calibration.NormalPrior], instruments: sensors.Instruments | None, max_step: float) -> dict:
    """What a bank depends on, as plain data: the signature library's and its members' (see :func:`key`)."""
    return {**signatures.spec(hyps, signature_entries, values, sampling, channels, grids, priors, instruments, max_step),
            "members": {"kinds": sorted(banked(hyps, kinds)), "n": MEMBERS, "seed": MEMBER_SEED,
                        "samples": _search_samples(sampling), "search": True}}


def key(bank_spec: Mapping) -> str:
    """The name of a bank: a hash of everything it depends on."""
    return hashlib.sha256(json.dumps(bank_spec, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _search_samples(sampling: model.Sampling) -> int:
    """The samples the fits' searches see: the longest of their windows."""
    return hypotheses.fit_windows(sampling)[: hypotheses.SEARCHES][-1]


def build(hyps: Mapping[str, hypotheses.Hypothesis], signature_entries, kinds: Sequence[str], values: Mapping[str, float],
          sampling: model.Sampling, channels: Sequence[str], grids: Mapping[str, calibration.GridSpec],
          priors: Mapping[str, calibration.NormalPrior], coarse: Mapping[str, np.ndarray], instruments: sensors.Instruments | None,
          max_step: float) -> xr.Dataset:
    """The bank: the signature library and, for each hypothesis of ``kinds`` with parameters, its members."""
    bank = with_members(signatures.build(hyps, signature_entries, values, sampling, channels, grids, priors, coarse, instruments,
                                         max_step), hyps, kinds, values, sampling, channels, max_step)
    bank_spec = spec(hyps, signature_entries, kinds, values, sampling, channels, grids, priors, instruments, max_step)
    bank.attrs.update(title="newdyn study bank: the signature library and the members of each hypothesis with parameters",
                      key=key(bank_spec), spec=json.dumps(bank_spec, sort_keys=True, default=str))
    return bank


def with_members(bank: xr.Dataset, hyps: Mapping[str, hypotheses.Hypothesis], kinds: Sequence[str], values: Mapping[str, float],
                 sampling: model.Sampling, channels: Sequence[str], max_step: float) -> xr.Dataset:
    """``bank`` with the members of each hypothesis of ``kinds`` at the rig ``values`` (in place of any it held)."""
    for kind, found in member_sets(hyps, kinds, values, sampling, channels, max_step).items():
        bank = bank.drop_vars([f"members_{kind}", f"member_outputs_{kind}", f"parameter_{kind}"], errors="ignore")
        bank[f"members_{kind}"] = ((f"member_{kind}", f"parameter_{kind}"), found.unit)
        bank[f"member_outputs_{kind}"] = ((f"member_{kind}", "channel", "search_time"), found.outputs)
        bank = bank.assign_coords({f"parameter_{kind}": hyps[kind].parameters})
    return bank


def member_sets(hyps: Mapping[str, hypotheses.Hypothesis], kinds: Sequence[str], values: Mapping[str, float],
                sampling: model.Sampling, channels: Sequence[str], max_step: float) -> dict[str, hypotheses.Members]:
    """The members of each hypothesis of ``kinds`` with parameters, simulated at a search's precision and kept in single
    precision (they only rank the members; a fit's least squares simulates its own)."""
    window = replace(sampling, n_samples=_search_samples(sampling))
    found = {}
    for kind in banked(hyps, kinds):
        hypothesis = hyps[kind]
        low = np.array([p.low for p in hypothesis.priors])
        span = np.array([p.high for p in hypothesis.priors]) - low
        unit = qmc.Sobol(len(low), seed=MEMBER_SEED).random(MEMBERS)
        outputs = hypotheses.evaluate(hypothesis, low + unit * span, values, window, channels, max_step, search=True)
        found[kind] = hypotheses.Members(unit, outputs.astype(np.float32), tuple(hypothesis.parameters))
    return found


def members(bank: xr.Dataset, kind: str) -> hypotheses.Members | None:
    """A hypothesis's members in ``bank`` (None when it has none)."""
    if f"members_{kind}" not in bank:
        return None
    return hypotheses.Members(bank[f"members_{kind}"].values, bank[f"member_outputs_{kind}"].values,
                              tuple(str(name) for name in bank[f"parameter_{kind}"].values))
