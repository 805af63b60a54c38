"""The command line, run as a user would (a subprocess), against the library API."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest
from test_model import CONFIG

import spacegrasp_jax as sg


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "spacegrasp_jax.cli", *args], capture_output=True, text=True, timeout=300
    )


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
    np.testing.assert_allclose(
        numbers_after("system CoM", out), sg.system_com(robot, jnp.zeros(3), jnp.eye(3), q), atol=1e-6
    )
    condition = numbers_after("mass matrix (13x13) condition number", out)[-1]
    np.testing.assert_allclose(condition, np.linalg.cond(sg.mass_matrix(robot, jnp.eye(3), q)), rtol=1e-5)


def test_the_command_line_loads_without_the_libraries_only_some_commands_use():
    # Every command's start pays for what the command line imports: matplotlib's pyplot (the
    # figures), scipy (the linear analysis, the statistics) and cma (CMA-ES) are imported
    # where they are used, about half a second of every start.
    probe = (
        "import sys, spacegrasp_jax.cli; print([m for m in ('matplotlib.pyplot', 'scipy', 'cma') if m in sys.modules])"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]", result.stdout


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
    assert "end_effector.mass: a mass must be positive or 0" in result.stderr
    assert "Traceback" not in result.stderr


# ---- reproduce and simulate (in-process: the session's compiled rollouts are reused) ------

import json  # noqa: E402
from pathlib import Path  # noqa: E402

from csv_files import assert_csv_holds  # noqa: E402

from spacegrasp_jax import cli  # noqa: E402
from spacegrasp_jax.jobs import executable_store  # noqa: E402
from spacegrasp_jax.loop.control import tuned_gains  # noqa: E402

SUMMARY_KEYS = {
    "max_abs_torque_Nm",
    "final_position_error_m",
    "final_orientation_error_rad",
    "max_contact_force_N",
    "first_contact_s",
    "max_linear_momentum_Ns",
    "max_angular_momentum_Nms",
    "max_base_speed_mps",
    "max_base_rate_radps",
    "compile_time_s",
    "run_time_s",
}
FIGURES = [
    f"fig{i}_{name}.png"
    for i, name in [
        (4, "ee_pose"),
        (5, "contact_force"),
        (6, "momentum"),
        (7, "base_velocity"),
        (8, "joint_torques"),
        (9, "fts_loads"),
    ]
]


def test_reproduce_writes_every_file_and_field_and_is_deterministic(tmp_path, full_runs, capsys):
    first, second = tmp_path / "a", tmp_path / "b"
    assert cli.main(["reproduce", "--compile-cache", "none", "--out", str(first)]) == 0
    printed = capsys.readouterr().out
    assert "Table 5" in printed and "final position error" in printed
    assert cli.main(["reproduce", "--compile-cache", "none", "--out", str(second)]) == 0
    for name in [
        "table5.csv",
        "summary.json",
        "config.json",
        "timeseries_admittance.npz",
        "timeseries_cartesian.npz",
        *FIGURES,
    ]:
        assert (first / name).stat().st_size > 0, name
    rows = (first / "table5.csv").read_text().splitlines()
    assert rows[0] == "joint,admittance_Nm,cartesian_Nm,paper_admittance_Nm,paper_cartesian_Nm"
    assert rows[2].split(",")[3:] == ["2.45", "4.21"] and len(rows) == 8
    assert (first / "table5.csv").read_text() == (second / "table5.csv").read_text()
    summaries = [json.loads((folder / "summary.json").read_text()) for folder in (first, second)]
    for key in ("admittance", "cartesian"):
        assert set(summaries[0][key]) >= SUMMARY_KEYS
        assert len(summaries[0][key]["max_abs_torque_Nm"]) == 7
        for field in SUMMARY_KEYS - {"compile_time_s", "run_time_s"}:
            assert summaries[0][key][field] == summaries[1][key][field], field
        with np.load(first / f"timeseries_{key}.npz") as a, np.load(second / f"timeseries_{key}.npz") as b:
            assert set(a.files) >= {
                "t",
                "pose_ee",
                "pose_des",
                "contact_force",
                "momentum",
                "V_base",
                "u",
                "fts_force",
                "fts_torque",
                "V_ref",
                "qd_des",
            }
            for name in a.files:
                np.testing.assert_array_equal(a[name], b[name])
    # The numbers on disk are the library's.
    np.testing.assert_allclose(
        summaries[0]["admittance"]["max_abs_torque_Nm"],
        full_runs["admittance"].summary["max_abs_torque_Nm"],
        rtol=1e-12,
    )
    record = json.loads((first / "config.json").read_text())["record"]
    assert {"robot", "scenario", "realism", "variants", "criteria", "command", "versions"} <= set(record)
    assert {"spacegrasp_jax_version", "jax_version", "git_revision"} <= set(record["versions"])
    assert [variant["controller"] for variant in record["variants"]] == ["admittance", "cartesian"]
    assert record["variants"][0]["gains"]["kp"] == [140.0, 210.0, 140.0, 105.0, 105.0, 21.0, 21.0]
    assert record["command"][:2] == ["spacegrasp", "reproduce"] and record["robot"] is None
    # The same command again replaces its own reproduction (the README's warm rerun); any
    # other command is refused there as everywhere
    assert cli.main(["reproduce", "--compile-cache", "none", "--out", str(first)]) == 0
    assert f"replacing the reproduction in {first} (the same command's" in capsys.readouterr().out
    assert (first / "table5.csv").read_text() == (second / "table5.csv").read_text()
    assert cli.main(["reproduce", "--compile-cache", "none", "--out", str(first), "--csv"]) == 2
    assert "already holds a reproduce run" in capsys.readouterr().err


def test_simulate_one_controller_with_gains_and_scenario_files(tmp_path, gains):
    gains_file = tmp_path / "gains.json"
    gains_file.write_text(json.dumps({**gains.to_dict(), "Kd": 300.0}))
    scenario_file = tmp_path / "scenario.toml"
    scenario_file.write_text("duration = 1.0\n")
    out = tmp_path / "sim"
    args = [
        "simulate",
        "--compile-cache",
        "none",
        "--controller",
        "admittance",
        "--gains",
        str(gains_file),
        "--scenario",
        str(scenario_file),
        "--out",
        str(out),
    ]
    assert cli.main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary) == {"admittance"} and set(summary["admittance"]) >= SUMMARY_KEYS
    assert (out / "timeseries_admittance.npz").exists() and all((out / name).exists() for name in FIGURES)
    record = json.loads((out / "config.json").read_text())["record"]
    assert record["variants"][0]["gains"]["Kd"] == [300.0] * 6 and record["sources"]["gains_filled"] is None
    assert record["variants"][0]["label"] == "gains" and record["sources"]["gains"] == str(gains_file)


def test_a_gains_file_runs_with_what_fill_from_gives_and_says_so(tmp_path, capsys):
    """A file without Kd runs only with --fill-from: the run's gains are the file's with the
    paper's Kd, a notice says so, and config.json records the groups filled and from where."""
    gains_file = tmp_path / "no_Kd.json"
    gains_file.write_text(json.dumps({"Md": 900.0, "Bd": 500.0, "kp": 140.0, "ki": 10.0, "kd": 0.01}))
    scenario_file = tmp_path / "scenario.toml"
    scenario_file.write_text("duration = 0.05\n[trajectory]\nduration = 0.05\n")
    args = ["simulate", "--compile-cache", "none", "--controller", "admittance", "--gains", str(gains_file)]
    args += ["--scenario", str(scenario_file), "--out", str(tmp_path / "sim")]
    assert cli.main(args) == 2
    assert "no_Kd.json: Kd: missing" in capsys.readouterr().err
    assert cli.main([*args, "--fill-from", "paper"]) == 0
    assert f"spacegrasp: notice: {gains_file}: Kd from paper (--fill-from)" in capsys.readouterr().err
    record = json.loads((tmp_path / "sim" / "config.json").read_text())["record"]
    assert record["sources"]["gains_filled"] == {"groups": ["Kd"], "from": "paper"}
    gains = record["variants"][0]["gains"]
    assert gains["Kd"] == [600.0] * 6 and gains["Md"] == [900.0] * 6
    # a shipped set by name
    args = ["simulate", "--compile-cache", "none", "--controller", "admittance", "--gains", "flight"]
    assert cli.main([*args, "--scenario", str(scenario_file), "--out", str(tmp_path / "flight")]) == 0
    notice = "spacegrasp: notice: --gains flight: tuned in the flight-like loop (--realism flight); this run's loop is the ideal one"
    assert notice in capsys.readouterr().err  # gains tuned for another loop than this run's
    record = json.loads((tmp_path / "flight" / "config.json").read_text())["record"]
    assert record["sources"]["gains"] == "flight" and record["variants"][0]["label"] == "flight"
    assert record["variants"][0]["gains"] == tuned_gains("flight").to_dict()


