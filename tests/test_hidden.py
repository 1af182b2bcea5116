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

from newdyn import effects, faults, hidden, io, model, noise, plots, signatures, simulation, slots, study
from newdyn.settings import Settings

BASE = slots.complete()
CONFIG = yaml.safe_load((Path(__file__).resolve().parents[1] / "config" / "config.yaml").read_text())
HIDDEN = CONFIG["hidden"]
HIDDEN["sets"]["other"] = {"cases": 24, "seed": 2027}
HIDDEN["sets"]["six"] = {"cases": 6, "seed": 5}
RANGES = study.hidden_ranges(CONFIG)
CLASSES = list(study.hidden_classes(CONFIG))


def draw(set_name, hidden_section=HIDDEN, ranges=RANGES, classes=CLASSES):
    return hidden.draw_cases(hidden_section, set_name, BASE, ranges, classes)


@pytest.fixture(scope="module")
def blind():
    return draw("blind")


def test_same_seed_same_cases_other_seed_others(blind):
    assert draw("blind") == blind
    other = draw("other")
    assert [c["truth"] for c in other] != [c["truth"] for c in blind]
    assert [c["noise_seed"] for c in other] != [c["noise_seed"] for c in blind]
    assert [c["name"] for c in blind] == [f"blind_{i:02d}" for i in range(1, 25)]
    assert len({c["noise_seed"] for c in blind}) == 24


def test_classes_balanced_and_shuffled(blind):
    labels = [c["class"] for c in blind]
    assert set(CLASSES) == set(hidden.CLASSES)  # the config draws every class: healthy, a drift, each effect
    share = len(blind) // len(CLASSES)
    assert {c: labels.count(c) for c in CLASSES} == {c: share for c in CLASSES}
    assert labels != sorted(labels, key=CLASSES.index)
    demo = draw("demo")
    assert len(demo) == 1 and demo[0]["name"] == "demo_01"
    assert set(HIDDEN["sets"]["demo"]["classes"]) == set(hidden.FAULT_CLASSES)  # the demo set's own classes: a hidden effect
    assert demo[0]["class"] in hidden.FAULT_CLASSES


def test_every_case_admissible_and_within_ranges(blind):
    for case in blind + draw("other"):
        kind, truth, scenario = case["class"], case["truth"], case["scenario"]
        values = faults.scenario_values(scenario, BASE)
        assert set(values) == set(slots.slot_names())
        if kind == "healthy":
            assert truth == {} and values == BASE
        elif kind == "parameter_change":
            continue  # its own test
        else:
            assert scenario == {"overrides": {}, "fault": {"kind": kind, "parameters": truth}}
            assert faults.fault_problems(kind, truth, BASE) == []
            ranges = RANGES[kind]
            assert set(truth) == set(ranges)
            for name, value in truth.items():
                assert ranges[name][0] <= value <= ranges[name][1]
            # the model runs with the effect present, at the drawn values and the rig values they set
            effect = effects.active()[kind]
            full = faults.effect_values(kind, truth, BASE)
            assert values[kind] == 1.0 and effect.problems(full, BASE) == []
            assert all(values[f"{kind}.{p.name}"] == full[p.name] for p in effect.kernel_parameters())
            for name, value in effect.rig_values(full, BASE).items():
                assert values[name] == value and model.PARAMETER_BY_NAME[name].problem(value) is None
            assert all(values[other] == 0.0 for other in effects.active() if other != kind)


def test_parameter_change_changes_exactly_one_parameter(blind):
    drifts = [c for c in blind + draw("other") if c["class"] == "parameter_change"]
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
    section = copy.deepcopy(HIDDEN)
    section["sets"]["one"] = {"cases": 1, "seed": 7}
    ranges = {**RANGES, "stick_slip": {"T_max": [1500.0, 1900.0], "r_k": [0.8, 1.0]}}
    cases = draw("blind", section, ranges, ["stick_slip"])
    assert cases == draw("blind", section, ranges, ["stick_slip"])
    assert all(c["truth"]["r_k"] * c["truth"]["T_max"] > BASE["T0"] for c in cases)
    ranges["stick_slip"] = {"T_max": [1000.0, 1500.0]}
    with pytest.raises(ValueError, match="no admissible draw"):
        draw("one", section, ranges, ["stick_slip"])
    ranges["stick_slip"] = {"T_maks": [1800.0, 1900.0]}
    with pytest.raises(ValueError, match="T_maks.*unknown parameter of stick_slip"):
        draw("one", section, ranges, ["stick_slip"])
    with pytest.raises(ValueError, match="no draw ranges"):
        draw("one", section, {}, ["stick_slip"])


