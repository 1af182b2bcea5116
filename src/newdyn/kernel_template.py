"""Compiled simulation kernel of the reference rig (rig.md), batched over parameter sets.

This file is a template: :mod:`newdyn.kernels` renders it, with a header that lays out the parameter
slots of the active effects and binds their functions, and the generated effect code
(``_forces``, ``_event_value``, ``_switch_effect``) appended, into one module per set of effects.

Fixed-step classical Runge-Kutta (RK4) with exact event location: a switching effect (stick-slip
onset and re-stick, loose-bearing contact) changes the force law only at a located event, so each
step integrates a smooth right-hand side and keeps fourth-order accuracy.

Design for speed: up to ``LANES`` parameter sets are integrated together as the lanes of a block.
Every per-lane quantity (parameters, modes, state, stage values) is a row of one flat work array
indexed ``row * LANES + lane``, and the hot loops run over lanes with bodies that have no calls and
no data-dependent branches (mode switches are selects, sin/cos is the inline :func:`sincos`), so
LLVM turns them into AVX lanes.  After each step the event functions of all lanes are checked
together; a lane whose step crosses an event is redone by the event-locating path, which runs the
same RK4 and RHS code on a one-lane scratch block.  A lane that settles after a switch of its effects, or whose
slip joint is open, takes several shorter steps for each step instead (``kernels.fine_steps``): such lanes are copied
into a second scratch block, stepped there side by side in its SIMD lanes, and copied back, so a slipping rig pays for
the finer steps only while its joint rings or slips.  The arithmetic is that of the scalar original,
operation for operation (no fast-math), so results do not depend on how simulations are grouped
into lanes; only sin/cos of the disk angles may differ from libm's by an ulp.  Blocks run in
parallel threads (``NUMBA_NUM_THREADS``).

State layout (42): positions θ1 θ2a θ2b θ3 θ4, x[8], y[8] (nodes b1 m1 b2 m2 m3 b3 m4 b4), then
the same velocities.  θ2a/θ2b move as one body J2a + J2b while stuck.
"""

# ruff: noqa: F821 - the layout (_I, N_PAR, N_SWITCHING, SWITCHING_ON, OUT_*) and the effect code (_forces,
# _event_value, _switch_effect) are generated into the rendered module by newdyn.kernels, which writes out the index
# _at too.
import math
from collections import namedtuple  # noqa: F401 - the generated effect parameters

import numpy as np
from numba import njit, prange

from newdyn.effects import loaded  # noqa: F401 - the generated effect bindings
from newdyn.effects import sincos as _sincos  # the package's own name: always the helper, never swapped
from newdyn.effects.base import Kinematics, RigValues, kernel_ready  # noqa: F401 - used by the generated code

# Options of every kernel function: 'numpy' error model so that x / 0 gives inf instead of a branch
# to a ZeroDivisionError (such a branch blocks vectorization); no fast-math, so every operation is
# the IEEE operation of the scalar original and vector and scalar lanes agree bit for bit.
_JIT = {"cache": True, "error_model": "numpy"}
_EFFECT_JIT = {"error_model": "numpy", "inline": "always"}
sincos = _sincos.compiled()

# @layout@

# Parameter slots (compile-time constants for numba); parameter k of a lane lives in work row k.
J1, J2A, J2B, J3, J4 = _I["J1"], _I["J2a"], _I["J2b"], _I["J3"], _I["J4"]
M1, M2, M3, M4, MB = _I["m1"], _I["m2"], _I["m3"], _I["m4"], _I["m_b"]
KT1, KT2, KT3 = _I["kT1"], _I["kT2"], _I["kT3"]
KS, KH, KC, KBX, KBY = _I["k_s"], _I["k_h"], _I["k_c"], _I["k_bx"], _I["k_by"]
BETA, SLIP, U1, U4, PHI1, PHI4 = _I["beta"], _I["slip"], _I["u1"], _I["u4"], _I["phi1"], _I["phi4"]
SPEED, T0, LOAD_AMP, LOAD_FREQ, LOAD_HARM = _I["speed_rpm"], _I["T0"], _I["load_amp"], _I["load_freq"], _I["load_harm"]
LOAD_PHASE = _I["load_phase"]

NQ = 21  # positions
NY = 42  # state

# Output codes (OUT_TORQUE_C, OUT_JOINT_TORQUE, OUT_MODES, OUT_STATE) are in the layout: see newdyn.kernels.

# Lanes per block: four AVX2 vectors of doubles.  Fewer lanes share the per-step scalar work (the
# load torque) among fewer simulations; 32 lanes no longer fit the work array in L1 (measured slower).
LANES = 16
# LLVM vectorizes the lane loops VECTOR lanes at a time (two AVX2 vectors) and runs the remainder
# scalar: a block of 4 lanes took 19 ms, one of 8 lanes 12 ms (healthy, 1.5 s).  Blocks of more
# than SCALAR_MAX lanes are therefore padded to a multiple of VECTOR lanes.
VECTOR = 8
SCALAR_MAX = 2

