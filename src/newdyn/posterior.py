"""The posterior of a fitted hypothesis's parameters from its Laplace approximation, verified: by quadrature for one
or two parameters, by importance sampling for more; where neither can be verified the caller samples by MCMC.

Both work in the Laplace approximation's whitened coordinates z, θ = θ* + s ⊙ (L z) with s the marginal sds and L L'
their correlation, so that z ~ N(0, I) under the approximation and scales as far apart as a stiffness of 1e6 and a
ratio of 1 stay well conditioned.

Quadrature (one or two parameters), where a first batch of importance sampling (below) leaves the answer unverified:
the midpoint rule on cells of side :data:`STEP` over ±:data:`HALF_WIDTH` in z (those of that batch's weighted draws'
mean and covariance where they are enough, :data:`LAID_ON_DRAWS_ESS`, to place a posterior their proposal missed),
grown where the posterior runs on past it: every cell on the lattice's edge denser than :data:`GROW_DENSITY` lays the
cells it lacks near it, so that the lattice follows a long ridge, however it runs, at the cost of the cells about it
rather than of a box around it. Where the mean and sd of every parameter agree to :data:`RESOLUTION` of its sd with
those of the lattice's points of even index (the lattice at twice the step, which costs no simulation), that is the
answer; else every cell but the lightest, which hold :data:`UNSPLIT_MASS` of it together, is split in halves, until
they agree between two splittings. Its draws are cells spread over their volume, kept in the prior's support. Where
the lattice's edge still holds more than :data:`EDGE_MASS` of the posterior, which it can only where it reached
±:data:`MAX_HALF_WIDTH`, the approximation's scale is far off, and the lattice is laid again about that lattice's own
mean and covariance. Splitting by weight, not by density, refines a thin ridge's long tail too. Exact to the lattice's
resolution whatever the posterior's shape: where a drift trades off with an effect along a thin curved ridge (cubic
coupling's γ against kT1), a Gaussian proposal's draws miss the ridge's ends and importance sampling understates the
spread.

Importance sampling (three or more): draws of a Student-t with the approximation's mean and covariance, weighted by
posterior over proposal and Pareto-smoothed (:func:`arviz.psislw`, Vehtari et al. 2024), a batch at a time until the
smoothed weights' effective sample size reaches its target.  Its k̂ says whether the estimate can be trusted (at most
:attr:`PosteriorSettings.pareto_k_max`); more draws of a proposal that misses the posterior would not mend it, and a
proposal whose batch falls short of the effective draws wastes most of its draws, so where a batch leaves the answer
unverified (k̂ too large, or too few effective draws), the proposal is fitted again to its weighted draws (their mean
and covariance, as in population Monte Carlo, Cappé et al. 2004), up to :data:`REFITS` times; the last proposal draws
batches until the answer is verified or it has drawn the most, and only its draws count.

A parameter whose conditional posterior is normal and narrow (the load's phase of a record) need not be sampled: the
caller's likelihood integrates it out for each point (:class:`Profiled`), which keeps a fault of two own values on the
quadrature, and each draw takes its value from that conditional normal.

The result is an :class:`arviz.InferenceData` shaped like :func:`newdyn.sampling.run`'s: a ``posterior`` of one chain
of equally weighted draws, ``sample_stats`` with their ``lp`` and ``log_likelihood``, a ``weighted`` group with every
lattice point or proposal inside the prior's support, its normalized log weight and log-likelihood, and attributes
``method``, ``converged`` (1 when verified, as netCDF has no booleans) and ``reason``; importance sampling adds
``pareto_k``, ``ess_bulk`` (the weights' effective sample size) and ``n_proposals``, quadrature ``step``,
``edge_mass`` and ``n_points``.  Nuisance parameters (:class:`Profiled`) are listed after the sampled ones in every group.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import xarray as xr
from scipy import stats
from scipy.special import logsumexp

from .io import netcdf_attribute

QUADRATURE, IMPORTANCE = "quadrature", "importance sampling"
MAX_QUADRATURE_PARAMETERS = 2  # a lattice in more dimensions costs more simulations than importance sampling
# Where quadrature can take over, importance sampling must leave weights of finite variance (Vehtari et al.: k̂ ≤ 0.5);
# between 0.5 and 0.7 a thin curved ridge's ends were missed and its spread understated by a third.
CHECKED_PARETO_K = 0.5
REFITS = 2  # times importance sampling (three or more parameters) may fit its proposal again to its weighted draws
BatchFn = Callable[[np.ndarray], np.ndarray]  # theta (n, k) -> (n,)

# The first lattice's step in z: two points per sd of the approximation. A posterior as wide as it or wider (a ridge the
# approximation misses is wider along it) is then exact to far below RESOLUTION; a thinner one shows in the comparison
# with the lattice at twice the step, and its cells are split.
STEP = 0.5
HALF_WIDTH = 5.0  # its first extent
MAX_HALF_WIDTH = 30.0  # beyond this the approximation is no guide: unverified
EDGE_MASS = 1e-4
# A cell of the first lattice whose weight per unit volume in z exceeds this lays the cells it lacks within GROW_REACH
# of it: a posterior the approximation matches has less at the middle of the lattice's edge at ±HALF_WIDTH (5.9e-7 in
# two dimensions, 1.5e-6 in one), and the cells on the lattice's edge hold far less than EDGE_MASS together.
GROW_DENSITY = 2e-6
GROW_REACH = 4  # cells: two sds of the approximation a growth, so that a long ridge is followed in few batches
# Effective draws of a first importance-sampling batch enough to lay the first lattice about their weighted mean and
# covariance: the variances' relative error is then about √(2/20) = 0.3, which the lattice's growth absorbs.
LAID_ON_DRAWS_ESS = 20.0
UNSPLIT_MASS = 1e-3  # the cells of least weight, together holding at most this much of the posterior, are not split
RESOLUTION = 0.1  # mean and sd of every parameter agree between two steps to this fraction of its sd: the finer's error
MAX_REFINEMENTS = 3  # is about half that, or a quarter where no prior bound cuts the lattice
# Draws a posterior that nothing rests on proposes (``verify`` off): enough to show how much of the fault the data leave
# room for, a quarter of a verified batch's simulations.
UNVERIFIED_BATCH = 250


@dataclasses.dataclass(frozen=True, kw_only=True)
class PosteriorSettings:
    """How many draws, from which proposal, and when an importance-sampled answer counts as verified."""

    seed: int
    batch: int = 1000  # draws proposed at a time, and the equally weighted draws kept
    max_draws: int = 8000  # proposals at most before an importance-sampled answer is unverified
    df: float = 5.0  # the Student-t proposal's degrees of freedom: tails heavier than the Laplace approximation's
    pareto_k_max: float = 0.7  # PSIS's bound on k̂ for a reliable estimate
    ess_min: float = 400.0  # effective sample size of the smoothed weights to reach

    @classmethod
    def from_config(cls, seed, ess_min, posterior: Mapping[str, float]) -> PosteriorSettings:
        """From a study's numbers, whole or not (a spec's JSON carries every number as a float)."""
        whole = {"batch", "max_draws"}
        return cls(seed=int(seed), ess_min=float(ess_min),
                   **{key: int(value) if key in whole else float(value) for key, value in posterior.items()})

    def __post_init__(self):
        if self.batch < 1 or self.max_draws < self.batch:
            raise ValueError(f"need 1 <= batch <= max_draws, got batch {self.batch}, max_draws {self.max_draws}")
        if not self.df > 0:
            raise ValueError(f"df must be > 0, got {self.df}")


@dataclasses.dataclass(frozen=True)
class Profiled:
    """What a likelihood that integrates nuisance parameters out itself returns for rows of the sampled ones: the
    log-likelihood where the nuisances are best, what integrating them over their prior adds to the log posterior,
    and their conditional normal's mean and sd (rows, nuisances)."""

    log_likelihood: np.ndarray
    log_integral: np.ndarray
    mean: np.ndarray
    sd: np.ndarray


