"""newdyn.hidden: deterministic balanced draws, truth-free measurement files, and the blind-test score."""

import copy
import json
import math
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import yaml
from matplotlib.figure import Figure

from newdyn import faults, hidden, io, model, plots

BASE = model.complete()
HIDDEN = yaml.safe_load((Path(__file__).resolve().parents[1] / "config" / "config.yaml").read_text())["hidden"]
HIDDEN["sets"]["other"] = {"cases": 24, "seed": 2027}
HIDDEN["sets"]["six"] = {"cases": 6, "seed": 5}
FAULT_KINDS = ("stick_slip", "breathing_crack", "cubic_coupling", "loose_bearing")


@pytest.fixture(scope="module")
def blind():
    return hidden.draw_cases(HIDDEN, "blind", BASE)


def test_same_seed_same_cases_other_seed_others(blind):
    assert hidden.draw_cases(HIDDEN, "blind", BASE) == blind
    other = hidden.draw_cases(HIDDEN, "other", BASE)
    assert [c["truth"] for c in other] != [c["truth"] for c in blind]
    assert [c["noise_seed"] for c in other] != [c["noise_seed"] for c in blind]
    assert [c["name"] for c in blind] == [f"blind_{i:02d}" for i in range(1, 25)]
    assert len({c["noise_seed"] for c in blind}) == 24


def test_classes_balanced_and_shuffled(blind):
    labels = [c["class"] for c in blind]
    assert {c: labels.count(c) for c in hidden.CLASSES} == {c: 4 for c in hidden.CLASSES}
    assert labels != sorted(labels, key=hidden.CLASSES.index)
    demo = hidden.draw_cases(HIDDEN, "demo", BASE)
    assert len(demo) == 1 and demo[0]["name"] == "demo_01"
    assert HIDDEN["sets"]["demo"]["classes"] == list(FAULT_KINDS)  # the demo set's own classes: a hidden effect
    assert demo[0]["class"] in FAULT_KINDS


def test_every_case_admissible_and_within_ranges(blind):
    for case in blind + hidden.draw_cases(HIDDEN, "other", BASE):
        kind, truth, scenario = case["class"], case["truth"], case["scenario"]
        values = faults.scenario_values(scenario, BASE)
        assert set(values) == set(model.PARAMETER_NAMES)
        if kind == "healthy":
            assert truth == {} and values == BASE
        elif kind == "parameter_change":
            continue  # its own test
        else:
            assert scenario["fault"]["kind"] == kind
            overrides = {**BASE, **scenario["overrides"]}
            assert faults.fault_problems(kind, scenario["fault"]["parameters"], overrides) == []
            ranges = HIDDEN["faults"][kind]
            assert set(truth) == set(ranges)
            for name, value in truth.items():
                assert ranges[name][0] <= value <= ranges[name][1]
            for name, value in scenario["fault"]["parameters"].items():
                assert truth[name] == value
            if kind == "stick_slip":
                assert values["r_k"] * values["T_max"] > BASE["T0"]
                assert values["J2a"] + values["J2b"] == pytest.approx(BASE["J2a"] + BASE["J2b"], rel=1e-14)
                assert values["J2a"] / (values["J2a"] + values["J2b"]) == pytest.approx(truth["J2a_share"])


def test_parameter_change_changes_exactly_one_parameter(blind):
    drifts = [c for c in blind + hidden.draw_cases(HIDDEN, "other", BASE) if c["class"] == "parameter_change"]
    low, high = HIDDEN["parameter_change"]["relative"]
    for case in drifts:
        values = faults.scenario_values(case["scenario"], BASE)
        changed = [name for name in model.PARAMETER_NAMES if values[name] != BASE[name]]
        assert changed == list(case["truth"])
        (name,) = changed
        assert name in HIDDEN["parameter_change"]["parameters"]
        assert values[name] == case["truth"][name]
        assert low <= abs(values[name] / BASE[name] - 1) <= high
    signs = {np.sign(c["truth"][p] - BASE[p]) for c in drifts for p in c["truth"]}
    assert signs == {-1.0, 1.0}


def test_inadmissible_draws_are_redrawn_deterministically():
    """A T_max range straddling T0 / r_k: every drawn stick-slip case still carries the mean load."""
    config = copy.deepcopy(HIDDEN)
    config["classes"] = ["stick_slip"]
    config["sets"]["one"] = {"cases": 1, "seed": 7}
    config["faults"]["stick_slip"] = {"T_max": [1500.0, 1900.0], "r_k": [0.8, 1.0]}
    cases = hidden.draw_cases(config, "blind", BASE)
    assert cases == hidden.draw_cases(config, "blind", BASE)
    assert all(c["truth"]["r_k"] * c["truth"]["T_max"] > BASE["T0"] for c in cases)
    config["faults"]["stick_slip"] = {"T_max": [1000.0, 1500.0]}
    with pytest.raises(ValueError, match="no admissible draw"):
        hidden.draw_cases(config, "one", BASE)
    config["faults"]["stick_slip"] = {"T_maks": [1800.0, 1900.0]}
    with pytest.raises(ValueError, match="T_maks.*unknown parameter of stick_slip"):
        hidden.draw_cases(config, "one", BASE)