# Rows of the work array.  Per-lane constants come first (parameters, then derived quantities),
# then the modes, so that the event path sets up its scratch lane by copying two ranges of rows.
R_OMEGA = N_PAR  # synchronous speed Ω
R_CM = R_OMEGA + 1  # motor torque slope c_m
R_INVJ2 = R_CM + 1  # 1 / (J2a + J2b)
R_MU2 = R_INVJ2 + 1  # J2a J2b / (J2a + J2b)
R_DELTA0 = R_MU2 + 1  # coupling reference twist T0 / kT2
R_INVM = R_DELTA0 + 1  # 8 inverse node masses
R_KLAT = R_INVM + 8  # 7 lateral spring stiffnesses
R_JRED1 = R_KLAT + 7  # J1 - u1² / m1: the disk-1 inertia left by the imbalance coupling
R_JRED4 = R_JRED1 + 1  # J4 - u4² / m4
R_SAME_LOAD = R_JRED4 + 1  # 1 if the load parameters equal those of the lane to the left, else 0
R_FINE_STEPS = R_SAME_LOAD + 1  # RK4 steps per step while the lane settles after a switch (1: never finer)
R_OPEN_STEPS = R_FINE_STEPS + 1  # RK4 steps per step while its joint is open once settled (1: the plain step)
R_SETTLE = R_OPEN_STEPS + 1  # how long after a switch of its effects the lane keeps the finest steps [s]
N_CONST = R_SETTLE + 1
R_MODES = N_CONST  # mode of each switching effect (0 at t = 0)
R_ONSETS = R_MODES + N_SWITCHING  # number of its switches out of mode 0 so far
R_FINE_UNTIL = R_ONSETS + N_SWITCHING  # the lane takes the finest steps until this time
N_MODES = 2 * N_SWITCHING + 1  # the rows the event path hands back: modes, onsets and R_FINE_UNTIL
R_TL = R_MODES + N_MODES  # load torque T_l at the stage time
R_TL_TIME = R_TL + 1  # lane 0 only: the time of the values in row R_TL (NaN: none)
R_G = R_TL_TIME + 1  # event function value (> 0: an event lies inside the step)
R_WHICH = R_G + 1  # whose event: 0 none, j + 1 switching effect j
R_COUNT = R_WHICH + 1  # the RK4 steps the lane takes for this step
R_Y = R_COUNT + 1  # state at the step start
R_TRIAL = R_Y + NY  # state at the step end while events are checked
R_STAGE = R_TRIAL + NY  # RK4 stage state
R_ACC = R_STAGE + NY  # RHS output: the 21 accelerations (dq/dt is the stage velocity itself)
R_K1V = R_ACC + NQ  # k1, velocity part (its position part is the velocity in R_Y)
R_K23 = R_K1V + NQ  # k2 + k3
R_DENSE = R_K23 + NY  # the state inside a step, interpolated from its stages (rows DENSE_ROWS and their velocities)
N_ROWS = R_DENSE + NY

# _at(row, lane), the flat index of (row, lane), is written out by newdyn.kernels as np.uint64((row) * LANES + (lane)).
# Unsigned, so numba emits no negative-index wraparound select, which would hide the unit lane stride from LLVM's
# vectorizer.


# --- the physics: one lane at state rows ``src`` ---------------------------------------------------
# The healthy elements are here; the active effects' forces are added to them by the generated
# ``_forces``, which returns everything the right-hand side needs.
@njit(**_JIT, inline="always")
def _shaft_torques(w, lane, src):
    """(t_s1, t_c): torque of shaft 1 on disk 1 (+) and of the coupling element on disk 3 (+)."""
    beta = w[_at(BETA, lane)]
    t_s1 = w[_at(KT1, lane)] * (
        (w[_at(src + 1, lane)] - w[_at(src, lane)]) + beta * (w[_at(src + NQ + 1, lane)] - w[_at(src + NQ, lane)])
    )
    delta = w[_at(src + 2, lane)] - w[_at(src + 3, lane)]
    t_c = w[_at(KT2, lane)] * (delta + beta * (w[_at(src + NQ + 2, lane)] - w[_at(src + NQ + 3, lane)]))
    return t_s1, t_c


@njit(**_JIT, inline="always")
def _load_shaft_torque(w, lane, src):
    """Torque of shaft 3 on disk 4 (+)."""
    beta = w[_at(BETA, lane)]
    return w[_at(KT3, lane)] * ((w[_at(src + 3, lane)] - w[_at(src + 4, lane)]) + beta * (w[_at(src + NQ + 3, lane)] - w[_at(src + NQ + 4, lane)]))


@njit(**_JIT, inline="always")
def _stick_torque(w, lane, t_s1, t_c):
    """Torque T_f the slip joint carries while locked (paper Eq. 3b): F_2a = -t_s1 on 2a, F_2b = -t_c on 2b."""
    return (-t_s1 / w[_at(J2A, lane)] + t_c / w[_at(J2B, lane)]) * w[_at(R_MU2, lane)]


@njit(**_JIT, inline="always")
def _spring(w, lane, pos, s, beta):
    """Force of lateral spring s (with its damper) between nodes s and s+1: + on s, - on s+1."""
    vel = pos + NQ
    return w[_at(R_KLAT + s, lane)] * (
        (w[_at(pos + s + 1, lane)] - w[_at(pos + s, lane)]) + beta * (w[_at(vel + s + 1, lane)] - w[_at(vel + s, lane)])
    )


@njit(**_JIT, inline="always")
def _ground(w, lane, pos, node, beta, k_ground):
    """Force of the ground spring (with its damper) at bearing ``node``, negated."""
    return k_ground * (w[_at(pos + node, lane)] + beta * w[_at(pos + NQ + node, lane)])


@njit(**_JIT, inline="always")
def _lateral(w, lane, pos, k_ground):
    """Spring + damper forces (f0, ..., f7) on the 8 nodes of one direction (position rows pos..,
    velocities NQ further), each bearing with its ground spring.  Returned as values, not stored, so
    that they can stay in registers."""
    beta = w[_at(BETA, lane)]
    s0, s1, s2, s3 = _spring(w, lane, pos, 0, beta), _spring(w, lane, pos, 1, beta), _spring(w, lane, pos, 2, beta), _spring(w, lane, pos, 3, beta)
    s4, s5, s6 = _spring(w, lane, pos, 4, beta), _spring(w, lane, pos, 5, beta), _spring(w, lane, pos, 6, beta)
    f0 = s0 - _ground(w, lane, pos, 0, beta, k_ground)
    f2 = (-s1 + s2) - _ground(w, lane, pos, 2, beta, k_ground)
    f5 = (-s4 + s5) - _ground(w, lane, pos, 5, beta, k_ground)
    f7 = -s6 - _ground(w, lane, pos, 7, beta, k_ground)
    return f0, -s0 + s1, f2, -s2 + s3, -s3 + s4, f5, -s5 + s6, f7


@njit(**_JIT, inline="always")
def _disk(w, lane, src, theta, node, u, jred, torque, s, c, fx, fy):
    """Imbalance disk with angle θ_theta at ``node``: exact 3×3 Lagrange solve (rig.md).  Returns
    its angular acceleration and the node forces (fx, fy) with the imbalance reaction added."""
    inv_m = w[_at(R_INVM + node, lane)]
    speed = w[_at(src + NQ + theta, lane)]
    acc = (torque + u * (s * fx - c * fy) * inv_m) / jred
    return acc, fx + u * (speed * speed * c + s * acc), fy + u * (speed * speed * s - c * acc)