def test_the_sets_said_to_be_tuned_in_the_flight_like_loop_are_those_whose_command_says_so():
    """``TUNED_IN_FLIGHT_LOOP`` (the notice above) against the shipped sets' own records:
    each ``*.settings.json``'s tuning command names its realism."""
    from spacegrasp_jax.loop.control.gains import TUNED_GAINS_FILES
    from spacegrasp_jax.loop.control.schedule import TUNED_IN_FLIGHT_LOOP, TUNED_SCHEDULE_FILES

    data = Path(sg.__file__).parent / "data"
    in_flight = set()
    for name, file in {**TUNED_GAINS_FILES, **TUNED_SCHEDULE_FILES}.items():
        command = json.loads((data / file.replace(".json", ".settings.json")).read_text())["command"]
        if "--realism flight" in " ".join([command] if isinstance(command, str) else command):
            in_flight.add(name)
    assert in_flight == set(TUNED_IN_FLIGHT_LOOP)


@pytest.mark.slow
def test_compare_names_the_robots_of_runs_of_different_arms(tmp_path, capsys):
    """A UR5 and a Panda, each on the paper's satellite with its own gains: ``compare``
    labels the runs by their robot (and gains), not by gains file names alone."""
    configs = Path(__file__).resolve().parents[1] / "configs"
    folders = []
    for arm in ("ur5", "panda"):
        scenario = tmp_path / f"{arm}_short.toml"
        scenario.write_text(
            (configs / f"{arm}_scenario.toml").read_text() + "\nduration = 0.05\n[trajectory]\nduration = 0.05\n"
        )
        folders.append(str(tmp_path / arm))
        args = ["simulate", "--compile-cache", "none", "--controller", "admittance"]
        args += [
            "--robot",
            str(configs / f"{arm}_on_satellite.toml"),
            "--gains",
            str(configs / f"{arm}_ideal_gains.json"),
        ]
        assert cli.main([*args, "--scenario", str(scenario), "--out", folders[-1]]) == 0
    assert cli.main(["compare", *folders, "--out", str(tmp_path / "both")]) == 0
    record = json.loads((tmp_path / "both" / "compare.json").read_text())
    assert record["differing"] == ["robot", "gains"]
    assert [run["label"] for run in record["runs"]] == [
        "robot ur5_on_satellite, gains ur5_ideal_gains",
        "robot panda_on_satellite, gains panda_ideal_gains",
    ]
    assert "robot ur5_on_satellite, gains ur5_ideal_gains" in capsys.readouterr().out


