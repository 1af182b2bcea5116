"""Plain NumPy/SciPy implementation of rig.md, independent of the compiled kernel: the oracle for tests and the speed baseline for bench/.

State layout (42), the same as :func:`newdyn.model.initial_state`: positions
``θ1 θ2a θ2b θ3 θ4, x[8], y[8]`` (nodes ``b1 m1 b2 m2 m3 b3 m4 b4``), then the same velocities.

Effects (:mod:`newdyn.effects`) enter through their declarations alone, called as plain Python: each
present effect's ``force`` is added at its place, and a switching effect's ``event`` is a terminal
event of ``solve_ivp`` (located by its root finder on the dense output), after which ``switch`` gives
the new mode and the integration restarts.  The switching state (the "modes") is one number per
present switching effect, carried beside the continuous state; the slip joint is locked (2a and 2b
one body) unless a present effect on it opens it.

The integrator works in a frame rotating at Ω: it carries φ = θ - Ωt and φ̇ = θ̇ - Ω instead of θ and
θ̇ (:func:`rhs` with ``rotating=True``).  That is an exact change of variables, done because θ grows to
~10² rad while the channels depend on twists of ~10⁻³ rad and speed ripples of ~10⁻¹ rad/s:
relative-tolerance control on θ would let the twist error grow to ~10⁻⁸ rad at rtol 1e-10.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

from . import effects, model, slots
from .effects.check import effect_parameters_type

N_DOF = 21  # θ1 θ2a θ2b θ3 θ4, x[8], y[8]
_X0, _Y0 = 5, 13  # offsets of the lateral x and y blocks in the positions
_DISKS = ((0, model.DISK_NODES["1"]), (4, model.DISK_NODES["4"]))  # (angle index, lateral node)

# Default atol = rtol * typical size of each state component, so every component is controlled to
# the same *relative* accuracy of its own physical scale (not of |y|, which is ~0 for oscillating
# lateral components): angles φ ~1e-3 rad (the shaft twists T0/kT they form), lateral displacements
# ~1e-7 m (imbalance response), speed ripple φ̇ ~1e-1 rad/s, lateral velocities ~1e-5 m/s.
_SCALE = np.concatenate([np.full(5, 1e-3), np.full(16, 1e-7), np.full(5, 1e-1), np.full(16, 1e-5)])


# Torsional places: (a, b) position indices, x = q[a] - q[b] (b None: x = q[a], an absolute angle).
_TORSIONAL = {"motor": (0, None), "motor_shaft": (0, 1), "slip_joint": (1, 2), "coupling": (2, 3),
              "load_shaft": (3, 4), "load": (4, None)}
# An immediate second switch right after one needs its new mode's event function above this: a
# located root leaves the function within ~1e-12 of zero on either side, a real re-slip far above it.
IMMEDIATE_SWITCH = 1e-9


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
    phi1: float
    phi4: float
    load_amp: float
    load_freq: float
    load_phase: float
    harmonics: np.ndarray  # h = 1 … H
    K_lat: np.ndarray  # (16, 16) lateral stiffness
    C_lat: np.ndarray  # (16, 16) lateral damping β·K_lat
    lateral_mass: np.ndarray  # (16,)
    rig_values: tuple  # the rig values the effects' functions see (newdyn.effects.RigValues)
    effects: tuple  # (effect class, its parameters as the named tuple its functions see) of each present effect

    @property
    def J2(self) -> float:
        return self.J2a + self.J2b

    @property
    def switching(self) -> tuple:
        """The present effects that switch, in order: the modes tuple has one entry for each."""
        return tuple(e for e in self.effects if e[0].switching())


def relative_rms(record: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per channel (the last axis is time), the RMS difference of ``record`` from ``reference`` over the reference
    channel's std: the scale the noise is set on, and the one rig.md's accuracy goals are stated on."""
    return np.sqrt(np.mean((record - reference) ** 2, axis=-1)) / np.std(reference, axis=-1)


def prepare(values: Mapping[str, float] | None = None) -> Rig:
    """The :class:`Rig` constants for ``values`` (missing names take their defaults)."""
    v = slots.complete(values)
    M, C, K = model.linear_matrices(v)
    # The lateral part is exactly the healthy matrix form; the torsional part is written element by
    # element in rhs() because θ2 splits into 2a/2b.
    names = ("J1", "J2a", "J2b", "J3", "J4", "m1", "m4", "kT1", "kT2", "kT3", "beta", "T0", "u1", "u4", "phi1", "phi4", "load_amp", "load_freq",
             "load_phase")
    present = []
    for kind, effect in effects.active().items():
        if v[slots.effect_slot(kind)] != 0.0:
            parameters = effect_parameters_type(effect)(
                *[v[slots.effect_slot(kind, p.name)] for p in effect.kernel_parameters()])
            present.append((effect, parameters))
    return Rig(
        values=v,
        Omega=model.omega(v),
        c_m=model.motor_slope(v),
        harmonics=np.arange(1, int(v["load_harm"]) + 1, dtype=float),
        K_lat=K[4:, 4:].copy(),
        C_lat=C[4:, 4:].copy(),
        lateral_mass=np.diag(M)[4:].copy(),
        rig_values=effects.RigValues(**{n: v[n] for n in model.PARAMETER_NAMES}, Omega=model.omega(v)),
        effects=tuple(present),
        **{n: v[n] for n in names},
    )