@njit(**_JIT, inline="always")
def _node_accelerations(w, lane, out, node, fx, fy):
    inv_m = w[_at(R_INVM + node, lane)]
    w[_at(out + 5 + node, lane)] = fx * inv_m
    w[_at(out + 13 + node, lane)] = fy * inv_m


@njit(**_JIT, inline="always")
def _rhs(w, lane, src, out, t):
    """The right-hand side: the 21 accelerations of one lane at state rows src.. and time t, into
    rows out.. (the other half of dy/dt, dq/dt, is the velocity itself).  The load torque is row R_TL.

    Straight-line code: both sides of a mode switch are computed and one is selected, so that lane
    loops vectorize.
    """
    f = _forces(w, lane, src, t)
    torque1, t_s1, t_c, t_s3, torque4, f_joint, joint_open = f[0], f[1], f[2], f[3], f[4], f[5], f[6]
    fx, fy = f[8:16], f[16:24]
    s1, c1, s4, c4 = f[24], f[25], f[26], f[27]
    acc1, fx1, fy1 = _disk(w, lane, src, 0, 1, w[_at(U1, lane)], w[_at(R_JRED1, lane)], torque1, s1, c1, fx[1], fy[1])
    acc4, fx6, fy6 = _disk(w, lane, src, 4, 6, w[_at(U4, lane)], w[_at(R_JRED4, lane)], torque4, s4, c4, fx[6], fy[6])

    # The slip joint: locked, 2a and 2b move as one body; open, each feels the joint's torque.
    common = (-t_s1 - t_c) * w[_at(R_INVJ2, lane)]
    acc_2a = (-t_s1 - f_joint) / w[_at(J2A, lane)]
    acc_2b = (-t_c + f_joint) / w[_at(J2B, lane)]
    w[_at(out, lane)] = acc1
    w[_at(out + 1, lane)] = common if joint_open == 0.0 else acc_2a
    w[_at(out + 2, lane)] = common if joint_open == 0.0 else acc_2b
    w[_at(out + 3, lane)] = (t_c - t_s3) / w[_at(J3, lane)]
    w[_at(out + 4, lane)] = acc4
    _node_accelerations(w, lane, out, 0, fx[0], fy[0])
    _node_accelerations(w, lane, out, 1, fx1, fy1)
    _node_accelerations(w, lane, out, 2, fx[2], fy[2])
    _node_accelerations(w, lane, out, 3, fx[3], fy[3])
    _node_accelerations(w, lane, out, 4, fx[4], fy[4])
    _node_accelerations(w, lane, out, 5, fx[5], fy[5])
    _node_accelerations(w, lane, out, 6, fx6, fy6)
    _node_accelerations(w, lane, out, 7, fx[7], fy[7])


@njit(**_JIT, inline="always")
def _load_torque(t, w, lane):
    """T_l(t) = T0 [1 + a Σ_h sin(h (2π f_l t + φ_l))/h]; sin(hx) by the Chebyshev recurrence (one sin/cos)."""
    x = 2.0 * math.pi * w[_at(LOAD_FREQ, lane)] * t + w[_at(LOAD_PHASE, lane)]
    s1, c1 = math.sin(x), math.cos(x)
    s_prev, s_h, total = 0.0, s1, 0.0
    for h in range(1, int(w[_at(LOAD_HARM, lane)]) + 1):
        total += s_h / h
        s_prev, s_h = s_h, 2.0 * c1 * s_h - s_prev
    return w[_at(T0, lane)] * (1.0 + w[_at(LOAD_AMP, lane)] * total)


# --- RK4 over the lanes of a block ------------------------------------------------------------------
@njit(**_JIT, inline="always")
def _set_load_torques(w, t, n_lanes):
    """Row R_TL ← T_l(t) per lane.

    T_l costs a libm sin and cos (kept for exact agreement with the scalar code), so it is skipped
    when the row already holds time t (stages 2 and 3 share their time, as do stage 4 of a step and stage 1 of the
    next), and a lane with the same load parameters as its left neighbour (R_SAME_LOAD) copies its value.
    """
    if w[_at(R_TL_TIME, 0)] == t:
        return
    w[_at(R_TL_TIME, 0)] = t
    for lane in range(n_lanes):
        if lane > 0 and w[_at(R_SAME_LOAD, lane)] != 0.0:
            w[_at(R_TL, lane)] = w[_at(R_TL, lane - 1)]
        else:
            w[_at(R_TL, lane)] = _load_torque(t, w, lane)


# The stages of a step, counted at run time: with the count a constant, LLVM would unroll the stage loop into four
# copies of the right-hand side, which no longer fit the CPU's micro-op cache (measured slower) and lengthen the compile.
RK4_STAGES = np.int64(4)


