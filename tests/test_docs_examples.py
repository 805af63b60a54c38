"""Every Python block of every documentation page and of the README runs, page by page, in
a fresh process, in order: the documentation's examples cannot rot."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from test_docs import PAGES, ROOT, docs_compile_cache, python_blocks


@pytest.mark.parametrize("page", [page for page in PAGES if python_blocks(page)], ids=lambda page: page.name)
def test_every_python_block_runs(page, tmp_path_factory):
    script = "\n\n".join(python_blocks(page))
    env = dict(os.environ, JAX_COMPILATION_CACHE_DIR=str(docs_compile_cache(tmp_path_factory)), MPLBACKEND="Agg")
    result = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, env=env, timeout=900
    )
    assert result.returncode == 0, f"{page.name}:\n{result.stderr[-4000:]}"
