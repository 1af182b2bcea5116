"""Independent tasks run side by side in threads: each spends its time in compiled code (the simulation kernel, the
instruments' closed form) that runs without the GIL, so a lone diagnosis uses every core numba is given."""

from __future__ import annotations

from collections.abc import Callable, Hashable, Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numba

K = TypeVar("K", bound=Hashable)
T = TypeVar("T")


def in_parallel(tasks: Mapping[K, Callable[[], T]]) -> dict[K, T]:
    """The results of ``tasks`` by name, in ``tasks``' order, run in as many threads as numba has.  Each task's result
    is what it would be alone: the compiled code's results do not depend on threads or on what runs beside it."""
    try:
        layer = numba.threading_layer()
    except ValueError:  # nothing parallel has run yet
        layer = None
    workers = min(len(tasks), numba.get_num_threads())
    if workers <= 1 or layer not in ("omp", "tbb"):  # numba's own workqueue layer may not be entered from two threads
        return {name: task() for name, task in tasks.items()}
    with ThreadPoolExecutor(workers) as pool:
        futures = {name: pool.submit(task) for name, task in tasks.items()}
        return {name: future.result() for name, future in futures.items()}
