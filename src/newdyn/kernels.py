"""Compiled simulation kernel of the reference rig (rig.md), batched over parameter sets.

Fixed-step classical Runge-Kutta (RK4) with exact event location: a switching fault (stick-slip
onset and re-stick, loose-bearing contact) changes the force law only at a located event, so each
step integrates a smooth right-hand side and keeps fourth-order accuracy.  The inference stages call
:func:`simulate_batch` tens of thousands of times; it runs parameter sets in parallel threads
(``NUMBA_NUM_THREADS``).

State layout (42): positions θ1 θ2a θ2b θ3 θ4, x[8], y[8] (nodes b1 m1 b2 m2 m3 b3 m4 b4), then
the same velocities.  θ2a/θ2b move as one body J2a + J2b while stuck.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .model import PARAMETER_INDEX as _I

# Parameter slots (compile-time constants for numba).
J1, J2A, J2B, J3, J4 = _I["J1"], _I["J2a"], _I["J2b"], _I["J3"], _I["J4"]
M1, M2, M3, M4, MB = _I["m1"], _I["m2"], _I["m3"], _I["m4"], _I["m_b"]
KT1, KT2, KT3 = _I["kT1"], _I["kT2"], _I["kT3"]
KS, KH, KC, KBX, KBY = _I["k_s"], _I["k_h"], _I["k_c"], _I["k_bx"], _I["k_by"]
BETA, SLIP, U1, U4 = _I["beta"], _I["slip"], _I["u1"], _I["u4"]
SPEED, T0, LOAD_AMP, LOAD_FREQ, LOAD_HARM = _I["speed_rpm"], _I["T0"], _I["load_amp"], _I["load_freq"], _I["load_harm"]
TMAX, RK, ALPHA, GAMMA, GAP = _I["T_max"], _I["r_k"], _I["crack_alpha"], _I["cubic_gamma"], _I["bearing_gap"]

NQ = 21  # positions
NY = 42  # state

# Output codes: 0..10 are model.CHANNELS in order; then diagnostics; STATE + i is state component i.
OUT_SLIP_ONSETS = 11  # cumulative number of slip onsets up to the sample
OUT_SLIPPING = 12  # 1 while the stick-slip interface slips, else 0
OUT_INTERFACE_TORQUE = 13  # the torque the interface would carry if stuck (the T_f of Eq. 3b)
OUT_BEARING_CONTACT = 14  # loose-bearing contact state -1, 0, +1
OUT_STATE = 100

# Derived-quantity slots computed once per simulation.
D_OMEGA, D_CM, D_INVJ2, D_MU2, D_DELTA0 = 0, 1, 2, 3, 4
D_INVM = 5  # 8 inverse node masses
D_KLAT = 13  # 7 lateral spring stiffnesses
D_SIZE = 20


@njit(cache=True)
def _derived(p):
    d = np.empty(D_SIZE)
    d[D_OMEGA] = 2.0 * math.pi * p[SPEED] / 60.0
    d[D_CM] = p[T0] / (p[SLIP] * d[D_OMEGA])
    d[D_INVJ2] = 1.0 / (p[J2A] + p[J2B])
    d[D_MU2] = p[J2A] * p[J2B] / (p[J2A] + p[J2B])
    d[D_DELTA0] = p[T0] / p[KT2]
    masses = (p[MB], p[M1], p[MB], p[M2], p[M3], p[MB], p[M4], p[MB])
    for i in range(8):
        d[D_INVM + i] = 1.0 / masses[i]
    springs = (p[KS], p[KS], p[KH], p[KC], p[KH], p[KS], p[KS])
    for i in range(7):
        d[D_KLAT + i] = springs[i]
    return d


@njit(cache=True)
def _shaft_torques(y, p, d):
    """Torques of shaft 1 on disk 1 (+), of the coupling element on disk 3 (+), of shaft 3 on disk 4 (+)."""
    beta = p[BETA]
    t_s1 = p[KT1] * ((y[1] - y[0]) + beta * (y[NQ + 1] - y[NQ]))
    delta = y[2] - y[3]
    cubic = 1.0 + p[GAMMA] * (delta / d[D_DELTA0]) ** 2 if p[GAMMA] != 0.0 else 1.0
    t_c = p[KT2] * (delta * cubic + beta * (y[NQ + 2] - y[NQ + 3]))
    k3 = p[KT3]
    if p[ALPHA] != 0.0:
        k3 *= 1.0 - 0.5 * p[ALPHA] * (1.0 - math.cos(y[4]))
    t_s3 = k3 * ((y[3] - y[4]) + beta * (y[NQ + 3] - y[NQ + 4]))
    return t_s1, t_c, t_s3


@njit(cache=True)
def _stick_torque(t_s1, t_c, p, d):
    """Interface torque T_f while stuck (paper Eq. 3b): F_2a = -t_s1 on 2a, F_2b = -t_c on 2b."""
    return (-t_s1 / p[J2A] + t_c / p[J2B]) * d[D_MU2]


@njit(cache=True)
def _load_torque(t, p):
    """T_l(t) = T0 [1 + a Σ_h sin(2π h f_l t)/h]; sin(hx) by the Chebyshev recurrence (one sin/cos)."""
    x = 2.0 * math.pi * p[LOAD_FREQ] * t
    s1, c1 = math.sin(x), math.cos(x)
    s_prev, s_h, total = 0.0, s1, 0.0
    for h in range(1, int(p[LOAD_HARM]) + 1):
        total += s_h / h
        s_prev, s_h = s_h, 2.0 * c1 * s_h - s_prev
    return p[T0] * (1.0 + p[LOAD_AMP] * total)


@njit(cache=True)
def _lateral(pos, vel, k_ground, beta, d, force, gap, contact):
    """Spring + damper forces on the 8 nodes of one direction; ``gap`` > 0 makes b1's ground spring a dead zone."""
    for i in range(8):
        force[i] = 0.0
    for s in range(7):
        f = d[D_KLAT + s] * ((pos[s + 1] - pos[s]) + beta * (vel[s + 1] - vel[s]))
        force[s] += f
        force[s + 1] -= f
    for n in (2, 5, 7):
        force[n] -= k_ground * (pos[n] + beta * vel[n])
    if gap == 0.0:
        force[0] -= k_ground * (pos[0] + beta * vel[0])
    elif contact != 0:
        force[0] -= k_ground * ((pos[0] - contact * gap) + beta * vel[0])


