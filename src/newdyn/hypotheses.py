"""The hypotheses a diagnosis weighs, and how well each one, fitted, explains a measurement.

A hypothesis is the healthy model plus named parameters with priors: ``healthy`` has none,
``parameter_change:<p>`` one rig parameter with its calibration prior, and each effect of
:mod:`newdyn.effects` its own parameters (uniform priors over its diagnosis ranges) plus the rig
parameters that may have drifted at the same time (``diagnosis.drift``).  :func:`fit` finds the best fit by least squares on the simulator and
scores it by reduced χ² and by a Laplace approximation of the log-evidence, so hypotheses with
different numbers of parameters compare on one scale (the Occam factor is in the evidence).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from scipy import optimize
from scipy.special import erfinv

from . import concurrency, effects, faults, likelihood, model, sensors, simulation, slots

HEALTHY = faults.HEALTHY
PARAMETER_CHANGE = faults.PARAMETER_CHANGE
UNIFORM_UNIT_VARIANCE = 1.0 / 12.0  # variance of a uniform prior in unit coordinates
FIT_MAX_EVALUATIONS = 60
# The least squares' passes, coarse then fine: each one's finite-difference step of the Jacobian, in prior-box units,
# and where it stops (scipy's ftol and xtol: gains in cost and steps in u below this fraction).  The coarse step sees
# the broad valley of a switching effect's misfit (a fine one is led off by its ripples), the fine one the narrow
# trough at the valley's floor, which the coarse step straddles; both far above the simulator's rounding.  A fit
# follows the valley through its windows with the coarse pass alone and looks for the trough's floor on the whole
# record only: a shorter window's floor is not the record's, and the next window's coarse pass starts from anywhere in
# its valley.  So the coarse pass stops once its steps are a tenth of its own difference step (at scipy's default it
# spent most of its simulations on gains in cost far below one), the fine one at scipy's default.
JACOBIAN_STEPS = ((1e-3, 1e-4), (1e-5, 1e-8))
# Global search before least squares: differential evolution over the prior box, each generation one
# batched simulation with a search's longer steps at a slipping joint (simulation.simulate_batch's search): it
# only chooses where least squares starts, which then runs on the exact simulator.  Measured on stick-slip
# (4 parameters, 0.1 s at 40 dB, three truths): 40 generations of 16·k members land every time in the basin of
# the truth, where 512 quasi-random points with 4-16 least-squares starts stay in a wrong one (χ² 1.54 against
# 1.08 at the truth).
SEARCH_GENERATIONS = 40
SEARCH_POPULATION = 16  # members per fitted parameter
# The searches see only the record's start: its first SEARCH_WINDOW seconds (most of a load cycle) and
# its first 2·SEARCH_WINDOW; least squares then follows each one's optimum through windows that double
# up to the whole record.  Over a long record a switching effect's misfit is a golf course (plateaus,
# one per slip pattern, and a needle at the truth) that no search of this size crosses; over part of a
# cycle the truth's basin is wide enough to be found, though not always on the same window, and a
# longer window only narrows it around where the shorter one left off (docs/validation.md: Stick-slip fits).
SEARCH_WINDOW = 0.05  # s
SEARCHES = 2  # on the first this many windows
# Where a fit's least squares started besides its given starts: the bank's members, or a differential evolution.
SEARCHED_FROM = ("members", "differential evolution", "an earlier pass's differential evolution")


@dataclass(frozen=True)
class Prior:
    """A fitted parameter's prior: Normal(mean, sd) truncated to [low, high], or uniform there."""

    name: str
    low: float
    high: float
    mean: float | None = None
    sd: float | None = None

    def log_pdf(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        inside = (x >= self.low) & (x <= self.high)
        density = (
            likelihood.gaussian_log_prior(x, self.mean, self.sd) if self.sd is not None
            else np.full(x.shape, -math.log(self.high - self.low))
        )
        return np.where(inside, density, -np.inf)

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        if self.sd is None:
            return rng.uniform(self.low, self.high, n)
        x = rng.normal(self.mean, self.sd, 4 * n)
        return x[(x >= self.low) & (x <= self.high)][:n]


@dataclass(frozen=True)
class Hypothesis:
    name: str  # "healthy", "parameter_change:kT1", or an effect's kind
    kind: str  # "healthy", "parameter_change", or an effect's kind
    priors: tuple[Prior, ...] = ()

    @property
    def parameters(self) -> list[str]:
        return [p.name for p in self.priors]

    @property
    def verdict_class(self) -> str:
        """The verdict this hypothesis stands for: "healthy", "parameter_change" or "new_dynamics"."""
        return self.kind if self.kind in (HEALTHY, PARAMETER_CHANGE) else "new_dynamics"

    @property
    def effect(self) -> str | None:
        """What the hypothesis adds: the drifted parameter's name or the effect's kind (None if healthy)."""
        return None if self.kind == HEALTHY else self.name.split(":")[-1]

    def _values(self, theta: np.ndarray, base: Mapping[str, float]):
        """What rows of fitted values (n, k) set: the effect this hypothesis adds (None for healthy and
        drifts), the other fitted values by name (columns: drifted rig parameters, or any model value),
        the rig the effect acts on (``base`` with those drifts) and the effect's values (columns by
        parameter name: the fitted ones, the others at their defaults on ``base``) made admissible."""
        effect = effects.active().get(self.kind)
        own = effect.parameter_names() if effect is not None else ()
        columns = {name: theta[:, i] for i, name in enumerate(self.parameters)}
        others = {name: column for name, column in columns.items() if name not in own}
        rig = {**base, **others}
        if effect is None:
            return None, others, rig, {}
        values = {name: np.full(len(theta), value) for name, value in faults.effect_values(self.kind, {}, base).items()}
        values.update({name: column for name, column in columns.items() if name in own})
        admissible = effect.admissible(values, rig)
        return effect, others, rig, {name: np.broadcast_to(np.asarray(v, dtype=float), (len(theta),)) for name, v in admissible.items()}

    def parameter_rows(self, theta: np.ndarray, base: Mapping[str, float]) -> np.ndarray:
        """Kernel parameter vectors (n, len(slots.slot_names())) for rows of fitted values (n, k).

        A fitted rig parameter (a drift) sets its column.  An effect's parameters go through the
        effect: its presence flag is set, its values are made admissible (:meth:`Effect.admissible`,
        e.g. a friction joint kept able to carry the mean load) and set its kernel slots and the rig
        values it sets (:meth:`Effect.rig_values`, on the drifted rig)."""
        theta = np.atleast_2d(np.asarray(theta, dtype=float))
        base = slots.complete(base)
        index = slots.slot_index()
        rows = np.tile(slots.parameter_vector(base), (len(theta), 1))
        effect, others, rig, values = self._values(theta, base)
        for name, column in others.items():
            rows[:, index[name]] = column
        if effect is not None:
            rows[:, index[slots.effect_slot(self.kind)]] = 1.0
            for p in effect.kernel_parameters():
                rows[:, index[slots.effect_slot(self.kind, p.name)]] = values[p.name]
            for name, column in effect.rig_values(values, rig).items():
                rows[:, index[name]] = column
        return rows

    def admissible_rows(self, theta: np.ndarray, base: Mapping[str, float]) -> np.ndarray:
        """Rows of fitted values (n, k) as the model runs with them on ``base``: made admissible by the effect
        (:meth:`Effect.admissible`)."""
        theta = np.atleast_2d(np.asarray(theta, dtype=float))
        _, others, _, values = self._values(theta, slots.complete(base))
        return np.stack([np.asarray(values[name] if name in values else others[name], dtype=float) for name in self.parameters],
                        axis=1) if self.parameters else theta

    def on_shaft(self) -> list[str]:
        """The fitted parameters that are angles on a shaft (:func:`newdyn.effects.shaft_angle`)."""
        effect = effects.active().get(self.kind)
        return [name for name in self.parameters if effect is not None and name in effect.shaft_angles()]

    def turned(self, theta: np.ndarray, turn: float | np.ndarray) -> np.ndarray:
        """Rows of fitted values (n, k) for a record whose start turned the shaft by ``turn`` (one for all rows, or one
        per row) from the one they were fitted on: each angle on a shaft turned with it, as the imbalances' angles are."""
        theta = np.array(np.atleast_2d(theta), dtype=float)
        for name in self.on_shaft():
            at = self.parameters.index(name)
            theta[:, at] = np.mod(theta[:, at] + turn + math.pi, 2 * math.pi) - math.pi
        return theta

    def effective_values(self, theta: np.ndarray, base: Mapping[str, float]) -> dict[str, float]:
        """The values the model runs with at one row of fitted values (:meth:`admissible_rows`)."""
        return dict(zip(self.parameters, self.admissible_rows(theta, base)[0].tolist()))

    def log_prior(self, theta: np.ndarray) -> np.ndarray:
        return log_prior(self.priors, theta)


def log_prior(priors: Sequence[Prior], theta: np.ndarray) -> np.ndarray:
    """The log prior density of rows of values (n, k), one column per prior."""
    return np.sum([p.log_pdf(theta[:, i]) for i, p in enumerate(priors)], axis=0) if priors else np.zeros(len(theta))


def library(calibration_priors: Mapping[str, Prior], fault_ranges: Mapping[str, Mapping[str, Sequence[float]]],
            drift: Sequence[str]) -> list[Hypothesis]:
    """Every hypothesis: healthy, a drift of each calibration parameter, and each effect of
    ``fault_ranges`` (kind -> its fitted parameters -> prior range) with the ``drift`` parameters.

    An effect's fitted parameters are taken in its declaration order; one without a range is held at
    its default (so every parameter without a default needs a range)."""
    hypotheses = [Hypothesis(HEALTHY, HEALTHY)]
    hypotheses += [Hypothesis(f"{PARAMETER_CHANGE}:{name}", PARAMETER_CHANGE, (prior,)) for name, prior in calibration_priors.items()]
    for kind, ranges in fault_ranges.items():
        if kind not in effects.active():
            raise KeyError(f"no active effect '{kind}' to diagnose (active: {', '.join(effects.active())})")
        effect = effects.active()[kind]
        unknown = [name for name in ranges if name not in effect.parameter_names()]
        if unknown:
            raise KeyError(f"{kind} has no parameter {unknown[0]} (its parameters: {', '.join(effect.parameter_names())})")
        missing = [p.name for p in effect.parameters if p.default is None and p.name not in ranges]
        if missing:
            raise KeyError(f"{kind} needs a range for {missing[0]}, which has no default")
        own = tuple(Prior(p.name, float(ranges[p.name][0]), float(ranges[p.name][1])) for p in effect.parameters if p.name in ranges)
        hypotheses.append(Hypothesis(kind, kind, own + tuple(calibration_priors[name] for name in drift)))
    return hypotheses


class Members(NamedTuple):
    """Points of a hypothesis's prior box and its outputs over the fits' search windows (:mod:`newdyn.bank`)."""

    unit: np.ndarray  # (member, parameter) in prior-box units: (θ − low) / (high − low)
    outputs: np.ndarray  # (member, channel, sample) over the longest search window
    parameters: tuple[str, ...]  # the columns of ``unit``: a fit may have more (the load's phase), held at the base's value


@dataclass(frozen=True)
class Fit:
    """A hypothesis fitted to a measurement: best values, misfit and (approximate) log-evidence."""

    hypothesis: Hypothesis
    values: dict[str, float]  # best-fit (maximum a posteriori) value of each fitted parameter
    model: np.ndarray  # the best fit's outputs (channel, time)
    log_likelihood: float
    chi2_red: float
    log_evidence: float
    n_simulations: int
    at_bound: tuple[str, ...] = ()
    covariance: np.ndarray | None = None  # Laplace posterior covariance of the fitted values
    instruments: sensors.Instruments | None = None  # the instrument errors its likelihood integrates out (None: exact)
    search: str | None = None  # where its least squares started besides the given starts: SEARCHED_FROM (None: nowhere)

    @property
    def theta(self) -> np.ndarray:
        return np.array([self.values[name] for name in self.hypothesis.parameters])

    def laplace_parameters(self) -> dict:
        return laplace_parameters(self.values, self.covariance)

    def summary(self) -> dict:
        return {
            "hypothesis": self.hypothesis.name, "kind": self.hypothesis.kind, "effect": self.hypothesis.effect,
            "parameters": self.values, "chi2": self.chi2_red, "log_likelihood": self.log_likelihood,
            "log_evidence": self.log_evidence, "at_bound": list(self.at_bound), "n_simulations": self.n_simulations,
            "search": self.search,
        }


def laplace_parameters(values: Mapping[str, float], covariance: np.ndarray | None) -> dict:
    """Each fitted value ± its Laplace approximation (Normal: MAP = mean, central 94 % interval); empty without a
    covariance."""
    if covariance is None:
        return {}
    sd = np.sqrt(np.diag(covariance))
    z = float(np.sqrt(2) * erfinv(likelihood.HDI_PROB))  # the Normal's central interval is mean ± z·sd
    return {name: {"map": v, "mean": v, "sd": float(s), "hdi_low": v - z * float(s), "hdi_high": v + z * float(s),
                   "method": "laplace"} for (name, v), s in zip(values.items(), sd)}


def evaluate(hypothesis: Hypothesis, theta: np.ndarray, base: Mapping[str, float], sampling: model.Sampling,
             channels: Sequence[str], max_step: float, search: bool = False) -> np.ndarray:
    """Model outputs (n, channel, time) of the hypothesis at rows of fitted values (n, k); ``search``: see
    ``simulation.simulate_batch``."""
    return simulation.simulate_batch(hypothesis.parameter_rows(np.atleast_2d(theta), base), sampling, channels, max_step,
                                     search)


def evaluate_each(hypothesis: Hypothesis, thetas: Sequence[np.ndarray], recordings: Sequence[Recording],
                  max_step: float, turns: Sequence[float | np.ndarray] | None = None) -> list[np.ndarray]:
    """:func:`evaluate` of each recording at its own rows of fitted values (``thetas``, one (n, k) array each), the
    recordings of one sampling simulated in one batch on all their channels: a joint fit's few rows per recording fill
    the kernel's lanes together where each recording's alone would leave most of a block empty.  A lane's result does
    not depend on its batch, so each recording's outputs are those :func:`evaluate` gives it.  Each recording's angles
    on a shaft are turned by its ``turns`` (one per row, or one for all), else by its own :attr:`Recording.turn`."""
    turns = [r.turn for r in recordings] if turns is None else turns
    found: list[np.ndarray | None] = [None] * len(recordings)
    for sampling in dict.fromkeys(r.sampling for r in recordings):
        mine = [i for i, r in enumerate(recordings) if r.sampling == sampling]
        channels = list(dict.fromkeys(c for i in mine for c in recordings[i].channels))
        rows = [hypothesis.parameter_rows(hypothesis.turned(thetas[i], turns[i]), recordings[i].base) for i in mine]
        for i, part in zip(mine, simulation.simulate_parts(rows, sampling, channels, max_step)):
            found[i] = part[:, [channels.index(c) for c in recordings[i].channels]]
    return found


def contribution(hypothesis: Hypothesis, values: Mapping[str, float], outputs: np.ndarray, base: Mapping[str, float],
                 sampling: model.Sampling, channels: Sequence[str], sigma: np.ndarray, max_step: float) -> float:
    """What ``hypothesis`` adds to the model, as the expected log Bayes factor of telling its ``outputs`` (at its fitted
    ``values`` on ``base``) from the model without it, ½ Σ ((outputs − without) / σ)²: without, the nominal model for a
    drift, the model with the same drifts but no effect for an effect."""
    effect = effects.active().get(hypothesis.kind)
    own = effect.parameter_names() if effect is not None else values
    without = evaluate(Hypothesis(HEALTHY, HEALTHY), np.zeros((1, 0)),
                       {**base, **{p: v for p, v in values.items() if p not in own}}, sampling, channels, max_step)[0]
    return float(0.5 * np.sum(((outputs - without) / np.asarray(sigma)[:, None]) ** 2))


def fit_windows(sampling: model.Sampling) -> list[int]:
    """Sample counts of the windows a fit goes through: the record's first :data:`SEARCH_WINDOW`
    seconds, doubled until the whole record."""
    counts = [min(sampling.n_samples, max(1, round(SEARCH_WINDOW * sampling.fs)))]
    while counts[-1] < sampling.n_samples:
        counts.append(min(2 * counts[-1], sampling.n_samples))
    return counts


def fit(
    hypothesis: Hypothesis,
    data: np.ndarray,
    sigma: np.ndarray,
    base: Mapping[str, float],
    sampling: model.Sampling,
    channels: Sequence[str],
    starts: Sequence[Mapping[str, float]] = (),
    max_step: float = simulation.DEFAULT_MAX_STEP,
    seed: int = 0,
    search: bool = True,
    instruments: sensors.Instruments | None = None,
    members: Members | None = None,
    chains: int | None = None,
    stop: threading.Event | None = None,
    whole_record: bool = False,
) -> Fit:
    """Best fit of ``hypothesis`` by bounded least squares on the simulator (misfit standardized by
    ``sigma``, plus the Normal priors' terms), the best of several starts kept; with ``instruments`` the
    channels' instrument offsets, gains and delays are integrated out (:mod:`newdyn.sensors`).

    Starts: the given ``starts`` (missing names at their prior's mean or mid-range) and, unless
    ``search`` is False, on each of the first :data:`SEARCHES` windows of :func:`fit_windows` the best of the
    bank's ``members`` when given, else the best member of a differential evolution (``seed``) over the prior box, simulated
    with a search's longer steps at a slipping joint.  Each start is fitted on its
    window, then on the longer ones up to the whole record, each from the last one's optimum (the coarse pass of
    :data:`JACOBIAN_STEPS` on each, the fine one on the whole record):
    stick-slip's misfit has many local minima, and only a short window shows the truth's basin wide.  With ``chains``,
    only that many starts are followed: those that fit the longest search window best.  Once ``stop`` is set, the next
    simulation raises :class:`newdyn.concurrency.Stopped` instead (a fit run on speculation that is no longer wanted).
    With ``whole_record``, the given starts are fitted on the whole record alone, each by the coarse pass (it stays in
    the record's basin it starts in, where the short windows would lead it to the basin of the record's start), and the
    best of them by the fine pass (:func:`in_neighbouring_basins`).

    Log-evidence by the Laplace approximation in unit coordinates u = (θ − low)/(high − low):
    log Z ≈ log L(u*) + log π(u*) + (k/2) log 2π − ½ log det H − (parameters at a bound)·log 2, with H the
    Gauss–Newton Hessian of the misfit plus the Normal priors' curvature.  A parameter with a uniform
    prior that the data leave unconstrained keeps its prior's width: its diagonal gets the uniform's
    precision 12 added, so an irrelevant parameter costs no spurious Occam factor nor makes H singular.
    """
    k = len(hypothesis.priors)
    runs = []  # simulations per call (appended from the threads the starts are followed in)

    def simulate(theta, window=sampling, for_search=False):
        if stop is not None and stop.is_set():
            raise concurrency.Stopped
        runs.append(len(theta))
        return evaluate(hypothesis, theta, base, window, channels, max_step, for_search)

    if k == 0:
        best = simulate(np.zeros((1, 0)))[0]
        ll = float(likelihood.log_likelihood(data, best, sigma, instruments=instruments))
        return Fit(hypothesis, {}, best, ll, float(likelihood.reduced_chi2(data, best, sigma, instruments=instruments)), ll, sum(runs),
                   instruments=instruments)

    low = np.array([p.low for p in hypothesis.priors])
    span = np.array([p.high for p in hypothesis.priors]) - low
    normal = np.array([p.sd is not None for p in hypothesis.priors])
    mean = np.array([p.mean if p.sd is not None else 0.0 for p in hypothesis.priors])
    sd = np.array([p.sd if p.sd is not None else 1.0 for p in hypothesis.priors])

    def residuals_of(u, outputs, n_samples):  # rows (m, k) with their outputs -> (m, n_samples·C + normal priors)
        theta = low + u * span
        misfit = likelihood.standardized_residuals(data[:, :n_samples], outputs, sigma, instruments).reshape(len(u), -1)
        return np.concatenate([misfit, ((theta - mean) / sd)[:, normal]], axis=1)

    def residuals(u, n_samples, for_search=False):  # on the record's first n_samples
        return residuals_of(u, simulate(low + u * span, replace(sampling, n_samples=n_samples), for_search), n_samples)

    windows = fit_windows(sampling)
    given = [[start.get(p.name, p.mean if p.sd is not None else p.low + 0.5 * (p.high - p.low)) for p in hypothesis.priors]
             for start in starts]
    # (start, index of its first window)
    u_starts = [((np.array(theta) - low) / span, len(windows) - 1 if whole_record else 0) for theta in given]
    searched_from = None if not search else SEARCHED_FROM[0] if members is not None else SEARCHED_FROM[1]
    if search and members is not None:
        # A parameter the members do not vary (the load's phase) is where they were simulated: the base's value.
        unit = np.tile([0.0 if p.name in members.parameters else (base[p.name] - p.low) / (p.high - p.low) for p in hypothesis.priors],
                       (len(members.unit), 1))
        unit[:, [hypothesis.parameters.index(name) for name in members.parameters]] = members.unit
        for first, n_samples in enumerate(windows[:SEARCHES]):
            misfit = residuals_of(unit, members.outputs[..., :n_samples], n_samples)
            u_starts.append((unit[int(np.argmin(np.sum(misfit**2, axis=1)))], first))
    elif search:
        for first, n_samples in enumerate(windows[:SEARCHES]):
            evolved = optimize.differential_evolution(
                lambda u, n: np.sum(residuals(np.atleast_2d(u.T), n, for_search=True) ** 2, axis=1), [(0.0, 1.0)] * k, args=(n_samples,),
                vectorized=True, updating="deferred", popsize=SEARCH_POPULATION, maxiter=SEARCH_GENERATIONS, seed=seed,
                polish=False, tol=0.0,
            )
            u_starts.append((evolved.x, first))

    def follow(u0, from_window, fine=True):  # least squares through the windows from the from_window-th to the whole record
        for n_samples in windows[from_window:]:
            result = _passes(lambda rows, n=n_samples: residuals(rows, n), u0,
                             JACOBIAN_STEPS if n_samples == windows[-1] and fine else JACOBIAN_STEPS[:1])
            u0 = result.x
        return result

    starts = [(u0, first, number < len(given)) for number, (u0, first) in enumerate(u_starts)]
    if chains is not None and len(starts) > chains:
        rows = np.array([np.clip(u0, 1e-6, 1 - 1e-6) for u0, _, _ in starts])
        costs = np.sum(residuals(rows, windows[min(SEARCHES, len(windows)) - 1]) ** 2, axis=1)
        starts = [starts[i] for i in sorted(np.argsort(costs, kind="stable")[:chains])]

    def chain(u0, first, given_start):
        result = follow(u0, first)
        # A given start that is already good over the whole record (the truth, a posterior's best
        # draw) can be led off by the short windows into a minimum of the record's start only.
        if given_start and first < len(windows) - 1 and (
            result.cost > 0.5 * np.sum(residuals(np.clip(u0, 1e-6, 1 - 1e-6)[None], windows[-1]) ** 2)
        ):
            result = follow(u0, len(windows) - 1)
        return result

    # Each start's chain of least squares runs few simulations at a time: the chains side by side fill the cores.
    if whole_record:  # the coarse pass from each start shows its basin; the fine one runs in the best basin only
        followed = concurrency.in_parallel({number: lambda u0=u0, first=first: follow(u0, first, fine=False)
                                               for number, (u0, first, _) in enumerate(starts)})
        best = _passes(lambda rows: residuals(rows, windows[-1]), min(followed.values(), key=lambda result: result.cost).x,
                       JACOBIAN_STEPS[1:])
    else:
        followed = concurrency.in_parallel({number: lambda start=start: chain(*start) for number, start in enumerate(starts)})
        best = min(followed.values(), key=lambda result: result.cost)  # the first of equals, as the starts are ordered
    theta_star = low + best.x * span
    model_star = simulate(theta_star[None])[0]
    ll = float(likelihood.log_likelihood(data, model_star, sigma, instruments=instruments))
    log_evidence, at_bound, covariance = _laplace(hypothesis.priors, best, theta_star, ll)
    return Fit(
        hypothesis, hypothesis.effective_values(theta_star, base), model_star, ll,
        float(likelihood.reduced_chi2(data, model_star, sigma, n_fitted=k, instruments=instruments)), log_evidence, sum(runs), at_bound,
        covariance, instruments, searched_from,
    )


# How far a neighbouring basin is looked for along each value, in its prior box: a slipping joint's misfit over the
# whole record has a basin every 0.05-0.06 of the J2a share (docs/validation.md), one slip pattern each, and the
# search's windows end in any of them; 0.075 of the share's box (0.8 wide) is one basin over.
NEIGHBOUR_STEP = 0.075


def in_neighbouring_basins(found: Fit, data: np.ndarray, sigma: np.ndarray, base: Mapping[str, float], sampling: model.Sampling,
                           channels: Sequence[str], max_step: float = simulation.DEFAULT_MAX_STEP,
                           instruments: sensors.Instruments | None = None) -> Fit | None:
    """The best least squares on the whole record from ``found``'s values moved :data:`NEIGHBOUR_STEP` of the prior box
    up and down along each of its effect's own values, those chains side by side (None where there are none, or every
    move leaves the box): a misfit with a basin per switching pattern, which the effect's values set, and whose search
    ends in the basin its short windows favour, may fit better in another."""
    hypothesis = found.hypothesis
    effect = effects.active().get(hypothesis.kind)
    switching = [p for p in hypothesis.priors if effect is not None and p.name in effect.parameter_names()]
    starts = [{**found.values, p.name: moved} for p in switching
              for moved in (found.values[p.name] + sign * NEIGHBOUR_STEP * (p.high - p.low) for sign in (-1.0, 1.0))
              if p.low < moved < p.high]
    if not starts:
        return None
    return fit(hypothesis, data, sigma, base, sampling, channels, starts, max_step, search=False, instruments=instruments,
               whole_record=True)


def _passes(residuals, u0: np.ndarray, passes) -> optimize.OptimizeResult:
    """:func:`_least_squares` of ``residuals`` through ``passes`` (of :data:`JACOBIAN_STEPS`), each from the last one's
    optimum: the last one's result."""
    for step, tolerance in passes:
        result = _least_squares(residuals, u0, step, tolerance)
        u0 = result.x
    return result


def _least_squares(residuals, u0: np.ndarray, step: float, tolerance: float) -> optimize.OptimizeResult:
    """Bounded least squares (scipy's TRF) of ``residuals`` (rows (m, k) of unit coordinates -> (m, n)) from ``u0``
    in the unit box, with one-sided difference Jacobians of ``step`` pointing into the box, until its gains in cost
    and its steps fall below ``tolerance`` (scipy's ftol and xtol).  The residual at a point is
    computed in one batch with its Jacobian's differences: k + 1 simulations side by side in the kernel's lanes cost
    little more than one alone, and the Jacobian the optimizer asks for after accepting the point is then at hand."""
    last = {}

    def residual(u):
        h = np.where(u + step <= 1.0, step, -step)
        rows = residuals(np.vstack([u[None], u + np.diag(h)]))
        last.update(u=u.copy(), jacobian=((rows[1:] - rows[0]) / h[:, None]).T)
        return rows[0]

    def jacobian(u):
        if "u" not in last or not np.array_equal(u, last["u"]):
            residual(u)
        return last["jacobian"]

    return optimize.least_squares(residual, np.clip(u0, 1e-6, 1 - 1e-6), jac=jacobian, bounds=(0.0, 1.0), method="trf",
                                  x_scale="jac", ftol=tolerance, xtol=tolerance, max_nfev=FIT_MAX_EVALUATIONS)


def _laplace(priors: Sequence[Prior], best: optimize.OptimizeResult, theta_star: np.ndarray, ll: float):
    """(log-evidence, the parameters at a bound, posterior covariance) by the Laplace approximation around the least
    squares' optimum ``best`` in unit coordinates, whose log-likelihood is ``ll`` (see :func:`fit`); one prior per
    fitted value."""
    k = len(priors)
    span = np.array([p.high - p.low for p in priors])
    normal = np.array([p.sd is not None for p in priors])
    hessian = best.jac.T @ best.jac + np.diag(np.where(normal, 0.0, 1.0 / UNIFORM_UNIT_VARIANCE))
    _, log_det = np.linalg.slogdet(hessian)
    log_prior_u = float(log_prior(priors, theta_star[None])[0] + np.sum(np.log(span)))
    at_bound = tuple(p.name for p, a in zip(priors, best.active_mask) if a)
    log_evidence = ll + log_prior_u + 0.5 * k * math.log(2 * math.pi) - 0.5 * log_det - len(at_bound) * math.log(2)
    covariance_u = np.linalg.inv(hessian)
    covariance_u = 0.5 * (covariance_u + covariance_u.T)  # symmetric as H is, not just to rounding
    return float(log_evidence), at_bound, span[:, None] * covariance_u * span[None, :]


@dataclass(frozen=True)
class Recording:
    """One recording as a joint fit sees it: its data on its channels, their noise σ, the model values at its operating
    condition, its record and its instruments, and how far its start turned the shaft from the recording the fit's
    angles on a shaft are stated for (:meth:`Hypothesis.turned`), with that turn's standard error (0: exactly; else
    a joint fit of angles on a shaft fits the turn within it)."""

    data: np.ndarray
    sigma: np.ndarray
    base: Mapping[str, float]
    sampling: model.Sampling
    channels: tuple[str, ...]
    instruments: sensors.Instruments | None = None
    turn: float = 0.0
    turn_sd: float = 0.0


@dataclass(frozen=True)
class JointFit:
    """A hypothesis fitted to several recordings with one set of parameters: per recording its model and misfit.  A
    parameter that each recording has its own value of (``own`` of :func:`fit_joint`) is in ``own_values``, one mapping
    per recording, and not in ``values``; the covariance is over the shared values, then each recording's own in turn.
    ``turns``: how far each recording's angles on a shaft were turned (:meth:`Hypothesis.turned`)."""

    hypothesis: Hypothesis
    values: dict[str, float]
    models: tuple[np.ndarray, ...]
    log_likelihood: float
    chi2_red: tuple[float, ...]
    log_evidence: float
    n_simulations: int
    at_bound: tuple[str, ...] = ()
    covariance: np.ndarray | None = None
    instruments: tuple[sensors.Instruments | None, ...] = ()  # each recording's, once one was widened beyond its datasheets
    own_values: tuple[dict[str, float], ...] = ()
    turns: tuple[float, ...] = ()  # each recording's turn its angles on a shaft were turned by (Recording.turn, or fitted)

    @property
    def theta(self) -> np.ndarray:
        return np.array([self.values[name] for name in self.hypothesis.parameters])

    def laplace_parameters(self) -> dict:
        """The shared values' Laplace posteriors (see :func:`laplace_parameters`)."""
        return laplace_parameters(self.values, None if self.covariance is None else self.covariance[:len(self.values), :len(self.values)])

    def own_parameters(self) -> list[dict]:
        """Each recording's own values' Laplace posteriors, one mapping per recording (empty where none is its own)."""
        if self.covariance is None:
            return [{} for _ in self.own_values]
        rows, at = [], len(self.values)
        for values in self.own_values:
            block = slice(at, at + len(values))
            rows.append(laplace_parameters(values, self.covariance[block, block]))
            at += len(values)
        return rows


def fit_joint(hypothesis: Hypothesis, recordings: Sequence[Recording], starts: Sequence[Mapping[str, float | Sequence[float]]],
              max_step: float = simulation.DEFAULT_MAX_STEP, own: Sequence[str] = ()) -> JointFit:
    """Best fit of ``hypothesis`` to all ``recordings`` at once, one parameter set shared by them (the likelihood the
    product of theirs), by least squares on their whole records from each of ``starts`` (each recording's own optimum,
    say), the best kept; log-evidence and covariance by the Laplace approximation as in :func:`fit`.

    The parameters named in ``own`` are each recording's own instead (a phase: separate recordings share no clock nor
    angle mark), each copy with the parameter's prior; a start gives them one value for all recordings or one each.
    Where the hypothesis has angles on a shaft, each recording whose :attr:`Recording.turn` has a standard error has
    that turn fitted too, a Normal prior of that width around it (it turns those angles in that recording only)."""
    k, n = len(hypothesis.priors), len(recordings)
    runs = []
    shared_priors = [p for p in hypothesis.priors if p.name not in own]
    own_priors = [p for p in hypothesis.priors if p.name in own]
    uncertain = [r for r in range(n) if recordings[r].turn_sd > 0] if hypothesis.on_shaft() else []
    turn_priors = [Prior(f"turn_{r}", recordings[r].turn - math.pi, recordings[r].turn + math.pi, recordings[r].turn, recordings[r].turn_sd)
                   for r in uncertain]
    # The fitted vector: the shared values, then each recording's own in turn, then the fitted turns.
    priors = shared_priors + own_priors * n + turn_priors
    turn_at = {r: len(priors) - len(uncertain) + i for i, r in enumerate(uncertain)}
    # Per recording, where each of the hypothesis's parameters sits in the fitted vector.
    columns = [np.array([shared_priors.index(p) if p.name not in own else len(shared_priors) + r * len(own_priors) + own_priors.index(p)
                         for p in hypothesis.priors], dtype=int) for r in range(n)]

    def admissible(theta):  # admissible at every recording's condition, so that all of them run with the same values
        for r in recordings:
            theta = hypothesis.admissible_rows(theta, r.base)
        return theta

    def outputs(theta):
        runs.append(len(theta) * n)
        turns = [theta[:, turn_at[r]] if r in turn_at else recordings[r].turn for r in range(n)]
        return evaluate_each(hypothesis, [admissible(theta[:, at]) for at in columns], recordings, max_step, turns)

    def summary(theta_star):
        models = tuple(found[0] for found in outputs(theta_star[None]))
        lls = [float(likelihood.log_likelihood(r.data, m, r.sigma, instruments=r.instruments)) for r, m in zip(recordings, models)]
        chi2 = tuple(float(likelihood.reduced_chi2(r.data, m, r.sigma, n_fitted=len(priors), instruments=r.instruments))
                     for r, m in zip(recordings, models))
        return models, sum(lls), chi2

    if k == 0:
        models, ll, chi2 = summary(np.zeros(0))
        return JointFit(hypothesis, {}, models, ll, chi2, ll, sum(runs))
    low = np.array([p.low for p in priors])
    span = np.array([p.high for p in priors]) - low
    normal = np.array([p.sd is not None for p in priors])
    mean = np.array([p.mean if p.sd is not None else 0.0 for p in priors])
    sd = np.array([p.sd if p.sd is not None else 1.0 for p in priors])

    def residuals(u):  # rows (m, len(priors)) -> (m, every recording's standardized misfit + normal priors)
        theta = low + u * span
        misfits = [likelihood.standardized_residuals(r.data, found, r.sigma, r.instruments).reshape(len(u), -1)
                   for r, found in zip(recordings, outputs(theta))]
        return np.concatenate([*misfits, ((theta - mean) / sd)[:, normal]], axis=1)

    def vector(start):
        shared = [start[p.name] for p in shared_priors]
        each = [np.broadcast_to(np.asarray(start[p.name], dtype=float), (n,)) for p in own_priors]
        return np.array(shared + [values[r] for r in range(n) for values in each] + [p.mean for p in turn_priors], dtype=float)

    u_starts = [(vector(start) - low) / span for start in starts]
    chains = concurrency.in_parallel({number: lambda u0=u0: _passes(residuals, u0, JACOBIAN_STEPS) for number, u0 in enumerate(u_starts)})
    best = min((chains[number] for number in sorted(chains)), key=lambda result: result.cost)
    theta_star = low + best.x * span
    models, ll, chi2 = summary(theta_star)
    log_evidence, at_bound, covariance = _laplace(priors, best, theta_star, ll)
    if covariance is not None and uncertain:  # the values' marginal: the fitted turns are each recording's, not the machine's
        covariance = covariance[:-len(uncertain), :-len(uncertain)]
    effective = [dict(zip(hypothesis.parameters, admissible(theta_star[None, at])[0].tolist())) for at in columns]
    return JointFit(hypothesis, {p.name: effective[0][p.name] for p in shared_priors}, models, ll, chi2, log_evidence, sum(runs),
                    at_bound, covariance, own_values=tuple({p.name: e[p.name] for p in own_priors} for e in effective) if own_priors else (),
                    turns=tuple(float(theta_star[turn_at[r]]) if r in turn_at else recordings[r].turn for r in range(n)))
