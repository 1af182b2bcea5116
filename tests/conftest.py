"""What every test shares: under pytest-xdist (one worker per core, as the README's test command runs), each worker's
compiled code runs on one thread, so that two workers, and the Snakemake jobs the workflow tests start beside them, do
not oversubscribe the cores; a test of threading raises its own count (numba's maximum stays one per core)."""

import os

import numba
import pytest


@pytest.fixture(scope="session", autouse=True)
def _one_numba_thread_per_worker():
    if os.environ.get("PYTEST_XDIST_WORKER"):
        numba.set_num_threads(1)
