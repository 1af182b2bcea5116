"""Simulate the rig: named outputs over the compiled kernel, single runs and batches.

Outputs are the measurement channels (``model.CHANNELS``), the switching diagnostics
(:func:`newdyn.kernels.diagnostics`) and the raw state components (``STATE_NAMES``, for physics checks).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from . import kernels, model, slots

# Longest RK4 step [s]: step halving stays within rig.md's bounds at it (tests/test_physics.py); a rig
# whose slip joint switches steps finer while the modes it kicks ring down, and while it is open, and one whose
# contact switches from its first switch on (kernels.fine_steps).
DEFAULT_MAX_STEP = 1.0e-4
DEFAULT_SAMPLING = model.Sampling()  # rig.md's record

_POSITIONS = model.ANGLES + tuple(f"{d}_{node}" for d in "xy" for node in model.NODES)
STATE_NAMES = _POSITIONS + tuple("d" + name for name in _POSITIONS)


def output_codes(outputs: Sequence[str]) -> np.ndarray:
    """Kernel codes of named outputs: channels, diagnostics (``joint_torque``, ``<kind>.<mode_name>``,
    ``<kind>.onsets`` of each switching effect) and state components (``STATE_NAMES``)."""
    codes = []
    for name in outputs:
        if name in model.CHANNELS:
            codes.append(model.CHANNELS.index(name))
        elif name in STATE_NAMES:
            codes.append(kernels.OUT_STATE + STATE_NAMES.index(name))
        elif (code := kernels.output_code(name)) is not None:
            codes.append(code)
        else:
            raise KeyError(f"unknown output {name}; channels are {', '.join(model.CHANNELS)}, "
                           f"diagnostics {', '.join(kernels.diagnostics())}")
    return np.array(codes, dtype=np.int64)


def substeps(fs: float, max_step: float) -> int:
    """RK4 steps per sample interval: the fewest that keep the step within ``max_step``."""
    return max(1, math.ceil(1.0 / (fs * max_step) - 1e-9))


def simulate_batch(
    values: Sequence[Mapping[str, float]] | np.ndarray,
    sampling: model.Sampling = DEFAULT_SAMPLING,
    outputs: Sequence[str] = model.CHANNELS,
    max_step: float = DEFAULT_MAX_STEP,
    search: bool = False,
) -> np.ndarray:
    """Simulate many parameter sets at once: (n_sets, len(outputs), n_samples).

    ``values`` is a sequence of parameter mappings or an array of parameter vectors
    (rows laid out as ``slots.slot_names()``), each started at t = 0 as ``sampling`` says (rig.md's state, or its
    linearized steady state, :func:`steady_states`).  Each sample interval is split into the fewest
    equal RK4 steps no longer than ``max_step``, and finer where an effect has switched (``kernels.fine_steps``).  For a
    ``search`` those finer steps are twice as long (``kernels.SEARCH_STEP_FACTOR``): cheaper where the joint slips, and
    less accurate where kinetic friction is well below static — for a global search that only chooses where least
    squares on the exact simulator starts, never for a result.
    """
    if isinstance(values, np.ndarray):
        params = np.ascontiguousarray(values, dtype=np.float64)
    else:
        params = np.stack([slots.parameter_vector(v) for v in values]) if len(values) else np.empty((0, len(slots.slot_names())))
    if params.ndim != 2 or params.shape[1] != len(slots.slot_names()):
        raise ValueError(f"parameter array must be (n, {len(slots.slot_names())}), got {params.shape}")
    return kernels.simulate_batch(
        params, float(sampling.t_first), float(sampling.fs), int(sampling.n_samples), substeps(sampling.fs, max_step), output_codes(outputs),
        search, steady_states(params) if sampling.steady else None,
    )


def steady_states(params: np.ndarray) -> np.ndarray:
    """:func:`newdyn.model.steady_states` of rows of kernel parameters (laid out as ``slots.slot_names()``)."""
    index = slots.slot_index()
    return model.steady_states({name: params[:, index[name]] for name in model.PARAMETER_NAMES})


def simulate_parts(parts: Sequence[np.ndarray], sampling: model.Sampling, outputs: Sequence[str], max_step: float) -> list[np.ndarray]:
    """:func:`simulate_batch` of several arrays of parameter rows in one batch, so that their few rows fill the kernel's
    lanes together, its outputs split back into one array per part.  A lane's result does not depend on its batch, so
    each part's outputs are those it gets alone."""
    found = simulate_batch(np.vstack(parts), sampling, outputs, max_step)
    return np.split(found, np.cumsum([len(part) for part in parts])[:-1])


def simulate(
    values: Mapping[str, float] | None = None,
    sampling: model.Sampling = DEFAULT_SAMPLING,
    outputs: Sequence[str] = model.CHANNELS,
    max_step: float = DEFAULT_MAX_STEP,
) -> np.ndarray:
    """Simulate one parameter set (missing names take the rig.md defaults): (len(outputs), n_samples)."""
    return simulate_batch([values or {}], sampling, outputs, max_step)[0]