def load_torque(t: float, p: Rig) -> float:
    """T_l(t) = T0 [1 + a Σ_{h=1..H} sin(h (2π f_l t + φ_l)) / h]."""
    h = p.harmonics
    return p.T0 * (1.0 + p.load_amp * float(np.sin((2.0 * math.pi * p.load_freq * t + p.load_phase) * h) @ (1.0 / h)))


def _kinematics(place: str, t: float, y: np.ndarray, ref_angle: float, ref_speed: float, joint_torque: float):
    """What an effect at ``place`` sees of state ``y`` (angles absolute, whatever the frame)."""
    q, v = y[:N_DOF], y[N_DOF:]
    if place in _TORSIONAL:
        a, b = _TORSIONAL[place]
        x, xd = (ref_angle + q[a], ref_speed + v[a]) if b is None else (q[a] - q[b], v[a] - v[b])
    else:
        node, _, axis = place.partition("_")
        i = (_X0 if axis == "x" else _Y0) + model.NODES.index(node)
        x, xd = q[i], v[i]
    return effects.Kinematics(t, x, xd, ref_angle + q[0], ref_angle + q[4], ref_speed + v[0], ref_speed + v[4],
                              joint_torque if place == "slip_joint" else 0.0)


def _mode_of(p: Rig, effect, modes: Sequence[float]) -> float:
    switching = [e for e, _ in p.switching]
    return float(modes[switching.index(effect)]) if effect in switching else 0.0


def element_torques(t: float, y: np.ndarray, p: Rig, modes: Sequence[float] = (), rotating: bool = False):
    """(τ1, τ2, τ3, T_f, f_joint, joint open, torque on disk 1, torque on disk 4, lateral forces (16,)):
    the element torques (motor shaft 1 → 2a, coupling 2b → 3, load shaft 3 → 4, spring + damper),
    the torque the slip joint carries while locked, every present effect's force added at its place."""
    ref_angle, ref_speed = (p.Omega * t, p.Omega) if rotating else (0.0, 0.0)
    q, v = y[:N_DOF], y[N_DOF:]
    tau = {"motor_shaft": p.kT1 * ((q[0] - q[1]) + p.beta * (v[0] - v[1])),
           "coupling": p.kT2 * ((q[2] - q[3]) + p.beta * (v[2] - v[3])),
           "load_shaft": p.kT3 * ((q[3] - q[4]) + p.beta * (v[3] - v[4])),
           "motor": 0.0, "load": 0.0}
    F = -(p.K_lat @ q[_X0:] + p.C_lat @ v[_X0:])
    joint = [(e, params) for e, params in p.effects if e.acts_on == "slip_joint"]
    for effect, params in p.effects:
        if effect.acts_on == "slip_joint":
            continue
        force = effect.force(_kinematics(effect.acts_on, t, y, ref_angle, ref_speed, 0.0), params, p.rig_values,
                             _mode_of(p, effect, modes))
        if effect.acts_on in tau:
            tau[effect.acts_on] += force
        else:
            node, _, axis = effect.acts_on.partition("_")
            F[(0 if axis == "x" else 8) + model.NODES.index(node)] += force
    tau1, tau2 = tau["motor_shaft"], tau["coupling"]
    T_f = (tau1 * p.J2b + tau2 * p.J2a) / p.J2  # Karnopp's (F_2a/J2a - F_2b/J2b)·J2a·J2b/J2, F_2a = τ1, F_2b = -τ2
    f_joint, joint_open = 0.0, False
    for effect, params in joint:
        mode = _mode_of(p, effect, modes)
        if not (effect.locks_joint and mode == 0.0):
            joint_open = True
            f_joint += effect.force(_kinematics("slip_joint", t, y, ref_angle, ref_speed, T_f), params, p.rig_values, mode)
    torque1 = p.T0 - p.c_m * (v[0] + ref_speed - p.Omega) - tau1 + tau["motor"]
    torque4 = tau["load_shaft"] - load_torque(t, p) + tau["load"]
    return tau1, tau2, tau["load_shaft"], T_f, f_joint, joint_open, torque1, torque4, F