@njit(**_JIT)
def _stages(w, n_lanes, t, h, n_stages):
    """The RK4 stages of a step from (t, rows R_Y) by h for lanes 0..n_lanes-1, the step's start copied into rows
    R_STAGE: k1 to k3 combined into rows R_K1V and R_K23, the last stage's accelerations left in R_ACC and its state
    in R_STAGE, for :func:`_finish_step`.

    One compiled loop over the stages, its right-hand side inlined once: a compiled call per stage, which takes the
    work array, costs atomic reference counts on entry and exit.  A stage derivative is k = (stage velocity,
    accelerations), so only accelerations are stored, and k2's position part is recomputed rather than stored (these
    loops are bound by stores).  Each combination loop handles position row i with its velocity row NQ+i; the
    operations are the scalar original's (stage = y + c k, then y + h/6 (k1 + 2 (k2 + k3) + k4)), so the rounding is
    the same.
    """
    half = 0.5 * h
    for stage in range(n_stages):
        t_stage = t if stage == 0 else (t + h if stage == 3 else t + 0.5 * h)
        _set_load_torques(w, t_stage, n_lanes)
        for lane in range(n_lanes):
            _rhs(w, lane, R_STAGE, R_ACC, t_stage)
        if stage == 0:  # k1 = (y', a1); stage 2 at y + h/2 k1
            for i in range(NQ):
                for lane in range(n_lanes):
                    a = w[_at(R_ACC + i, lane)]
                    w[_at(R_K1V + i, lane)] = a
                    w[_at(R_STAGE + i, lane)] = w[_at(R_Y + i, lane)] + half * w[_at(R_Y + NQ + i, lane)]
                    w[_at(R_STAGE + NQ + i, lane)] = w[_at(R_Y + NQ + i, lane)] + half * a
        elif stage == 1:  # k2 = (stage-2 velocity, a2); stage 3 at y + h/2 k2
            for i in range(NQ):
                for lane in range(n_lanes):
                    v = w[_at(R_STAGE + NQ + i, lane)]
                    a = w[_at(R_ACC + i, lane)]
                    w[_at(R_K23 + NQ + i, lane)] = a
                    w[_at(R_STAGE + i, lane)] = w[_at(R_Y + i, lane)] + half * v
                    w[_at(R_STAGE + NQ + i, lane)] = w[_at(R_Y + NQ + i, lane)] + half * a
        elif stage == 2:  # k2 + k3, the stage-2 velocity recomputed; stage 4 at y + h k3
            for i in range(NQ):
                for lane in range(n_lanes):
                    v = w[_at(R_STAGE + NQ + i, lane)]
                    a = w[_at(R_ACC + i, lane)]
                    v2 = w[_at(R_Y + NQ + i, lane)] + half * w[_at(R_K1V + i, lane)]
                    w[_at(R_K23 + i, lane)] = v2 + v
                    w[_at(R_K23 + NQ + i, lane)] += a
                    w[_at(R_STAGE + i, lane)] = w[_at(R_Y + i, lane)] + h * v
                    w[_at(R_STAGE + NQ + i, lane)] = w[_at(R_Y + NQ + i, lane)] + h * a


@njit(**_JIT)
def _rk4(w, t, h, n_lanes, in_place):
    """One RK4 step of size h from (t, rows R_Y) into rows R_TRIAL, or into R_Y if ``in_place``,
    for lanes 0..n_lanes-1."""
    for i in range(NY):
        for lane in range(n_lanes):
            w[_at(R_STAGE + i, lane)] = w[_at(R_Y + i, lane)]
    _stages(w, n_lanes, t, h, RK4_STAGES)
    if in_place:  # two inlined copies, so that each loop has constant rows
        _finish_step(w, h, n_lanes, R_Y)
    else:
        _finish_step(w, h, n_lanes, R_TRIAL)


@njit(**_JIT, inline="always")
def _finish_step(w, h, n_lanes, out):
    """Rows out ← y + h/6 (k1 + 2 (k2 + k3) + k4), with k4 = (stage velocity, R_ACC); out may be R_Y."""
    sixth = h / 6.0
    for i in range(NQ):
        for lane in range(n_lanes):
            q = w[_at(R_Y + i, lane)]
            v = w[_at(R_Y + NQ + i, lane)]
            q_new = q + sixth * (v + 2.0 * w[_at(R_K23 + i, lane)] + w[_at(R_STAGE + NQ + i, lane)])
            v_new = v + sixth * (w[_at(R_K1V + i, lane)] + 2.0 * w[_at(R_K23 + NQ + i, lane)] + w[_at(R_ACC + i, lane)])
            w[_at(out + i, lane)] = q_new
            w[_at(out + NQ + i, lane)] = v_new


# --- events -------------------------------------------------------------------------------------------
# A step's event functions are checked at its end and at INTERIOR_CHECKS - 1 points inside it, on the
# third-order continuous extension of RK4, so that a slip that starts and ends inside one step is
# found too.  Only the state rows the event functions read are interpolated (DENSE_ROWS).
INTERIOR_CHECKS = 4


@njit(**_JIT, inline="always")
def _dense(w, lane, theta, h):
    """Rows R_DENSE ← the state at t + θh of the step just taken from rows R_Y (its stages intact):
    y0 + h (b1 k1 + b23 (k2 + k3) + b4 k4), the stages' third-order interpolant."""
    theta2 = theta * theta
    theta3 = theta2 * theta
    b1 = h * (theta - 1.5 * theta2 + (2.0 / 3.0) * theta3)
    b23 = h * (theta2 - (2.0 / 3.0) * theta3)
    b4 = h * ((2.0 / 3.0) * theta3 - 0.5 * theta2)
    for i in DENSE_ROWS:
        w[_at(R_DENSE + i, lane)] = w[_at(R_Y + i, lane)] + (
            b1 * w[_at(R_Y + NQ + i, lane)] + b23 * w[_at(R_K23 + i, lane)] + b4 * w[_at(R_STAGE + NQ + i, lane)])
        w[_at(R_DENSE + NQ + i, lane)] = w[_at(R_Y + NQ + i, lane)] + (
            b1 * w[_at(R_K1V + i, lane)] + b23 * w[_at(R_K23 + NQ + i, lane)] + b4 * w[_at(R_ACC + i, lane)])


@njit(**_JIT)
def _interior_events(w, n_lanes, t, h):
    """For every lane whose step just taken ends without an event, rows R_G and R_WHICH ← the first
    positive event function at the interior check points, if any (straight-line code over the lanes)."""
    for k in range(1, INTERIOR_CHECKS):
        theta = k / INTERIOR_CHECKS
        for lane in range(n_lanes):
            _dense(w, lane, theta, h)
            g, which = _event_value(w, lane, R_DENSE, t + theta * h)
            g_end = w[_at(R_G, lane)]
            found = (g > 0.0) & (g_end <= 0.0)
            w[_at(R_G, lane)] = g if found else g_end
            w[_at(R_WHICH, lane)] = which if found else w[_at(R_WHICH, lane)]


@njit(**_JIT)
def _lane_event(w, lane, src, t):
    """:func:`_event_value` of one lane, compiled once for the paths that take one lane at a time: each inlined copy
    of it (the vectorized loops need theirs) lengthens the compile."""
    return _event_value(w, lane, src, t)


@njit(**_JIT)
def _interpolant_event(w, lane, t, h, theta):
    """:func:`_lane_event` at t + θh on the interpolant of the step just taken from t by h."""
    _dense(w, lane, theta, h)
    return _lane_event(w, lane, R_DENSE, t + theta * h)


