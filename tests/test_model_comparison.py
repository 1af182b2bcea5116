"""Model versions compared by PSIS-LOO over blocks of one channel and one load cycle."""

import numpy as np
import pytest

from newdyn import likelihood, model_comparison

TIMES = 0.5 + np.arange(5000) / 5000.0
SIGMA = np.array([1.0, 2.0])
SHAPE = np.sin(2 * np.pi * 5.0 * TIMES) * np.array([[1.0], [3.0]])


def test_blocks_are_whole_load_cycles_and_their_log_likelihoods_add_up_to_the_total():
    cycle = model_comparison.cycles(TIMES, 12.0)
    assert cycle.max() == 11 and np.all(np.diff(cycle) >= 0)
    assert set(np.bincount(cycle)) == {416, 417}  # 5000 samples over 12 cycles
    rng = np.random.default_rng(3)
    data = SHAPE + rng.normal(size=SHAPE.shape) * SIGMA[:, None]
    outputs = SHAPE[None] * np.array([0.9, 1.0, 1.1])[:, None, None]
    blocks = model_comparison.pointwise(data, SIGMA, outputs, cycle)
    assert blocks.shape == (3, 2, 12)
    assert blocks.sum(axis=(1, 2)) == pytest.approx(likelihood.log_likelihood(data, outputs, SIGMA), rel=1e-12)


def test_truncated_normal_draws_stay_in_the_box_and_a_point_repeats():
    rng = np.random.default_rng(0)
    theta = model_comparison.draws(np.array([1.0, 0.0]), np.diag([0.25, 1.0]), np.array([0.5, -1.0]), np.array([2.0, 1.0]), rng)
    assert theta.shape == (model_comparison.DRAWS, 2) and np.all((theta >= [0.5, -1.0]) & (theta <= [2.0, 1.0]))
    point = model_comparison.draws(np.array([3.0]), None, np.array([0.0]), np.array([5.0]), rng)
    assert np.all(point == 3.0)


def test_compare_ranks_the_model_that_made_the_data_above_one_without_it():
    rng = np.random.default_rng(1)
    data = SHAPE + rng.normal(size=SHAPE.shape) * SIGMA[:, None]
    cycle = model_comparison.cycles(TIMES, 12.0)

    def scaled(theta):
        return theta[:, 0, None, None] * SHAPE[None]

    amplitude = model_comparison.draws(np.array([1.0]), np.array([[1e-4]]), np.array([0.0]), np.array([2.0]), rng)
    versions = model_comparison.evaluate_versions(
        {"with the term": model_comparison.Version(scaled, amplitude, ["a"]),
         "without": model_comparison.Version(lambda theta: np.zeros((len(theta), *SHAPE.shape)), np.zeros((64, 0)), [])},
        data, SIGMA, cycle, ["b1_x", "w1"])
    assert versions["with the term"].log_likelihood["y"].dims == ("chain", "draw", "channel", "cycle")
    rows = model_comparison.compare(versions)
    assert [r["version"] for r in rows] == ["with the term", "without"]
    # Without the term each block loses the term's Σ (s/σ)²/2: elpd_diff is that total, to the noise's share.
    expected = 0.5 * np.sum((SHAPE / SIGMA[:, None]) ** 2)
    assert rows[1]["elpd_diff"] == pytest.approx(expected, rel=0.05) and rows[0]["weight"] > 0.99
    assert [r["rank"] for r in rows] == [0, 1] and all(isinstance(r["rank"], int) for r in rows)
    # The version without parameters is exact (one model for every draw), the one that made the data well sampled.
    assert rows[1]["pareto_k_max"] is None and not rows[1]["warning"] and rows[1]["warning_reason"] == ""
    assert rows[0]["pareto_k_max"] < model_comparison.PARETO_K_MAX and not rows[0]["warning"]
