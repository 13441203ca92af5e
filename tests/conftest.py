"""Shared test settings: hypothesis runs derandomized in CI so a run is reproducible; under
pytest-xdist (``make test`` runs 2 workers) each worker and the processes it starts use one
thread, and the long files are handed out first so that they do not end the run alone."""
import os
import sys
from pathlib import Path

import pytest
import torch
from hypothesis import settings

# the tests' own modules: helpers (tests/helpers) and the bad-input corpus package (tests/fuzz/bad_inputs)
sys.path[:0] = [str(Path(__file__).resolve().parent / "helpers"), str(Path(__file__).resolve().parent / "fuzz")]

settings.register_profile("ci", derandomize=True, print_blob=True)
settings.register_profile("dev", print_blob=True)
settings.load_profile("ci" if os.environ.get("CI") else "dev")


@pytest.fixture
def one_torch_thread():
    """Tiny models: a second OpenMP thread only thrashes when the 2 cores are shared."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(autouse=True)
def _own_hash_cache(monkeypatch):
    """An in-process ``typ`` call points TYP_HASH_CACHE at its project (``os.environ.setdefault``);
    it is unset around every test, so that no test inherits another's cache."""
    monkeypatch.delenv("TYP_HASH_CACHE", raising=False)


#: the files that take minutes (the pipeline end to end, the stages run as processes): first
LONG_FILES = ("test_pipeline_e2e.py", "test_real_target_e2e.py", "test_crash_safety.py", "test_real_data.py",
              "test_dask.py", "test_deploy.py", "test_server_lifecycle.py", "test_bad_inputs.py")


def pytest_configure(config):
    if os.environ.get("PYTEST_XDIST_WORKER"):
        # two workers on two cores: a second OpenMP thread each would only thrash
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
            os.environ[var] = "1"
        torch.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FILES)))  # stable: file order kept otherwise
