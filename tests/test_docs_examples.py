"""Every Python block of every documentation page and of the README runs, page by page, in
a fresh process, in order: the documentation's examples cannot rot."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from test_docs import PAGES, ROOT, python_blocks

pytestmark = pytest.mark.slow  # each page in a fresh process, compiling what it runs


@pytest.mark.parametrize("page", [page for page in PAGES if python_blocks(page)], ids=lambda page: page.name)
def test_every_python_block_runs(page):
    script = "\n\n".join(python_blocks(page))
    env = dict(os.environ, MPLBACKEND="Agg")  # the test run's compilation cache comes with it (conftest.py)
    result = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, env=env, timeout=900
    )
    assert result.returncode == 0, f"{page.name}:\n{result.stderr[-4000:]}"