def _texts(value):
    """The ways a drawn number could be spelled in a file."""
    return {repr(value), f"{value:g}", f"{value:.6g}", f"{value:.4g}", f"{value:.3e}", json.dumps(value)}


def test_measurement_file_carries_no_truth(tmp_path):
    cases = hidden.draw_cases(HIDDEN, "six", BASE)
    assert {c["class"] for c in cases} == set(hidden.CLASSES)
    sampling = model.Sampling(fs=2500.0, t_first=0.5, n_samples=1500)
    forbidden_keys = {"scenario", "fault", "class", "truth", "description", "sigma", "snr_db", "seed", "noise_seed",
                      "parameters", "overrides", "kind", "J2a_share", *hidden.CLASSES, *model.RIG_PARAMETERS,
                      *(p for kind in FAULT_KINDS for p in faults.FAULT_KINDS[kind].allowed()),
                      "T_max", "r_k", "crack_alpha", "cubic_gamma", "bearing_gap", "crack", "cubic", "loose", "stick"}
    for case in cases:
        path = tmp_path / f"{case['name']}.nc"
        hidden.write_case_measurement(case, BASE, sampling, 40.0, path, code_hash="abc123")
        with xr.open_dataset(path, engine="netcdf4") as ds:
            ds.load()
        names = set(ds.variables) | set(ds.coords) | set(ds.dims)
        assert names == {"y", "time", "channel"}
        attrs = {**ds.attrs, **{f"{v}.{k}": a for v in ds.variables for k, a in ds[v].attrs.items()}}
        text = json.dumps({k: str(v) for k, v in attrs.items()}).lower()
        for key in forbidden_keys:
            assert key.lower() not in {k.lower() for k in attrs}, key
            if key not in ("seed",):  # "seed" may not appear either, but guard against false hits below
                assert f'"{key.lower()}' not in text and f"{key.lower()}:" not in text, (case["name"], key)
        assert "seed" not in text and "sigma" not in text and "snr" not in text and "class" not in text
        for value in [*case["truth"].values(), *case["scenario"]["overrides"].values(), case["noise_seed"]]:
            for spelling in _texts(value):
                assert spelling.lower() not in text, (case["name"], spelling)
        assert ds.attrs["code_hash"] == "abc123"
        for name in model.OPERATING_PARAMETERS:
            assert float(ds.attrs[name]) == BASE[name]

        measurement = io.read_measurement(path)
        assert measurement.channels == model.CHANNELS and len(measurement.channels) == 11
        assert measurement.sigma is None and "snr_db" not in measurement.attrs
        assert measurement.sampling.n_samples == sampling.n_samples
        assert measurement.sampling.t_first == sampling.t_first
        assert measurement.sampling.fs == pytest.approx(sampling.fs, rel=1e-12)
        assert measurement.operating == {name: BASE[name] for name in model.OPERATING_PARAMETERS}

    # The signal itself is the case's: 40 dB noise around its clean simulation, reproducible from the seed.
    from newdyn import simulation

    case = next(c for c in cases if c["class"] == "loose_bearing")
    clean = simulation.simulate(hidden.case_values(case, BASE), sampling, model.CHANNELS)
    y = io.read_measurement(tmp_path / f"{case['name']}.nc").y
    ratio = np.std(y - clean, axis=1) / np.std(clean, axis=1)
    np.testing.assert_allclose(ratio, 0.01, rtol=0.1)
    hidden.write_case_measurement(case, BASE, sampling, 40.0, tmp_path / "again.nc")
    np.testing.assert_array_equal(io.read_measurement(tmp_path / "again.nc").y, y)


def test_truth_file_round_trip(tmp_path, blind):
    hidden.write_truth(blind, tmp_path / "truth.json", code_hash="h1")
    assert hidden.read_truth(tmp_path / "truth.json") == blind
    document = json.loads((tmp_path / "truth.json").read_text())
    assert document["code_hash"] == "h1" and "versions" in document


# ----------------------------------------------------------------------------------------- scoring


def _case(name, kind, truth):
    return {"name": name, "class": kind, "truth": truth, "scenario": {"overrides": {}}, "noise_seed": 1}


def _summary(mean, low, high, sd=1.0):
    return {"mean": mean, "sd": sd, "hdi_low": low, "hdi_high": high}


