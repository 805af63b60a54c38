"""Plausibility warnings: each unit slip a user met (degrees for radians, millimetres for
metres, a planet for a target) gets its line naming the value and what was probably meant,
the paper's scenario none; a run that never touched the target says so; the command line
prints the input warnings before it refuses or compiles anything."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spacegrasp_jax import cli
from spacegrasp_jax.envelope.plausibility import input_warnings, result_warnings
from spacegrasp_jax.envelope.scenario import PAPER_Q_INIT, paper_scenario

TARGET = {"mass": 300.0, "inertia": [60.0, 50.0, 40.0], "com_in_lar": [0.0, 0.0, 0.5]}


def test_the_paper_and_free_target_scenarios_are_plausible(robot):
    assert input_warnings(paper_scenario(robot)) == []
    assert input_warnings(paper_scenario(robot, target={**TARGET, "angular_velocity": [0, 0, 0.002]})) == []


def test_joint_angles_in_degrees(robot):
    degrees = np.degrees(np.asarray(PAPER_Q_INIT))
    lines = input_warnings(paper_scenario(robot, q_init=degrees))
    turned = [joint for joint in range(7) if abs(degrees[joint]) > 2.0 * math.pi]
    assert len(lines) == len(turned) >= 1
    joint = turned[0]
    assert lines[0].startswith(f"q_init[{joint}] = {degrees[joint]:g} rad is more than a turn: degrees?")
    assert f"({math.radians(degrees[joint]):.4g} rad)" in lines[0]


@pytest.mark.parametrize(
    "keywords, expected",
    [
        (
            {"sphere_radius": 30.0},
            "contact sphere radius = 30 m is 1e+03 times the paper's 0.03 m: millimetres? (0.03 m)",
        ),
        ({"contact_stiffness": 1e3}, "contact stiffness = 1000 N m^2 is 1e+04 times the paper's 0.1 N m^2"),
        ({"contact_stiffness": 1e-4}, "contact stiffness = 0.0001 N m^2 is 0.001 times the paper's 0.1 N m^2"),
        (
            {"target": {**TARGET, "mass": 5e9, "inertia": [1e9, 1e9, 1e9]}},
            "target mass = 5e+09 kg is outside a satellite's range",
        ),
        ({"target": {**TARGET, "inertia": [6e4, 5e4, 4e4], "mass": 0.3}}, "target mass = 0.3 kg"),
        ({"target": {**TARGET, "inertia": [6e-3, 5e-3, 4e-3]}}, "target inertia: radii of gyration"),
        ({"target": {**TARGET, "velocity": [5.0, 0.0, 0.0]}}, "target velocity = 5 m/s: mm/s? (0.005 m/s)"),
        (
            {"target": {**TARGET, "angular_velocity": [0, 0, 5.0]}},
            "target angular velocity = 5 rad/s: deg/s? (0.08727 rad/s)",
        ),
    ],
)
def test_each_implausible_input_gets_one_line(robot, keywords, expected):
    lines = input_warnings(paper_scenario(robot, **keywords))
    assert any(line.startswith(expected) for line in lines), lines
    assert len(lines) == 1 or "mass = 0.3" in expected  # a 0.3 kg target with kg m^2 of inertia: two slips


def test_a_run_that_never_touched_the_target_says_so():
    assert result_warnings({"max_contact_force_N": 0.0})[0].startswith("the end-effector never touched the target")
    assert result_warnings({"max_contact_force_N": 0.4}) == []
    assert result_warnings({"diverged": True, "max_contact_force_N": 0.0}) == []


def test_the_command_line_warns_before_anything_else(tmp_path, capsys):
    scenario = tmp_path / "degrees.toml"
    scenario.write_text(f"q_init = {np.degrees(np.asarray(PAPER_Q_INIT)).tolist()}\n[contact]\nradius = 30.0\n")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("")
    code = cli.main(
        ["simulate", "--controller", "admittance", "--scenario", str(scenario), "--out", str(tmp_path / "out")]
    )
    lines = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("compilation cache")]
    assert code == 2
    assert lines[-1].startswith("spacegrasp: error:") and "already holds files" in lines[-1]
    warnings = lines[:-1]
    assert warnings and all(line.startswith("spacegrasp: warning: ") for line in warnings)
    assert any("degrees?" in line for line in warnings) and any("millimetres? (0.03 m)" in line for line in warnings)
