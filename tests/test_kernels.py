"""Properties of the compiled kernel that the physics tests do not reach: its own sin/cos and batching."""

import ast
import json
import math
import subprocess
import sys

import numba
import numpy as np
from numba import njit

from newdyn import effects, faults, kernels, model, slots
from newdyn.simulation import simulate, simulate_batch

SINCOS = effects.sincos.compiled()  # what a kernel calls


@njit
def _sincos_many(x):
    out = np.empty((2, x.size))
    for i in range(x.size):
        out[0, i], out[1, i] = SINCOS(x[i])
    return out


def test_vectorizable_sincos_matches_libm_to_an_ulp_and_plain_python_bit_for_bit():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(-1e3, 1e3, 200_000), np.arange(-700, 700) * math.pi / 4, [0.0, -0.0, 1e-300]])
    s, c = _sincos_many(x)
    assert np.max(np.abs(s - np.sin(x))) <= 2.3e-16
    assert np.max(np.abs(c - np.cos(x))) <= 2.3e-16
    assert np.mean((s == np.sin(x)) & (c == np.cos(x))) > 0.9
    every_100th = x[::100].tolist()  # the effect files' checks and the SciPy reference call it as Python
    assert [effects.sincos(v) for v in every_100th] == list(zip(s[::100].tolist(), c[::100].tolist(), strict=True))


def test_results_do_not_depend_on_how_simulations_are_grouped():
    """Lanes of a SIMD block, threads and mixed effects in one batch give bit-identical results."""
    sampling = model.Sampling(fs=5000.0, t_first=0.1, n_samples=300)
    sets = [{"kT1": k} for k in np.linspace(2.5e6, 3.5e6, 9)]
    base = {**model.DEFAULTS, "T0": 1500.0}
    for kind, effect in effects.active().items():  # each effect, at the middle of its blind-test range
        parameters = {p.name: 0.5 * sum(p.draw_range) for p in effect.parameters}
        sets.append(faults.scenario_values({"fault": {"kind": kind, "parameters": parameters}}, base))
    outputs = [*model.CHANNELS, *[name for name in kernels.diagnostics() if name.endswith(".onsets")]]
    alone = np.stack([simulate(v, sampling, outputs) for v in sets])
    threads = numba.get_num_threads()
    try:
        for n in sorted({1, numba.config.NUMBA_NUM_THREADS}):  # one thread and as many as numba may run
            numba.set_num_threads(n)
            np.testing.assert_array_equal(simulate_batch(sets, sampling, outputs), alone)
            np.testing.assert_array_equal(simulate_batch(sets[::-1], sampling, outputs), alone[::-1])
            for k in (3, 5):  # narrow blocks, padded with a fault-free copy of their last lane
                np.testing.assert_array_equal(simulate_batch(sets[-k:], sampling, outputs), alone[-k:])
    finally:
        numba.set_num_threads(threads)


def test_slipping_rigs_get_the_same_bits_in_a_block_of_their_own_as_alone():
    """A block of rigs whose joints slip together (every lane stepping finely, so none takes the plain step) and the
    same rigs in another order, which fills the blocks' lanes differently, give each rig's own result."""
    sampling = model.Sampling(fs=5000.0, t_first=0.1, n_samples=300)
    sets = [faults.scenario_values({"fault": {"kind": "stick_slip", "parameters": {"T_max": t_max, "r_k": r_k, "J2a_share": 0.3}}},
                                   model.DEFAULTS) for t_max in (1680.0, 1720.0, 1760.0, 1800.0) for r_k in (0.97, 0.98, 0.99, 1.0)]
    outputs = [*model.CHANNELS, "stick_slip.onsets"]
    alone = np.stack([simulate(v, sampling, outputs) for v in sets])
    assert alone[:, -1, -1].min() >= 2  # every one slips
    np.testing.assert_array_equal(simulate_batch(sets, sampling, outputs), alone)
    np.testing.assert_array_equal(simulate_batch(sets[::-1], sampling, outputs), alone[::-1])


