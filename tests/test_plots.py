"""newdyn.plots on small synthetic result files: what each figure draws, and the files it writes."""

import csv
import itertools
import json
import math
import warnings

import arviz as az
import matplotlib.image
import numpy as np
import pytest
import xarray as xr
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from PIL import Image

from newdyn import comparison, io, model, plots, sampling

SAMPLING = model.Sampling(fs=1000.0, t_first=0.5, n_samples=8192)
CHANNELS = ["b1_x", "w1"]
SIGMA = np.array([2e-8, 0.05])
PRIOR = {"mean": 3.0e6, "sd": 0.5e6}
TRUE_KT1 = 3.25e6


def clean_signal():
    t = SAMPLING.times
    return np.array([1e-7 * np.sin(2 * np.pi * 24.7 * t), 155.0 + 0.5 * np.sin(2 * np.pi * 12.0 * t)])


@pytest.fixture
def measurement(tmp_path):
    """A measurement of known white noise σ around the clean signal, which is also every fit's best fit."""
    noise = np.random.default_rng(1).standard_normal((2, SAMPLING.n_samples)) * SIGMA[:, None]
    ds = io.measurement_dataset(
        clean_signal() + noise, CHANNELS, SAMPLING, {name: model.DEFAULTS[name] for name in io.OPERATING_ATTRS},
        {"scenario": "kT1_up", "snr_db": 40.0}, sigma=SIGMA,
    )
    path = tmp_path / "snr40_seed1.nc"
    io.write_netcdf(ds, path)
    return path


def write_grid_result(path, parameter="kT1", peak=TRUE_KT1, true_value=TRUE_KT1, verdict="explained"):
    """A grid calibration file as the workflow writes it: Gaussian likelihood, Normal prior, refined grid."""
    grid = np.unique(np.concatenate([np.linspace(1.5e6, 4.5e6, 61), np.linspace(peak - 1e5, peak + 1e5, 41)]))
    log_likelihood = -0.5 * ((grid - peak) / 2e4) ** 2
    prior = np.exp(-0.5 * ((grid - PRIOR["mean"]) / PRIOR["sd"]) ** 2) / (PRIOR["sd"] * math.sqrt(2 * math.pi))
    posterior = np.exp(log_likelihood) * prior
    posterior /= np.trapezoid(posterior, grid)
    settings = {"prior": PRIOR, "grid": {"low": 1.5e6, "high": 4.5e6, "points": 61}, "values": {}, "channels": CHANNELS}
    ds = xr.Dataset(
        {
            "posterior": ("grid", posterior),
            "log_likelihood": ("grid", log_likelihood),
            "scaled_likelihood": ("grid", np.exp(log_likelihood)),
            "prior": ("grid", prior),
            "best_fit": (("channel", "time"), clean_signal()),
        },
        coords={"grid": grid, "channel": CHANNELS, "time": SAMPLING.times},
        attrs={
            "parameter": parameter, "method": "grid", "map": float(grid[np.argmax(posterior)]),
            "mean": float(np.trapezoid(grid * posterior, grid)), "sd": 2e4,
            "hdi_low": peak - 4e4, "hdi_high": peak + 4e4,
            "sd_ratio": 0.04, "n_peaks": 1, "chi2_red": 1.02, "verdict": verdict, "measurement": "snr40_seed1",
            "scenario": "kT1_up", "snr_db": 40.0, "seed": 1, "settings": json.dumps(settings), "true_value": true_value,
        },
    )
    io.write_netcdf(ds, path)
    return path


def assert_written(png_path, code_hash):
    """A valid PNG carrying the code hash in its text chunks, and its PDF twin carrying it too."""
    assert png_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    height, width, colours = matplotlib.image.imread(png_path).shape
    assert height > 100 and width > 100 and colours in (3, 4)
    with Image.open(png_path) as image:
        assert image.text["code_hash"] == code_hash
        assert json.loads(image.text["versions"])["newdyn"] == image.text["newdyn_version"]
    pdf = png_path.with_suffix(".pdf").read_bytes()
    assert pdf.startswith(b"%PDF") and code_hash.encode() in pdf