RECORD = ("phi1", "phi4", "load_phase", "start", "speed_offset_rpm")


def _in_ranges(record, fs=5000.0):
    for name in ("phi1", "phi4", "load_phase"):
        if name in record:
            assert -math.pi <= record[name] < math.pi, (name, record[name])
    assert 0.5 <= record["start"] < 1.5 and record["start"] * fs == pytest.approx(round(record["start"] * fs), abs=1e-6)
    assert -5.0 <= record["speed_offset_rpm"] <= 5.0 and record["speed_offset_rpm"] != 0.0


def test_every_case_draws_what_a_real_machine_leaves_open(blind):
    """Angles, load phase, start and speed offset: reproducible from the seed, in their ranges, each case its own."""
    assert [c["record"] for c in draw("blind")] == [c["record"] for c in blind]
    for case in blind:
        assert tuple(case["record"]) == RECORD
        _in_ranges(case["record"])
    for name in RECORD:
        drawn = [c["record"][name] for c in blind]
        assert len(set(drawn)) == len(blind), name
    for name in ("phi1", "phi4", "load_phase", "speed_offset_rpm"):  # spread over the whole range, either sign
        assert min(c["record"][name] for c in blind) < 0 < max(c["record"][name] for c in blind)
    assert max(c["record"]["start"] for c in blind) - min(c["record"]["start"] for c in blind) > 0.5
    assert [c["record"] for c in draw("other")] != [c["record"] for c in blind]
    # the record's start lies on the grid of the rate the set is drawn for; the rest of the record does not depend on it
    slow = hidden.draw_cases(HIDDEN, "blind", BASE, RANGES, CLASSES, fs=2133.0)
    for fast, case in zip(blind, slow):
        _in_ranges(case["record"], fs=2133.0)
        assert {k: v for k, v in case["record"].items() if k != "start"} == {k: v for k, v in fast["record"].items() if k != "start"}


def test_the_record_leaves_every_other_draw_as_it_was(blind):
    """Drawn from a stream of its own: classes, parameter values and noise seeds are those drawn before it existed
    (pinned from the code without it)."""
    assert [c["class"] for c in blind] == [
        "cubic_coupling", "breathing_crack", "parameter_change", "parameter_change", "healthy", "stick_slip", "loose_bearing",
        "stick_slip", "healthy", "cubic_coupling", "loose_bearing", "healthy", "cubic_coupling", "breathing_crack",
        "cubic_coupling", "stick_slip", "parameter_change", "breathing_crack", "parameter_change", "healthy",
        "breathing_crack", "stick_slip", "loose_bearing", "loose_bearing"]
    assert (blind[0]["truth"], blind[0]["noise_seed"]) == ({"gamma": 0.3520007662677691}, 1388764162)
    assert (blind[2]["truth"], blind[2]["noise_seed"]) == ({"kT2": 932111.5050045272}, 1596297866)
    assert (blind[3]["truth"], blind[3]["noise_seed"]) == ({"kT1": 2687619.3128597084}, 1480113845)


@pytest.fixture
def order_force(request):
    """An effect with a parameter of negative range: the open-world bench's order force, cos(n θ1 + phase) on m1."""
    request.addfinalizer(lambda: effects.use([]))
    effects.use(["ow_order_m1_x"], folder=Path(__file__).resolve().parents[1] / "bench" / "open_world" / "effects")
    return effects.active()["ow_order_m1_x"]