@njit(**_JIT)
def _first_interior_event(w, lane, t, h):
    """The first interior check point θ of the step just taken where an event function is positive
    (its value in row R_G, whose in R_WHICH), or 1.0 if there is none."""
    for k in range(1, INTERIOR_CHECKS):
        theta = k / INTERIOR_CHECKS
        g, which = _interpolant_event(w, lane, t, h, theta)
        if g > 0.0:
            w[_at(R_G, lane)] = g
            w[_at(R_WHICH, lane)] = which
            return theta
    return 1.0


# Right after a switch, the new mode's event functions are checked again at once: a joint that re-sticks
# and cannot hold its torque slips again.  This many immediate switches at most, so that a declaration
# whose switch does not lead into its new mode cannot hang the simulation.
MAX_IMMEDIATE_SWITCHES = 8


@njit(**_JIT)
def _events(w, src, n_lanes, t):
    """Event function of the current modes at state rows src and time t, per lane, into rows R_G and R_WHICH.

    An event lies where the function turns positive: the largest of the enabled switching effects'
    is stored with its number j + 1, or -inf and 0 when none is enabled.  Straight-line code, so
    that it vectorizes.
    """
    for lane in range(n_lanes):
        g, which = _event_value(w, lane, src, t)
        w[_at(R_G, lane)] = g
        w[_at(R_WHICH, lane)] = which


@njit(**_JIT)
def _switch(w, lane, which, t):
    """Apply the mode change of event ``which`` at the located state (rows R_Y) of ``lane``, then any
    that the new modes call for at once; the lane takes the finest steps for its settling time after it."""
    for _ in range(MAX_IMMEDIATE_SWITCHES):
        _switch_effect(w, lane, which, t)
        g, which = _lane_event(w, lane, R_Y, t)
        if not g > 0.0:
            break
    w[_at(R_FINE_UNTIL, lane)] = t + w[_at(R_SETTLE, lane)]


# Events are located just past their boundary, the event function (in its own units) below EVENT_TOL there or the
# boundary pinned within EVENT_TOL seconds.  The root on the step's interpolant costs no right-hand side; Newton
# steps with its slope on RK4 partial steps then meet the tolerance in one or two, Illinois where they do not.
EVENT_TOL = 1e-13
NEWTON_STEPS = 3


@njit(**_JIT, inline="always")
def _regula_falsi(lo, hi, g_lo, g_hi):
    """The secant root of the bracket, or its middle where that does not lie strictly inside."""
    x = (lo * g_hi - hi * g_lo) / (g_hi - g_lo) if g_hi != g_lo else 0.5 * (lo + hi)
    return x if lo < x < hi else 0.5 * (lo + hi)


@njit(**_JIT, inline="always")
def _illinois(x, g, lo, hi, g_lo, g_hi, side):
    """The bracket (lo, hi, g_lo, g_hi, side) after the value g at x: the end on g's side moves to x, and the other
    end's value is halved when it stays for the second time in a row (Illinois); side 0 halves nothing."""
    if g > 0.0:
        return lo, x, 0.5 * g_lo if side == 1 else g_lo, g, 1
    return x, hi, g, 0.5 * g_hi if side == -1 else g_hi, -1


@njit(**_JIT)
def _interpolant_root(w, lane, t, h, g0, g1):
    """Where the event function crosses zero on the interpolant of the step just taken from t by h (g0 ≤ 0 at its
    start, g1 > 0 at its end), as a fraction of h, and the function's slope there per unit fraction."""
    lo, hi, g_lo, g_hi, side = 0.0, 1.0, g0, g1, 0
    theta = 1.0
    for _ in range(60):
        theta = _regula_falsi(lo, hi, g_lo, g_hi)
        g = _interpolant_event(w, lane, t, h, theta)[0]
        lo, hi, g_lo, g_hi, side = _illinois(theta, g, lo, hi, g_lo, g_hi, side)
        if abs(g) < EVENT_TOL or (hi - lo) * h < EVENT_TOL:
            break
    eta = 1e-6
    slope = (_interpolant_event(w, lane, t, h, theta + eta)[0] - _interpolant_event(w, lane, t, h, theta - eta)[0]) / (2.0 * eta)
    return theta, slope


@njit(**_JIT)
def _advance_alone(w, t, h):
    """Advance lane 0 of block ``w`` from (t, rows R_Y) by h, locating and applying every event; its RK4 step from
    t by h is in rows R_TRIAL.. already (the block's plain step, the same bits).

    The event path, for a lane whose plain step crosses an event: the event's root on the step's interpolant,
    refined on RK4 partial steps to a stop just past it, the mode switch, and on with the rest of the step.
    """
    # Lane 0 of one, as run-time values: literals would make numba compile the callees (the RK4 stages
    # with the whole right-hand side inlined, the switches) a second time, for those literals.
    lanes, lane = np.int64(1), np.int64(0)
    t_end = t + h
    step_taken = True
    while True:
        step = t_end - t
        if step <= 0.0:
            return
        t_next = t_end
        if not step_taken:
            _rk4(w, t, step, lanes, False)
        step_taken = False
        _events(w, R_TRIAL, lanes, t_next)
        hi = 1.0
        if w[_at(R_G, 0)] <= 0.0 and w[_at(R_G, 0)] > -math.inf:
            hi = _first_interior_event(w, lane, t, step)
            if hi < 1.0:  # bracket the event on the RK4 step that ends there
                _rk4(w, t, hi * step, lanes, False)
                _events(w, R_TRIAL, lanes, t + hi * step)
        g_end, which = w[_at(R_G, 0)], w[_at(R_WHICH, 0)]
        if g_end <= 0.0:
            if hi < 1.0:  # the interpolant saw an event that the step to there does not reach
                _rk4(w, t, step, lanes, False)
            _copy_lane_rows(w, lane, w, lane, R_TRIAL, R_Y, NY)
            t = t_next
            continue
        # g(0) < 0 because we start inside the mode.
        _events(w, R_Y, lanes, t)
        g0 = min(w[_at(R_G, 0)], 0.0)
        theta, slope = _interpolant_root(w, lane, t, hi * step, g0, g_end)  # on the step that ends at hi
        frac, slope = theta * hi, slope / hi
        target = 0.5 * EVENT_TOL * min(1.0, slope / step)  # Newton aims just past the root, within both tolerances
        lo, g_lo, g_hi, side = 0.0, g0, g_end, 0
        trial_at_hi = False
        for k in range(60):
            newton = k < NEWTON_STEPS and lo < frac < hi  # (a slope that is not positive puts frac outside)
            if not newton:
                frac = _regula_falsi(lo, hi, g_lo, g_hi)
            _rk4(w, t, frac * step, lanes, False)
            _events(w, R_TRIAL, lanes, t + frac * step)
            g = w[_at(R_G, 0)]
            trial_at_hi = g > 0.0
            if trial_at_hi:
                which = w[_at(R_WHICH, 0)]
            lo, hi, g_lo, g_hi, side = _illinois(frac, g, lo, hi, g_lo, g_hi, side if not newton else 0)
            # The switch is applied at hi, so converge there: just past the boundary, or pinned in time.
            if g_hi < EVENT_TOL or (hi - lo) * step < EVENT_TOL or (trial_at_hi and g * step < EVENT_TOL * slope):
                break
            frac -= (g - target) / slope
        # Stop just on the far side of the event so the new mode starts at its own boundary.
        if not trial_at_hi:
            _rk4(w, t, hi * step, lanes, False)
        _copy_lane_rows(w, lane, w, lane, R_TRIAL, R_Y, NY)
        t = t + hi * step
        _switch(w, lane, which, t)


