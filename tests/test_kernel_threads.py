"""The compiled kernels' parallel loops on several threads: the test workers run numba on one thread
(conftest.py), so the kernels' reference tests run again here in a fresh process with two."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from conftest import ROOT

KERNEL_TESTS = ["tests/test_model_math.py", "tests/test_simulator.py", "tests/test_compiled_objective.py"]


@pytest.mark.slow
def test_the_parallel_kernels_match_their_references_on_two_threads():
    env = {**os.environ, "NUMBA_NUM_THREADS": "2", "OMP_NUM_THREADS": "1"}
    env.pop("PYTEST_XDIST_WORKER", None)   # else conftest.py would set one thread again
    check = subprocess.run([sys.executable, "-c", "import numba; print(numba.get_num_threads())"],
                           capture_output=True, text=True, env=env, check=True)
    assert check.stdout.strip() == "2"
    result = subprocess.run([sys.executable, "-m", "pytest", "-n", "0", "-q", "-p", "no:cacheprovider",
                             *KERNEL_TESTS, "-k", "chamfer or edgeconv or compiled"],
                            cwd=ROOT, capture_output=True, text=True, timeout=600, env=env)
    assert result.returncode == 0, result.stdout[-3000:]
    assert " passed" in result.stdout and " failed" not in result.stdout