def test_an_effects_angle_is_drawn_through_its_range_either_sign(order_force):
    low, high = dict(hidden.default_ranges()["ow_order_m1_x"])["phase"]
    assert low < 0 < high
    section = {**HIDDEN, "sets": {"orders": {"cases": 12, "seed": 4}}}
    cases = hidden.draw_cases(section, "orders", BASE, classes=["ow_order_m1_x"])
    phases = [c["truth"]["phase"] for c in cases]
    assert all(low <= phase <= high for phase in phases) and min(phases) < 0 < max(phases)
    assert all(faults.fault_problems("ow_order_m1_x", c["truth"], BASE) == [] for c in cases)
    assert hidden.recorded_values(cases[0], BASE)["ow_order_m1_x.phase"] == phases[0]


def _texts(value):
    """The ways a drawn number could be spelled in a file."""
    return {repr(value), f"{value:g}", f"{value:.6g}", f"{value:.4g}", f"{value:.3e}", json.dumps(value)}


def test_measurement_file_carries_no_truth(tmp_path):
    cases = draw("six")
    assert {c["class"] for c in cases} == set(CLASSES)
    sampling = model.Sampling(fs=2500.0, t_first=0.5, n_samples=1500)
    forbidden_keys = {"scenario", "fault", "class", "truth", "description", "sigma", "snr_db", "seed", "noise_seed",
                      "parameters", "overrides", "kind", *hidden.CLASSES, *model.RIG_PARAMETERS,
                      *(slot for slot in slots.slot_names() if slot not in model.PARAMETER_NAMES),
                      *(p for effect in effects.active().values() for p in effect.parameter_names()),
                      *(part for kind in hidden.FAULT_CLASSES for part in kind.split("_"))}
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
        for value in case["record"].values():
            assert repr(value) not in text and f"{value:.6g}" not in text, (case["name"], value)
        assert ds.attrs["code_hash"] == "abc123"
        for name in model.OPERATING_PARAMETERS:  # the nameplate: the speed the machine runs at is not stated
            assert float(ds.attrs[name]) == BASE[name]
        assert case["record"]["speed_offset_rpm"] != 0.0
        # the recorder's clock: from 0, at the sampling's rate, wherever in the model's time the record starts
        np.testing.assert_allclose(ds["time"].values, np.arange(sampling.n_samples) / sampling.fs, rtol=0, atol=1e-12)
        assert ds["time"].values[0] == 0.0 and case["record"]["start"] >= 0.5

        measurement = io.read_measurement(path)
        assert measurement.channels == model.CHANNELS and len(measurement.channels) == 11
        assert measurement.sigma is None and "snr_db" not in measurement.attrs
        assert measurement.sampling.n_samples == sampling.n_samples
        assert measurement.sampling.fs == pytest.approx(sampling.fs, rel=1e-12)

    # The signal itself is the case's: 40 dB noise around its clean simulation, reproducible from the seed.
    case = next(c for c in cases if c["class"] == "loose_bearing")
    clean = simulation.simulate(_recorded(case, BASE), model.Sampling(sampling.fs, case["record"]["start"], sampling.n_samples))
    y = io.read_measurement(tmp_path / f"{case['name']}.nc").y
    ratio = np.std(y - clean, axis=1) / np.std(clean, axis=1)
    np.testing.assert_allclose(ratio, 0.01, rtol=0.1)
    hidden.write_case_measurement(case, BASE, sampling, 40.0, tmp_path / "again.nc")
    np.testing.assert_array_equal(io.read_measurement(tmp_path / "again.nc").y, y)


def _recorded(case, nameplate, recording=None):
    """The values a case's file was simulated with, built by hand: the case at its nameplate, with its record's angles
    and load phase and the nameplate speed plus the offset."""
    record = {**case["record"], **(recording["record"] if recording else {})}
    at = {**nameplate, **(recording["condition"] if recording else {})}
    at = {**at, "phi1": record["phi1"], "phi4": record["phi4"], "load_phase": record["load_phase"],
          "speed_rpm": at["speed_rpm"] + record["speed_offset_rpm"]}
    return faults.scenario_values(case["scenario"], at)


