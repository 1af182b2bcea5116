"""Where a recording sits on the machine's turn and on the load's cycle: the imbalances' angles ``phi1``, ``phi4`` and
the load pulsation's phase ``load_phase`` (and, for a record without a disk speed, the running speed), found from the
data before any fit.

A recording starts at any moment: the shaft's angle at its first sample is folded into the imbalances' angles (turning
the whole shaft by ψ is turning both by ψ; an effect fixed to a shaft, such as a crack, has its own angle), and the
load's phase is its own parameter.  They enter the steady-state response almost linearly, which gives a closed-form
first guess: the response to an imbalance at angle φ is cos φ times the response at 0 plus sin φ times the response at
π/2, so four simulations of one imbalance each and one of the rig without imbalance per load phase on a grid give the
misfit of every pair of angles on a fine grid as a quadratic form.  Least squares on the full simulator then polishes
the best few grid points.

Before any hypothesis is fitted, only the lines the angles set are compared (:func:`lines`): each displacement's
once-per-revolution line and each torsional channel's load fundamental, as a keyphasor references a vibration's phase.
A fault the nominal model lacks changes the rest of the waveform far more than these lines, so it cannot pull the
angles to cover its misfit.  Under the best hypothesis's fit, which explains the whole waveform, the whole waveform is
compared (:func:`waveform`).  Each channel's mean is left out of both: a probe's static gap is no angle's.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields

import numpy as np
from scipy import optimize, stats

from . import concurrency, likelihood, model, running_speed, simulation
from .posterior import Profiled

LOAD_PHASES = 48  # grid of the load's phase for the first guess
ANGLES = 72  # grid of each imbalance angle for the first guess
STARTS = 3  # the best distinct grid points polished by least squares
ANGLE_SCAN = 24  # points of an imbalance angle's turn scanned under a fit for a basin least squares would not reach
JACOBIAN_STEP = 1e-4  # rad: far above the simulator's rounding, below the angles' precision
RELATIVE_STEP = 1e-6  # of a speed or a hypothesis's value, for the same reasons
# The stated angles stand unless moving them lowers χ² by more than noise alone would with this probability.
KEEP_STATED = 1e-3
# A found value lies elsewhere than an earlier one where it is more of its sds from it than a Normal estimate would be
# one time in 1/KEEP_STATED.
MOVED_SDS = float(stats.norm.isf(KEEP_STATED / 2))
# ... and a record placed in one basin of an imbalance's turn moves to another (that imbalance's angle MOVED_SDS away)
# that fits better by more than this in χ², odds beyond e to 1, however far short of KEEP_STATED's test: two basins are
# no refinement noise could make, and a fault's values taken in the worse one carry its bias (a crack's angle).
OTHER_BASIN = 2.0
# A disk speed's mean is the running speed to its tachometer's spread; the speed is fitted from the shaft's line where
# that spread turns the line by at least this much over the record (a 0.1 % gain at 1480 rpm: over 0.65 s).  On a
# shorter record the line tells the speed no better, and a probe's gain the nominal model lacks pulled it until the
# tachometer read out of its spec (a 0.1-s record).
SPEED_TURN = 0.1  # rad
FREE_EVALUATIONS = 30  # least squares' evaluations at most with the angles free
# ... and with them held (where the file states them, where the record was placed): only the hypothesis's values move,
# from their fit, and where the held angles are where the data put them that settles within a few evaluations; a chain
# still falling after this many is at angles the data tell apart from the found ones by far more than KEEP_STATED's.
HELD_EVALUATIONS = 10
# An effect's fit finds the load's phase beside its own values, this far either side of where the lines put it: a fault
# that reshapes the torsional response moves even the load's fundamental.
FIT_HALF_WIDTH = math.pi
# An angle the data hardly hold is known no better than one drawn uniformly on the circle: its variance π²/3 bounds a
# found angle's, as that uniform prior's precision added to the data's.
ANGLE_PRIOR_PRECISION = 3.0 / math.pi**2
SEGMENT_CYCLES = 3  # the lines are read over segments of at least this many load cycles, up to MAX_SEGMENTS of them,
MAX_SEGMENTS = 4  # so that the once-per-revolution line's phase shows how fast the shaft turns

Compared = Callable[[np.ndarray], np.ndarray]  # (..., channel, time) over σ -> (..., what is compared)


def moves(held: float, held_sd: float, found: float, found_sd: float) -> bool:
    """Whether an angle ``found`` ± ``found_sd`` moves one ``held`` ± ``held_sd`` (an sd of inf: nothing known of its
    precision): whether their precision-weighted mean lies more than :data:`MOVED_SDS` of its sd from ``held``.  Of two
    as precise, whether they differ by MOVED_SDS of their difference's sd; a precise finding moves a value the data
    hardly held (a record's load phase where the lines barely see the load) however near it, and a vague one does not
    move a precise value."""
    # The mean lies |d| h²/(h² + f²) from the held value, its sd is h f/√(h² + f²): their ratio against MOVED_SDS.
    return abs(model.wrap_angle(found - held)) > MOVED_SDS * found_sd * math.hypot(1.0, found_sd / held_sd)


@dataclass(frozen=True)
class Alignment:
    """The angles (and speed) found, and the χ² of what was compared (per compared number) at the stated values and at
    the found ones."""

    values: dict[str, float]
    chi2_stated: float
    chi2_found: float
    n_simulations: int
    compared: str  # "lines" or "waveform"
    speed_sd: float | None = None  # rpm: the prior spread of a fitted speed about the stated one (None: free within FAR)
    sd: dict[str, float] = field(default_factory=dict)  # each found value's standard error (:func:`standard_errors`)

    def summary(self) -> dict:
        return {"values": self.values, "sd": self.sd, "chi2_stated": self.chi2_stated, "chi2_found": self.chi2_found,
                "n_simulations": self.n_simulations, "compared": self.compared}


def standard_errors(jacobian: np.ndarray, names: Sequence[str]) -> dict[str, float]:
    """The standard errors of ``names``, the first columns of the Jacobian of a least squares's residuals (in units of
    the noise) at its optimum, whose Gram matrix is the data's information; further columns are values fitted beside
    them, which widen them.  An angle also carries the information :data:`ANGLE_PRIOR_PRECISION` of a uniform one, so
    that an angle the compared channels do not see (an imbalance on a disk no probe is near) reads about π/√3, not
    infinity."""
    prior = np.zeros(jacobian.shape[1])
    prior[: len(names)] = [ANGLE_PRIOR_PRECISION if n in model.ANGLE_PARAMETERS else 0.0 for n in names]
    information = jacobian.T @ jacobian + np.diag(prior)
    scale = np.sqrt(np.diag(information))  # values of any units (a gap in metres beside a stiffness) on one footing
    scale[scale == 0] = 1.0
    sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(information / np.outer(scale, scale))), 0.0, None)) / scale
    return {n: float(v) for n, v in zip(names, sd)}


def _bounds(names: Sequence[str], stated: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """Where the record's values may go: the angles anywhere on the turn, the speed within
    :data:`newdyn.running_speed.FAR` of the stated one (farther, the file is refused): a waveform compared without its
    means does not see a disk speed's level, and a short record's shaft line alone may not hold the speed."""
    margin = np.array([running_speed.FAR * stated[n] if n == "speed_rpm" else np.inf for n in names])
    centre = np.array([stated[n] if n == "speed_rpm" else 0.0 for n in names])
    return centre - margin, centre + margin


def _found(names: Sequence[str], x: Sequence[float]) -> dict[str, float]:
    """Found values by name, each angle on the circle's turn."""
    return {n: (float(v) if n == "speed_rpm" else model.wrap_angle(v)) for n, v in zip(names, x)}


