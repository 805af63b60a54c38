"""The command line, run as a user would (a subprocess), against the library API."""

from __future__ import annotations

import subprocess
import sys

import jax.numpy as jnp
import numpy as np
from test_model import CONFIG

import spacegrasp_jax as sg


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "spacegrasp_jax.cli", *args], capture_output=True, text=True, timeout=300)


def numbers_after(label: str, text: str) -> np.ndarray:
    line = next(line for line in text.splitlines() if line.startswith(label))
    body = line.split(":", 1)[1].replace("[", " ").replace("]", " ").replace(",", " ")
    return np.array([float(token) for token in body.split() if token not in {"kg", "m", "rad"}])


def test_info_prints_the_paper_robot(robot):
    result = run_cli("info")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert numbers_after("total mass", out)[0] == 587.0  # 500 + 80 (links) + 7 (EE) kg, the paper
    q = jnp.asarray(sg.PAPER_Q_INIT)
    p_ee, _ = sg.ee_pose(robot, jnp.zeros(3), jnp.eye(3), q)
    np.testing.assert_allclose(numbers_after("EE position", out), p_ee, atol=1e-6)
    np.testing.assert_allclose(numbers_after("system CoM", out), sg.system_com(robot, jnp.zeros(3), jnp.eye(3), q), atol=1e-6)
    condition = numbers_after("mass matrix (13x13) condition number", out)[-1]
    np.testing.assert_allclose(condition, np.linalg.cond(sg.mass_matrix(robot, jnp.eye(3), q)), rtol=1e-5)


def test_info_reads_a_robot_file(tmp_path):
    path = tmp_path / "heavy.toml"
    path.write_text(CONFIG.read_text().replace("mass = 500.0", "mass = 1000.0", 1))
    result = run_cli("info", "--robot", str(path))
    assert result.returncode == 0, result.stderr
    assert numbers_after("total mass", result.stdout)[0] == 1087.0


def test_info_reports_a_bad_robot_file_clearly(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(CONFIG.read_text().replace("mass = 7.0", "mass = -7.0", 1))
    result = run_cli("info", "--robot", str(path))
    assert result.returncode == 2
    assert "end_effector.mass: masses must be positive" in result.stderr
    assert "Traceback" not in result.stderr