def _y(path):
    with xr.open_dataset(path, engine="netcdf4") as ds:
        return ds["y"].values, ds["time"].values, dict(ds.attrs)


def test_a_case_is_simulated_with_its_record_and_written_from_time_zero(tmp_path, blind):
    """The file is the case simulated at its drawn angles, load phase and running speed from its drawn start, its own
    noise added, stamped from 0 with the nameplate speed; instruments still read each channel late by their delay."""
    case = next(c for c in blind if c["class"] == "stick_slip")
    sampling = model.Sampling(fs=5000.0, t_first=0.5, n_samples=1000)
    record = case["record"]
    at = model.Sampling(sampling.fs, record["start"], sampling.n_samples)
    values = _recorded(case, BASE)
    assert values["speed_rpm"] != BASE["speed_rpm"] and values["load_phase"] == record["load_phase"]
    hidden.write_case_measurement(case, BASE, sampling, 40.0, tmp_path / "case.nc")
    y, time, attrs = _y(tmp_path / "case.nc")
    assert time[0] == 0.0 and float(attrs["speed_rpm"]) == BASE["speed_rpm"]
    clean = simulation.simulate(values, at)
    np.testing.assert_array_equal(y, noise.add_noise(clean, model.CHANNELS, 40.0, case["noise_seed"])[0])
    # the old clock (the model's own, at zero phases and the nameplate speed) is not what is written
    assert not np.allclose(clean, simulation.simulate(hidden.case_values(case, BASE), sampling))

    late = {**case, "instruments": {"b1_x": {"offset": 0.0, "gain": 1.0, "delay": 3e-4}}}
    hidden.write_case_measurement(late, BASE, sampling, 40.0, tmp_path / "late.nc")
    b1_x = model.CHANNELS.index("b1_x")
    clean[b1_x] = simulation.simulate(values, model.Sampling(sampling.fs, record["start"] - 3e-4, sampling.n_samples), ["b1_x"])[0]
    np.testing.assert_array_equal(_y(tmp_path / "late.nc")[0], noise.add_noise(clean, model.CHANNELS, 40.0, case["noise_seed"])[0])


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
    assert confusion["truth"] == list(hidden.CLASSES)  # every class has a case here, in the classes' order
    assert confusion["predicted"] == [*hidden.CLASSES, "unexplained"]
    counts = {(truth, predicted): n for truth, row in zip(confusion["truth"], confusion["counts"])
              for predicted, n in zip(confusion["predicted"], row) if n}
    assert counts == {
        ("healthy", "healthy"): 1, ("healthy", "parameter_change"): 1,
        ("parameter_change", "parameter_change"): 3,  # t_04 names the wrong parameter: counted, not correct
        ("stick_slip", "stick_slip"): 1, ("breathing_crack", "cubic_coupling"): 1,
        ("cubic_coupling", "cubic_coupling"): 1, ("loose_bearing", "unexplained"): 1,
    }
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


# ----------------------------------------------------------------------------------------- a user's effect



@pytest.fixture
def torque_ripple(request):
    """A user's effect (tests/effects/torque_ripple.py: amplitude·sin(order·θ1) on the motor) made active."""
    request.addfinalizer(lambda: effects.use([]))
    effects.use(["torque_ripple"], folder=Path(__file__).parent / "effects")
    return effects.active()["torque_ripple"]


