"""Plain NumPy/SciPy implementation of rig.md, independent of the compiled kernel: the oracle for tests and the speed baseline for bench/.

State layout (42), the same as :func:`newdyn.model.initial_state`: positions
``θ1 θ2a θ2b θ3 θ4, x[8], y[8]`` (nodes ``b1 m1 b2 m2 m3 b3 m4 b4``), then the same velocities.

Switching state (the "mode"), carried beside the continuous state:

* ``slip``: 0 while J2a and J2b stick (Karnopp), ±1 while they slip with friction torque direction d;
* ``region``: where b1 sits in x relative to its housing clearance ±g: -1 beyond -g, 0 inside, +1
  beyond +g.  Ignored when ``bearing_gap == 0`` (the ground spring then always acts).

The integrator works in a frame rotating at Ω: it carries φ = θ - Ωt and φ̇ = θ̇ - Ω instead of θ and
θ̇ (:func:`rhs` with ``rotating=True``).  That is an exact change of variables, done because θ grows to
~10² rad while the channels depend on twists of ~10⁻³ rad and speed ripples of ~10⁻¹ rad/s:
relative-tolerance control on θ would let the twist error grow to ~10⁻⁸ rad at rtol 1e-10.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from scipy.integrate import solve_ivp

from . import model

N_DOF = 21  # θ1 θ2a θ2b θ3 θ4, x[8], y[8]
_X0, _Y0 = 5, 13  # offsets of the lateral x and y blocks in the positions
_DISKS = ((0, model.DISK_NODES["1"]), (4, model.DISK_NODES["4"]))  # (angle index, lateral node)

# Default atol = rtol * typical size of each state component, so every component is controlled to
# the same *relative* accuracy of its own physical scale (not of |y|, which is ~0 for oscillating
# lateral components): angles φ ~1e-3 rad (the shaft twists T0/kT they form), lateral displacements
# ~1e-7 m (imbalance response), speed ripple φ̇ ~1e-1 rad/s, lateral velocities ~1e-5 m/s.
_SCALE = np.concatenate([np.full(5, 1e-3), np.full(16, 1e-7), np.full(5, 1e-1), np.full(16, 1e-5)])


@dataclass(frozen=True)
class Rig:
    """Constants of the right-hand side, precomputed once from the parameter values (:func:`prepare`)."""

    values: dict
    J1: float
    J2a: float
    J2b: float
    J3: float
    J4: float
    m1: float
    m4: float
    kT1: float
    kT2: float
    kT3: float
    beta: float
    T0: float
    Omega: float
    c_m: float
    u1: float
    u4: float
    load_amp: float
    load_freq: float
    harmonics: np.ndarray  # h = 1 … H
    T_max: float
    r_k: float
    crack_alpha: float
    cubic_gamma: float
    bearing_gap: float
    k_bx: float
    K_lat: np.ndarray  # (16, 16) lateral stiffness; without b1's x ground spring when bearing_gap > 0
    C_lat: np.ndarray  # (16, 16) lateral damping β·K_lat
    lateral_mass: np.ndarray  # (16,)

    @property
    def J2(self) -> float:
        return self.J2a + self.J2b


def prepare(values: Mapping[str, float] | None = None) -> Rig:
    """The :class:`Rig` constants for ``values`` (missing names take their rig.md defaults)."""
    v = model.complete(values)
    M, C, K = model.linear_matrices(v)
    # The lateral part is exactly the healthy matrix form; the torsional part is written element by
    # element in rhs() because θ2 splits into 2a/2b and the crack/cubic faults make it nonlinear.
    K_lat, C_lat = K[4:, 4:].copy(), C[4:, 4:].copy()
    if v["bearing_gap"] > 0:  # b1's x ground spring and damper become the dead-zone element of rhs()
        K_lat[0, 0] -= v["k_bx"]
        C_lat[0, 0] -= v["beta"] * v["k_bx"]
    names = ("J1", "J2a", "J2b", "J3", "J4", "m1", "m4", "kT1", "kT2", "kT3", "beta", "T0", "u1", "u4",
             "load_amp", "load_freq", "T_max", "r_k", "crack_alpha", "cubic_gamma", "bearing_gap", "k_bx")
    return Rig(
        values=v,
        Omega=model.omega(v),
        c_m=model.motor_slope(v),
        harmonics=np.arange(1, int(v["load_harm"]) + 1, dtype=float),
        K_lat=K_lat,
        C_lat=C_lat,
        lateral_mass=np.diag(M)[4:].copy(),
        **{n: v[n] for n in names},
    )


def load_torque(t: float, p: Rig) -> float:
    """T_l(t) = T0 [1 + a Σ_{h=1..H} sin(2π h f_l t) / h]."""
    h = p.harmonics
    return p.T0 * (1.0 + p.load_amp * float(np.sin((2.0 * math.pi * p.load_freq * t) * h) @ (1.0 / h)))


def shaft_torques(y: np.ndarray, p: Rig):
    """Motor shaft torque τ1 (1 → 2a) and coupling torque τ2 (2b → 3), spring + damper.

    Only twists enter, so this holds in either frame; works on a state (42,) or states (42, n).
    τ2 = kT2 (δ + γ δ³/δ0²) + β kT2 δ̇, δ = θ2b - θ3, δ0 = T0/kT2 (the damper stays linear).
    """
    tau1 = p.kT1 * ((y[0] - y[1]) + p.beta * (y[N_DOF] - y[N_DOF + 1]))
    delta = y[2] - y[3]
    delta0 = p.T0 / p.kT2
    tau2 = p.kT2 * (delta + p.cubic_gamma * delta**3 / delta0**2 + p.beta * (y[N_DOF + 2] - y[N_DOF + 3]))
    return tau1, tau2


def stuck_interface_torque(y: np.ndarray, p: Rig) -> float:
    """Karnopp's T_f while sticking: (F_2a/J2a - F_2b/J2b)·J2a·J2b/J2 with F_2a = τ1, F_2b = -τ2."""
    tau1, tau2 = shaft_torques(y, p)
    return (tau1 * p.J2b + tau2 * p.J2a) / p.J2