@njit(cache=True)
def _rhs(t, y, p, d, slip_dir, contact, dydt, fx, fy):
    """dy/dt for fixed switching modes ``slip_dir`` (0 stuck, ±1 slipping) and ``contact`` (-1, 0, +1)."""
    for i in range(NQ):
        dydt[i] = y[NQ + i]
    beta = p[BETA]
    t_s1, t_c, t_s3 = _shaft_torques(y, p, d)
    t_motor = p[T0] - d[D_CM] * (y[NQ] - d[D_OMEGA])
    torque1 = t_s1 + t_motor
    torque4 = t_s3 - _load_torque(t, p)

    _lateral(y[5:13], y[NQ + 5 : NQ + 13], p[KBX], beta, d, fx, p[GAP], contact)
    _lateral(y[13:21], y[NQ + 13 : NQ + 21], p[KBY], beta, d, fy, 0.0, 0)

    # Imbalance disks (θ index, node, u, J): exact 3×3 Lagrange solve, rig.md.
    for th, node, u, inertia, torque in ((0, 1, p[U1], p[J1], torque1), (4, 6, p[U4], p[J4], torque4)):
        inv_m = d[D_INVM + node]
        w = y[NQ + th]
        s, c = math.sin(y[th]), math.cos(y[th])
        acc = (torque + u * (s * fx[node] - c * fy[node]) * inv_m) / (inertia - u * u * inv_m)
        dydt[NQ + th] = acc
        fx[node] += u * (w * w * c + s * acc)
        fy[node] += u * (w * w * s - c * acc)

    if slip_dir == 0:
        common = (-t_s1 - t_c) * d[D_INVJ2]
        dydt[NQ + 1] = common
        dydt[NQ + 2] = common
    else:
        friction = p[RK] * p[TMAX] * slip_dir
        dydt[NQ + 1] = (-t_s1 - friction) / p[J2A]
        dydt[NQ + 2] = (-t_c + friction) / p[J2B]
    dydt[NQ + 3] = (t_c - t_s3) / p[J3]
    for i in range(8):
        dydt[NQ + 5 + i] = fx[i] * d[D_INVM + i]
        dydt[NQ + 13 + i] = fy[i] * d[D_INVM + i]