def test_a_users_effect_is_a_hypothesis_of_the_diagnosis_and_a_class_of_the_blind_test(torque_ripple):
    # the diagnosis fits it, with its prior range and the drift parameters, like any built-in effect
    settings = Settings.from_config(CONFIG)
    assert settings.fault_ranges["torque_ripple"] == {"amplitude": (0.0, 50.0), "order": (1.0, 12.0)}
    hypothesis = next(h for h in settings.hypotheses() if h.name == "torque_ripple")
    assert (hypothesis.kind, hypothesis.effect) == ("torque_ripple", "torque_ripple")
    assert hypothesis.parameters == ["amplitude", "order", *settings.drift]
    row = hypothesis.parameter_rows(np.array([[20.0, 3.0, *(1.1 * BASE[name] for name in settings.drift)]]), BASE)[0]
    index = slots.slot_index()
    assert row[index["torque_ripple"]] == 1.0 and row[index["torque_ripple.amplitude"]] == 20.0
    assert row[index["torque_ripple.order"]] == 3.0
    assert all(row[index[name]] == pytest.approx(1.1 * BASE[name]) for name in settings.drift)
    assert all(row[index[kind]] == 0.0 for kind in effects.active() if kind != "torque_ripple")
    entries = signatures.entries({h.name: h for h in settings.hypotheses()}, list(settings.grids), settings.drift_sizes,
                                 settings.fault_ranges, settings.severities, slots.complete())
    assert [v["amplitude"] for name, v in entries if name == "torque_ripple"] == pytest.approx(
        [50.0 * (i + 0.5) / settings.severities for i in range(settings.severities)])

    # the blind test draws it (from its file's hidden range by default) and scores a verdict naming it
    assert "torque_ripple" in hidden.CLASSES and "torque_ripple" in hidden.FAULT_CLASSES
    section = {**HIDDEN, "sets": {"ripple": {"cases": 4, "seed": 3}}}
    cases = hidden.draw_cases(section, "ripple", BASE, classes=["torque_ripple", "healthy"])
    ripples = [c for c in cases if c["class"] == "torque_ripple"]
    assert len(ripples) == 2
    for case in ripples:
        assert set(case["truth"]) == {"amplitude", "order"} and 5.0 <= case["truth"]["amplitude"] <= 20.0
        values = hidden.case_values(case, BASE)
        assert values["torque_ripple"] == 1.0 and values["torque_ripple.amplitude"] == case["truth"]["amplitude"]
    assert {c["class"] for c in hidden.draw_cases(section, "ripple", BASE)} <= set(hidden.CLASSES)
    verdict = {"verdict": "new_dynamics", "effect": "torque_ripple", "equivalent": [], "chi2_before": 9.0, "chi2_after": 1.0,
               "parameters": {"amplitude": {"mean": ripples[0]["truth"]["amplitude"], "sd": 1.0, "hdi_low": 0.0, "hdi_high": 200.0}}}
    result = hidden.score(ripples[:1], {ripples[0]["name"]: verdict})
    assert result["accuracy"] == 1.0 and result["confusion"]["truth"] == ["torque_ripple"]
    assert [e["parameter"] for e in result["parameter_errors"]] == ["amplitude"]


DATASHEETS = {"b1_x": {"offset_sd": 1e-7, "gain_sd": 0.02, "delay_sd": 1e-4}, "w1": {"gain_sd": 0.001, "delay_sd": 1e-4},
              "torque_c": {"offset_sd": 5.0}}


def test_instrument_errors_are_drawn_on_top_of_the_same_machines(blind):
    section = copy.deepcopy(HIDDEN)
    section["sets"]["blind"] = {**section["sets"]["blind"], "instruments": True, "out_of_spec": 5}
    seen = hidden.draw_cases(section, "blind", BASE, RANGES, CLASSES, DATASHEETS, ("b1_x", "w1"))
    assert [{k: v for k, v in c.items() if k not in ("instruments", "out_of_spec")} for c in seen] == blind
    bad = [c for c in seen if "out_of_spec" in c]
    assert len(bad) == 5
    for case in seen:
        assert set(case["instruments"]) == set(DATASHEETS)
        assert case["instruments"]["w1"]["offset"] == 0.0 and case["instruments"]["torque_c"]["gain"] == 1.0  # no datasheet: exact
    for case in bad:
        where = case["out_of_spec"]
        assert where["channel"] in ("b1_x", "w1") and 10 <= abs(where["sds"]) <= 30  # on a compared channel, far off
        sd = DATASHEETS[where["channel"]][f"{where['quantity']}_sd"]
        error = case["instruments"][where["channel"]][where["quantity"]] - {"gain": 1.0}.get(where["quantity"], 0.0)
        assert error == pytest.approx(where["sds"] * sd)
    # Within spec the errors follow their datasheets' Normal priors.
    gains = np.array([c["instruments"]["b1_x"]["gain"] for c in seen if "out_of_spec" not in c or c["out_of_spec"]["channel"] != "b1_x"])
    assert abs(np.mean(gains) - 1.0) < 4 * 0.02 / np.sqrt(len(gains)) and 0.01 < np.std(gains) < 0.03


