"""Tasks side by side in threads, and speculative ones stopped when their results are not wanted."""

import os
import subprocess
import sys
import threading

import numba
import numpy as np
import pytest

from newdyn import concurrency


@numba.njit(parallel=True)
def _parallel_sum(x):
    total = 0.0
    for i in numba.prange(x.size):
        total += x[i]
    return total


@pytest.fixture(params=["threads", "one thread"])
def threads(request):
    """Both ways :func:`concurrency.in_parallel` runs: in a pool (once numba's threading layer is up) and in turn."""
    _parallel_sum(np.ones(100))  # starts numba's threading layer
    if request.param == "threads" and numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread at most here")
    before = numba.get_num_threads()
    numba.set_num_threads(2 if request.param == "threads" else 1)
    if request.param == "threads" and concurrency._threads(2) < 2:
        numba.set_num_threads(before)
        pytest.skip(f"numba's {numba.threading_layer()} threading layer is not entered from two threads")
    yield request.param
    numba.set_num_threads(before)


def test_tasks_run_side_by_side_before_anything_parallel_has_run():
    """A process's first tasks (a machine's joint fits, before any simulation) run side by side, not in turn: two that
    wait for each other both return.  In a process of its own, as numba's threading layer starts only once."""
    script = """
import threading, numba
from newdyn import concurrency
barrier = threading.Barrier(2, timeout=5)
try:
    concurrency.in_parallel({"a": barrier.wait, "b": barrier.wait})
    side_by_side = True
except threading.BrokenBarrierError:
    side_by_side = False
print(side_by_side, numba.threading_layer())
"""
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                         env={**os.environ, "NUMBA_NUM_THREADS": "2"})
    side_by_side, layer = run.stdout.split()
    if layer not in ("omp", "tbb"):
        pytest.skip(f"numba's {layer} threading layer is not entered from two threads")
    assert side_by_side == "True"


def test_results_are_by_name_in_the_tasks_order(threads):
    results = concurrency.in_parallel({name: lambda name=name: name * 2 for name in "cab"})
    assert list(results) == list("cab") and results == {"c": "cc", "a": "aa", "b": "bb"}


def waits_for(stop: threading.Event, ran: list):
    """A speculative task that runs until it is stopped, as a fit's simulations do."""
    ran.append("told to stop" if stop.wait(timeout=60) else "never told to stop")
    raise concurrency.Stopped


def test_speculative_tasks_are_kept_when_wanted(threads):
    seen = []
    results = concurrency.in_parallel({"small": lambda: 1}, {"large": lambda stop: 0 if stop.is_set() else 2},
                                      lambda done: seen.append(done) or True)
    assert results == {"small": 1, "large": 2} and seen == [{"small": 1}]


def test_unwanted_speculative_tasks_are_stopped_and_left_out(threads):
    ran = []
    results = concurrency.in_parallel({"small": lambda: 1}, {"large": lambda stop: waits_for(stop, ran)}, lambda done: False)
    assert results == {"small": 1}
    # in a pool it ran beside the small task until stopped; in turn it never started
    assert ran == (["told to stop"] if threads == "threads" else [])


def test_a_failing_task_stops_the_speculative_ones_and_is_raised(threads):
    ran = []

    def fails():
        raise RuntimeError("a fit failed")

    with pytest.raises(RuntimeError, match="a fit failed"):
        concurrency.in_parallel({"small": fails}, {"large": lambda stop: waits_for(stop, ran)}, lambda done: True)
    assert ran == (["told to stop"] if threads == "threads" else [])


def test_a_module_imported_beside_is_imported_once_in_its_thread_and_a_later_import_waits_for_it(tmp_path, monkeypatch):
    (tmp_path / "import_gate.py").write_text("import threading\nentered = threading.Event()\n")
    (tmp_path / "slow_to_import.py").write_text(
        "import threading, time\nimport import_gate\nimporters = [threading.current_thread().name]\n"
        "import_gate.entered.set()\ntime.sleep(0.3)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("import_gate", "slow_to_import"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    import import_gate

    thread = concurrency.import_beside("slow_to_import")
    assert import_gate.entered.wait(10)  # the thread is inside the module's body
    import slow_to_import  # waits for the thread's import to finish instead of importing it a second time

    assert slow_to_import.importers == ["import slow_to_import"]
    assert sys.modules["slow_to_import"] is slow_to_import
    thread.join()
