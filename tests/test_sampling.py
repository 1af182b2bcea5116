"""newdyn.sampling on cheap, vectorized analytic log-probabilities (each test runs in a few seconds)."""

import json
import logging
import warnings

import arviz as az
import emcee
import numpy as np
import pytest
import xarray as xr

from newdyn import sampling


@pytest.fixture(autouse=True)
def _quiet_emcee_autocorr_warning():
    # Short test chains make emcee log "chain is shorter than 50 times the autocorrelation time".
    logging.getLogger("emcee.autocorr").setLevel(logging.ERROR)


def mean_and_mcse(z):
    """Mean of a (chain, draw) series and its Monte-Carlo standard error from ArviZ's ESS of the mean."""
    return float(z.mean()), float(z.std() / np.sqrt(az.ess(z, method="mean")))


def draws(idata, name):
    return idata.posterior[name].values  # (chain, draw)


# (a) conjugate 1-D Gaussian: y_i ~ N(theta, SIGMA^2), theta ~ N(0, TAU0^2)
Y = np.array([0.8, 1.7, 0.4, 1.1, 1.9, 0.6, 1.3, 1.0, 0.2, 1.5])
SIGMA, TAU0 = 1.0, 2.0


def conjugate_loglik(theta):
    return -0.5 * np.sum((Y[None, :] - theta[:, :1]) ** 2, axis=1) / SIGMA**2


def conjugate_logprior(theta):
    return -0.5 * (theta[:, 0] / TAU0) ** 2


def test_conjugate_gaussian_matches_closed_form_and_converges():
    settings = sampling.MCMCSettings(n_walkers=8, n_steps=1500, n_burn=100, seed=1)
    start = np.random.default_rng(0).normal(0.0, 1.0, size=(8, 1))
    idata = sampling.run(conjugate_loglik, conjugate_logprior, ["theta"], start, settings)

    precision = 1 / TAU0**2 + len(Y) / SIGMA**2
    mean_exact, sd_exact = Y.sum() / SIGMA**2 / precision, precision**-0.5
    theta = draws(idata, "theta")
    mean, mean_se = mean_and_mcse(theta)
    var, var_se = mean_and_mcse((theta - mean) ** 2)
    sd, sd_se = np.sqrt(var), var_se / (2 * np.sqrt(var))  # delta method
    assert abs(mean - mean_exact) < 4 * mean_se
    assert abs(sd - sd_exact) < 4 * sd_se

    diag = sampling.diagnostics(idata, settings)
    assert diag["converged"], diag["reason"]
    assert diag["reason"] == ""
    assert diag["n_draws"] == 8 * settings.n_steps
    assert 0.2 < diag["acceptance"] < 0.95
    assert 1 < diag["tau"] < settings.n_steps / 50  # emcee's own criterion: run > 50 tau

    # the stored blob is the log-likelihood at the stored position, lp = prior + likelihood
    flat = theta.reshape(-1, 1)
    np.testing.assert_allclose(idata.log_likelihood["y"].values.ravel(), conjugate_loglik(flat), rtol=1e-12)
    np.testing.assert_allclose(
        idata.sample_stats["lp"].values.ravel(), conjugate_logprior(flat) + conjugate_loglik(flat), rtol=1e-12
    )


def test_an_independence_proposal_far_from_the_posterior_still_samples_it_exactly():
    """The Metropolis-Hastings correction, not the proposal, sets what the chain samples: a Student-t proposal centred
    one posterior sd off and twice as wide gives the closed-form posterior, and the moves it makes are recorded."""
    precision = 1 / TAU0**2 + len(Y) / SIGMA**2
    mean_exact, sd_exact = Y.sum() / SIGMA**2 / precision, precision**-0.5
    centre, scale, df = mean_exact + sd_exact, 2 * sd_exact, 5.0
    from scipy import stats

    move = sampling.independence_move(
        lambda random, n: stats.t.rvs(df, centre, scale, size=(n, 1), random_state=random),
        lambda x: stats.t.logpdf(x[:, 0], df, centre, scale),
    )
    settings = sampling.MCMCSettings(n_walkers=8, n_steps=1500, n_burn=20, seed=1)
    start = np.random.default_rng(0).normal(0.0, 1.0, size=(8, 1))
    idata = sampling.run(conjugate_loglik, conjugate_logprior, ["theta"], start, settings, move=(move, "t proposal"))
    theta = draws(idata, "theta")
    mean, mean_se = mean_and_mcse(theta)
    var, var_se = mean_and_mcse((theta - mean) ** 2)
    sd, sd_se = np.sqrt(var), var_se / (2 * np.sqrt(var))
    assert abs(mean - mean_exact) < 4 * mean_se
    assert abs(sd - sd_exact) < 4 * sd_se
    assert 0.2 < float(idata.sample_stats["acceptance_fraction"].mean()) < 0.9  # rejections did the correcting
    assert "t proposal" in idata.attrs["sampler"]