CASES = [
    _case("t_01", "healthy", {}),
    _case("t_02", "healthy", {}),
    _case("t_03", "parameter_change", {"kT2": 1.1e6}),
    _case("t_04", "parameter_change", {"kT2": 0.9e6}),
    _case("t_05", "parameter_change", {"k_bx": 5.5e8}),
    _case("t_06", "stick_slip", {"T_max": 1900.0, "r_k": 0.95, "J2a_share": 0.3}),
    _case("t_07", "breathing_crack", {"alpha": 0.3}),
    _case("t_08", "cubic_coupling", {"gamma": 0.2}),
    _case("t_09", "loose_bearing", {"gap": 1e-8}),
]
VERDICTS = {
    "t_01": {"verdict": "healthy", "effect": None, "equivalent": [], "parameters": {}, "chi2_before": 1.0, "chi2_after": 1.0},
    "t_02": {"verdict": "parameter_change", "effect": "kT1", "equivalent": ["kT1"], "chi2_before": 1.3, "chi2_after": 1.0,
             "parameters": {"kT1": _summary(3.1e6, 3.0e6, 3.2e6)}},
    # identifiable only up to kT1 ~ kT2 ~ kT3: the ranking has the true parameter's own fit
    "t_03": {"verdict": "parameter_change", "effect": "kT1", "equivalent": ["kT1", "kT2", "kT3"],
             "parameters": {"kT1": _summary(3.4e6, 3.3e6, 3.5e6)}, "chi2_before": 4.0, "chi2_after": 1.0,
             "ranking": [{"hypothesis": "parameter_change:kT1", "confidence": 0.4, "chi2": 1.0,
                          "parameters": {"kT1": _summary(3.4e6, 3.3e6, 3.5e6)}},
                         {"hypothesis": "parameter_change:kT2", "confidence": 0.4, "chi2": 1.0,
                          "parameters": {"kT2": _summary(1.111e6, 1.09e6, 1.12e6)}}]},
    "t_04": {"verdict": "parameter_change", "effect": "kT1", "equivalent": ["kT1"], "chi2_before": 4.0, "chi2_after": 1.0,
             "parameters": {"kT1": _summary(2.7e6, 2.6e6, 2.8e6)}},
    "t_05": {"verdict": "parameter_change", "effect": "k_bx", "equivalent": [], "chi2_before": 20.0, "chi2_after": 1.0,
             "parameters": {"k_bx": _summary(5.6e8, 5.45e8, 5.7e8)}},
    "t_06": {"verdict": "new_dynamics", "effect": "stick_slip", "equivalent": [], "chi2_before": 50.0, "chi2_after": 1.05,
             "parameters": {"T_max": _summary(1890.0, 1880.0, 1895.0), "r_k": _summary(0.95, 0.94, 0.96)}},
    "t_07": {"verdict": "new_dynamics", "effect": "cubic_coupling", "equivalent": [], "chi2_before": 3.0, "chi2_after": 1.4,
             "parameters": {"gamma": _summary(0.1, 0.05, 0.15)}},
    "t_08": {"verdict": "new_dynamics", "effect": "cubic_coupling", "equivalent": [], "chi2_before": 3.0, "chi2_after": 1.3,
             "parameters": {"gamma": _summary(0.2, 0.19, 0.21)}},
    "t_09": {"verdict": "unexplained", "effect": None, "equivalent": [], "chi2_before": 30.0, "chi2_after": 5.0,
             "parameters": {}},
}


def test_score_by_hand():
    result = hidden.score(CASES, VERDICTS)
    correct = {row["name"]: row["correct"] for row in result["rows"]}
    assert correct == {"t_01": True, "t_02": False, "t_03": True, "t_04": False, "t_05": True,
                       "t_06": True, "t_07": False, "t_08": True, "t_09": False}
    assert result["cases"] == 9 and result["correct"] == 5 and result["accuracy"] == pytest.approx(5 / 9)
    assert result["per_class"]["healthy"] == {"cases": 2, "correct": 1, "accuracy": 0.5}
    assert result["per_class"]["parameter_change"]["accuracy"] == pytest.approx(2 / 3)
    assert result["per_class"]["breathing_crack"]["accuracy"] == 0.0
    confusion = result["confusion"]
    assert confusion["truth"] == ["healthy", "parameter_change", *FAULT_KINDS]
    assert confusion["predicted"] == ["healthy", "parameter_change", *FAULT_KINDS, "unexplained"]
    assert confusion["counts"] == [
        # healthy, parameter_change, stick_slip, breathing_crack, cubic_coupling, loose_bearing, unexplained
        [1, 1, 0, 0, 0, 0, 0],  # healthy
        [0, 3, 0, 0, 0, 0, 0],  # parameter_change (t_04 names the wrong parameter: counted, not correct)
        [0, 0, 1, 0, 0, 0, 0],  # stick_slip
        [0, 0, 0, 0, 1, 0, 0],  # breathing_crack
        [0, 0, 0, 0, 1, 0, 0],  # cubic_coupling
        [0, 0, 0, 0, 0, 0, 1],  # loose_bearing
    ]
    row = next(r for r in result["rows"] if r["name"] == "t_07")
    assert (row["predicted"], row["effect"], row["chi2_before"], row["chi2_after"]) == ("cubic_coupling", "cubic_coupling", 3.0, 1.4)