def line(ax, label):
    (found,) = [candidate for candidate in ax.get_lines() if candidate.get_label().startswith(label)]
    return found


def test_posterior_panels_draw_each_file_as_in_the_paper(tmp_path):
    known = write_grid_result(tmp_path / "kT1_grid.nc")
    unknown = write_grid_result(tmp_path / "kT3_grid.nc", "kT3", 2.6e6, math.nan, "not explained")
    fig = plots.posterior_panels([known, unknown], tmp_path / "fig4.png", title="stick-slip", code_hash="feed01")

    assert_written(tmp_path / "fig4.png", "feed01")
    with Image.open(tmp_path / "fig4.png") as image:
        assert json.loads(image.text["sources"]) == [str(known), str(unknown)]
    (full_kT1, full_kT3), (zoom_kT1, _) = np.reshape(fig.axes, (2, 2))
    with xr.open_dataset(known, engine="netcdf4") as ds:
        ds.load()
    posterior = line(full_kT1, "posterior")
    np.testing.assert_array_equal(posterior.get_xdata(), ds["grid"].values)
    np.testing.assert_array_equal(posterior.get_ydata(), ds["posterior"].values)
    np.testing.assert_allclose(line(full_kT1, "likelihood").get_ydata().max(), ds["posterior"].values.max(), rtol=1e-12)
    np.testing.assert_array_equal(line(full_kT1, "prior").get_ydata(), ds["prior"].values)
    assert line(full_kT1, "original value").get_xdata()[0] == PRIOR["mean"]
    assert line(full_kT1, "MAP").get_xdata()[0] == ds.attrs["map"]
    assert line(full_kT1, "true value").get_xdata()[0] == TRUE_KT1
    assert not [c for c in full_kT3.get_lines() if c.get_label().startswith("true value")]  # truth unknown: NaN
    assert full_kT1.get_xlim() == (1.5e6, 4.5e6)
    assert zoom_kT1.get_xlim()[0] > 3.1e6 and zoom_kT1.get_xlim()[1] < 3.4e6  # mean ± 6 sd
    assert "not explained" in full_kT3.texts[0].get_text() and "1.02" in full_kT3.texts[0].get_text()
    assert "N·m/rad" in full_kT1.get_xlabel()


def test_heatmap_writes_each_value_and_frames_only_marked_cells(tmp_path):
    values = np.array([[0.1234, math.nan, 0.9], [0.0, 0.5, 1.0]])
    marks = np.array([[True, False, False], [False, False, True]])
    fig = plots.heatmap(values, ["a", "b"], ["x", "y", "z"], tmp_path / "h.png", "T", "distance", code_hash="h1",
                        marks=marks, mark_label="not explained")
    assert_written(tmp_path / "h.png", "h1")
    ax = fig.axes[0]
    texts = {tuple(map(round, t.get_position())): t.get_text() for t in ax.texts}
    assert texts == {(c, r): f"{v:.3g}" for (r, c), v in np.ndenumerate(values) if np.isfinite(v)}  # NaN blank
    framed = {(round(p.get_x() + p.get_width() / 2), round(p.get_y() + p.get_height() / 2)) for p in ax.patches}
    assert framed == {(c, r) for r, c in np.argwhere(marks)}
    assert "not explained" in ax.get_title()
    assert ax.images[0].get_array().mask[0, 1]  # NaN drawn in the colormap's "bad" grey
    with pytest.raises(ValueError, match="shape"):
        plots.heatmap(values, ["a"], ["x", "y", "z"], tmp_path / "bad.png", "T", "d")