def rhs(t: float, y: np.ndarray, rig: Rig | Mapping[str, float], slip: int = 0, region: int = 1,
        rotating: bool = False) -> np.ndarray:
    """dy/dt of the rig of rig.md for state ``y`` (42, layout of the module docstring) in mode (slip, region).

    ``rig``: a :class:`Rig` (fast) or a parameter mapping (prepared on every call).  With
    ``rotating=True`` the angles and angular speeds in ``y`` are φ = θ - Ωt and φ̇ = θ̇ - Ω; the result
    is then the derivative of that state (dφ/dt = φ̇, dφ̇/dt = θ̈).  While sticking (``slip == 0``)
    2a and 2b get the same acceleration, so the caller must start them with θ̇2a = θ̇2b.
    """
    p = rig if isinstance(rig, Rig) else prepare(rig)
    ref_angle, ref_speed = (p.Omega * t, p.Omega) if rotating else (0.0, 0.0)
    q, v = y[:N_DOF], y[N_DOF:]
    acc = np.empty(N_DOF)

    # Torsional elements (each spring k with its damper β·k).
    tau1, tau2 = shaft_torques(y, p)
    kT3 = p.kT3 * (1.0 - p.crack_alpha * (1.0 - math.cos(ref_angle + q[4])) / 2.0)  # breathing crack
    tau3 = kT3 * ((q[3] - q[4]) + p.beta * (v[3] - v[4]))
    T1 = p.T0 - p.c_m * (v[0] + ref_speed - p.Omega) - tau1  # motor torque T_m minus shaft 1
    T4 = tau3 - load_torque(t, p)
    acc[3] = (tau2 - tau3) / p.J3

    # Lateral spring + damper forces; b1's dead-zone ground element when there is a clearance.
    F = -(p.K_lat @ q[_X0:] + p.C_lat @ v[_X0:])
    g = p.bearing_gap
    if g > 0 and region != 0:
        F[0] -= p.k_bx * ((q[_X0] - g * region) + p.beta * v[_X0])
    a_lat = F / p.lateral_mass

    # Imbalanced disks: the 3×3 Lagrange system of rig.md, solved in closed form.  The θ̇² terms
    # cancel in θ̈ and reappear in ẍ, ÿ by back-substitution.
    for (i, node), T, J, M, u in zip(_DISKS, (T1, T4), (p.J1, p.J4), (p.m1, p.m4), (p.u1, p.u4)):
        theta, theta_d = ref_angle + q[i], ref_speed + v[i]
        s, c = math.sin(theta), math.cos(theta)
        Fx, Fy = F[node], F[8 + node]
        theta_dd = (T + u * (s * Fx - c * Fy) / M) / (J - u * u / M)
        acc[i] = theta_dd
        a_lat[node] = (Fx + u * (theta_d * theta_d * c + s * theta_dd)) / M
        a_lat[8 + node] = (Fy + u * (theta_d * theta_d * s - c * theta_dd)) / M

    # Stick-slip interface: F_2a = τ1 on 2a, F_2b = -τ2 on 2b.
    if slip == 0:
        acc[1] = acc[2] = (tau1 - tau2) / p.J2
    else:
        T_f = p.r_k * p.T_max * slip
        acc[1] = (tau1 - T_f) / p.J2a
        acc[2] = (-tau2 + T_f) / p.J2b
    acc[_X0:] = a_lat
    return np.concatenate((v, acc))