@pytest.mark.slow
def test_compare_overlays_runs_of_different_realisms(tmp_path, capsys):
    """Two runs that differ in their loop only: ``compare`` labels them by it, names what
    they share in the figures' caption, and its table holds each run's own numbers;
    ``--csv`` writes the time series the .npz holds, number for number."""
    scenario = tmp_path / "short.toml"
    scenario.write_text("duration = 0.2\n[trajectory]\nduration = 0.2\n")
    base = ["simulate", "--compile-cache", "none", "--controller", "admittance", "--scenario", str(scenario)]
    assert cli.main([*base, "--out", str(tmp_path / "ideal"), "--csv"]) == 0
    assert cli.main([*base, "--realism", "flight", "--out", str(tmp_path / "flight")]) == 0
    printed = capsys.readouterr().out
    assert "maximal absolute joint torques" in printed and "paper" not in printed.split("running")[1]  # no paper column
    assert (
        cli.main(["compare", str(tmp_path / "ideal"), str(tmp_path / "flight"), "--out", str(tmp_path / "both")]) == 0
    )
    printed = capsys.readouterr().out
    record = json.loads((tmp_path / "both" / "compare.json").read_text())
    assert record["differing"] == ["loop"] and [run["label"] for run in record["runs"]] == ["loop ideal", "loop flight"]
    assert record["common"] == "law admittance, robot paper, gains paper, target fixed"
    assert all((tmp_path / "both" / name).stat().st_size > 0 for name in FIGURES)
    for run in record["runs"]:
        summary = json.loads((Path(run["folder"]) / "summary.json").read_text())["admittance"]
        assert record["table"][run["label"]]["largest_peak_torque_Nm"] == summary["largest_peak_torque_Nm"]
        assert run["label"] in printed
    peaks = [record["table"][label]["largest_peak_torque_Nm"] for label in ("loop ideal", "loop flight")]
    assert peaks[0] != peaks[1]  # two different runs, not one twice
    with np.load(tmp_path / "ideal" / "timeseries_admittance.npz") as data:
        assert_csv_holds(tmp_path / "ideal" / "timeseries_admittance.csv", dict(data), rows=200)
    assert cli.main(["compare", str(tmp_path / "ideal"), "--out", str(tmp_path / "one")]) == 2
    assert "compare: needs at least two runs, found 1" in capsys.readouterr().err


