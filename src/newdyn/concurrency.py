"""Independent tasks run side by side in threads: each spends its time in compiled code (the simulation kernel, the
instruments' closed form) that runs without the GIL, so a lone diagnosis uses every core numba is given."""

from __future__ import annotations

import importlib
import threading
from collections.abc import Callable, Hashable, Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numba

K = TypeVar("K", bound=Hashable)
T = TypeVar("T")


class Stopped(Exception):
    """Raised by a speculative task that was told to stop (:func:`in_parallel`'s ``speculative``)."""


def import_beside(module: str) -> threading.Thread:
    """Start importing ``module`` in a thread of its own, for a later import of it to find it done: a slow import
    (ArviZ's, which compiles a numba function and imports Matplotlib) then runs while the compiled code, which runs
    without the GIL, leaves a core free.  An import of the module meanwhile waits for this one (Python's import lock),
    and the module is the same whoever imported it."""
    thread = threading.Thread(target=importlib.import_module, args=(module,), name=f"import {module}", daemon=True)
    thread.start()
    return thread


def _threads(n_tasks: int) -> int:
    """Threads for ``n_tasks`` side by side: as many as numba has, or 1 where its threading layer may not be entered
    from two threads (numba's own workqueue)."""
    threads = numba.get_num_threads()  # first: it starts numba's threads, which chooses the layer
    return min(n_tasks, threads) if numba.threading_layer() in ("omp", "tbb") else 1


def in_parallel(tasks: Mapping[K, Callable[[], T]], speculative: Mapping[K, Callable[[threading.Event], T]] | None = None,
                wanted: Callable[[dict[K, T]], bool] | None = None) -> dict[K, T]:
    """The results of ``tasks`` by name, in ``tasks``' order, run in as many threads as numba has.  Each task's result
    is what it would be alone: the compiled code's results do not depend on threads or on what runs beside it.

    ``speculative`` tasks run beside them, on the chance that ``wanted`` (of ``tasks``' results) will be true once
    those are done; where it is false, or a task fails, they are told to stop (their event is set, on which they raise
    :class:`Stopped`) and left out of the result, so that speculating costs only their share of the cores while
    ``tasks`` ran.  Where there is one thread, they run after ``tasks``, and only when wanted."""
    speculative = dict(speculative or {})
    if speculative and wanted is None:
        raise ValueError("speculative tasks need a wanted() to decide on them")
    stop = threading.Event()
    threads = _threads(len(tasks) + len(speculative))
    if threads <= 1:
        results = {name: task() for name, task in tasks.items()}
        if speculative and wanted(results):
            return {**results, **{name: task(stop) for name, task in speculative.items()}}
        return results
    keep = False
    with ThreadPoolExecutor(threads) as pool:
        # the speculative first, as the largest tasks, so that they do not start last
        guesses = {name: pool.submit(task, stop) for name, task in speculative.items()}
        futures = {name: pool.submit(task) for name, task in tasks.items()}
        try:
            results = {name: future.result() for name, future in futures.items()}
            keep = not speculative or wanted(results)
        finally:
            if not keep:
                stop.set()
    return {**results, **{name: future.result() for name, future in guesses.items()}} if keep else results
