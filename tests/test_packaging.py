"""What installing the package puts on the import path (spacegrasp_jax and nothing generic), and
the JAX release it declares it needs."""

from __future__ import annotations

import inspect
import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import jax

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


#: JAX APIs the package calls that older releases lack, and the release that added each
#: (JAX's changelog; 0.6.0 has no ``jax.shard_map``).
JAX_APIS = {"jax.shard_map(..., check_vma=...)": (0, 6, 1)}


def test_the_declared_jax_floor_has_every_api_the_package_calls():
    pyproject = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    (requirement,) = [item for item in pyproject["project"]["dependencies"] if re.match(r"jax\s*>=", item)]
    floor = tuple(int(part) for part in requirement.split(">=")[1].strip().split("."))
    for api, release in JAX_APIS.items():
        assert floor >= release, f"pyproject.toml declares {requirement}, but {api} needs jax>={release}"
    assert "check_vma" in inspect.signature(jax.shard_map).parameters