@njit(**_JIT)
def _copy_lane_rows(a, lane_a, b, lane_b, first_a, first_b, count):
    """Rows first_b.. of lane_b in block b ← rows first_a.. of lane_a in block a."""
    for i in range(count):
        b[_at(first_b + i, lane_b)] = a[_at(first_a + i, lane_a)]


# --- driver ---------------------------------------------------------------------------------------
@njit(**_JIT, inline="always")
def _step_with_events(w, alone, t, h, n_lanes):
    """Advance all lanes of block ``w`` from t by h at that step; a lane whose step crosses an event is redone by
    the event path on the one-lane scratch block ``alone`` (each lane on its own, so that results do not depend on
    how simulations are grouped).  Leaves the event check of each lane's step in row R_G (> 0: it had one)."""
    _rk4(w, t, h, n_lanes, False)
    _events(w, R_TRIAL, n_lanes, t + h)
    _interior_events(w, n_lanes, t, h)
    for lane in range(n_lanes):
        if not w[_at(R_G, lane)] <= 0.0:
            _redo_alone(w, alone, lane, t, h)
    for j in range(NY * LANES):
        w[_at(R_Y, j)] = w[_at(R_TRIAL, j)]


@njit(**_JIT)
def _redo_alone(w, alone, lane, t, h):
    """Rows R_TRIAL of ``lane`` ← its step from t by h on the event path, its modes updated; its plain step from t
    by h is in rows R_TRIAL.. (with the stages that the interpolant reads)."""
    _copy_lane_rows(w, lane, alone, 0, 0, 0, N_CONST + N_MODES)
    _copy_lane_rows(w, lane, alone, 0, R_Y, R_Y, R_DENSE - R_Y)
    alone[_at(R_TL_TIME, 0)] = math.nan  # another lane's load torque
    _advance_alone(alone, t, h)
    _copy_lane_rows(alone, 0, w, lane, R_MODES, R_MODES, N_MODES)
    _copy_lane_rows(alone, 0, w, lane, R_Y, R_TRIAL, NY)


@njit(**_JIT, inline="always")
def _advance(w, alone, fine, picked, group, t, h, n_lanes, n_run, events_possible):
    """Advance block ``w`` from t by h: the plain RK4 step in place where no lane has a switching effect (no event can
    occur), else :func:`_step`.  Inlined, so that a smooth block's step makes no call that takes the scratch blocks:
    each array a compiled call takes costs an atomic reference count on entry and on exit.  Returns the new time."""
    if events_possible:
        return _step(w, alone, fine, picked, group, t, h, n_lanes, n_run)
    t_end = t + h
    step = t_end - t
    if step > 0.0:
        _rk4(w, t, step, n_run, True)
    return t_end


@njit(**_JIT, inline="always")
def _step(w, alone, fine, picked, group, t, h, n_lanes, n_run):
    """Advance the ``n_lanes`` lanes of block ``w`` (run as ``n_run`` with its padding) from t by h.  A lane that
    settles after a switch of its effects, or whose step crosses an event while it may step finely, takes R_FINE_STEPS
    steps instead, and one whose joint is open once settled R_OPEN_STEPS, side by side with the other lanes of its step
    count in the block ``fine`` (``picked`` and ``group`` are scratch for their lane numbers), or in ``w`` itself when
    all its lanes take that count; any other lane whose step crosses an event is redone on the event path; when every
    lane steps finely, none takes the plain step.  Each lane's steps depend on its own state only, so results do not
    depend on how simulations are grouped.  Returns the new time."""
    t_end = t + h
    step = t_end - t
    if step <= 0.0:
        return t_end
    if _any_plain(w, n_lanes, t):  # else every lane steps finely whatever its plain step finds
        _rk4(w, t, step, n_run, False)
        _events(w, R_TRIAL, n_run, t_end)
        _interior_events(w, n_run, t, step)
    else:  # the padding lanes, which nothing reads, may then stay behind
        for lane in range(n_run):
            w[_at(R_G, lane)] = -math.inf
    # Counters as run-time int64 from the start: numba types a literal 0 first and would compile the callees that
    # take it (_pad, _copy_lane_rows) once more for Literal[int](0), as it would _step for a literal False.
    n_fine = np.int64(0)
    for lane in range(n_lanes):
        event = not w[_at(R_G, lane)] <= 0.0
        count = _step_count(w, lane, t, event)
        if count > 1.0:
            w[_at(R_COUNT, lane)] = count
            picked[n_fine] = lane
            n_fine += 1
        elif event:
            _redo_alone(w, alone, lane, t, step)
    if n_fine == n_lanes and _one_count(w, n_lanes):  # the whole block steps finely in place, its padding too
        _fine_steps(w, alone, t, step, int(w[_at(R_COUNT, 0)]), n_run)
        return t_end
    while n_fine > 0:  # the picked lanes, those of one step count at a time
        count = w[_at(R_COUNT, picked[0])]
        n_group, rest = np.int64(0), np.int64(0)
        for i in range(n_fine):
            lane = picked[i]
            if w[_at(R_COUNT, lane)] == count:
                group[n_group] = lane
                _copy_lane_rows(w, lane, fine, n_group, 0, 0, N_CONST + N_MODES)
                _copy_lane_rows(w, lane, fine, n_group, R_Y, R_Y, NY)
                n_group += 1
            else:
                picked[rest] = lane
                rest += 1
        n_group_run = _pad(fine, n_group)
        fine[_at(R_TL_TIME, 0)] = math.nan  # other lanes' load torques
        _fine_steps(fine, alone, t, step, int(count), n_group_run)
        for i in range(n_group):
            _copy_lane_rows(fine, i, w, group[i], R_MODES, R_MODES, N_MODES)
            _copy_lane_rows(fine, i, w, group[i], R_Y, R_TRIAL, NY)
        n_fine = rest
    for j in range(NY * LANES):
        w[_at(R_Y, j)] = w[_at(R_TRIAL, j)]
    return t_end