def test_summary_heatmaps_put_variants_side_by_side_for_one_seed(tmp_path):
    columns = ["variant", "scenario", "parameter", "snr_db", "seed", "method", "chi2_red", "verdict",
               "hellinger_to_healthy"]
    rows = []
    for variant, scale in (("paper", 2.0), ("default", 1.0)):
        for seed in (1, 2):
            for method in ("grid", "mcmc"):
                for i, scenario in enumerate(("stick_slip", "healthy")):
                    for j, (parameter, snr) in enumerate((("kT1", 40.0), ("kT1", 20.0), ("kT3", 40.0))):
                        chi2 = scale * 10.0 ** (i + j) if (seed, method) == (1, "grid") else 999.0
                        hellinger = "" if (i, j) == (1, 2) else 0.1 * (i + j)
                        rows.append([variant, scenario, parameter, snr, seed, method, chi2,
                                     "not explained" if chi2 > 5 else "explained", hellinger])
    summary = tmp_path / "summary.csv"
    with open(summary, "w", newline="") as f:
        csv.writer(f).writerows([columns, *rows])

    hellinger, chi2 = plots.summary_heatmaps(summary, tmp_path / "hellinger.png", tmp_path / "chi2.png", "s1")
    for name in ("hellinger.png", "chi2.png"):
        assert_written(tmp_path / name, "s1")
    ax = chi2.axes[0]
    assert [t.get_text() for t in ax.get_yticklabels()] == ["healthy", "stick_slip"]  # the reference first
    assert [t.get_text() for t in ax.get_xticklabels()] == [
        f"{variant}: {column}" for variant in ("default", "paper") for column in ("kT1 @ 40 dB", "kT1 @ 20 dB", "kT3 @ 40 dB")
    ]
    default = np.array([[10.0, 100.0, 1000.0], [1.0, 10.0, 100.0]])  # 10 ** (i + j), healthy is i = 1
    expected = np.hstack([default, 2 * default])
    texts = {tuple(map(round, t.get_position())): float(t.get_text()) for t in ax.texts}
    assert texts == {(c, r): v for (r, c), v in np.ndenumerate(expected)}
    assert isinstance(ax.images[0].norm, LogNorm)
    framed = {(round(p.get_x() + 0.45), round(p.get_y() + 0.45)) for p in ax.patches}
    assert framed == {(c, r) for r, c in np.argwhere(expected > 5)}
    ax = hellinger.axes[0]
    norm = ax.images[0].norm
    assert (norm.vmin, norm.vmax) == (0.0, 1.0) and not isinstance(norm, LogNorm)
    assert len(ax.texts) == 10  # the empty healthy kT3 cells are blank
    assert "seed 1" in ax.get_title()


def test_signature_heatmaps_draw_one_symmetric_panel_per_parameter(tmp_path):
    grid = np.linspace(-10.0, 10.0, 2001)
    posteriors = {
        (scenario, parameter, snr, 1): (grid, np.exp(-0.5 * (grid - shift) ** 2))
        for scenario, shift in (("healthy", 0.0), ("kT1_up", 1.0), ("stick_slip", 3.0))
        for parameter in ("kT1", "kT3")
        for snr in (40.0, 20.0)
    }
    path = tmp_path / "hellinger.nc"
    xr.Dataset({"hellinger": comparison.signature_matrices(posteriors)}).to_netcdf(path)
    fig = plots.signature_heatmaps(path, tmp_path / "signatures.png", 40, 1, code_hash="s2")
    assert_written(tmp_path / "signatures.png", "s2")
    panels = [ax for ax in fig.axes if ax.images]
    assert [ax.get_title() for ax in panels] == ["posteriors of kT1", "posteriors of kT3"]
    texts = {tuple(map(round, t.get_position())): float(t.get_text()) for t in panels[0].texts}
    for (r, shift_r), (c, shift_c) in itertools.product(enumerate((0.0, 1.0, 3.0)), repeat=2):
        closed_form = comparison.hellinger_gaussians(shift_r, 1.0, shift_c, 1.0)
        assert texts[c, r] == pytest.approx(closed_form, abs=2e-3)