@njit(cache=True)
def _rk4(t, y, h, p, d, slip_dir, contact, out, w):
    """One RK4 step of size h from (t, y) into ``out``; ``w`` is a (6, NY) work array."""
    k1, k2, k3, k4, tmp = w[0], w[1], w[2], w[3], w[4]
    fx, fy = w[5, :8], w[5, 8:16]
    _rhs(t, y, p, d, slip_dir, contact, k1, fx, fy)
    for i in range(NY):
        tmp[i] = y[i] + 0.5 * h * k1[i]
    _rhs(t + 0.5 * h, tmp, p, d, slip_dir, contact, k2, fx, fy)
    for i in range(NY):
        tmp[i] = y[i] + 0.5 * h * k2[i]
    _rhs(t + 0.5 * h, tmp, p, d, slip_dir, contact, k3, fx, fy)
    for i in range(NY):
        tmp[i] = y[i] + h * k3[i]
    _rhs(t + h, tmp, p, d, slip_dir, contact, k4, fx, fy)
    for i in range(NY):
        out[i] = y[i] + h / 6.0 * (k1[i] + 2.0 * (k2[i] + k3[i]) + k4[i])


@njit(cache=True)
def _event(y, p, d, slip_dir, contact):
    """Event function of the current modes: an event lies where it turns positive.

    Returns the largest of the active event functions and which one (0 none, 1 slip onset,
    2 re-stick, 3 bearing contact change).
    """
    best, which = -math.inf, 0
    if p[TMAX] < math.inf:
        if slip_dir == 0:
            t_s1, t_c, _ = _shaft_torques(y, p, d)
            g = (abs(_stick_torque(t_s1, t_c, p, d)) - p[TMAX]) / p[TMAX]
            best, which = g, 1
        else:
            g = -(y[NQ + 1] - y[NQ + 2]) * slip_dir / d[D_OMEGA]
            best, which = g, 2
    if p[GAP] > 0.0:
        x = y[5] / p[GAP]
        g = abs(x) - 1.0 if contact == 0 else 1.0 - contact * x
        if g > best:
            best, which = g, 3
    return best, which


@njit(cache=True)
def _switch(y, p, d, slip_dir, contact, which):
    """Apply the mode change of event ``which`` at the located state ``y``; returns the new modes."""
    if which == 3:
        contact = 0 if contact != 0 else (1 if y[5] > 0.0 else -1)
        return slip_dir, contact
    if which == 2:  # re-stick: both sides take the momentum-weighted common speed
        common = (p[J2A] * y[NQ + 1] + p[J2B] * y[NQ + 2]) * d[D_INVJ2]
        y[NQ + 1] = common
        y[NQ + 2] = common
        slip_dir = 0
    t_s1, t_c, _ = _shaft_torques(y, p, d)
    t_f = _stick_torque(t_s1, t_c, p, d)
    if abs(t_f) > p[TMAX] or which == 1:
        slip_dir = 1 if t_f > 0.0 else -1
    return slip_dir, contact