@njit(**_JIT, inline="always")
def _fine_steps(w, alone, t, h, substeps, n_run):
    """Advance the ``n_run`` lanes of block ``w`` from t by h in ``substeps`` equal steps, each with its events."""
    for k in range(substeps):
        t_k = t + k * h / substeps
        _step_with_events(w, alone, t_k, t + (k + 1) * h / substeps - t_k, n_run)


@njit(**_JIT)
def _one_count(w, n_lanes):
    """Whether the first ``n_lanes`` lanes of block ``w`` take the same number of steps (rows R_COUNT)."""
    for lane in range(1, n_lanes):
        if w[_at(R_COUNT, lane)] != w[_at(R_COUNT, 0)]:
            return False
    return True


@njit(**_JIT)
def _step_count(w, lane, t, event):
    """The RK4 steps ``lane`` takes for the step from t: R_FINE_STEPS while it settles after a switch of its effects,
    R_OPEN_STEPS while the joint is open once settled, and else 1, or R_FINE_STEPS where its plain step crossed an
    ``event`` (only a lane that takes the plain step looks at it: others may not have taken one).  A switch of the
    joint rings the chain's fastest modes, whose phase error would move the next event; once they have rung down, an
    open joint's smooth motion needs only its own fastest mode resolved."""
    if t < w[_at(R_FINE_UNTIL, lane)]:
        return w[_at(R_FINE_STEPS, lane)]
    if w[_at(R_OPEN_STEPS, lane)] > 1.0 and _joint_open(w, lane) != 0.0:
        return w[_at(R_OPEN_STEPS, lane)]
    return w[_at(R_FINE_STEPS, lane)] if event else 1.0


@njit(**_JIT, inline="always")
def _any_plain(w, n_lanes, t):
    """Whether a lane of the block may take the plain step from t: one that does not step finely there."""
    for lane in range(n_lanes):
        if not _step_count(w, lane, t, False) > 1.0:
            return True
    return False