def write_mcmc(path, converged):
    """Two well-mixed parameters (as a joint calibration would have) with given convergence attributes."""
    rng = np.random.default_rng(2)
    idata = az.from_dict(posterior={"kT1": rng.normal(3.2e6, 2e4, (4, 200)), "kT3": rng.normal(2.5e6, 3e4, (4, 200))})
    idata.attrs = {"parameter": "kT1", "scenario": "kT1_up", "measurement": "snr40_seed1", "snr_db": 40.0,
                   "rhat": 1.002 if converged else 1.3, "ess_bulk": 750.0 if converged else 12.0,
                   "converged": int(converged), "reason": "" if converged else "rhat 1.3 > 1.01; ess_bulk 12 < 400"}
    sampling.save(idata, path)
    return path


@pytest.mark.filterwarnings(  # ArviZ 0.23's own call, deprecated by matplotlib 3.11
    "ignore:Passing a dict or None as alias_mapping:matplotlib.MatplotlibDeprecationWarning"
)
def test_mcmc_diagnostics_block_title_says_unconverged_exactly_when_so(tmp_path):
    runs = [write_mcmc(tmp_path / "good.nc", True), write_mcmc(tmp_path / "bad.nc", False)]
    fig = plots.mcmc_diagnostics(runs, tmp_path / "mcmc.png", code_hash="m1")
    assert_written(tmp_path / "mcmc.png", "m1")
    good, bad = (block.get_suptitle() for block in fig.subfigs)
    assert "R-hat = 1.0020" in good and "UNCONVERGED" not in good
    assert "R-hat = 1.3000" in bad and "UNCONVERGED: rhat 1.3 > 1.01; ess_bulk 12 < 400" in bad
    assert fig.subfigs[1]._suptitle.get_color() == plots.MARK_COLOR
    for block in fig.subfigs:  # trace, density and rank for each of the two variables
        assert len(block.axes) == 6 and {ax.get_title() for ax in block.axes} == {"kT1", "kT3"}


def test_model_overlays_show_a_white_noise_residual_at_the_noise_floor(tmp_path, measurement):
    fits = [write_grid_result(tmp_path / "kT1_grid.nc"), write_grid_result(tmp_path / "kT3_grid.nc", "kT3", 2.6e6)]
    fig = plots.model_overlays(measurement, fits, tmp_path / "overlay.png", window=0.1, code_hash="o1")
    assert_written(tmp_path / "overlay.png", "o1")
    (signal_b1, psd_b1), _ = np.reshape(fig.axes, (2, 2))
    data = line(signal_b1, "data")
    assert data.get_xdata()[-1] < SAMPLING.t_first + 0.1 <= data.get_xdata()[-1] + 1 / SAMPLING.fs
    assert "1.02" in line(signal_b1, "kT3 best fit").get_label()
    floor = 2 * SIGMA[0] ** 2 / SAMPLING.fs
    np.testing.assert_allclose(line(psd_b1, "noise floor").get_ydata(), floor, rtol=1e-12)
    # The residual is the pure white noise: Welch's mean one-sided PSD is 2σ²/fs (Nyquist bin left out).
    # (Ratios, since pytest.approx's default absolute tolerance would swallow PSDs of 1e-18 m²/Hz.)
    assert line(psd_b1, "data − kT1").get_ydata()[:-1].mean() / floor == pytest.approx(1.0, abs=0.05)
    assert psd_b1.get_yscale() == "log"


def test_save_refuses_a_path_that_is_not_png(tmp_path):
    with pytest.raises(ValueError, match=r"\.png"):
        plots.save(Figure(), tmp_path / "figure.pdf")