@dataclasses.dataclass(frozen=True)
class _Whitened:
    """θ ↔ z of a Laplace approximation."""

    mean: np.ndarray
    scale: np.ndarray
    chol: np.ndarray

    @classmethod
    def of(cls, mean, covariance) -> _Whitened:
        scale = np.sqrt(np.diag(covariance))
        return cls(np.asarray(mean, dtype=float), scale, np.linalg.cholesky(covariance / np.outer(scale, scale)))

    def theta(self, z: np.ndarray) -> np.ndarray:
        return self.mean + (z @ self.chol.T) * self.scale

    def z(self, theta: np.ndarray) -> np.ndarray:
        return np.linalg.solve(self.chol, ((theta - self.mean) / self.scale).T).T


def sample(
    log_likelihood_batch: BatchFn,
    log_prior_batch: BatchFn,
    names: Sequence[str],
    mean: np.ndarray,
    covariance: np.ndarray,
    settings: PosteriorSettings,
    *,
    observed: Mapping[str, xr.DataArray] | None = None,
    attrs: Mapping[str, object] | None = None,
    to_values: BatchFn | None = None,
    verify: bool = True,
    nuisance: Sequence[str] = (),
    refit_below: float | None = None,
):
    """The posterior of ``names`` around the Laplace approximation (``mean``, ``covariance``): by quadrature for up to
    :data:`MAX_QUADRATURE_PARAMETERS`, else by importance sampling.  ``log_prior_batch`` is −inf outside the prior's
    support, where the likelihood is never called; the likelihood must return −inf, never NaN, where a simulation
    fails.  With ``to_values`` the functions and the approximation are in coordinates of the caller's choosing (the
    prior's density with its Jacobian), where a ridge may be straighter, and the draws are mapped to the values by it.
    Without ``verify`` (nothing the caller concludes rests on it) one batch of at most :data:`UNVERIFIED_BATCH` draws
    of importance sampling, verified only if that batch is enough, and no quadrature.  With ``nuisance`` names, the
    likelihood integrates those parameters out itself and returns a :class:`Profiled` for its rows: the posterior of
    ``names`` is sampled, and each draw's nuisance values are drawn from their conditional normal at the point it was
    drawn from.  With ``refit_below`` (a log-likelihood), a batch that leaves the answer unverified and holds a draw
    above it ends the sampling, unverified, before any proposal is fitted again: the approximation's optimum was
    missed, and the caller fits again from the best draw and samples about that fit instead."""
    whitened = _Whitened.of(mean, covariance)
    n_nuisance = len(nuisance)

    def log_posterior(theta):  # (log prior + log-likelihood, log-likelihood, nuisances' (means, sds)), inside the support
        lp = np.asarray(log_prior_batch(theta), dtype=float)
        ll, conditional = np.full(len(theta), -np.inf), np.full((len(theta), 2 * n_nuisance), np.nan)
        inside = np.isfinite(lp)
        if inside.any() and n_nuisance:
            profiled = log_likelihood_batch(theta[inside])
            ll[inside] = profiled.log_likelihood
            lp[inside] += profiled.log_integral
            conditional[inside] = np.hstack([profiled.mean, profiled.sd])
        elif inside.any():
            ll[inside] = log_likelihood_batch(theta[inside])
        return lp + ll, ll, conditional

    checkable = verify and len(names) <= MAX_QUADRATURE_PARAMETERS
    unverified = min(settings.batch, UNVERIFIED_BATCH)
    effort = settings if verify else dataclasses.replace(settings, batch=unverified, max_draws=unverified)
    theta, log_weight, log_post, log_like, conditional, cells, found = _importance(
        log_posterior, whitened, dataclasses.replace(effort, pareto_k_max=min(effort.pareto_k_max, CHECKED_PARETO_K))
        if checkable else effort, refits=REFITS if verify and not checkable else 0,
        refit_below=refit_below)
    if checkable and not found["converged"]:
        tried = f"importance sampling first: {found['reason']}"
        # Its weighted draws place the posterior better than the approximation their proposal missed (as a proposal
        # fitted again to them would): the first lattice is laid about them where they are enough.
        drawn = _recentred(theta, log_weight) if found["ess_bulk"] >= LAID_ON_DRAWS_ESS else None
        laid, about = (drawn, "the importance sampler's draws") if drawn is not None else (whitened, "the Laplace approximation")
        theta, log_weight, log_post, log_like, conditional, cells, found = _quadrature(
            log_posterior, laid, _ridge(laid.z(theta), np.exp(log_weight)))
        recentred = _recentred(theta, log_weight) if found["edge_mass"] > EDGE_MASS else None
        if recentred is not None:
            tried += f"; quadrature about {about}: {found['reason']}"
            theta, log_weight, log_post, log_like, conditional, cells, found = _quadrature(
                log_posterior, recentred, _ridge(recentred.z(theta), np.exp(log_weight)))
        found["tried"] = tried
    rng = np.random.default_rng(settings.seed)
    picked = _systematic(np.exp(log_weight), settings.batch, rng)
    draws = theta[picked]
    if cells is not None:  # cell centres spread over their cells, where that stays inside the support
        centres, sides, theta_at = cells
        spread = theta_at(centres[picked] + rng.uniform(-0.5, 0.5, draws.shape) * sides[picked][:, None])
        inside = np.isfinite(np.asarray(log_prior_batch(spread), dtype=float))
        draws = np.where(inside[:, None], spread, draws)
    kept = np.isfinite(log_weight)
    points = theta[kept]
    if to_values is not None:
        draws, points = (np.asarray(to_values(x), dtype=float) for x in (draws, points))
    if n_nuisance:  # drawn where each draw was drawn from; a point keeps its conditional mean
        means, sds = conditional[:, :n_nuisance], conditional[:, n_nuisance:]
        draws = np.hstack([draws, means[picked] + sds[picked] * rng.standard_normal((len(picked), n_nuisance))])
        points = np.hstack([points, means[kept]])
    return _inference_data([*names, *nuisance], draws, log_post[picked], log_like[picked], points, log_weight[kept],
                           log_like[kept], {**(attrs or {}), **found}, observed, settings)