def test_lanes_are_filled_by_fine_step_count_then_by_the_slip_joint_parameters():
    rows = [faults.scenario_values({"fault": {"kind": "stick_slip", "parameters": {"T_max": t_max, "J2a_share": share}}}, model.DEFAULTS)
            for t_max, share in ((2000.0, 0.1), (1700.0, 0.9), (1900.0, 0.1), (1800.0, 0.9))]
    params = np.array([slots.parameter_vector(v) for v in [{}, *rows, {"kT1": 2.9e6}]])
    steps, _ = kernels.fine_steps(params)
    order = kernels.lane_order(params, steps)
    assert (steps[[0, -1]] == 1).all() and steps[2, 0] < steps[1, 0]  # a larger J2a has a slower fastest mode
    assert order.tolist() == [0, 5, 2, 4, 3, 1]  # rigs without a slip joint first, as given; then by count, then T_max


def test_an_open_joint_once_settled_steps_to_resolve_the_body_it_frees():
    """Once the modes a switch kicked have rung down, an open joint's lane steps to resolve its fastest mode: here J2a
    freed on the motor shaft against the motor, sqrt(kT1 (1/J1 + 1/J2a)) in closed form (the other side, J2b on the
    coupling, is slower at these splits); a search takes half as many steps."""
    params = np.array([slots.parameter_vector(faults.scenario_values(
        {"fault": {"kind": "stick_slip", "parameters": {"T_max": 1900.0, "J2a_share": share}}}, model.DEFAULTS)) for share in (0.1, 0.3, 0.5)])
    index = slots.slot_index()
    kT1, J1, J2a = (params[:, index[name]] for name in ("kT1", "J1", "J2a"))
    freed = np.sqrt(kT1 * (1.0 / J1 + 1.0 / J2a))
    steps, _ = kernels.fine_steps(params)
    np.testing.assert_array_equal(steps[:, 1], np.ceil(freed / kernels.OPEN_OMEGA_RATE))
    assert steps[:, 1].max() > 1  # the lightest J2a needs more than the plain step
    searched, _ = kernels.fine_steps(params, search=True)
    np.testing.assert_array_equal(searched[:, 1], np.maximum(1, np.ceil(freed / (kernels.SEARCH_STEP_FACTOR * kernels.OPEN_OMEGA_RATE))))


def test_a_contact_steps_finely_from_its_first_switch_on_and_a_search_plainly():
    """A loose bearing's lanes take CONTACT_STEPS steps per step for ever after a switch (its contacts recur every
    vibration cycle); with no clearance it never switches, so it takes the healthy rig's steps and gives its bits."""
    sets = [faults.scenario_values({"fault": {"kind": "loose_bearing", "parameters": {"gap": gap}}}, model.DEFAULTS)
            for gap in (0.0, 3e-8)]
    params = np.array([slots.parameter_vector(v) for v in [{}, *sets]])
    steps, settle = kernels.fine_steps(params)
    np.testing.assert_array_equal(steps[:, 0], [1, kernels.CONTACT_STEPS, kernels.CONTACT_STEPS])
    assert settle[0] == 0 and np.isinf(settle[1:]).all()
    searched, _ = kernels.fine_steps(params, search=True)
    np.testing.assert_array_equal(searched, 1)
    sampling = model.Sampling(fs=5000.0, t_first=0.1, n_samples=300)
    healthy, closed, loose = simulate_batch([{}, *sets], sampling, [*model.CHANNELS, "loose_bearing.onsets"])
    np.testing.assert_array_equal(closed, healthy)
    assert loose[-1, -1] > 10  # the 30-nm clearance is crossed many times


def test_an_effect_file_is_compiled_once_wherever_it_lies_and_anew_when_edited(tmp_path):
    """numba caches machine code by the rendered file: an edit of an effect must change the kernel's
    name, or the old effect's code would run; the same file in another study's folder must not."""
    source = effects.LIBRARY / "cubic_coupling.py"
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "user_cubic.py").write_text(source.read_text().replace('"cubic_coupling"', '"user_cubic"'))
    try:
        here, elsewhere = (kernels.kernel_digest(dict(effects.use(["user_cubic"], tmp_path / f))) for f in ("a", "b"))
        with open(tmp_path / "a" / "user_cubic.py", "a") as f:
            f.write("# an edit\n")
        edited = kernels.kernel_digest(dict(effects.use(["user_cubic"], tmp_path / "a")))
    finally:
        effects.use([])
    assert here == elsewhere
    assert edited != here
    assert kernels.kernel_digest(dict(effects.active())) not in (here, edited)