def _crowded_figure():
    """A constrained-layout figure whose layout matters: long labels, a title, a legend and a colorbar."""
    fig = Figure(figsize=(6.0, 4.0), layout="constrained")
    line_ax, mesh_ax = fig.subplots(1, 2)
    line_ax.plot([0.0, 1.0e6], [1.0e-9, 3.0e-9], label="a long legend entry")
    line_ax.set(xlabel="stiffness kT1 [N·m/rad]", ylabel="displacement [m]", title="a title that needs room")
    line_ax.legend()
    fig.colorbar(mesh_ax.pcolormesh(np.arange(12.0).reshape(3, 4)), ax=mesh_ax, label="a colorbar's label")
    return fig


def test_save_lays_a_figure_out_as_its_layout_engine_does_and_keeps_that_layout_in_the_pdf(tmp_path):
    plots.save(_crowded_figure(), tmp_path / "once.png")
    reference = _crowded_figure()
    reference.savefig(tmp_path / "engine.png", dpi=plots.PNG_DPI)
    assert np.array_equal(matplotlib.image.imread(tmp_path / "once.png"), matplotlib.image.imread(tmp_path / "engine.png"))
    reference.set_layout_engine("none")
    reference.savefig(tmp_path / "engine.pdf", metadata={"CreationDate": None})
    assert _pdf_drawing(tmp_path / "once.pdf") == _pdf_drawing(tmp_path / "engine.pdf")


def test_save_keeps_its_layout_under_a_matplotlibrc_that_asks_for_another_engine(tmp_path):
    plots.save(_crowded_figure(), tmp_path / "default.png")
    with matplotlib.rc_context({"figure.autolayout": True}):
        plots.save(_crowded_figure(), tmp_path / "autolayout.png")
    assert np.array_equal(matplotlib.image.imread(tmp_path / "default.png"), matplotlib.image.imread(tmp_path / "autolayout.png"))
    assert _pdf_drawing(tmp_path / "default.pdf") == _pdf_drawing(tmp_path / "autolayout.pdf")


def _pdf_drawing(path):
    """A PDF's objects but its metadata (plots.save stamps Creator and Subject) and the byte offsets that follow them."""
    return [chunk for chunk in path.read_bytes().split(b"endobj")[:-1] if b"/Creator" not in chunk]


def test_a_log_axis_over_many_decades_draws_no_minor_ticks_and_a_short_one_keeps_them(tmp_path):
    fig = Figure()
    short, long, subfigure_long = (*fig.subfigures(1, 2)[0].subplots(2, 1), fig.subfigs[1].subplots())
    for ax, decades in ((short, plots.LOG_MINOR_DECADES - 1), (long, plots.LOG_MINOR_DECADES + 1), (subfigure_long, 9)):
        ax.semilogy([0.0, 1.0], [1.0, 10.0**decades])
    plots.save(fig, tmp_path / "ticks.png")
    assert len(short.yaxis.get_minorticklocs()) > 0
    assert len(long.yaxis.get_minorticklocs()) == 0 and len(subfigure_long.yaxis.get_minorticklocs()) == 0
    assert len(long.yaxis.get_majorticklocs()) > 0 and short.xaxis.get_scale() == "linear"


def _discovery_result(line_hz=37.0, amplitude=8.0):
    """A diagnosis file holding a force estimate at two places: at `load` a line of ``amplitude`` at ``line_hz``."""
    pulses = np.arange(0.002, 1.5, 0.002)
    theta1 = 2 * np.pi * 24.7 * pulses
    force = np.stack([amplitude * np.sin(2 * np.pi * line_hz * pulses), np.zeros_like(pulses)])
    return xr.Dataset(
        {"y": (("channel", "time"), clean_signal()), "force_mean": (("place", "pulse_time"), force),
         "force_sd": (("place", "pulse_time"), np.full_like(force, 0.5)), "theta1_at_pulse": ("pulse_time", theta1),
         "theta4_at_pulse": ("pulse_time", theta1 - 0.3)},
        coords={"channel": CHANNELS, "time": SAMPLING.times, "place": ["load", "b1_x"], "pulse_time": pulses},
        attrs={"load_freq": 12.0},
    )