def _ridge(z: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Where a posterior of two parameters runs in z: the quadratic z₂ ≈ c₀ + c₁ z₁ + c₂ z₁² through weighted draws of
    it (their weights need not be right, only where they are large), as coefficients c; none for one parameter."""
    if z.shape[1] != 2:
        return np.zeros(0)
    basis = np.column_stack([np.ones(len(z)), z[:, 0], z[:, 0] ** 2])
    return np.linalg.lstsq(basis * np.sqrt(weights)[:, None], z[:, 1] * np.sqrt(weights), rcond=None)[0]


def _quadrature(log_posterior, whitened: _Whitened, ridge: np.ndarray):
    """The posterior by the midpoint rule on cells in sheared coordinates u, z = (u₁, u₂ + ridge(u₁)), which bend the
    lattice along the posterior's ``ridge`` at unit Jacobian (module docstring): (cell centres θ, normalized log
    weights, log posteriors, log-likelihoods, nuisances' conditionals, (cell centres u, sides, u → θ), what it found).  A cell's weight is its density times its
    volume, so cells of every size sum together: the split ones where the posterior has weight, the first beyond."""
    k = len(whitened.mean)

    def theta_at(u):
        if not ridge.size:
            return whitened.theta(u)
        return whitened.theta(np.column_stack([u[:, 0], u[:, 1] + ridge @ np.stack([np.ones(len(u)), u[:, 0], u[:, 0] ** 2])]))
    finest = STEP / 2 ** (MAX_REFINEMENTS + 1)  # the children of the last refinement sit on this lattice
    known: dict[tuple[int, ...], np.ndarray] = {}  # (log posterior, log-likelihood, nuisances' conditional) by lattice index

    def evaluate(z):
        keys = [tuple(row) for row in np.rint(z / finest).astype(np.int64)]
        new = list({key: i for i, key in enumerate(keys) if key not in known}.values())
        if new:
            post, like, conditional = log_posterior(theta_at(z[new]))
            known.update({keys[i]: np.concatenate([[post[j], like[j]], conditional[j]]) for j, i in enumerate(new)})
        return np.array([known[key] for key in keys], dtype=float).reshape(len(z), -1)

    index = np.stack(np.meshgrid(*[np.arange(-round(HALF_WIDTH / STEP), round(HALF_WIDTH / STEP) + 1)] * k, indexing="ij"),
                     axis=-1).reshape(-1, k)
    values = evaluate(index * STEP)
    while True:  # grow the first lattice where the posterior runs on past it
        heavy = _normalized(values[:, 0]) > GROW_DENSITY * STEP**k
        grown = _beyond(index, heavy & _on_edge(index), GROW_REACH, round(MAX_HALF_WIDTH / STEP))
        if not len(grown):
            break
        index = np.concatenate([index, grown])
        values = np.concatenate([values, evaluate(grown * STEP)])
    z = index * STEP
    edge_mass = float(_normalized(values[:, 0])[_on_edge(index)].sum())
    size = np.full(len(z), STEP)  # each cell's side
    moments = _moments(theta_at(z), values[:, 0] + k * np.log(size))
    # The lattice at twice the step is the points of even index: where its moments agree with the full lattice's, the
    # full one's error is as small as a split one's would be when they agree with it, at no simulation more.
    even = np.all(np.rint(z / STEP) % 2 == 0, axis=1)
    converged, step = _settled(_moments(theta_at(z[even]), values[even, 0] + k * np.log(2 * STEP)), moments), STEP
    children = np.stack(np.meshgrid(*[np.array([-0.25, 0.25])] * k, indexing="ij"), axis=-1).reshape(-1, k)
    for _ in range(0 if converged else MAX_REFINEMENTS):  # split the cells where the posterior peaks, until the moments settle
        log_weight = values[:, 0] + k * np.log(size)
        order = np.argsort(-log_weight)
        held = np.cumsum(_normalized(log_weight[order]))
        split = np.zeros(len(z), dtype=bool)
        split[order[: np.searchsorted(held, 1.0 - UNSPLIT_MASS) + 1]] = True
        split &= size == step
        step /= 2
        new_z = (z[split][:, None, :] + children[None] * size[split][:, None, None]).reshape(-1, k)
        z = np.concatenate([z[~split], new_z])
        values = np.concatenate([values[~split], evaluate(new_z)])
        size = np.concatenate([size[~split], np.full(len(new_z), step)])
        refined = _moments(theta_at(z), values[:, 0] + k * np.log(size))
        converged, moments = _settled(moments, refined), refined
        if converged:
            break
    failed = []
    if edge_mass > EDGE_MASS:
        failed.append(f"{edge_mass:.2g} of the posterior at the lattice's edge {MAX_HALF_WIDTH:g} sds from its centre")
    if not converged:
        failed.append(f"mean or sd still moved by more than {RESOLUTION:g} sd when the cells were split to {step:g} sd")
    found = {"method": QUADRATURE, "converged": not failed, "reason": "; ".join(failed), "step": step, "edge_mass": edge_mass,
             "n_points": len(known)}
    return (theta_at(z), _normalized(values[:, 0] + k * np.log(size), log=True), values[:, 0], values[:, 1], values[:, 2:],
            (z, size, theta_at), found)


def _on_edge(index: np.ndarray) -> np.ndarray:
    """Which cells of a lattice (their integer indices, (n, k)) miss a neighbour along an axis."""
    known = set(map(tuple, index.tolist()))
    edge = np.zeros(len(index), dtype=bool)
    for step in np.vstack([np.eye(index.shape[1], dtype=np.int64), -np.eye(index.shape[1], dtype=np.int64)]):
        edge |= np.array([cell not in known for cell in map(tuple, (index + step).tolist())])
    return edge


def _beyond(index: np.ndarray, sources: np.ndarray, reach: int, limit: int) -> np.ndarray:
    """The cells within ``reach`` along every axis of the ``sources`` rows of a lattice's ``index`` that it lacks, each
    index within ±``limit``."""
    k = index.shape[1]
    offsets = np.stack(np.meshgrid(*[np.arange(-reach, reach + 1)] * k, indexing="ij"), axis=-1).reshape(-1, k)
    near = (index[sources][:, None, :] + offsets[None]).reshape(-1, k)
    near = np.unique(near[np.all(np.abs(near) <= limit, axis=1)], axis=0)
    known = set(map(tuple, index.tolist()))
    return near[np.array([cell not in known for cell in map(tuple, near.tolist())], dtype=bool)].reshape(-1, k)


def _settled(coarser: tuple[np.ndarray, np.ndarray], finer: tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether two lattices' (means, sds) of every parameter agree to :data:`RESOLUTION` of the finer's sd."""
    return bool(np.all(np.abs(finer[0] - coarser[0]) <= RESOLUTION * finer[1])
                and np.all(np.abs(finer[1] - coarser[1]) <= RESOLUTION * finer[1]))


def _importance(log_posterior, whitened: _Whitened, settings: PosteriorSettings, refits: int = 0,
                refit_below: float | None = None):
    """Importance sampling from a Student-t around the approximation, its proposal fitted again to its weighted draws
    after a batch that leaves the answer unverified, up to ``refits`` times (module docstring), but not after one that
    holds a log-likelihood above ``refit_below`` (:func:`sample`): (the last proposal's θ, smoothed normalized log
    weights, log posteriors, log-likelihoods, nuisances' conditionals, None, what it found)."""
    missed, proposal = [], "the Laplace approximation"
    one_batch = dataclasses.replace(settings, max_draws=settings.batch)
    while True:
        effort = settings if len(missed) == refits else one_batch
        theta, log_weight, log_post, log_like, conditional, found = _importance_from(log_posterior, whitened, effort, proposal)
        if found["converged"] or len(missed) == refits:
            break
        if refit_below is not None and np.max(log_like) > refit_below:
            found["reason"] += "; a draw fits better than the approximation's optimum"
            break
        refitted = _recentred(theta, log_weight)
        if refitted is None:
            break
        missed.append(f"{found['reason']} ({found['n_proposals']} draws)")
        whitened, proposal = refitted, "the proposal fitted again"
    found["refits"] = len(missed)
    if missed:
        found["tried"] = "proposal fitted again to its weighted draws after: " + "; then ".join(missed)
    return theta, log_weight, log_post, log_like, conditional, None, found


def _importance_from(log_posterior, whitened: _Whitened, settings: PosteriorSettings, proposal: str):
    """Importance sampling from a Student-t with ``whitened``'s mean and covariance (``proposal`` says whose, for the
    reason it may give): (proposals θ, smoothed normalized log weights, log posteriors, log-likelihoods, nuisances'
    conditionals, what it found)."""
    import arviz as az

    k = len(whitened.mean)
    student_t = stats.multivariate_t(loc=np.zeros(k), shape=np.eye(k), df=settings.df)
    rng = np.random.default_rng(settings.seed)
    theta, log_q, log_post, log_like, conditional = np.empty((0, k)), np.empty(0), np.empty(0), np.empty(0), None
    while True:
        t = np.asarray(student_t.rvs(settings.batch, random_state=rng)).reshape(settings.batch, k)
        post, like, more = log_posterior(whitened.theta(t))
        conditional = more if conditional is None else np.vstack([conditional, more])
        theta = np.vstack([theta, whitened.theta(t)])
        log_q, log_post, log_like = (np.concatenate([a, b]) for a, b in ((log_q, student_t.logpdf(t).reshape(-1)),
                                                                          (log_post, post), (log_like, like)))
        raw = log_post - log_q
        finite = np.isfinite(raw)
        log_weight = np.full(raw.shape, -np.inf)
        pareto_k, ess = math.inf, 0.0
        if finite.sum() >= 2:
            log_weight[finite], pareto_k = az.psislw(raw[finite])
            ess = float(1.0 / np.sum(np.exp(2 * log_weight[finite])))
        failed = []
        if not pareto_k <= settings.pareto_k_max:
            failed.append(f"pareto_k {pareto_k:.2f} > {settings.pareto_k_max:g}: {proposal} misses the posterior")
        if not ess >= settings.ess_min:
            failed.append(f"ess {ess:.0f} < {settings.ess_min:g}")
        if not failed or len(theta) + settings.batch > settings.max_draws or pareto_k > settings.pareto_k_max:
            break
    found = {"method": IMPORTANCE, "converged": not failed, "reason": "; ".join(failed), "pareto_k": float(pareto_k),
             "ess_bulk": ess, "n_proposals": len(theta)}
    return theta, log_weight, log_post, log_like, conditional, found


def _normalized(log_values: np.ndarray, log: bool = False) -> np.ndarray:
    """Weights ∝ exp(log_values) summing to 1 (their logs with ``log``); −inf stays weightless."""
    log_weight = log_values - logsumexp(log_values)
    return log_weight if log else np.exp(log_weight)


def _moments(theta: np.ndarray, log_values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, sd) per parameter under weights ∝ exp(log_values)."""
    weight = _normalized(log_values)
    mean = weight @ theta
    return mean, np.sqrt(weight @ (theta - mean) ** 2)


def _recentred(theta: np.ndarray, log_weight: np.ndarray) -> _Whitened | None:
    """Whitened coordinates about the mean and covariance of points ``theta`` (n, k) under normalized log weights:
    lattice points where the posterior reaches past the widest lattice about the Laplace approximation, whose scale
    is far off (those of all but the edge's mass are near the posterior's), or the draws of a proposal that missed it.
    None where the weights span fewer than k dimensions: no lattice nor proposal can be laid about them."""
    weight = np.exp(log_weight)
    covariance = np.cov(theta, rowvar=False, aweights=weight, ddof=0).reshape(theta.shape[1], theta.shape[1])
    if not np.all(np.diag(covariance) > 0):
        return None
    try:
        return _Whitened.of(weight @ theta, covariance)
    except np.linalg.LinAlgError:
        return None


def _systematic(weights: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``n`` equally weighted draws resampled from ``weights`` (normalized), systematically: each
    draw is picked within one of its expected count."""
    edges = np.cumsum(weights)
    edges[-1] = 1.0
    return np.searchsorted(edges, (rng.uniform() + np.arange(n)) / n)


def _inference_data(names, draws, log_post, log_like, points, log_weight, point_log_like, found, observed, settings):
    import arviz as az

    def chain(values):  # (draw,) -> (chain, draw)
        return np.asarray(values)[None]

    groups = {
        "posterior": az.dict_to_dataset({name: chain(draws[:, i]) for i, name in enumerate(names)}),
        "sample_stats": az.dict_to_dataset({"lp": chain(log_post), "log_likelihood": chain(log_like)}),
        "weighted": xr.Dataset(
            {**{name: ("point", points[:, i]) for i, name in enumerate(names)},
             "log_weight": ("point", log_weight), "log_likelihood": ("point", point_log_like)},
            attrs={"long_name": "every lattice point or proposal inside the prior's support, with its normalized log weight"},
        ),
    }
    if observed is not None:
        groups["observed_data"] = xr.Dataset(dict(observed))
    idata = az.InferenceData(**groups)
    idata.attrs = {
        **{key: netcdf_attribute(value) for key, value in found.items()},
        "posterior_settings": json.dumps(dataclasses.asdict(settings)),
        "arviz_version": az.__version__,
        "n_draws": len(draws),
    }
    if found["method"] == IMPORTANCE:
        fitted = "the Laplace approximation" if not found["refits"] else "the weighted draws of the proposal before it"
        idata.attrs["proposal"] = f"multivariate Student-t (df {settings.df:g}) with the mean and covariance of {fitted}"
    return idata