def test_identifiability_rule():
    case = _case("c", "parameter_change", {"kT2": 1.1e6})
    verdict = {"verdict": "parameter_change", "effect": "kT1", "equivalent": ["kT1", "kT2", "kT3"]}
    assert hidden.is_correct(case, verdict)
    assert not hidden.is_correct(case, {**verdict, "equivalent": ["kT1"]})
    assert hidden.is_correct(case, {**verdict, "effect": "kT2", "equivalent": []})
    assert not hidden.is_correct(case, {"verdict": "new_dynamics", "effect": "cubic_coupling", "equivalent": ["kT2"]})
    assert not hidden.is_correct(_case("h", "healthy", {}), {"verdict": "parameter_change", "effect": "kT2"})


def test_parameter_errors_and_fault_fit():
    result = hidden.score(CASES, VERDICTS)
    errors = {(e["case"], e["parameter"]): e for e in result["parameter_errors"]}
    # t_03: the true kT2 from its own ranking entry, not the verdict's kT1
    e = errors[("t_03", "kT2")]
    assert e["source"] == "ranking parameter_change:kT2"
    assert e["relative_error"] == pytest.approx(0.01) and e["in_hdi"] is True
    e = errors[("t_05", "k_bx")]
    assert e["relative_error"] == pytest.approx(5.6 / 5.5 - 1) and e["in_hdi"] is True
    assert errors[("t_06", "T_max")]["relative_error"] == pytest.approx(-10 / 1900)
    assert errors[("t_06", "T_max")]["in_hdi"] is False  # 1900 outside [1880, 1895]
    assert errors[("t_06", "r_k")]["in_hdi"] is True
    assert errors[("t_08", "gamma")]["relative_error"] == pytest.approx(0.0)
    # wrong cases and parameters nobody fitted (J2a_share) have no entry
    assert set(errors) == {("t_03", "kT2"), ("t_05", "k_bx"), ("t_06", "T_max"), ("t_06", "r_k"), ("t_08", "gamma")}
    assert result["hdi_coverage"] == pytest.approx(4 / 5)
    # correct fault cases t_06 (χ² 1.05) and t_08 (1.3): one explained
    assert result["fault_fit"] == {"cases": 2, "explained": 1, "chi2_max": 1.1, "fraction": 0.5}


def test_missing_or_malformed_verdict_names_the_case():
    verdicts = {k: v for k, v in VERDICTS.items() if k != "t_05"}
    with pytest.raises(ValueError, match="t_05"):
        hidden.score(CASES, verdicts)
    with pytest.raises(ValueError, match="t_07.*no library fault kind"):
        hidden.score(CASES, {**VERDICTS, "t_07": {"verdict": "new_dynamics", "effect": "kT1"}})


def test_write_score_and_figure(tmp_path):
    result = hidden.score(CASES, VERDICTS)
    hidden.write_score(result, tmp_path / "score.json", tmp_path / "cases.csv", code_hash="h2")
    document = json.loads((tmp_path / "score.json").read_text())
    assert document["accuracy"] == pytest.approx(5 / 9) and document["code_hash"] == "h2"
    lines = (tmp_path / "cases.csv").read_text().splitlines()
    assert lines[0].split(",")[:3] == ["name", "class", "truth"] and len(lines) == 10

    fig = plots.blind_test_figure(result, tmp_path / "blind_test.png", "blind set", code_hash="h2",
                                  sources=[tmp_path / "score.json"])
    assert isinstance(fig, Figure)
    assert (tmp_path / "blind_test.png").stat().st_size > 0 and (tmp_path / "blind_test.pdf").stat().st_size > 0
    assert "top-1 accuracy 56% (5/9)" in fig._suptitle.get_text()
    matrix_ax, error_ax = fig.axes[0], fig.axes[1]
    cell_texts = [t.get_text() for t in matrix_ax.texts]
    assert "3\n(2 right)" in cell_texts
    assert len(error_ax.get_yticklabels()) == 5
    assert not math.isnan(result["accuracy"])


def test_figure_without_fitted_parameters(tmp_path):
    cases, verdicts = CASES[:1], {"t_01": VERDICTS["t_01"]}
    fig = plots.blind_test_figure(hidden.score(cases, verdicts), tmp_path / "b.png", "demo")
    assert "top-1 accuracy 100% (1/1)" in fig._suptitle.get_text()
    assert (tmp_path / "b.pdf").exists()