def rhs(t: float, y: np.ndarray, rig: Rig | Mapping[str, float], modes: Sequence[float] = (),
        rotating: bool = False) -> np.ndarray:
    """dy/dt of the rig of rig.md for state ``y`` (42, layout of the module docstring) in ``modes``
    (one per present switching effect, :attr:`Rig.switching`).

    ``rig``: a :class:`Rig` (fast) or a parameter mapping (prepared on every call).  With
    ``rotating=True`` the angles and angular speeds in ``y`` are φ = θ - Ωt and φ̇ = θ̇ - Ω; the result
    is then the derivative of that state (dφ/dt = φ̇, dφ̇/dt = θ̈).  While the slip joint is locked,
    2a and 2b get the same acceleration, so the caller must start them with θ̇2a = θ̇2b.
    """
    p = rig if isinstance(rig, Rig) else prepare(rig)
    ref_angle, ref_speed = (p.Omega * t, p.Omega) if rotating else (0.0, 0.0)
    q, v = y[:N_DOF], y[N_DOF:]
    acc = np.empty(N_DOF)
    tau1, tau2, tau3, _, f_joint, joint_open, T1, T4, F = element_torques(t, y, p, modes, rotating)
    acc[3] = (tau2 - tau3) / p.J3
    a_lat = F / p.lateral_mass

    # Imbalanced disks: the 3×3 Lagrange system of rig.md, solved in closed form.  The θ̇² terms
    # cancel in θ̈ and reappear in ẍ, ÿ by back-substitution.
    for (i, node), T, J, M, u, phi in zip(_DISKS, (T1, T4), (p.J1, p.J4), (p.m1, p.m4), (p.u1, p.u4), (p.phi1, p.phi4)):
        theta, theta_d = ref_angle + q[i], ref_speed + v[i]
        s, c = math.sin(theta + phi), math.cos(theta + phi)  # the imbalance sits at angle phi on its disk
        Fx, Fy = F[node], F[8 + node]
        theta_dd = (T + u * (s * Fx - c * Fy) / M) / (J - u * u / M)
        acc[i] = theta_dd
        a_lat[node] = (Fx + u * (theta_d * theta_d * c + s * theta_dd)) / M
        a_lat[8 + node] = (Fy + u * (theta_d * theta_d * s - c * theta_dd)) / M

    # The slip joint: F_2a = τ1 on 2a, F_2b = -τ2 on 2b, and the joint's torque between them when open.
    if joint_open:
        acc[1] = (tau1 - f_joint) / p.J2a
        acc[2] = (-tau2 + f_joint) / p.J2b
    else:
        acc[1] = acc[2] = (tau1 - tau2) / p.J2
    acc[_X0:] = a_lat
    return np.concatenate((v, acc))


def _event_value(j: int, t: float, y: np.ndarray, p: Rig, modes: Sequence[float]) -> float:
    """Event function of present switching effect j in ``modes`` (rotating frame)."""
    effect, params = p.switching[j]
    T_f = element_torques(t, y, p, modes, True)[3] if effect.acts_on == "slip_joint" else 0.0
    s = _kinematics(effect.acts_on, t, y, p.Omega * t, p.Omega, T_f)
    return effect.event(s, params, p.rig_values, modes[j])


def _events(p: Rig, modes: tuple) -> list:
    """A terminal event per present switching effect: where its event function rises through zero."""
    out = []
    for j in range(len(p.switching)):
        def event(t, y, *args, j=j):
            return _event_value(j, t, y, p, modes)
        event.terminal, event.direction = True, +1
        out.append(event)
    return out


def _switch(j: int, t: float, y: np.ndarray, p: Rig, modes: tuple) -> tuple:
    """Modes after effect j's event at state ``y`` (rotating frame); locking the slip joint also sets
    2a and 2b to their momentum-weighted common speed in ``y``."""
    effect, params = p.switching[j]
    T_f = element_torques(t, y, p, modes, True)[3] if effect.acts_on == "slip_joint" else 0.0
    s = _kinematics(effect.acts_on, t, y, p.Omega * t, p.Omega, T_f)
    new = float(effect.switch(s, params, p.rig_values, modes[j]))
    if effect.locks_joint and new == 0.0 and modes[j] != 0.0:  # the offset θ2a - θ2b is kept
        y[N_DOF + 1] = y[N_DOF + 2] = (p.J2a * y[N_DOF + 1] + p.J2b * y[N_DOF + 2]) / p.J2
    return modes[:j] + (new,) + modes[j + 1:]