def _event(fun, direction: int):
    fun.terminal, fun.direction = True, direction
    return fun


def _events(p: Rig, slip: int, region: int) -> list:
    """Terminal events of mode (slip, region) as (function, tag); `direction` makes a restart on a root safe."""
    out = []
    if slip == 0 and math.isfinite(p.T_max):  # sticking: slip onset when |T_f| rises through T_max
        out.append((_event(lambda t, y, *a: stuck_interface_torque(y, p) - p.T_max, +1), ("slip", +1)))
        out.append((_event(lambda t, y, *a: stuck_interface_torque(y, p) + p.T_max, -1), ("slip", -1)))
    elif slip != 0:  # slipping: re-stick when (θ̇2a - θ̇2b)·d falls to 0
        out.append((_event(lambda t, y, *a: (y[N_DOF + 1] - y[N_DOF + 2]) * slip, -1), ("stick", 0)))
    g = p.bearing_gap
    if g > 0:
        if region >= 0:  # x_b1 - g: up-crossing from inside, down-crossing from beyond +g
            out.append((_event(lambda t, y, *a: y[_X0] - g, +1 if region == 0 else -1), ("gap", +1)))
        if region <= 0:
            out.append((_event(lambda t, y, *a: y[_X0] + g, -1 if region == 0 else +1), ("gap", -1)))
    return out


def _stick_or_slip(y: np.ndarray, p: Rig) -> int:
    """Mode of a sticking interface at rest relative to itself: slip in the direction of T_f if it exceeds T_max."""
    T_f = stuck_interface_torque(y, p)
    return int(np.sign(T_f)) if abs(T_f) > p.T_max else 0


def _switch(tag, y: np.ndarray, p: Rig, slip: int, region: int):
    """New (slip, region) after event ``tag`` at state ``y``; a re-stick also updates ``y`` in place."""
    kind, side = tag
    if kind == "slip":
        slip = side
    elif kind == "stick":  # momentum-weighted common speed; the offset θ2a - θ2b is kept
        y[N_DOF + 1] = y[N_DOF + 2] = (p.J2a * y[N_DOF + 1] + p.J2b * y[N_DOF + 2]) / p.J2
        slip = _stick_or_slip(y, p)
    else:  # crossing x_b1 = side·g: the velocity's sign says which side we enter (robust at a root)
        region = side if y[N_DOF + _X0] * side > 0 else 0
    return slip, region


