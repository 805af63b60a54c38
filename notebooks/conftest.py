"""The test suite executes every notebook (nbmake) at quick sizes: ``SPACEGRASP_NOTEBOOK_QUICK=1``
unless the caller set it. ``notebooks/run_full.sh`` sets it to 0 to regenerate the committed
full-size outputs. The kernels inherit this process's environment. Every notebook is in the
``slow`` tier: each starts a kernel that compiles its own programs."""

import os

import pytest

os.environ.setdefault("SPACEGRASP_NOTEBOOK_QUICK", "1")


def pytest_collection_modifyitems(items):
    for item in items:
        if item.path.suffix == ".ipynb":
            item.add_marker(pytest.mark.slow)