def _channel(name: str, times: np.ndarray, states: np.ndarray, modes: np.ndarray, p: Rig) -> np.ndarray:
    if name == "w1":
        return states[N_DOF] + p.Omega
    if name == "w4":
        return states[N_DOF + 4] + p.Omega
    if name == "torque_c":  # the coupling's torque, with its effects
        return np.array([element_torques(t, y, p, tuple(m), True)[1] for t, y, m in zip(times, states.T, modes.T)])
    node, _, axis = name.partition("_")
    if node in model.NODES and axis in ("x", "y"):  # any lateral node, not only the bearings
        return states[(_X0 if axis == "x" else _Y0) + model.NODES.index(node)]
    raise KeyError(f"unknown channel {name!r}")


def _settle(t: float, z: np.ndarray, p: Rig, modes: tuple, switches: list) -> tuple:
    """Switch for as long as some event function of the current modes stands clearly above zero at
    (t, z): at the start, and right after a switch (a joint that re-sticks and cannot hold its torque)."""
    for _ in range(8):
        values = [_event_value(j, t, z, p, modes) for j in range(len(modes))]
        if not values or max(values) <= IMMEDIATE_SWITCH:
            return modes
        j = int(np.argmax(values))
        modes = _switch(j, t, z, p, modes)
        switches.append((t, p.switching[j][0].name, modes))
    raise RuntimeError(f"switching without end at t = {t}")


def simulate_reference(values: Mapping[str, float], sampling: model.Sampling,
                       channels: Sequence[str] = model.CHANNELS, rtol: float = 1e-10,
                       atol: float | np.ndarray | None = None, method: str = "DOP853",
                       return_switches: bool = False):
    """Channels (len(channels), sampling.n_samples) of the rig of rig.md, started at t = 0 from
    :func:`model.initial_state` and sampled at ``sampling.times``.

    Integrated with ``scipy.integrate.solve_ivp`` piecewise between switches, each located as a
    terminal event and restarted in the new modes.  ``atol=None``: rtol times a physical scale per
    state component (see ``_SCALE``).  With ``return_switches=True`` also returns the list of
    (t, effect, modes after it) of every switch.
    """
    p = prepare(values)
    times = sampling.times
    for name in channels:  # fail before integrating
        _channel(name, times[:0], np.zeros((2 * N_DOF, 0)), np.zeros((len(p.switching), 0)), p)
    atol = rtol * _SCALE if atol is None else atol
    # At most one radian of the fastest (stuck, linearized) mode per step.  Without a cap DOP853
    # lets the step grow to its stability limit whenever the rig is quiet (e.g. at equilibrium),
    # and error control there leaks ~1e-8 relative noise; with it the equilibrium holds to ~1e-15.
    # It costs ~10 % on the default rig, whose steps are accuracy-limited near this size anyway.
    max_step = 1.0 / (2.0 * math.pi * model.natural_frequencies(p.values, damped=False)[-1])

    z = model.initial_state(p.values)  # at t = 0, φ = θ; φ̇ = θ̇ - Ω
    z[N_DOF:N_DOF + 5] -= p.Omega
    switches: list = []
    modes = _settle(0.0, z, p, (0.0,) * len(p.switching), switches)
    states = np.empty((2 * N_DOF, times.size))
    sample_modes = np.empty((len(modes), times.size))
    t, done, stalls = 0.0, 0, 0
    while done < times.size:
        events = _events(p, modes)
        sol = solve_ivp(rhs, (t, times[-1]), z, method=method, t_eval=times[done:], rtol=rtol, atol=atol,
                        max_step=max_step, events=events or None, args=(p, modes, True))
        if sol.status < 0:
            raise RuntimeError(f"integration failed after t = {t}: {sol.message}")
        n_new = len(sol.t)  # a plain [] when the segment ended before the next sample
        if n_new:
            states[:, done:done + n_new] = sol.y
            sample_modes[:, done:done + n_new] = np.array(modes)[:, None]
        done += n_new
        if sol.status != 1:
            break
        which = next(i for i, te in enumerate(sol.t_events) if te.size)
        t_switch, z = sol.t_events[which][0], sol.y_events[which][0].copy()
        stalls = stalls + 1 if t_switch <= t else 0  # guard against chattering without progress
        if stalls > 50:
            raise RuntimeError(f"switching without progress at t = {t_switch}")
        t = t_switch
        modes = _switch(which, t, z, p, modes)
        switches.append((t, p.switching[which][0].name, modes))
        modes = _settle(t, z, p, modes, switches)
    if done < times.size:
        raise RuntimeError("integration stopped before the last sample")
    out = np.stack([_channel(name, times, states, sample_modes, p) for name in channels])
    return (out, switches) if return_switches else out
