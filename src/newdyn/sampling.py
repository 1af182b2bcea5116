"""Ensemble MCMC (emcee) on the batched simulator, saved as ArviZ InferenceData.

The caller supplies two vectorized functions of ``theta`` (n, ndim): the log-likelihood (one rig
simulation per row, expensive) and the log-prior (cheap, ``-inf`` outside its support).  The
likelihood is only evaluated on rows with a finite prior and is kept as an emcee blob, so no
simulation is ever repeated.  Note that emcee's stretch move proposes for half of the ensemble at a
time, so a likelihood call gets at most ``n_walkers // 2`` rows (all ``n_walkers`` on the first call).

The result is an :class:`arviz.InferenceData` with groups ``posterior`` (chain = walker, draw),
``log_likelihood`` (``y``: the *total* log-likelihood of the data per draw, not pointwise, so LOO/WAIC
do not apply), ``sample_stats`` (``lp``, ``log_likelihood``, ``acceptance_fraction`` per walker, emcee's
integrated autocorrelation time ``tau`` per parameter), and, when given, ``prior`` and
``observed_data``.  Its attributes hold the settings, the seed, the versions, the caller's attributes,
the number of ``rounds`` run (see :class:`MCMCSettings`) and the convergence diagnostics, including
``converged`` (1 or 0: netCDF has no booleans).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections.abc import Callable, Mapping, Sequence

import arviz as az
import emcee
import numpy as np
import xarray as xr

from .io import atomic_write, netcdf_attribute

log = logging.getLogger("newdyn")

__all__ = ["MCMCSettings", "diagnostics", "load", "run", "save"]

BatchFn = Callable[[np.ndarray], np.ndarray]  # theta (n, ndim) -> (n,)


class KDEMove(emcee.moves.KDEMove):
    """emcee's KDE move, with a differential-evolution proposal for the steps where the complementary
    walkers span fewer dimensions than the posterior has (a posterior far narrower in one direction
    than in the others, such as stick-slip's near its chaotic region): a Gaussian KDE has no density
    there and scipy raises."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._flat = emcee.moves.DEMove()

    def setup(self, coords):
        super().setup(coords)
        self._flat.setup(coords)

    def get_proposal(self, s, c, random):
        try:
            return super().get_proposal(s, c, random)
        except np.linalg.LinAlgError:
            return self._flat.get_proposal(s, c, random)


MOVES = {"kde": KDEMove, "stretch": emcee.moves.StretchMove, "de": emcee.moves.DEMove}

# Attribute keys that run() and diagnostics() write; a caller's ``attrs`` may not use them.
DIAGNOSTIC_KEYS = ("rhat", "ess_bulk", "ess_tail", "acceptance", "tau", "n_draws", "converged", "reason")
RESERVED_KEYS = ("mcmc_settings", "seed", "sampler", "emcee_version", "arviz_version", "rounds") + DIAGNOSTIC_KEYS


@dataclasses.dataclass(frozen=True, kw_only=True)
class MCMCSettings:
    """Run length, seed and convergence thresholds.

    The sampler runs ``n_burn + n_steps`` steps, discards the first ``n_burn`` and keeps every
    ``thin``-th of the rest, so each walker contributes ``n_steps // thin`` draws.  A run that misses
    its thresholds then goes on, ``n_steps`` more steps at a time, until it meets them or has run
    ``max_rounds`` × ``n_steps``; only then is it marked unconverged.  Every round keeps all steps
    after the burn-in.
    """

    n_walkers: int
    n_steps: int
    n_burn: int
    seed: int
    thin: int = 1
    rhat_max: float = 1.01
    ess_min: float = 400.0
    max_rounds: int = 1
    # emcee proposal. "kde" (KDEMove) decorrelates the low-dimensional, near-Gaussian calibration
    # posteriors in ~2 steps; the default stretch move needs ~18 in 1-D (measured), too slow when
    # every step simulates the rig.
    move: str = "kde"

    @classmethod
    def from_config(cls, mcmc: Mapping) -> MCMCSettings:
        """From a config block (``calibration.mcmc``'s keys: walkers, steps, burn, seed, rhat_max,
        ess_min, move, max_rounds)."""
        return cls(
            n_walkers=int(mcmc["walkers"]), n_steps=int(mcmc["steps"]), n_burn=int(mcmc["burn"]), seed=int(mcmc["seed"]),
            rhat_max=float(mcmc["rhat_max"]), ess_min=float(mcmc["ess_min"]), move=str(mcmc["move"]),
            max_rounds=int(mcmc["max_rounds"]),
        )

    def __post_init__(self):
        if self.move not in MOVES:
            raise ValueError(f"move must be one of {', '.join(MOVES)}, got {self.move!r}")
        if self.n_walkers < 2:
            raise ValueError(f"n_walkers must be >= 2, got {self.n_walkers}")
        if self.thin < 1:
            raise ValueError(f"thin must be >= 1, got {self.thin}")
        if self.n_steps < self.thin:
            raise ValueError(f"n_steps must be >= thin ({self.thin}), got {self.n_steps}")
        if self.n_burn < 0:
            raise ValueError(f"n_burn must be >= 0, got {self.n_burn}")
        if self.max_rounds < 1:
            raise ValueError(f"max_rounds must be >= 1, got {self.max_rounds}")
        if not 0 <= self.seed < 2**32:
            raise ValueError(f"seed must be in [0, 2**32), got {self.seed}")


def run(
    log_likelihood_batch: BatchFn,
    log_prior_batch: BatchFn,
    names: Sequence[str],
    initial: np.ndarray,
    settings: MCMCSettings,
    *,
    to_values: BatchFn | None = None,
    prior_samples: Mapping[str, np.ndarray] | None = None,
    observed: Mapping[str, np.ndarray | xr.DataArray] | None = None,
    attrs: Mapping[str, object] | None = None,
    move: tuple[emcee.moves.Move, str] | None = None,
) -> az.InferenceData:
    """Sample the posterior with emcee's ensemble sampler and return it as InferenceData.

    ``initial`` (n_walkers, ndim) are the start positions; all must have a finite prior.  The
    likelihood must return ``-inf``, never NaN, where a simulation fails (emcee stops on NaN).
    ``to_values`` maps rows of walker positions (n, ndim) to the variables' values when the walkers
    move in other coordinates: the posterior group and the convergence diagnostics are of the values
    (emcee's ``tau`` stays in the walkers' coordinates).
    ``prior_samples`` ({name: (draw,) or (chain, draw) array}) becomes the ``prior`` group and
    ``observed`` ({name: array or DataArray}, e.g. a measurement Dataset) the ``observed_data`` group.
    ``move`` (an emcee move and its description) replaces ``settings.move``, e.g. an independence proposal
    (:func:`independence_move`).
    Identical arguments give bit-identical chains: all randomness comes from ``settings.seed``.
    """
    names = list(names)
    initial = np.array(initial, dtype=np.float64)
    n_walkers, ndim = settings.n_walkers, len(names)
    if initial.shape != (n_walkers, ndim):
        raise ValueError(f"initial must have shape (n_walkers, ndim) = {(n_walkers, ndim)}, got {initial.shape}")
    bad = ~np.isfinite(_batch(log_prior_batch, initial, "log_prior_batch"))
    if bad.any():
        raise ValueError(f"initial positions {np.flatnonzero(bad).tolist()} are outside the prior's support")
    clash = sorted(set(attrs or {}) & set(RESERVED_KEYS))
    if clash:
        raise ValueError(f"attrs may not use the reserved keys {clash}")

    def log_prob(theta):
        # One row per walker: [log posterior, log-likelihood]; emcee keeps column 1 as the blob.
        lp = _batch(log_prior_batch, theta, "log_prior_batch")
        ll = np.full(len(theta), -np.inf)
        inside = np.isfinite(lp)
        if inside.any():  # never simulate where the prior is zero
            ll[inside] = _batch(log_likelihood_batch, theta[inside], "log_likelihood_batch")
        return np.column_stack([lp + ll, ll])

    chosen, described = move if move is not None else (MOVES[settings.move](), f"{MOVES[settings.move].__name__}()")
    sampler = emcee.EnsembleSampler(n_walkers, ndim, log_prob, vectorize=True, moves=chosen)
    # Seed emcee's own generator (sampler._random, which draws the move, the split and the stretch
    # factors), never numpy's global one: sample() sets it from the State's random_state.
    start = emcee.State(initial, random_state=np.random.RandomState(settings.seed).get_state())
    sampler.run_mcmc(start, settings.n_burn + settings.n_steps, progress=False)
    rounds = 1
    while True:
        idata = _inference_data(sampler, names, settings, to_values, prior_samples, observed)
        idata.attrs = {
            **{k: netcdf_attribute(v) for k, v in (attrs or {}).items()},
            "mcmc_settings": json.dumps(dataclasses.asdict(settings)),
            "seed": settings.seed,
            "sampler": f"emcee.EnsembleSampler(moves={described}, vectorize=True); chain = walker",
            "emcee_version": emcee.__version__,
            "arviz_version": az.__version__,
            "rounds": rounds,
        }
        checked = diagnostics(idata, settings)
        if checked["converged"] or rounds == settings.max_rounds:
            return idata
        # A run that goes on can take minutes: say how far it is, in the job's log and (a diagnosis's) terminal.
        log.info("MCMC of %s: round %d of at most %d not converged (%s); %d more steps", ", ".join(names), rounds,
                 settings.max_rounds, checked["reason"], settings.n_steps)
        sampler.run_mcmc(None, settings.n_steps, progress=False)  # continues from the last state and random state
        rounds += 1


def independence_move(draw: Callable[[np.random.RandomState, int], np.ndarray], log_density: BatchFn) -> emcee.moves.MHMove:
    """emcee's Metropolis-Hastings move with an independence proposal: every walker proposes a fresh draw of ``draw``
    (random state, n) -> (n, ndim), whose log density is ``log_density``; the posterior's ratio times the proposal's
    decides each move, so the chain targets the posterior exactly whatever the proposal, and the closer the proposal
    is to the posterior the more moves are accepted and the less consecutive draws are correlated."""

    def propose(coords, random):
        new = draw(random, len(coords))
        return new, log_density(coords) - log_density(new)  # ln q(x) - ln q(x'): emcee's factors

    return emcee.moves.MHMove(propose)


def _inference_data(sampler, names, settings, to_values, prior_samples, observed) -> az.InferenceData:
    kept = {"discard": settings.n_burn, "thin": settings.thin}
    chain = sampler.get_chain(**kept).swapaxes(0, 1)  # (walker, draw, ndim)
    if to_values is not None:
        chain = np.asarray(to_values(chain.reshape(-1, len(names))), dtype=np.float64).reshape(chain.shape)
    lp = sampler.get_log_prob(**kept).T  # (walker, draw)
    ll = sampler.get_blobs(**kept).T
    with np.errstate(invalid="ignore"):  # a walker that never moved has no autocorrelation: that parameter's tau is NaN
        tau = sampler.get_autocorr_time(quiet=True, **kept)  # in steps; emcee logs if the run is < 50 tau

    def draws(data):  # (chain, draw, ...) arrays
        return az.dict_to_dataset(data, library=emcee)

    stats = draws({"lp": lp, "log_likelihood": ll}).assign_coords(parameter=names)
    stats["acceptance_fraction"] = ("chain", sampler.acceptance_fraction)  # over burn-in and kept steps
    stats["tau"] = ("parameter", tau)
    groups = {
        "posterior": draws({name: chain[..., i] for i, name in enumerate(names)}),
        "log_likelihood": draws({"y": ll}),
        "sample_stats": stats,
    }
    if prior_samples is not None:
        groups["prior"] = az.dict_to_dataset({k: np.asarray(v) for k, v in prior_samples.items()})
    if observed is not None:
        groups["observed_data"] = xr.Dataset(
            {k: v if isinstance(v, xr.DataArray) else _data_array(k, v) for k, v in observed.items()}
        )
    return az.InferenceData(**groups)


def diagnostics(idata: az.InferenceData, settings: MCMCSettings) -> dict:
    """Convergence summary of a run; also written into ``idata.attrs`` (``converged`` as 1/0).

    ``converged`` means rhat <= ``rhat_max`` and both ESS >= ``ess_min``; otherwise ``reason`` names
    the failed checks.  ``rhat`` is the worst (max) and the ESS the worst (min) over parameters.
    """
    # ArviZ (from_emcee too) treats each walker as a chain.  Walkers of one ensemble are not
    # independent (every move uses the others' positions), so rank-R-hat and ESS are heuristics here,
    # ESS can be optimistic; emcee's own tau (n_steps / tau is the per-walker ESS) is a cross-check.
    posterior = idata.posterior
    def worst(ds, pick):
        return float(pick(np.concatenate([ds[v].values.ravel() for v in ds.data_vars])))

    result = {
        "rhat": worst(az.rhat(posterior, method="rank"), np.max),
        "ess_bulk": worst(az.ess(posterior, method="bulk"), np.min),
        "ess_tail": worst(az.ess(posterior, method="tail"), np.min),
        "acceptance": float(idata.sample_stats["acceptance_fraction"].mean()),
        "tau": float(idata.sample_stats["tau"].max()),
        "n_draws": int(posterior.sizes["chain"] * posterior.sizes["draw"]),
    }
    failed = []
    if not result["rhat"] <= settings.rhat_max:  # written so that NaN fails
        failed.append(f"rhat {result['rhat']:.4f} > {settings.rhat_max}")
    for ess in ("ess_bulk", "ess_tail"):
        if not result[ess] >= settings.ess_min:
            failed.append(f"{ess} {result[ess]:.0f} < {settings.ess_min:g}")
    result["converged"] = not failed
    result["reason"] = "; ".join(failed)
    idata.attrs.update({k: netcdf_attribute(v) for k, v in result.items()})
    return result


# The netCDF-C library reads and writes an InferenceData file several times faster than ArviZ's default h5netcdf, and
# every other NetCDF file of a study goes through it already.
NETCDF_ENGINE = "netcdf4"


def save(idata: az.InferenceData, path: str | os.PathLike) -> None:
    """Write ``idata`` to a netCDF file atomically: a reader sees the old file or the whole new one.  ArviZ's
    ``created_at`` stamps are dropped (from ``idata`` too): the wall clock is the one thing that would make two runs
    of the same study differ, and the file's provenance attributes say what made it."""
    for group in idata.groups():
        idata[group].attrs.pop("created_at", None)
    atomic_write(path, lambda tmp: idata.to_netcdf(tmp, engine=NETCDF_ENGINE))


def load(path: str | os.PathLike) -> az.InferenceData:
    """Read a file written by :func:`save`, fully into memory (no file handle stays open)."""
    with az.rc_context({"data.load": "eager"}):
        return az.from_netcdf(os.fspath(path), engine=NETCDF_ENGINE)


def _batch(fn: BatchFn, theta: np.ndarray, what: str) -> np.ndarray:
    out = np.asarray(fn(theta), dtype=np.float64)
    if out.shape != (len(theta),):
        raise ValueError(f"{what} must return shape ({len(theta)},) for theta of shape {theta.shape}, got {out.shape}")
    return out


def _data_array(name: str, values) -> xr.DataArray:
    values = np.asarray(values)
    return xr.DataArray(values, dims=[f"{name}_dim_{i}" for i in range(values.ndim)])