def test_discovery_figure_shows_the_force_where_the_best_form_acts_and_its_line(tmp_path):
    candidate = {"term": "periodic", "acts_on": "load", "shape": "37.00 Hz", "frequency_hz": 37.0,
                 "parameters": {"amplitude": {"value": 8.0, "unit": "N·m"}}}
    verdict = {"measurement": "m", "verdict": "unexplained", "discovery": {"from": "healthy", "candidates": [candidate]}}
    fig = plots.discovered_force(verdict, _discovery_result(), tmp_path / "d.png")
    time_ax, spectrum_ax, angle_ax, phase_ax = fig.axes
    t, mean = time_ax.lines[0].get_data()
    assert t.min() >= SAMPLING.t_first and np.max(np.abs(mean)) == pytest.approx(8.0, rel=0.01)  # the record only
    frequency, amplitude = spectrum_ax.lines[0].get_data()
    assert frequency[np.argmax(amplitude)] == pytest.approx(37.0, abs=1.0) and np.max(amplitude) == pytest.approx(8.0, rel=0.1)
    angle, phase = angle_ax.lines[0].get_xdata(), phase_ax.lines[0].get_xdata()
    assert 0.0 <= angle.min() and angle.max() < 2 * np.pi and 0.0 <= phase.min() and phase.max() < 1.0
    assert "load" in fig._suptitle.get_text() and (tmp_path / "d.pdf").exists()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a note alone has no axes for a layout engine, which would warn in the job's log
        note = plots.discovered_force({"measurement": "m", "verdict": "healthy"}, _discovery_result(), tmp_path / "n.png")
    assert "no discovery" in note.texts[0].get_text()


def machine_verdict(record_next):
    candidates = [{"parameter": "T0", "value": v, "unit": "N·m", "expected_log_bayes_factor": f}
                  for v, f in ((800.0, 0.0), (1300.0, 0.0), (1800.0, 4.0e4))]
    return {
        "machine": "pump7", "verdict": "healthy", "effect": None, "model": "healthy",
        "recordings": [{"name": "full", "channels": ["b1_x", "w1"], "chi2_before": 1.02, "chi2_after": 1.02,
                        "finding_log_bayes_factor": 0.0},
                       {"name": "part", "channels": ["w1"], "chi2_before": 0.98, "chi2_after": 0.98,
                        "finding_log_bayes_factor": 0.0}],
        "record_next": {"model": "healthy", "rivals": [{"rival": "stick_slip", "candidates": candidates,
                                                        "advice": {"parameter": "T0"}}]} if record_next else None,
        "settings": {"diagnosis": {"evidence_margin": 6.9}, "calibration": {"chi2_max": 1.1}},
    }


def test_the_machine_figure_draws_each_recordings_misfit_and_where_a_next_recording_would_tell_the_rivals_apart(tmp_path):
    fig = plots.machine_verdict(machine_verdict(True), tmp_path / "machine.png", code_hash="m7")
    assert_written(tmp_path / "machine.png", "m7")
    chi_ax, shows_ax, next_ax = fig.axes
    assert [p.get_height() for p in chi_ax.patches] == [1.02, 0.98, 1.02, 0.98]  # nominal, then final, per recording
    assert [p.get_height() for p in shows_ax.patches] == [1e-3, 1e-3]  # nowhere visible: at the log axis's floor
    curve = line(next_ax, "stick_slip (T0)")
    assert list(curve.get_xdata()) == [800.0, 1300.0, 1800.0] and curve.get_ydata()[-1] == 4.0e4
    quiet = plots.machine_verdict(machine_verdict(False), tmp_path / "quiet.png")
    assert not quiet.axes[2].axison and "nothing to record next" in quiet.axes[2].texts[0].get_text()