def short_run(seed):
    settings = sampling.MCMCSettings(n_walkers=16, n_steps=200, n_burn=50, seed=seed)
    start = np.random.default_rng(0).normal(0.0, 1.0, size=(16, 1))
    return sampling.run(conjugate_loglik, conjugate_logprior, ["theta"], start, settings)


def test_same_seed_gives_bit_identical_chains_different_seed_does_not():
    first = short_run(seed=7)
    np.random.seed(12345)  # numpy's global generator must play no part
    np.random.uniform(size=99)
    again = short_run(seed=7)
    other = short_run(seed=8)
    np.testing.assert_array_equal(draws(first, "theta"), draws(again, "theta"))
    np.testing.assert_array_equal(first.sample_stats["lp"].values, again.sample_stats["lp"].values)
    assert not np.array_equal(draws(first, "theta"), draws(other, "theta"))


def test_too_short_run_is_reported_not_converged():
    settings = sampling.MCMCSettings(n_walkers=16, n_steps=30, n_burn=0, seed=3)
    start = 5.0 + 0.01 * np.random.default_rng(0).normal(size=(16, 1))  # tight ball far from the posterior
    idata = sampling.run(conjugate_loglik, conjugate_logprior, ["theta"], start, settings)
    diag = sampling.diagnostics(idata, settings)
    assert not diag["converged"]
    assert "ess_bulk" in diag["reason"]
    assert idata.attrs["converged"] == 0
    assert idata.attrs["reason"] == diag["reason"]


def test_a_walker_that_never_moves_gives_a_nan_autocorrelation_time_without_a_warning_and_no_convergence():
    # A single point of high density: the walker that starts on it rejects every proposal, the others move freely.
    def spike(theta):
        return np.where(theta[:, 0] == 0.3, 0.0, -1e3)

    settings = sampling.MCMCSettings(n_walkers=8, n_steps=40, n_burn=0, seed=4)
    start = np.concatenate([[0.3], np.linspace(-0.5, 0.5, 7)])[:, None]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        idata = sampling.run(spike, lambda theta: np.zeros(len(theta)), ["theta"], start, settings)
    assert np.all(draws(idata, "theta")[0] == 0.3) and np.ptp(draws(idata, "theta")[1:], axis=1).min() > 0
    assert np.isnan(idata.sample_stats["tau"].values[0])
    assert not sampling.diagnostics(idata, settings)["converged"]


def test_a_run_that_misses_its_thresholds_goes_on_in_rounds_and_keeps_its_first_steps():
    precision = 1 / TAU0**2 + len(Y) / SIGMA**2
    start = np.random.default_rng(0).normal(Y.sum() / SIGMA**2 / precision, precision**-0.5, size=(16, 1))
    base = {"n_walkers": 16, "n_steps": 20, "n_burn": 0, "seed": 3}  # 320 draws from the posterior: ESS < 400
    one = sampling.run(conjugate_loglik, conjugate_logprior, ["theta"], start, sampling.MCMCSettings(**base))
    more = sampling.run(conjugate_loglik, conjugate_logprior, ["theta"], start, sampling.MCMCSettings(**base, max_rounds=20))
    assert not one.attrs["converged"] and one.attrs["rounds"] == 1
    rounds = int(more.attrs["rounds"])
    assert more.attrs["converged"] == 1 and 1 < rounds < 20  # it stops at the first round that meets them
    assert draws(more, "theta").shape == (16, 20 * rounds)
    np.testing.assert_array_equal(draws(more, "theta")[:, :20], draws(one, "theta"))  # one chain, continued
    shorter = sampling.run(conjugate_loglik, conjugate_logprior, ["theta"], start, sampling.MCMCSettings(**base, max_rounds=rounds - 1))
    assert shorter.attrs["rounds"] == rounds - 1 and shorter.attrs["converged"] == 0  # and runs no further than allowed