def test_a_measurement_through_instruments_is_offset_scaled_and_late():
    sampling = model.Sampling(fs=5000.0, t_first=0.1, n_samples=400)
    case = {"scenario": {"overrides": {}}, "instruments": {"b1_x": {"offset": 2e-8, "gain": 1.01, "delay": 3e-4}}}
    read = hidden._through_instruments(case, BASE, sampling, 1e-4)
    exact = hidden._through_instruments({"scenario": {"overrides": {}}}, BASE, sampling, 1e-4)
    late = model.Sampling(sampling.fs, sampling.t_first - 3e-4, sampling.n_samples)
    assert np.array_equal(exact, simulation.simulate(BASE, sampling, model.CHANNELS, 1e-4))
    b1_x = model.CHANNELS.index("b1_x")
    assert np.allclose(read[b1_x], 2e-8 + 1.01 * simulation.simulate(BASE, late, ["b1_x"], 1e-4)[0], rtol=0, atol=1e-15)
    assert np.array_equal(np.delete(read, b1_x, axis=0), np.delete(exact, b1_x, axis=0))


def test_the_score_counts_named_and_false_instrument_problems():
    cases = [{**CASES[0], "instruments": {}}, {**CASES[1], "instruments": {}, "out_of_spec": {"channel": "w1", "quantity": "gain", "sds": 12.0}},
             {**CASES[4], "instruments": {}, "out_of_spec": {"channel": "b1_x", "quantity": "delay", "sds": -15.0}}]
    problem = {"channel": "w1", "quantity": "gain"}
    verdicts = {"t_01": {**VERDICTS["t_01"], "sensor_problems": [{"channel": "b1_x", "quantity": "offset"}]},
                "t_02": {**VERDICTS["t_01"], "verdict": "sensor_problem", "sensor_problems": [problem]},
                "t_05": {**VERDICTS["t_05"], "sensor_problems": [], "sensor_alternatives": [
                    {"hypothesis": "healthy", "sensor_problems": [{"channel": "b1_x", "quantity": "delay"}]}]}}
    result = hidden.score(cases, verdicts)
    assert result["instruments"] == {"cases": 3, "out_of_spec": 2, "named": 1, "named_as_alternative": 1, "false_alarms": 1}
    assert [row["predicted"] for row in result["rows"]] == ["healthy", "healthy", "parameter_change"]  # a sensor problem: a healthy machine


MACHINES = {**HIDDEN, "sets": {**HIDDEN["sets"], "fleet": {"cases": 7, "seed": 11, "recordings": [2, 3]}}}
OPERATING_RANGE = CONFIG["operating_range"]
SHORT = model.Sampling(fs=5000.0, t_first=0.5, n_samples=1000)


@pytest.fixture(scope="module")
def fleet():
    cases = hidden.draw_cases(MACHINES, "fleet", BASE, RANGES, CLASSES)
    return hidden.draw_recordings(cases, "fleet", MACHINES["sets"]["fleet"], OPERATING_RANGE, ("b1_x", "b2_x", "w1"),
                                  BASE, SHORT, 40.0)