def test_compare_tells_apart_two_gains_files_of_one_name(tmp_path, capsys, gains):
    """Two tuning runs' ``gains.json`` (the same name in two folders): ``compare`` labels the
    runs by their folders, whole on the console (no default ``--controller``: the admittance law)."""
    scenario = tmp_path / "short.toml"
    scenario.write_text("duration = 0.2\n[trajectory]\nduration = 0.2\n")
    base = ["simulate", "--compile-cache", "none", "--scenario", str(scenario)]
    for name, Kd in (("first_tuning_run_of_the_week", 600.0), ("second_tuning_run_of_the_week", 300.0)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "gains.json").write_text(json.dumps({**gains.to_dict("admittance"), "Kd": Kd}))
        assert (
            cli.main([*base, "--gains", str(tmp_path / name / "gains.json"), "--out", str(tmp_path / f"run_{Kd:g}")])
            == 0
        )
    capsys.readouterr()
    runs = [str(tmp_path / "run_600"), str(tmp_path / "run_300")]
    assert cli.main(["compare", *runs, "--out", str(tmp_path / "both")]) == 0
    record = json.loads((tmp_path / "both" / "compare.json").read_text())
    labels = ["gains first_tuning_run_of_the_week-gains", "gains second_tuning_run_of_the_week-gains"]
    assert record["differing"] == ["gains"] and [run["label"] for run in record["runs"]] == labels
    assert record["runs"][0]["law"] == "admittance"
    printed = capsys.readouterr().out
    assert all(f"{label} " in printed for label in labels)  # whole, not cut at 40 characters


@pytest.mark.slow
def test_xlas_own_log_is_hidden_unless_verbose(tmp_path):
    """XLA's C++ log (where its "Very slow compile?" banner is written, at ERROR level) made
    to write its INFO lines too: the command hides every line of it written after it
    starts, ``--verbose`` shows them."""
    scenario = tmp_path / "short.toml"
    scenario.write_text("duration = 0.05\n[trajectory]\nduration = 0.05\n")
    env = dict(os.environ, TF_CPP_MIN_LOG_LEVEL="0")
    xla_line = re.compile(r"^[IWEF]\d{4} \d\d:\d\d:\d\d", re.MULTILINE)  # the C++ log's format

    def simulate(out, *extra):
        command = [sys.executable, "-m", "spacegrasp_jax.cli", "simulate", "--controller", "cartesian"]
        command += ["--scenario", str(scenario), "--out", str(tmp_path / out), "--compile-cache", "none", *extra]
        result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
        assert result.returncode == 0, result.stderr
        return result.stderr.split("compilation cache: off", 1)[1]  # what is written after the command starts

    assert not xla_line.search(simulate("quiet"))
    assert xla_line.search(simulate("verbose", "--verbose"))


