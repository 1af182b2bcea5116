"""What every test shares: under pytest-xdist (one worker per core, as the README's test command runs), each worker's
compiled code and linear algebra run on one thread, so that two workers, and the Snakemake jobs the workflow tests
start beside them, do not oversubscribe the cores; a test of threading raises its own count (numba's maximum stays one
per core).  The longest test files are handed to the workers first."""

import os

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Before NumPy loads OpenBLAS, which reads it once: its threads spin while they wait, and beside another worker and
    # a Snakemake job they doubled an MCMC test's time.
    os.environ["OPENBLAS_NUM_THREADS"] = "1"

import numba
import pytest


@pytest.fixture(scope="session", autouse=True)
def _one_numba_thread_per_worker():
    if os.environ.get("PYTEST_XDIST_WORKER"):
        numba.set_num_threads(1)


# The test files that take longest (measured with --durations=0: the CI study and its reruns, the diagnoses, the MCMC
# runs), started first.  xdist hands whole files to its workers in collection order (--no-loadscope-reorder), and a
# long file handed out last runs alone while the other worker has nothing left to do.
LONGEST_FIRST = ("test_workflow.py", "test_diagnosis.py", "test_joint.py", "test_machine.py", "test_calibration.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # a stable sort: the rest keep their order