def test_a_machine_set_draws_recordings_that_the_workflow_can_name_before_the_draw(fleet):
    names = hidden.recording_names("fleet", MACHINES["sets"]["fleet"])
    assert {c["name"]: [f"{c['name']}/{r['name']}" for r in c["recordings"]] for c in fleet} == names
    assert {len(r) for r in names.values()} == {2, 3}
    assert {c["class"] for c in fleet} == set(CLASSES)  # the machines are a set's cases: every class once
    for case in fleet:
        for r in case["recordings"]:
            assert set(r["condition"]) == set(OPERATING_RANGE)
            assert all(low <= r["condition"][p] <= high for p, (low, high) in OPERATING_RANGE.items())
            assert r["channels"] and set(r["channels"]) <= {"b1_x", "b2_x", "w1"}
        conditions = [r["condition"]["T0"] for r in case["recordings"]]
        assert len(set(conditions)) == len(conditions)
    again = hidden.draw_recordings(hidden.draw_cases(MACHINES, "fleet", BASE, RANGES, CLASSES), "fleet",
                                   MACHINES["sets"]["fleet"], OPERATING_RANGE, ("b1_x", "b2_x", "w1"), BASE, SHORT, 40.0)
    assert again == fleet


def test_a_machines_angles_are_shared_by_its_recordings_and_the_rest_is_each_recordings_own(fleet):
    plain = hidden.draw_cases({**MACHINES, "sets": {"fleet": {"cases": 7, "seed": 11}}}, "fleet", BASE, RANGES, CLASSES)
    for case, alone in zip(fleet, plain):
        assert case["record"] == {"phi1": alone["record"]["phi1"], "phi4": alone["record"]["phi4"]}  # the machine's
        records = [r["record"] for r in case["recordings"]]
        for record in records:
            assert tuple(record) == ("load_phase", "start", "speed_offset_rpm")
            _in_ranges(record, SHORT.fs)
        for name in ("load_phase", "start", "speed_offset_rpm"):
            assert len({record[name] for record in records}) == len(records), (case["name"], name)
    assert len({case["record"]["phi1"] for case in fleet}) == len(fleet)
    # the conditions are those drawn before the record existed (pinned from the code without it)
    assert fleet[0]["recordings"][0] == {
        "name": "r1", "condition": {"T0": 884.0037509941055, "load_amp": 0.2961886147653513, "speed_rpm": 1062.2576226929748},
        "channels": ["b1_x", "w1"], "noise_seed": 226417662, "record": fleet[0]["recordings"][0]["record"]}


def test_every_hidden_machines_finding_shows_in_one_of_its_recordings(fleet):
    """Checked here independently of the draw: the truth against the nominal model at each recording's condition and
    record."""
    for case in fleet:
        if case["class"] == "healthy":
            continue
        excess = []
        for r in case["recordings"]:
            at = model.Sampling(SHORT.fs, r["record"]["start"], SHORT.n_samples)
            truth = simulation.simulate(_recorded(case, BASE, r), at, r["channels"])
            nominal = simulation.simulate(_recorded({**case, "scenario": {"overrides": {}}}, BASE, r), at, r["channels"])
            excess.append(float(np.mean(((truth - nominal) / noise.noise_sigma(truth, 40.0)[:, None]) ** 2)))
        assert max(excess) >= hidden.VISIBLE_CHI2 - 1, (case["name"], excess)


def test_a_machines_recording_file_holds_its_channels_at_its_condition_and_no_truth(tmp_path, fleet):
    case = next(c for c in fleet if c["class"] == "stick_slip")
    r = case["recordings"][0]
    path = tmp_path / "r.nc"
    hidden.write_recording_measurement(case, r["name"], BASE, SHORT, 40.0, path)
    m = io.read_measurement(path)
    assert m.channels == tuple(r["channels"]) and m.sigma is None
    y, time, attrs = _y(path)
    assert all(float(attrs[p]) == v for p, v in r["condition"].items())  # the nameplate speed
    text = json.dumps({k: str(v) for k, v in attrs.items()}).lower()
    assert "stick" not in text and "t_max" not in text and "seed" not in text
    assert all(repr(v) not in text for v in [*case["record"].values(), *r["record"].values()])
    # simulated at its condition and record from its start, written from 0
    np.testing.assert_allclose(time, np.arange(SHORT.n_samples) / SHORT.fs, rtol=0, atol=1e-12)
    clean = simulation.simulate(_recorded(case, BASE, r), model.Sampling(SHORT.fs, r["record"]["start"], SHORT.n_samples), r["channels"])
    np.testing.assert_array_equal(y, noise.add_noise(clean, r["channels"], 40.0, r["noise_seed"])[0])