def test_rounds_stop_at_max_rounds_and_the_run_is_marked_unconverged_and_each_round_going_on_is_logged(caplog):
    settings = sampling.MCMCSettings(n_walkers=8, n_steps=20, n_burn=10, seed=1, ess_min=1e9, max_rounds=3)
    with caplog.at_level("INFO", logger="newdyn"):
        idata = sampling.run(conjugate_loglik, conjugate_logprior, ["theta"], np.zeros((8, 1)) + 0.1 * np.arange(8)[:, None], settings)
    assert idata.attrs["rounds"] == 3 and idata.attrs["converged"] == 0
    assert idata.attrs["n_draws"] == 8 * 60
    assert "ess_bulk" in idata.attrs["reason"]
    going_on = [r.getMessage() for r in caplog.records if "not converged" in r.getMessage()]
    assert [line.split(":")[1].split(" not")[0] for line in going_on] == [" round 1 of at most 3", " round 2 of at most 3"]
    assert all(line.startswith("MCMC of theta:") and "ess_bulk" in line and "20 more steps" in line for line in going_on)


class GuardedLikelihood:
    """A 'simulator' that must never see a parameter outside the unit square."""

    def __init__(self):
        self.batch_sizes = []

    def __call__(self, theta):
        assert theta.ndim == 2 and len(theta) > 0
        assert np.all((theta > 0) & (theta < 1)), f"likelihood called outside the prior: {theta}"
        self.batch_sizes.append(len(theta))
        return -0.5 * np.sum(((theta - [0.02, 0.98]) / 0.1) ** 2, axis=1)  # mass piled on two walls


class UnitSquarePrior:
    def __init__(self):
        self.rows = self.outside = 0

    def __call__(self, theta):
        inside = np.all((theta > 0) & (theta < 1), axis=1)
        self.rows += len(theta)
        self.outside += int((~inside).sum())
        return np.where(inside, 0.0, -np.inf)


def test_likelihood_is_never_called_outside_the_prior():
    likelihood, prior = GuardedLikelihood(), UnitSquarePrior()
    settings = sampling.MCMCSettings(n_walkers=16, n_steps=300, n_burn=50, seed=5)
    start = np.random.default_rng(1).uniform(0.3, 0.7, size=(16, 2))
    idata = sampling.run(likelihood, prior, ["a", "b"], start, settings)

    assert prior.outside > 100  # many proposals left the support ...
    assert sum(likelihood.batch_sizes) == prior.rows - prior.outside - 16  # ... none was simulated
    # (the 16 is run()'s prior check of the start positions, which simulates nothing)
    assert likelihood.batch_sizes[0] == 16  # then emcee proposes for half of the ensemble at a time
    assert max(likelihood.batch_sizes[1:]) <= 8
    for name in ("a", "b"):
        assert np.all((draws(idata, name) > 0) & (draws(idata, name) < 1))
    assert np.all(np.isfinite(idata.log_likelihood["y"].values))


def test_inference_data_round_trips_through_netcdf(tmp_path):
    rng = np.random.default_rng(2)
    settings = sampling.MCMCSettings(n_walkers=8, n_steps=200, n_burn=20, seed=11, thin=2)
    measured = xr.DataArray(Y[None, :], dims=("channel", "time"), coords={"channel": ["w1"], "time": np.arange(10)})
    idata = sampling.run(
        conjugate_loglik,
        conjugate_logprior,
        ["theta"],
        rng.normal(size=(8, 1)),
        settings,
        prior_samples={"theta": rng.normal(0.0, TAU0, size=500)},
        observed={"y": measured, "sigma": np.array([SIGMA])},
        attrs={"scenario": "kT1_up", "operating": {"speed_rpm": 1200.0}, "snr_db": 40.0},
    )
    path = tmp_path / "posterior.nc"
    sampling.save(idata, path)
    sampling.save(idata, path)  # overwriting works
    loaded = sampling.load(path)
    sampling.save(loaded, path)  # load() holds no handle on the file it read

    assert [p.name for p in tmp_path.iterdir()] == ["posterior.nc"]  # no temporary file left behind
    groups = {"posterior", "prior", "log_likelihood", "observed_data", "sample_stats"}
    assert set(loaded.groups()) == groups
    for group in groups:
        xr.testing.assert_identical(loaded[group], idata[group])
    assert loaded.posterior.sizes == {"chain": 8, "draw": 100}
    assert loaded.observed_data["y"].dims == ("channel", "time")
    assert set(loaded.sample_stats.data_vars) == {"lp", "log_likelihood", "acceptance_fraction", "tau"}
    assert loaded.sample_stats["tau"].sel(parameter="theta") > 0

    assert loaded.attrs == idata.attrs
    assert loaded.attrs["converged"] in (0, 1)
    assert json.loads(loaded.attrs["operating"]) == {"speed_rpm": 1200.0}
    assert json.loads(loaded.attrs["mcmc_settings"])["seed"] == 11
    assert loaded.attrs["emcee_version"] and loaded.attrs["arviz_version"]