def test_a_kernel_counts_as_compiled_once_it_is_and_not_for_an_effect_set_never_run(tmp_path):
    simulate({}, model.Sampling(n_samples=1))
    assert kernels.is_compiled(dict(effects.active()))
    source = (effects.LIBRARY / "cubic_coupling.py").read_text().replace('"cubic_coupling"', '"user_cubic"')
    (tmp_path / "user_cubic.py").write_text(f"{source}# written for {tmp_path}\n")  # a set no run has had
    try:
        assert not kernels.is_compiled(dict(effects.use(["user_cubic"], tmp_path)))
    finally:
        effects.use([])


def test_the_rendered_kernel_writes_every_flat_index_out_as_the_index_it_stands_for():
    """Each _at(row, lane) call, over lines, nested and after non-ASCII text on its line, becomes np.uint64((row) *
    LANES + (lane)); the rendered kernel calls _at nowhere."""
    source = "x = w[_at(R_Y + 1,  # θ\n         lane)]  # ω\ny = 'θ' + str(_at(k, _at(2, 3)))\n"
    assert kernels._index_written_out(source) == (
        "x = w[np.uint64((R_Y + 1) * LANES + (lane))]  # ω\n"
        "y = 'θ' + str(np.uint64((k) * LANES + (np.uint64((2) * LANES + (3)))))\n"
    )
    calls = [node for node in ast.walk(ast.parse(kernels.render(effects.active()))) if isinstance(node, ast.Call)]
    assert calls and not [call for call in calls if isinstance(call.func, ast.Name) and call.func.id == "_at"]


# Run in a fresh process (numba's compiled functions are per process), on the kernel file argv[2]: its parts
# compiled as a helper process compiles them (argv[1] "helper"), or the whole kernel as a simulation compiles it
# (argv[1] "entry"); printed are the parts' names and each kernel function's signatures compiled in this process and
# loaded from numba's cache.
_COMPILE_IN_A_PROCESS = """
import json, sys
from pathlib import Path
import numba
from newdyn import kernels
what, path = sys.argv[1:]
if what == "helper":
    compiled = kernels.help_compile(path, [])
else:
    compiled = kernels._import(Path(path))
    kernels._compile_once(compiled, Path(path), {})
functions = {name: f for name, f in vars(compiled).items() if isinstance(f, numba.core.registry.CPUDispatcher)}
found = {kind: {name: sorted(map(str, getattr(f.stats, kind))) for name, f in functions.items() if getattr(f.stats, kind)}
         for kind in ("cache_misses", "cache_hits")}
print(json.dumps({"parts": [part.py_func.__name__ for part in compiled.COMPILE_PARTS], **found}))
"""


def test_a_helper_compiles_the_parts_of_a_kernel_that_the_compiling_process_then_loads_and_no_more(tmp_path, monkeypatch):
    """Processes share a first compile by compiling parts of the kernel apart (a helper process on a second core):
    the process that compiles the entry point must find each function a part calls in numba's cache, with the
    argument types the part called it with, and compile nothing a part compiled again (else a part's work is lost and
    the shared compile is no shorter than one process's).  The kernel of no effects, the cheapest to compile: the
    parts' argument types are the template's."""
    monkeypatch.setenv("NEWDYN_CACHE", str(tmp_path))
    monkeypatch.setenv("NUMBA_NUM_THREADS", "1")
    rendered = kernels.render({})
    path = kernels._written(rendered, kernels.kernel_digest({}, rendered))

    def compile_in_a_process(what: str) -> dict:
        run = subprocess.run([sys.executable, "-c", _COMPILE_IN_A_PROCESS, what, str(path)], capture_output=True,
                             text=True, check=True)
        return json.loads(run.stdout)

    parts = compile_in_a_process("helper")
    entry = compile_in_a_process("entry")
    names = set(parts["parts"])
    called = {node.func.id for function in ast.parse(rendered).body
              if isinstance(function, ast.FunctionDef) and function.name in names
              for node in ast.walk(function) if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)}
    by_the_parts = {name: set(signatures) for name, signatures in parts["cache_misses"].items() if name not in names}
    loaded = {name: set(signatures) for name, signatures in entry["cache_hits"].items() if name not in names}
    assert {"_rk4", "_lane_event", "_switch", "_record"} <= called & set(by_the_parts) <= set(loaded)  # as called
    assert all(signatures <= by_the_parts[name] for name, signatures in loaded.items())
    again = {name: signatures & set(entry["cache_misses"].get(name, ())) for name, signatures in by_the_parts.items()}
    assert not any(again.values())