@pytest.mark.slow
def test_simulate_never_overwrites_a_run_without_overwrite(tmp_path, capsys):
    """The folder rule end to end: a folder of the user's files is refused, then shared with
    ``--overwrite``; a second run is refused, then replaces the first with ``--overwrite``
    (the first run's files gone, the user's kept)."""
    scenario_file = tmp_path / "scenario.toml"
    scenario_file.write_text("duration = 0.2\n[trajectory]\nduration = 0.2\n")
    out = tmp_path / "sim"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    args = ["simulate", "--compile-cache", "none", "--controller", "cartesian", "--scenario", str(scenario_file)]
    args += ["--out", str(out)]
    assert cli.main(args) == 2
    assert "sim already holds files this tool did not write (notes.txt): pass --overwrite" in capsys.readouterr().err
    assert cli.main([*args, "--overwrite"]) == 0
    assert (out / "summary.json").exists() and (out / "notes.txt").read_text() == "mine\n"
    printed = capsys.readouterr()
    # 0.2 s ends before the end-effector reaches the contact sphere: said after the run
    assert (
        "spacegrasp: warning: cartesian: the end-effector never touched the target (max contact force 0 N)"
        in printed.err
    )
    assert "cartesian: final position error" in printed.out and "capture" in printed.out
    assert cli.main(args) == 2
    assert "sim already holds a simulate run (started" in capsys.readouterr().err
    (out / "stale.npz").write_bytes(b"left by the first run")
    assert cli.main([*args, "--overwrite"]) == 0
    assert not (out / "stale.npz").exists() and (out / "notes.txt").read_text() == "mine\n"
    assert (out / "summary.json").exists() and (out / "fig4_ee_pose.png").exists()
    # the 0.2 s run stops far from the target: a result (0) unless --strict asks for its own code
    assert cli.main([*args, "--overwrite", "--strict"]) == 4
    assert "spacegrasp: capture failed (cartesian): exit 4 (--strict)" in capsys.readouterr().err
    assert (out / "summary.json").exists()


def test_simulate_rejects_bad_files_before_running(tmp_path, gains, capsys):
    bad_gains = tmp_path / "gains.json"
    bad_gains.write_text(json.dumps({**gains.to_dict(), "Kd": -1.0}))
    assert (
        cli.main(
            [
                "simulate",
                "--compile-cache",
                "none",
                "--controller",
                "cartesian",
                "--gains",
                str(bad_gains),
                "--out",
                str(tmp_path / "x"),
            ]
        )
        == 2
    )
    assert "gains.json: Kd: gains must be positive" in capsys.readouterr().err
    bad_scenario = tmp_path / "scenario.toml"
    bad_scenario.write_text("dt = 0.0\n")
    assert (
        cli.main(
            [
                "simulate",
                "--compile-cache",
                "none",
                "--controller",
                "cartesian",
                "--scenario",
                str(bad_scenario),
                "--out",
                str(tmp_path / "y"),
            ]
        )
        == 2
    )
    assert "dt: must be positive" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


COMPILE_ONE = """
import sys, jax
from spacegrasp_jax import compilation
folder = compilation.use_compile_cache(None if sys.argv[1] == "default" else sys.argv[1])
jax.jit(lambda x: 2.0 * x + 1.0)(1.0)  # a toy program: kept too
print(folder)
print(jax.config.jax_persistent_cache_min_compile_time_secs)
"""