def test_correlated_2d_gaussian_means_and_covariance():
    mu = np.array([1.0, -2.0])
    cov = np.array([[1.0, 0.4], [0.4, 0.25]])  # correlation 0.8
    inv = np.linalg.inv(cov)

    def loglik(theta):
        d = theta - mu
        return -0.5 * np.einsum("ni,ij,nj->n", d, inv, d)

    def logprior(theta):  # flat on a wide box
        return np.where(np.all(np.abs(theta) < 50, axis=1), 0.0, -np.inf)

    settings = sampling.MCMCSettings(n_walkers=16, n_steps=800, n_burn=100, seed=2)
    start = np.random.default_rng(3).normal(size=(16, 2))
    idata = sampling.run(loglik, logprior, ["a", "b"], start, settings)

    x = np.stack([draws(idata, "a"), draws(idata, "b")], axis=-1)  # (chain, draw, 2)
    for i in range(2):
        mean, se = mean_and_mcse(x[..., i])
        assert abs(mean - mu[i]) < 4 * se
    centred = x - x.mean(axis=(0, 1))
    for i, j in [(0, 0), (0, 1), (1, 1)]:
        c, se = mean_and_mcse(centred[..., i] * centred[..., j])
        assert abs(c - cov[i, j]) < 4 * se


def test_bad_inputs_fail_before_sampling():
    settings = sampling.MCMCSettings(n_walkers=8, n_steps=10, n_burn=0, seed=0)
    good = np.random.default_rng(0).normal(size=(8, 1))

    def run(start, **kw):
        return sampling.run(conjugate_loglik, conjugate_logprior, ["theta"], start, settings, **kw)

    with pytest.raises(ValueError, match="shape"):
        run(good[:4])
    with pytest.raises(ValueError, match="support"):
        sampling.run(conjugate_loglik, lambda t: np.where(t[:, 0] > 0, 0.0, -np.inf), ["theta"], good, settings)
    with pytest.raises(ValueError, match="reserved"):
        run(good, attrs={"converged": 1})
    with pytest.raises(ValueError, match="log_likelihood_batch must return shape"):
        sampling.run(lambda t: np.zeros((len(t), 1)), conjugate_logprior, ["theta"], good, settings)
    with pytest.raises(ValueError, match="seed"):
        sampling.MCMCSettings(n_walkers=8, n_steps=10, n_burn=0, seed=-1)


def test_every_move_samples_the_same_posterior():
    """The proposal is a setting; each one must leave the posterior unchanged (here N(1, 0.5²))."""
    def log_like(theta):
        return -0.5 * ((theta[:, 0] - 1.0) / 0.5) ** 2

    def flat(theta):
        return np.zeros(len(theta))

    initial = np.random.default_rng(0).normal(1.0, 0.5, (16, 1))
    for move in sampling.MOVES:
        settings = sampling.MCMCSettings(n_walkers=16, n_steps=1500, n_burn=100, seed=4, move=move)
        draws = sampling.run(log_like, flat, ["x"], initial, settings).posterior["x"].values.ravel()
        assert abs(draws.mean() - 1.0) < 0.05 and abs(draws.std() - 0.5) < 0.05, move


def test_kde_move_proposes_where_the_walkers_span_fewer_dimensions_than_the_posterior():
    """Walkers that have collapsed onto a line (a posterior far narrower across it than along it): a
    Gaussian KDE of them has no density and scipy raises; the move proposes by differential evolution
    there, along the line, instead of ending the run."""
    rng = np.random.default_rng(1)
    walkers = np.column_stack([rng.normal(size=8), np.zeros(8)])
    others = [np.column_stack([rng.normal(size=8), np.zeros(8)])]
    with pytest.raises(np.linalg.LinAlgError):
        emcee.moves.KDEMove().get_proposal(walkers, others, np.random.RandomState(0))
    move = sampling.KDEMove()
    move.setup(np.concatenate([walkers, *others]))
    proposal, log_factors = move.get_proposal(walkers, others, np.random.RandomState(0))
    assert np.all(np.isfinite(proposal)) and np.all(log_factors == 0.0)
    assert np.all(proposal[:, 1] == 0.0) and not np.allclose(proposal[:, 0], walkers[:, 0])