def waveform(channels: Sequence[str], values: Mapping[str, float], sampling: model.Sampling) -> Compared:
    """Every sample of every channel, its mean left out."""
    return lambda y: (y - y.mean(axis=-1, keepdims=True)).reshape(*y.shape[:-2], -1)


def lines(channels: Sequence[str], values: Mapping[str, float], sampling: model.Sampling) -> Compared:
    """Each channel's line the angles set, in each segment of the record: a displacement's once-per-revolution line, a
    torsional channel's load fundamental; as the coefficients of the segment's orthonormal cosine and sine at that
    frequency beside a constant, so that white noise of σ 1 gives each coefficient σ 1."""
    t = np.arange(sampling.n_samples) / sampling.fs
    cycles = sampling.n_samples / sampling.fs * values["load_freq"]
    segments = int(min(MAX_SEGMENTS, max(1, cycles // SEGMENT_CYCLES)))
    bounds = np.linspace(0, sampling.n_samples, segments + 1).astype(int)
    projections = []
    for channel in channels:
        hz = model.omega(values) / (2 * math.pi) if channel in running_speed.DISPLACEMENTS else values["load_freq"]
        basis = np.zeros((sampling.n_samples, 3 * segments))
        for s, (a, b) in enumerate(itertools.pairwise(bounds)):
            piece = t[a:b]
            basis[a:b, 3 * s: 3 * s + 3] = np.column_stack(
                [np.ones_like(piece), np.cos(2 * math.pi * hz * piece), np.sin(2 * math.pi * hz * piece)])
        q, _ = np.linalg.qr(basis)
        projections.append(q[:, [k for k in range(3 * segments) if k % 3]])  # the lines' part beside the constant
    return lambda y: np.concatenate([y[..., c, :] @ p for c, p in enumerate(projections)], axis=-1)


def first_guess(target: np.ndarray, compare: Compared, sigma: np.ndarray, channels: Sequence[str], values: Mapping[str, float],
                sampling: model.Sampling, max_step: float) -> list[dict[str, float]]:
    """The :data:`STARTS` best (phi1, phi4, load_phase) of the grids, in distinct load phases, by the linearised
    response; ``target`` is the data as compared."""
    phases = np.arange(LOAD_PHASES) * 2 * math.pi / LOAD_PHASES
    bare = {**values, "u1": 0.0, "u4": 0.0}
    rows = [{**bare, "load_phase": p} for p in phases]
    rows += [{**bare, "load_phase": 0.0, u: values[u], phi: angle}
             for u, phi in (("u1", "phi1"), ("u4", "phi4")) for angle in (0.0, math.pi / 2)]
    compared = compare(simulation.simulate_batch(rows, sampling, channels, max_step) / sigma[:, None])
    basis = compared[LOAD_PHASES:] - compared[0]  # responses to u1 at 0, π/2 and u4 at 0, π/2
    remainders = target[None] - compared[:LOAD_PHASES]
    gram = basis @ basis.T
    projections = remainders @ basis.T  # (load phase, 4)
    norms = np.einsum("ij,ij->i", remainders, remainders)
    grid = np.arange(ANGLES) * 2 * math.pi / ANGLES
    a1, a4 = np.meshgrid(grid, grid, indexing="ij")
    z = np.stack([np.cos(a1), np.sin(a1), np.cos(a4), np.sin(a4)], axis=-1).reshape(-1, 4)
    cost = norms[:, None] - 2 * projections @ z.T + np.einsum("ij,jk,ik->i", z, gram, z)[None]
    best_angles = np.argmin(cost, axis=1)
    order = np.argsort(cost[np.arange(LOAD_PHASES), best_angles])
    starts = []
    for i in order:  # distinct load phases: at least an eighth of a turn apart from the ones taken
        if all(abs(model.wrap_angle(phases[i] - s["load_phase"])) > math.pi / 4 for s in starts):
            k = best_angles[i]
            starts.append({"phi1": float(a1.ravel()[k]), "phi4": float(a4.ravel()[k]), "load_phase": float(phases[i])})
        if len(starts) == STARTS:
            break
    return starts


def align(data: np.ndarray, sigma: np.ndarray, channels: Sequence[str], values: Mapping[str, float],
          sampling: model.Sampling, max_step: float, fit_speed: bool = False, compared: str = "lines",
          speed_sd: float | None = None) -> Alignment:
    """The angles (and with ``fit_speed`` the speed) at which the model ``values`` fits ``data`` best in what is
    ``compared`` (:func:`lines` or :func:`waveform`); the values' own angles where the data cannot tell them apart.
    With ``speed_sd`` (rpm) the speed is fitted too, a normal prior of that spread about the stated one beside the
    data: a disk speed's mean is the running speed only to its sensor's gain, and a short record's lines alone may not
    hold the speed."""
    fit_speed = fit_speed or speed_sd is not None
    names = ["phi1", "phi4", "load_phase"] + (["speed_rpm"] if fit_speed else [])
    compare = {"lines": lines, "waveform": waveform}[compared](channels, values, sampling)
    target = compare(data / sigma[:, None])
    count = [0]

    def residuals(rows: np.ndarray) -> np.ndarray:
        points = [{**values, **dict(zip(names, row))} for row in rows]
        count[0] += len(points)
        misfit = compare(simulation.simulate_batch(points, sampling, channels, max_step) / sigma[:, None]) - target[None]
        return _with_speed_prior(misfit, rows[:, -1], values["speed_rpm"], speed_sd)

    def fun(x):
        return residuals(x[None])[0]

    def jac(x):
        steps = np.full(len(x), JACOBIAN_STEP)
        if fit_speed:
            steps[-1] = x[-1] * RELATIVE_STEP
        found = residuals(np.vstack([x, x + np.diag(steps)]))
        return ((found[1:] - found[0]) / steps[:, None]).T

    stated = float(np.sum(fun(np.array([values[n] for n in names])) ** 2))
    best = None
    for start in first_guess(target, compare, sigma, channels, values, sampling, max_step):
        x0 = np.array([start[n] for n in names[:3]] + ([values["speed_rpm"]] if fit_speed else []))
        found = optimize.least_squares(fun, x0, jac=jac, bounds=_bounds(names, values), method="trf", x_scale="jac", max_nfev=40)
        if best is None or found.cost < best.cost:
            best = found
    chi2 = 2.0 * best.cost
    if stated - chi2 < stats.chi2.isf(KEEP_STATED, len(names)):  # the data cannot tell them apart
        best_values, chi2 = {n: float(values[n]) for n in names}, stated
    else:
        best_values = _found(names, best.x)
    return Alignment(best_values, stated / target.size, chi2 / target.size, count[0], compared, speed_sd,
                     standard_errors(best.jac, names))


def _with_speed_prior(misfit: np.ndarray, speeds: np.ndarray, stated: float, speed_sd: float | None) -> np.ndarray:
    """Rows of ``misfit`` with a fitted speed's normal prior about the ``stated`` speed as one more residual each."""
    return misfit if speed_sd is None else np.column_stack([misfit, (speeds - stated) / speed_sd])


def align_jointly(data: np.ndarray, sigma: np.ndarray, channels: Sequence[str], sampling: model.Sampling, max_step: float,
                  rows: Callable[[np.ndarray], np.ndarray], names: Sequence[str], angles: Mapping[str, float],
                  current: Mapping[str, float], theta: np.ndarray, low: np.ndarray, high: np.ndarray,
                  instruments=None, speed_sd: float | None = None) -> tuple[Alignment | None, dict[str, float]]:
    """Where the record sits under a fitted hypothesis, its fitted values ``theta`` (in [``low``, ``high``]) free beside
    the angles ``names``, on the whole waveform as the fit saw it (through its ``instruments``, whose delays take up what
    the angles need not): ``rows`` makes kernel parameter rows of (angles, theta).  Returns the alignment where the
    data place the angles farther from ``current`` than noise would, or in another basin of an imbalance's turn that
    fits better by :data:`OTHER_BASIN` (its χ² at ``current`` and at the found angles), else None; the ``angles``
    stated where the data cannot tell those from the found ones (and then wherever ``current`` is).  Beside it, the
    angles' standard errors under the hypothesis (:func:`standard_errors`): a fault may take up what an imbalance would
    show, and instruments' delays what its angle would.  A fitted speed keeps its prior (``speed_sd``, :func:`align`)."""
    compare = waveform(channels, {}, sampling)
    target = compare(data / sigma[:, None])
    k = len(names)
    simulated = []  # each batch's rows: least squares from each start runs in a thread of its own
    angle_low, angle_high = _bounds(names, angles)

    speed = list(names).index("speed_rpm") if "speed_rpm" in names else None

    def residuals(x: np.ndarray) -> np.ndarray:
        simulated.append(len(x))
        outputs = simulation.simulate_batch(rows(x), sampling, channels, max_step)
        if instruments is None:
            misfit = compare(outputs / sigma[:, None]) - target[None]
        else:
            misfit = likelihood.standardized_residuals(data, outputs, sigma, instruments).reshape(len(x), -1)
        return misfit if speed is None else _with_speed_prior(misfit, x[:, speed], angles["speed_rpm"], speed_sd)

    def best(start: Mapping[str, float], free_angles: bool) -> tuple[float, np.ndarray, np.ndarray]:
        """χ², the angles and the residuals' Jacobian in what was free at the best theta, the angles from ``start``,
        free or held there."""
        free = np.arange(k + theta.size) if free_angles else np.arange(k, k + theta.size)
        x = np.concatenate([[start[n] for n in names], np.clip(theta, low, high)])
        lower = np.concatenate([angle_low, low])[free]
        upper = np.concatenate([angle_high, high])[free]

        def fun(z):
            point = x.copy()
            point[free] = z
            return residuals(point[None])[0]

        def jac(z):
            steps = np.where(free < k, JACOBIAN_STEP, RELATIVE_STEP * np.maximum(np.abs(z), 1e-12))
            steps = np.where((free >= k) & (z + steps > upper), -steps, steps)
            points = np.tile(x, (len(z) + 1, 1))
            points[:, free] = np.vstack([z, z + np.diag(steps)])
            found = residuals(points)
            return ((found[1:] - found[0]) / steps[:, None]).T

        found = optimize.least_squares(fun, x[free], jac=jac, bounds=(lower, upper), method="trf", x_scale="jac",
                                       max_nfev=FREE_EVALUATIONS if free_angles else HELD_EVALUATIONS)
        x[free] = found.x
        return 2.0 * found.cost, x[:k], found.jac

    threshold = stats.chi2.isf(KEEP_STATED, k)
    # An imbalance angle whose disk the channels barely see can have a second basin, where the fitted values and the
    # instruments' gains and delays take up what it misplaces (a loose bearing on the motor's probes: disk 4's angle
    # half a turn off, 9 in χ² from the truth's, the gap 1 % off): each is scanned over its turn at the fitted values,
    # and least squares starts from the best other basin too where the scan finds one nearly as good.
    x = np.concatenate([[current[n] for n in names], np.clip(theta, low, high)])
    at_current = float(np.sum(residuals(x[None])[0] ** 2))
    turn = np.arange(ANGLE_SCAN) * 2 * math.pi / ANGLE_SCAN
    starts = [current]
    for i, name in enumerate(names):
        if name in model.IMBALANCE_ANGLES:
            points = np.tile(x, (ANGLE_SCAN, 1))
            points[:, i] = current[name] + turn
            chi2 = np.sum(residuals(points) ** 2, axis=1)
            basins = [j for j in range(1, ANGLE_SCAN) if chi2[j] <= min(chi2[j - 1], chi2[(j + 1) % ANGLE_SCAN])
                      and chi2[j] < at_current + threshold]
            if basins:
                starts.append({**current, name: current[name] + turn[min(basins, key=lambda j: chi2[j])]})
    # Each least squares is a chain of small batches that leaves a core idle: the free starts and the angles held where
    # the file states them and where the record was placed run side by side.
    chains = concurrency.in_parallel({**{i: (lambda start=start: best(start, True)) for i, start in enumerate(starts)},
                                      "stated": lambda: best(angles, False), "current": lambda: best(current, False)})
    chi2_free, found_angles, jacobian = min((chains[i] for i in range(len(starts))), key=lambda chain: chain[0])
    chi2_stated, chi2_current = chains["stated"][0], chains["current"][0]
    stated = chi2_stated - chi2_free < threshold
    if stated:  # the file's own angles stand, wherever the lines had put them
        found_angles, chi2_free = np.array([angles[n] for n in names]), chi2_stated
    sd = standard_errors(jacobian, names)
    if all(found_angles[i] == current[n] for i, n in enumerate(names)):
        return None, sd
    elsewhere = any(abs(model.wrap_angle(found_angles[i] - current[n])) > MOVED_SDS * sd[n]
                    for i, n in enumerate(names) if n in model.IMBALANCE_ANGLES)
    if not stated and chi2_current - chi2_free < (OTHER_BASIN if elsewhere else threshold):
        return None, sd
    return Alignment(_found(names, found_angles), chi2_current / data.size, chi2_free / data.size, sum(simulated), "waveform", speed_sd,
                     sd), sd


def load_phase_integral(values: Mapping[str, float], sigma: np.ndarray, channels: Sequence[str], sampling: model.Sampling,
                     max_step: float, half_width: float, data: np.ndarray | None = None, fitted: Mapping[str, float] | None = None,
                     instruments=None) -> float:
    """What integrating the load's phase over a uniform prior ``half_width`` either side of ``values["load_phase"]`` adds
    (log) to an evidence found with the phase held there and the ``fitted`` parameters (name -> difference step)
    integrated: by the Laplace approximation, ½ g²/S + ½ log 2π − ½ log S − log(2 half_width), S the phase's curvature
    given the fitted parameters (its Schur complement in the whole waveform's Gauss–Newton Hessian) and g the gradient
    of the log-likelihood along the phase with them moving too; with no ``data``, the phase is taken where it is best
    (g = 0).  A drift of a torsional stiffness moves the load response's phase: held where the nominal model put it, the
    drift would fit worse and pay a narrower phase's factor than an effect that finds the phase beside its values."""
    steps = {"load_phase": JACOBIAN_STEP, **(fitted or {})}
    rows = [{**values, name: values[name] + side * step} for name, step in steps.items() for side in (-1.0, 1.0)]
    outputs = simulation.simulate_batch(rows + ([] if data is None else [dict(values)]), sampling, channels, max_step)
    r = likelihood.standardized_residuals(np.zeros_like(outputs[0]) if data is None else data, outputs, sigma,
                                          instruments).reshape(len(outputs), -1)
    jacobian = ((r[1 : 2 * len(steps) : 2] - r[0 : 2 * len(steps) : 2]) / (2 * np.array(list(steps.values())))[:, None]).T
    hessian = jacobian.T @ jacobian
    gradient = np.zeros(len(steps)) if data is None else -(jacobian.T @ r[-1])
    given = hessian[1:, 1:]
    coupling = hessian[0, 1:]
    schur = hessian[0, 0] - (coupling @ np.linalg.solve(given, coupling) if len(given) else 0.0)
    along = gradient[0] - (coupling @ np.linalg.solve(given, gradient[1:]) if len(given) else 0.0)
    return float(0.5 * along**2 / schur + 0.5 * math.log(2 * math.pi / schur) - math.log(2 * half_width))


def load_phase_integral_at(values: Mapping[str, float], fitted: Mapping[str, float], data: np.ndarray, sigma: np.ndarray,
                           channels: Sequence[str], sampling: model.Sampling, max_step: float, instruments=None) -> float:
    """:func:`load_phase_integral` for a fit held at the lines' phase (healthy, a drift): over the fits' prior of the
    phase, :data:`FIT_HALF_WIDTH` either side, at the ``fitted`` values, which move with it."""
    return load_phase_integral({**values, **fitted}, sigma, channels, sampling, max_step, FIT_HALF_WIDTH, data,
                               {name: RELATIVE_STEP * abs(value) for name, value in fitted.items()}, instruments)


def phase_profiled(hypothesis, theta: np.ndarray, covariance: np.ndarray, data: np.ndarray, sigma: np.ndarray,
                   channels: Sequence[str], sampling: model.Sampling, max_step: float, values: Mapping[str, float],
                   instruments=None) -> tuple[list[str], Callable[[np.ndarray], Profiled]]:
    """The names of ``hypothesis``'s values but the load's phase and a likelihood of rows of them with the phase
    integrated out (:class:`newdyn.posterior.Profiled`): at each row, from the phase's conditional mean under the fit's
    Laplace approximation (``theta``, ``covariance``), one Gauss–Newton step along the phase.  The phase's posterior is
    normal and narrow beside a fault's values, so a fault of two values keeps its quadrature instead of sampling three
    dimensions; and the residual's derivative along the phase hardly moves over the values' posterior, so it is taken
    once, at the fit, and each row costs one simulation."""
    names = list(hypothesis.parameters)
    phase_index = names.index("load_phase")
    own = [i for i in range(len(names)) if i != phase_index]
    slope = np.linalg.solve(covariance[np.ix_(own, own)], covariance[own, phase_index])
    moved = np.array(theta, dtype=float)
    moved[phase_index] += JACOBIAN_STEP
    at_fit = simulation.simulate_batch(hypothesis.parameter_rows(np.vstack([theta, moved]), values), sampling, channels, max_step)
    r_fit = likelihood.standardized_residuals(data, at_fit, sigma, instruments).reshape(2, -1)
    along = (r_fit[1] - r_fit[0]) / JACOBIAN_STEP
    curvature = float(along @ along)

    def rows_of(own_rows: np.ndarray) -> Profiled:
        phase = theta[phase_index] + (own_rows - theta[own]) @ slope
        if not curvature > 0:  # the phase moves nothing the channels record: no point can be integrated
            return Profiled(np.full(len(phase), -np.inf), np.zeros(len(phase)), phase[:, None], np.zeros((len(phase), 1)))
        at = np.insert(own_rows, phase_index, phase, axis=1)
        outputs = simulation.simulate_batch(hypothesis.parameter_rows(at, values), sampling, channels, max_step)
        r = likelihood.standardized_residuals(data, outputs, sigma, instruments).reshape(len(at), -1)
        gradient = r @ along
        best = likelihood.log_likelihood(data, outputs, sigma, instruments=instruments) + 0.5 * gradient**2 / curvature
        return Profiled(np.where(np.isfinite(best), best, -np.inf), np.full(len(at), 0.5 * math.log(2 * math.pi / curvature)),
                        (phase - gradient / curvature)[:, None], np.full((len(at), 1), 1.0 / math.sqrt(curvature)))

    def profiled(own_rows: np.ndarray) -> Profiled:  # a few rows at a time: their simulations are in memory at once
        parts = [rows_of(own_rows[i : i + likelihood.SCORED_ROWS]) for i in range(0, len(own_rows), likelihood.SCORED_ROWS)]
        return Profiled(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(Profiled)))

    return [names[i] for i in own], profiled