def test_the_machine_score_sets_each_recordings_own_verdict_beside_the_machines():
    cases = [{**_case("m_01", "stick_slip", {"T_max": 1900.0}), "recordings": [{"name": "r1"}, {"name": "r2"}]},
             {**_case("m_02", "healthy", {}), "recordings": [{"name": "r1"}, {"name": "r2"}]}]
    slipping = {"verdict": "new_dynamics", "effect": "stick_slip", "chi2_before": [4.0, 1.0], "chi2_after": [1.0, 1.02],
                "parameters": {"T_max": {"mean": 1890.0, "sd": 20.0, "hdi_low": 1850.0, "hdi_high": 1930.0}}}
    machines = hidden.score(cases, {"m_01": slipping, "m_02": {"verdict": "healthy", "chi2_before": [1.0, 1.1]}})
    assert machines["accuracy"] == 1.0 and machines["rows"][0]["chi2_before"] == 4.0  # a machine's worst recording
    assert machines["parameter_errors"][0]["in_hdi"]
    alone = hidden.score_recordings(cases, {"m_01/r1": slipping, "m_01/r2": {"verdict": "healthy"},
                                            "m_02/r1": {"verdict": "healthy"}, "m_02/r2": {"verdict": "healthy"}})
    assert (alone["recordings"], alone["correct"], alone["accuracy"]) == (4, 3, 0.75)
    assert [row["recording"] for row in alone["rows"] if not row["correct"]] == ["m_01/r2"]


@pytest.mark.parametrize("phi1_off, phi1_sd, phi4_off, phi4_sd", [
    (0.0, 0.01, 0.0, 0.01),  # both imbalances seen
    (0.0, 0.002, 1.1, math.pi / math.sqrt(3)),  # the load's imbalance unseen (no probe near disk 4): its angle is anywhere
    (-0.9, math.pi / math.sqrt(3), 0.0, 0.003),  # the motor's unseen
])
def test_an_angle_on_the_shaft_is_scored_in_the_turn_the_imbalances_seen_give(phi1_off, phi1_sd, phi4_off, phi4_sd):
    """Where a record starts turns the whole shaft by ψ: a crack found at angle a + ψ is the truth a, whatever ψ,
    across the circle's seam too; ψ is what the found imbalance angles say, each as far as the data hold it."""
    case = {"name": "c_01", "class": "breathing_crack", "truth": {"alpha": 0.3, "angle": 3.0},
            "record": {"phi1": 0.1, "phi4": 0.5}}
    turn = 2.9  # the shaft's angle at the record's start
    found = 3.0 + turn - 2 * math.pi  # reported on the other side of the seam
    record = {"values": {"phi1": 0.1 + turn + phi1_off, "phi4": 0.5 + turn + phi4_off, "load_phase": 1.0},
              "sd": {"phi1": phi1_sd, "phi4": phi4_sd, "load_phase": 0.01}}
    verdict = {"verdict": "new_dynamics", "effect": "breathing_crack", "record": record,
               "parameters": {"alpha": {"mean": 0.31, "hdi_low": 0.29, "hdi_high": 0.33},
                              "angle": {"mean": found + 0.01, "hdi_low": found - 0.02, "hdi_high": found + 0.03, "sd": 0.01}}}
    errors = {e["parameter"]: e for e in hidden._parameter_errors(case, verdict)}
    assert errors["angle"]["truth"] == pytest.approx(3.0) and errors["angle"]["mean"] == pytest.approx(3.01, abs=0.005)
    assert errors["angle"]["in_hdi"] is True and errors["angle"]["relative_error"] is None
    # The interval holds the turn's own error too (the found angles' precisions added), each side in quadrature with
    # the angle's sd.
    turn_sd = 1 / math.sqrt(phi1_sd**-2 + phi4_sd**-2)
    assert errors["angle"]["hdi_high"] - errors["angle"]["mean"] == pytest.approx(0.02 * math.hypot(1.0, turn_sd / 0.01))
    assert errors["alpha"]["in_hdi"] is True