def _channel(name: str, states: np.ndarray, p: Rig) -> np.ndarray:
    if name == "w1":
        return states[N_DOF] + p.Omega
    if name == "w4":
        return states[N_DOF + 4] + p.Omega
    if name == "torque_c":
        return shaft_torques(states, p)[1]
    node, _, axis = name.partition("_")
    if node in model.NODES and axis in ("x", "y"):  # any lateral node, not only the bearings
        return states[(_X0 if axis == "x" else _Y0) + model.NODES.index(node)]
    raise KeyError(f"unknown channel {name!r}")


def simulate_reference(values: Mapping[str, float], sampling: model.Sampling,
                       channels: Sequence[str] = model.CHANNELS, rtol: float = 1e-10,
                       atol: float | np.ndarray | None = None, method: str = "DOP853",
                       return_switches: bool = False):
    """Channels (len(channels), sampling.n_samples) of the rig of rig.md, started at t = 0 from
    :func:`model.initial_state` and sampled at ``sampling.times``.

    Integrated with ``scipy.integrate.solve_ivp`` piecewise between switches (slip onset, re-stick,
    bearing-clearance crossings), each located as a terminal event and restarted in the new mode.
    ``atol=None``: rtol times a physical scale per state component (see ``_SCALE``).
    With ``return_switches=True`` also returns the list of (t, tag, slip, region) of every switch.
    """
    p = prepare(values)
    times = sampling.times
    for name in channels:  # fail before integrating
        _channel(name, np.zeros((2 * N_DOF, 1)), p)
    atol = rtol * _SCALE if atol is None else atol
    # At most one radian of the fastest (stuck, linearized) mode per step.  Without a cap DOP853
    # lets the step grow to its stability limit whenever the rig is quiet (e.g. at equilibrium),
    # and error control there leaks ~1e-8 relative noise; with it the equilibrium holds to ~1e-15.
    # It costs ~10 % on the default rig, whose steps are accuracy-limited near this size anyway.
    max_step = 1.0 / (2.0 * math.pi * model.natural_frequencies(p.values, damped=False)[-1])

    z = model.initial_state(p.values)  # at t = 0, φ = θ; φ̇ = θ̇ - Ω
    z[N_DOF:N_DOF + 5] -= p.Omega
    slip = _stick_or_slip(z, p)
    region = 0 if p.bearing_gap > 0 else 1  # b1 starts centred in its clearance
    states = np.empty((2 * N_DOF, times.size))
    switches = [(0.0, ("slip", slip), slip, region)] if slip else []  # T_max < T0: slips from the start
    t, done, stalls = 0.0, 0, 0
    while done < times.size:
        events = _events(p, slip, region)
        sol = solve_ivp(rhs, (t, times[-1]), z, method=method, t_eval=times[done:], rtol=rtol, atol=atol,
                        max_step=max_step, events=[e for e, _ in events] or None, args=(p, slip, region, True))
        if sol.status < 0:
            raise RuntimeError(f"integration failed after t = {t}: {sol.message}")
        n_new = len(sol.t)  # a plain [] when the segment ended before the next sample
        if n_new:
            states[:, done:done + n_new] = sol.y
        done += n_new
        if sol.status != 1:
            break
        which = next(i for i, te in enumerate(sol.t_events) if te.size)
        t_switch, z = sol.t_events[which][0], sol.y_events[which][0].copy()
        stalls = stalls + 1 if t_switch <= t else 0  # guard against chattering without progress
        if stalls > 50:
            raise RuntimeError(f"switching without progress at t = {t_switch}")
        t = t_switch
        slip, region = _switch(events[which][1], z, p, slip, region)
        switches.append((t, events[which][1], slip, region))
    if done < times.size:
        raise RuntimeError("integration stopped before the last sample")
    out = np.stack([_channel(name, states, p) for name in channels])
    return (out, switches) if return_switches else out
