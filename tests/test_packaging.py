"""What installing the package puts on the import path: spacegrasp_jax and nothing generic."""

from __future__ import annotations

import json
import subprocess
import sys

PROBE = """
import importlib.util, json
names = ["tuning", "benchmarks", "spacegrasp_jax", "spacegrasp_jax.tuning", "spacegrasp_jax.benchmarks"]
print(json.dumps({name: importlib.util.find_spec(name) is not None for name in names}))
"""


def test_tuning_and_benchmarks_are_installed_under_the_package_only(tmp_path):
    # Run from an empty folder, so that only what is installed can be found.
    result = subprocess.run([sys.executable, "-c", PROBE], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == {
        "tuning": False,
        "benchmarks": False,
        "spacegrasp_jax": True,
        "spacegrasp_jax.tuning": True,
        "spacegrasp_jax.benchmarks": True,
    }