@njit(**_JIT)
def _pad(w, n_lanes):
    """The lanes block ``w`` runs for its first ``n_lanes``: they alone when at most SCALAR_MAX, else rounded up to
    VECTOR lanes, the padding ones copies of the last without its switching effects (they never take the event
    path, and lanes are independent, so they change no other lane's result).  Sets each lane's R_SAME_LOAD."""
    n_run = n_lanes if n_lanes <= SCALAR_MAX else min(LANES, (n_lanes + VECTOR - 1) // VECTOR * VECTOR)
    for lane in range(n_lanes, n_run):
        _copy_lane_rows(w, n_lanes - 1, w, lane, 0, 0, N_CONST + N_MODES)
        _copy_lane_rows(w, n_lanes - 1, w, lane, R_Y, R_Y, NY)
        for slot in SWITCHING_ON:
            w[_at(slot, lane)] = 0.0
        w[_at(R_FINE_STEPS, lane)] = 1.0
        w[_at(R_OPEN_STEPS, lane)] = 1.0
    for lane in range(n_run):
        same = lane > 0
        for k in (T0, LOAD_AMP, LOAD_FREQ, LOAD_HARM, LOAD_PHASE):
            same = same and w[_at(k, lane)] == w[_at(k, lane - 1)]
        w[_at(R_SAME_LOAD, lane)] = 1.0 if same else 0.0
    return n_run


@njit(**_JIT)
def _setup_lane(w, lane, p, steps, settle, start):
    """Parameters, derived quantities, modes and the initial state of one lane, which takes ``steps[0]`` steps
    per step for ``settle`` seconds after a switch of its effects and ``steps[1]`` while its slip joint is open after
    that: the state ``start`` (NY values) where it has them, else rig.md's."""
    for k in range(N_PAR):
        w[_at(k, lane)] = p[k]
    omega = 2.0 * math.pi * p[SPEED] / 60.0
    w[_at(R_OMEGA, lane)] = omega
    w[_at(R_CM, lane)] = p[T0] / (p[SLIP] * omega)
    w[_at(R_INVJ2, lane)] = 1.0 / (p[J2A] + p[J2B])
    w[_at(R_MU2, lane)] = p[J2A] * p[J2B] / (p[J2A] + p[J2B])
    w[_at(R_DELTA0, lane)] = p[T0] / p[KT2]
    masses = (p[MB], p[M1], p[MB], p[M2], p[M3], p[MB], p[M4], p[MB])
    for i in range(8):
        w[_at(R_INVM + i, lane)] = 1.0 / masses[i]
    springs = (p[KS], p[KS], p[KH], p[KC], p[KH], p[KS], p[KS])
    for i in range(7):
        w[_at(R_KLAT + i, lane)] = springs[i]
    w[_at(R_JRED1, lane)] = p[J1] - p[U1] * p[U1] * w[_at(R_INVM + 1, lane)]
    w[_at(R_JRED4, lane)] = p[J4] - p[U4] * p[U4] * w[_at(R_INVM + 6, lane)]
    w[_at(R_FINE_STEPS, lane)] = steps[0]
    w[_at(R_OPEN_STEPS, lane)] = steps[1]
    w[_at(R_SETTLE, lane)] = settle
    for k in range(N_MODES):
        w[_at(R_MODES + k, lane)] = 0.0
    w[_at(R_FINE_UNTIL, lane)] = settle if _joint_open(w, lane) != 0.0 else -math.inf  # a joint open at t = 0 settles
    for i in range(NY):
        w[_at(R_Y + i, lane)] = start[i] if start.shape[0] == NY else 0.0
    if start.shape[0] == NY:
        return
    theta3 = p[T0] / p[KT3]
    theta2 = theta3 + p[T0] / p[KT2]
    for i, theta in enumerate((theta2 + p[T0] / p[KT1], theta2, theta2, theta3, 0.0)):
        w[_at(R_Y + i, lane)] = theta
        w[_at(R_Y + NQ + i, lane)] = omega


@njit(**_JIT)
def _record(w, codes, out, sims, k, n_lanes, t):
    """Sample k (time t) of every output code for the block's lanes (simulations sims[0], sims[1], ...)."""
    for c in range(codes.shape[0]):
        code = codes[c]
        if code == OUT_TORQUE_C or code == OUT_JOINT_TORQUE:
            for lane in range(n_lanes):
                torques = _joint_torques(w, lane, R_Y, t)
                out[sims[lane], c, k] = torques[1] if code == OUT_TORQUE_C else torques[2]
            continue
        if code < 8:  # bearing displacement: (node b1,b2,b3,b4) × (x,y)
            row = R_Y + 5 + 8 * (code % 2) + (0, 2, 5, 7)[code // 2]
        elif code == 8:
            row = R_Y + NQ
        elif code == 9:
            row = R_Y + NQ + 4
        elif code < OUT_STATE:
            row = R_MODES + code - OUT_MODES
        else:
            row = R_Y + code - OUT_STATE
        for lane in range(n_lanes):
            out[sims[lane], c, k] = w[_at(row, lane)]


@njit(**_JIT)
def _simulate_block(params, states, fine_steps, settle, sims, t_first, fs, n_samples, substeps, codes, out):
    """Simulate rows ``sims`` of ``params`` together, one per lane, from their rows of ``states`` (rig.md's state where
    they are empty), with ``substeps`` RK4 steps per sample interval (and each row's ``fine_steps`` times as many while it
    settles after a switch or its slip joint is open)."""
    n_lanes = sims.shape[0]
    h_target = 1.0 / (fs * substeps)
    w = np.zeros(N_ROWS * LANES)  # unused lanes stay finite: the flat copy in _step reads them
    alone = np.zeros(N_ROWS * LANES)  # scratch block of the event path (lane 0 only)
    fine = np.zeros(N_ROWS * LANES)  # scratch block of the lanes that step finely
    picked = np.zeros(LANES, dtype=np.int64)
    group = np.zeros(LANES, dtype=np.int64)
    w[_at(R_TL_TIME, 0)] = math.nan
    events_possible = np.bool_(False)  # not a literal False: see _step's counters
    for lane in range(n_lanes):
        row = sims[lane]
        _setup_lane(w, lane, params[row], fine_steps[row], settle[row], states[min(row, states.shape[0] - 1)])
        for slot in SWITCHING_ON:
            events_possible = events_possible or params[row, slot] != 0.0
    n_run = _pad(w, n_lanes)
    for lane in range(n_lanes):  # an effect whose event function is already positive at t = 0 switches there
        g, which = _lane_event(w, lane, R_Y, 0.0)
        if g > 0.0:
            _switch(w, lane, which, 0.0)
    t = 0.0
    n_warm = math.ceil(t_first / h_target - 1e-9)
    for k in range(n_warm):
        t = _advance(w, alone, fine, picked, group, t, (k + 1) * t_first / n_warm - t, n_lanes, n_run, events_possible)
    t = t_first
    for k in range(n_samples):
        if k > 0:
            t_sample = t_first + k / fs
            for s in range(substeps):
                t_next = t_first + (k - 1 + (s + 1) / substeps) / fs
                t = _advance(w, alone, fine, picked, group, t, t_next - t, n_lanes, n_run, events_possible)
            t = t_sample
        _record(w, codes, out, sims, k, n_lanes, t)


@njit(cache=True, error_model="numpy", parallel=True, nogil=True)
def _simulate_batch(params, states, fine_steps, settle, order, starts, counts, substeps, t_first, fs, n_samples, codes):
    """Simulate the blocks of rows order[starts[b] : starts[b] + counts[b]] of ``params`` in parallel, each from its
    row of ``states`` (n, NY), or each from rig.md's initial state where ``states`` is (1, 0), with ``substeps`` RK4
    steps per sample interval (each row's ``fine_steps`` times as many while its joint settles or is open)."""
    out = np.empty((params.shape[0], codes.shape[0], n_samples))
    for b in prange(starts.shape[0]):
        rows = order[starts[b] : starts[b] + counts[b]]
        _simulate_block(params, states, fine_steps, settle, rows, t_first, fs, n_samples, substeps, codes, out)
    return out


# --- the first compile, shared ------------------------------------------------------------------------
# Two parts of the kernel that do not call each other, each compiled on its own into numba's cache by calling its
# functions with the argument types their callers pass (lanes as run-time int64, rows as the literal constants):
# processes that compile the kernel together (a study's first jobs, a process's helper on its second core) take one
# part each, and the entry point then loads them from the cache (newdyn.kernels.compile_parts).
@njit(**_JIT)
def _compile_steps():
    """The RK4 step, with the whole right-hand side inlined: the larger part."""
    w = np.zeros(N_ROWS * LANES)
    lanes, t = np.int64(1), 0.0
    _rk4(w, t, t, lanes, False)
    _rk4(w, t, t, lanes, True)


@njit(**_JIT)
def _compile_events():
    """The event functions and switches, and the set-up and recording of lanes."""
    w = np.zeros(N_ROWS * LANES)
    lane, t = np.int64(0), 0.0
    _, which = _lane_event(w, lane, R_Y, t)
    _switch(w, lane, which, t)
    _events(w, R_TRIAL, lane, t)
    _events(w, R_Y, lane, t)
    _interior_events(w, lane, t, t)
    _first_interior_event(w, lane, t, t)
    _setup_lane(w, lane, w, w, t, w)
    _pad(w, lane)
    sims = np.zeros(1, dtype=np.int64)
    _record(w, sims, np.zeros((1, 1, 1)), sims, lane, lane, t)


COMPILE_PARTS = (_compile_steps, _compile_events)