@njit(cache=True)
def _advance(t, y, h, p, d, modes, w, onsets):
    """Advance (t, y) by h in place, locating and applying every event on the way.

    ``modes`` = [slip_dir, contact]; ``onsets`` [0] counts slip onsets.  Returns the new time.
    """
    trial = w[6]
    t_end = t + h
    while True:
        step = t_end - t
        if step <= 0.0:
            return t_end
        _rk4(t, y, step, p, d, modes[0], modes[1], trial, w)
        g_end, which = _event(trial, p, d, modes[0], modes[1])
        if g_end <= 0.0:
            y[:] = trial
            return t_end
        # Illinois regula falsi on the step fraction; g(0) < 0 because we start inside the mode.
        g0, _ = _event(y, p, d, modes[0], modes[1])
        g0 = min(g0, 0.0)
        lo, hi, g_lo, g_hi, side = 0.0, 1.0, g0, g_end, 0
        for _ in range(60):
            frac = (lo * g_hi - hi * g_lo) / (g_hi - g_lo) if g_hi != g_lo else 0.5 * (lo + hi)
            if not lo < frac < hi:
                frac = 0.5 * (lo + hi)
            _rk4(t, y, frac * step, p, d, modes[0], modes[1], trial, w)
            g, which_here = _event(trial, p, d, modes[0], modes[1])
            if g > 0.0:
                hi, g_hi = frac, g
                which = which_here
                if side == 1:
                    g_lo *= 0.5
                side = 1
            else:
                lo, g_lo = frac, g
                if side == -1:
                    g_hi *= 0.5
                side = -1
            if (hi - lo) * step < 1e-13 or g_lo > -1e-13:
                break
        # Stop just on the far side of the event so the new mode starts at its own boundary.
        _rk4(t, y, hi * step, p, d, modes[0], modes[1], trial, w)
        y[:] = trial
        t = t + hi * step
        modes[0], modes[1] = _switch(y, p, d, modes[0], modes[1], which)
        if which != 3 and modes[0] != 0:
            onsets[0] += 1


@njit(cache=True)
def _record(y, p, d, modes, onsets, code):
    if code < 8:  # bearing displacement: (node b1,b2,b3,b4) × (x,y)
        node = (0, 2, 5, 7)[code // 2]
        return y[5 + 8 * (code % 2) + node]
    if code == 8:
        return y[NQ]
    if code == 9:
        return y[NQ + 4]
    t_s1, t_c, _ = _shaft_torques(y, p, d)
    if code == 10:
        return t_c
    if code == OUT_SLIP_ONSETS:
        return float(onsets[0])
    if code == OUT_SLIPPING:
        return 1.0 if modes[0] != 0 else 0.0
    if code == OUT_INTERFACE_TORQUE:
        return _stick_torque(t_s1, t_c, p, d)
    if code == OUT_BEARING_CONTACT:
        return float(modes[1])
    return y[code - OUT_STATE]


@njit(cache=True)
def _initial_state(p, d, y):
    y[:] = 0.0
    theta3 = p[T0] / p[KT3]
    theta2 = theta3 + p[T0] / p[KT2]
    y[0], y[1], y[2], y[3], y[4] = theta2 + p[T0] / p[KT1], theta2, theta2, theta3, 0.0
    for i in range(5):
        y[NQ + i] = d[D_OMEGA]


@njit(cache=True)
def _simulate_one(p, t_first, fs, n_samples, substeps, codes, out):
    d = _derived(p)
    y = np.empty(NY)
    _initial_state(p, d, y)
    w = np.empty((7, NY))
    modes = np.zeros(2, dtype=np.int64)
    onsets = np.zeros(1, dtype=np.int64)
    h_target = 1.0 / (fs * substeps)
    t = 0.0
    n_warm = int(math.ceil(t_first / h_target - 1e-9))
    for k in range(n_warm):
        t = _advance(t, y, (k + 1) * t_first / n_warm - t, p, d, modes, w, onsets)
    t = t_first
    for k in range(n_samples):
        if k > 0:
            t_sample = t_first + k / fs
            for s in range(substeps):
                t_next = t_first + (k - 1 + (s + 1) / substeps) / fs
                t = _advance(t, y, t_next - t, p, d, modes, w, onsets)
            t = t_sample
        for c in range(codes.shape[0]):
            out[c, k] = _record(y, p, d, modes, onsets, codes[c])


@njit(cache=True, parallel=True)
def simulate_batch(params, t_first, fs, n_samples, substeps, codes):
    """Simulate each row of ``params`` (n, n_parameters); returns (n, len(codes), n_samples).

    Samples lie at t_first + k/fs; the model starts from the rig.md initial state at t = 0.
    """
    n = params.shape[0]
    out = np.empty((n, codes.shape[0], n_samples))
    for i in prange(n):
        _simulate_one(params[i], t_first, fs, n_samples, substeps, codes, out[i])
    return out