#: The environment variables of the cache's settings, dropped from a test's processes.
CACHE_VARIABLES = ("JAX_COMPILATION_CACHE_DIR", "XDG_CACHE_HOME", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS")


@pytest.mark.parametrize("case", ["explicit", "xdg_default", "jax_variable", "off"])
def test_compile_cache_folder_and_precedence(tmp_path, case):
    """``--compile-cache``: a folder given wins; without one, JAX's own variable, else the
    XDG cache folder; ``none`` writes nothing. The program must land in the folder chosen, however small."""
    env = {k: v for k, v in os.environ.items() if k not in CACHE_VARIABLES}
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    env["MPLCONFIGDIR"] = str(tmp_path.parent / f"{tmp_path.name}-matplotlib")  # not a JAX cache
    argument, expected = {
        "explicit": (str(tmp_path / "mine"), tmp_path / "mine"),
        "xdg_default": ("default", tmp_path / "xdg" / "spacegrasp-jax" / "xla"),
        "jax_variable": ("default", tmp_path / "jax"),
        "off": ("none", None),
    }[case]
    if case == "jax_variable":
        env["JAX_COMPILATION_CACHE_DIR"] = str(tmp_path / "jax")
    result = subprocess.run(
        [sys.executable, "-c", COMPILE_ONE, argument], capture_output=True, text=True, env=env, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.split("\n")[0] == str(expected)
    written = [p for p in tmp_path.rglob("*") if p.is_file()]
    if expected is None:
        assert written == []
    else:
        assert written and all(expected in p.parents for p in written), written


@pytest.mark.parametrize("variable", [None, "2.5"])
def test_the_cache_keeps_every_program_unless_the_user_chose_a_threshold(tmp_path, variable):
    env = {k: v for k, v in os.environ.items() if k not in CACHE_VARIABLES}
    if variable is not None:
        env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = variable
    command = [sys.executable, "-c", COMPILE_ONE, str(tmp_path / "cache")]
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    assert result.returncode == 0, result.stderr
    assert float(result.stdout.split("\n")[1]) == (0.0 if variable is None else 2.5)
    assert bool(list((tmp_path / "cache").glob("jit_*"))) == (variable is None)


@pytest.mark.slow
def test_a_command_keeps_its_programs_in_the_compile_cache_and_loads_them_for_other_values(tmp_path, gains):
    """A second run with other values (gains, the scenario's numbers, the realism's noise
    levels, the noise seed) loads every program from the persistent cache: the cache key
    does not change with values, only with settings that shape the program."""
    cache = tmp_path / "cache"
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    first_scenario, second_scenario = tmp_path / "short.toml", tmp_path / "other.toml"
    first_scenario.write_text("duration = 0.2\n")
    second_scenario.write_text("duration = 0.2\nq_init = [2.21, -2.386, -2.011, 2.595, 2.558, 0.756, 0.949]\n")
    other_gains = tmp_path / "gains.json"
    other_gains.write_text(json.dumps({**gains.to_dict(), "K_lin": 2.0}))
    noisy, noisier = tmp_path / "noisy.toml", tmp_path / "noisier.toml"
    noisy.write_text("[joint_sensors]\nrate_noise_std_radps = 0.001\n")
    noisier.write_text("[joint_sensors]\nrate_noise_std_radps = 0.003\n")

    def simulate(out, *options):
        command = [sys.executable, "-m", "spacegrasp_jax.cli", "simulate", "--controller", "cartesian"]
        command += [*options, "--out", str(tmp_path / out), "--compile-cache", str(cache)]
        result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
        assert result.returncode == 0, result.stderr
        assert f"compilation cache: {cache}" in result.stderr
        summary = json.loads((tmp_path / out / "summary.json").read_text())["cartesian"]
        return sorted(path.name for path in cache.iterdir()), result.stderr, summary

    first, printed, first_summary = simulate("a", "--scenario", str(first_scenario))
    assert any(name.startswith("jit_closed_loop") for name in first)  # the closed loop, compiled once
    assert (
        "compiling the cartesian law's ideal rollout (first time on this machine: 4 to 12 s on a quiet 2-core VM"
        in printed
    )
    stored = sorted((cache / executable_store.FOLDER).iterdir())
    assert len(stored) == 1  # the closed loop, under the package's own key
    second, printed, second_summary = simulate("b", "--scenario", str(second_scenario), "--gains", str(other_gains))
    assert second == first  # other gains and initial angles: the program is loaded, nothing new written
    assert sorted((cache / executable_store.FOLDER).iterdir()) == stored
    assert second_summary["max_abs_torque_Nm"] != first_summary["max_abs_torque_Nm"]  # the values were used
    assert "compiling the cartesian law's ideal rollout" not in printed  # loaded before tracing
    # Without the stored executable, the program is traced and found in JAX's own cache
    # (under the same key: nothing new written), and the compile line says how long it took.
    shutil.rmtree(cache / executable_store.FOLDER)
    again, printed, again_summary = simulate("b2", "--scenario", str(second_scenario), "--gains", str(other_gains))
    assert again == [name for name in first if name != executable_store.FOLDER]
    timings = ("compile_time_s", "run_time_s")
    assert {k: v for k, v in again_summary.items() if k not in timings} == {
        k: v for k, v in second_summary.items() if k not in timings
    }
    assert re.search(
        r"compiling the cartesian law's ideal rollout \(last time \d+\.\d s on this machine\)\.\.\.", printed
    )
    history = json.loads((cache / cli.COMPILE_TIMES).read_text())
    assert len(history) == 2  # the program's times and its kind's: the first compile and the later run's
    assert all(len(times) == 2 and all(0.0 < seconds < 300.0 for seconds in times) for times in history.values())

    third, printed, third_summary = simulate("c", "--scenario", str(first_scenario), "--realism", str(noisy))
    assert len(third) > len(second)  # the flight-like loop is another program
    fourth, _, fourth_summary = simulate(
        "d", "--scenario", str(first_scenario), "--realism", str(noisier), "--seed", "7"
    )
    assert fourth == third  # other noise levels and another seed: the same program
    assert fourth_summary["max_abs_torque_Nm"] != third_summary["max_abs_torque_Nm"]
