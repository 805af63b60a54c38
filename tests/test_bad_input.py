"""Bad input on the command line: every kind of mistake is refused with exit code 2 and one
line naming the file and key or the option, with no traceback, before any program of the
package is built (every closed-loop program is built by ``compilation.jit``; the driver
below counts its calls) and without leaving files behind.

All cases run in one fresh process (``DRIVER``), which calls ``cli.main`` on each.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

DRIVER = textwrap.dedent(
    """
    import contextlib, io, json, sys, traceback
    from spacegrasp_jax import cli, compilation

    built = []
    original_jit = compilation.jit

    def counting_jit(fun, **keywords):
        built.append(getattr(fun, "__name__", repr(fun)))
        return original_jit(fun, **keywords)

    compilation.jit = counting_jit
    results = {}
    for name, argv in json.load(open(sys.argv[1])).items():
        built.clear()
        stderr = io.StringIO()
        crashed = None
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            try:
                code = cli.main(argv)
            except SystemExit as exit:
                code = exit.code
            except BaseException:
                code, crashed = None, traceback.format_exc()
        results[name] = {"code": code, "stderr": stderr.getvalue(), "crashed": crashed, "built": list(built)}
    json.dump(results, open(sys.argv[2], "w"))
    """
)

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
ARMS = Path(__file__).resolve().parent / "data" / "arms"
#: The paper's gains as an admittance law's file holds them (Section 4 and Table 4).
PAPER_ADMITTANCE = {"Md": 800.0, "Bd": 500.0, "Kd": 600.0, "kp": [140, 210, 140, 105, 105, 21, 21]} | {
    "ki": [10, 10, 10, 1, 1, 1, 1],
    "kd": [0.01] * 7,
}
SIMULATE = ["simulate", "--controller", "admittance"]
TUNE = ["tune", "--steps", "1", "--holdout", "0"]
MONTECARLO = ["montecarlo", "--n", "2", "--chunk", "2"]
MARGINS = ["margins", "--samples", "2"]
WORSTCASE = ["worstcase", "--budget", "40"]


def files(folder):
    """Malformed input files, by name -> path."""
    contents = {
        "binary.json": b"\x00\xff\xfe\x80 not text",
        "binary.toml": b"\x89PNG\r\n\x1a\n\x00\x00",
        "deep.json": b"[" * 100_000,
        "deep.toml": b"a = " + b"[" * 100_000,
        "list.json": b"[1, 2, 3]",
        "number.json": b"17",
        "null.json": b"null",
        "kp_string.json": b'{"kp": "140"}',
        "kp_true.json": b'{"kp": true}',
        "Kp.json": b'{"Kp": [1, 1, 1, 1, 1, 1, 1]}',
        "no_Kd.json": json.dumps({k: v for k, v in PAPER_ADMITTANCE.items() if k != "Kd"}).encode(),
        "Md_nested_string.json": b'{"Md": [800, 800, "800", 800, 800, 800]}',
        "duration_string.toml": b'duration = "17"',
        "duration_true.toml": b"duration = true",
        "dt_string.json": b'{"dt": "0.001"}',
        "target_mass_true.toml": b"[target]\nmass = true\ninertia = [1.0, 1.0, 1.0]",
        "duration_huge.toml": b"duration = 1e300",
        "dt_tiny.toml": b"dt = 1e-300",
        "ragged.json": b'{"q_init": [0.1, [0.2, 0.3]]}',
        "lar_not_table.toml": b"lar = 5",
        "noise_huge_int.toml": b"[force_torque_sensor]\nforce_noise_std = " + b"9" * 400,
        "period_huge_int.toml": b"[timing]\ncontrol_period = " + b"9" * 400,
        "range_huge_int.toml": b"q_init_rad = " + b"9" * 400,
        "servo_below_dt.toml": b"[timing]\ncontrol_period = 0.01\nservo_period = 0.0005",
        "servo_denormal.toml": b"[timing]\ncontrol_period = 0.01\nservo_period = 5e-324",  # the ratio overflows
        "target_null.json": b'{"target": null}',
    }
    paper_robot = (Path(__file__).resolve().parents[1] / "configs" / "paper_robot.toml").read_text()
    assert "mass = 500.0" in paper_robot
    contents["satellite_mass_string.toml"] = paper_robot.replace("mass = 500.0", 'mass = "500"', 1).encode()
    paths = {}
    for name, content in contents.items():
        (folder / name).write_bytes(content)
        paths[name] = str(folder / name)
    (folder / "a_folder").mkdir()
    paths["a_folder"] = str(folder / "a_folder")
    (folder / "a_file").write_text("not a folder\n")
    paths["missing"] = str(folder / "missing.toml")
    paths["under_a_file"] = str(folder / "a_file" / "results")
    (folder / "simulated").mkdir()
    (folder / "simulated" / ".spacegrasp-run.json").write_text(json.dumps({"command": "simulate"}))
    paths["simulated"] = str(folder / "simulated")
    occupied = folder / "occupied"  # another command's run
    occupied.mkdir()
    (occupied / ".spacegrasp-run.json").write_text(
        json.dumps({"command": "tune", "started": "2026-01-01T00:00:00+00:00"})
    )
    (occupied / "summary.json").write_text("{}\n")
    paths["occupied"] = str(occupied)
    (folder / "shared_cache").mkdir()  # a compilation cache anyone can write
    (folder / "shared_cache").chmod(0o777)
    paths["shared_cache"] = str(folder / "shared_cache")
    (folder / "foreign").mkdir()  # files this tool did not write
    (folder / "foreign" / "notes.txt").write_text("mine\n")
    paths["foreign"] = str(folder / "foreign")
    return paths


def cases(paths, out):
    """Case name -> (argv, text the error line must contain)."""
    p = paths
    return {
        # unreadable files, in every loader
        "gains binary": ([*SIMULATE, "--gains", p["binary.json"], "--out", out], "binary.json: not UTF-8"),
        "scenario binary": ([*SIMULATE, "--scenario", p["binary.toml"], "--out", out], "binary.toml: not UTF-8"),
        "robot binary": (["info", "--robot", p["binary.toml"]], "binary.toml: not UTF-8"),
        "ranges binary": ([*MONTECARLO, "--ranges", p["binary.toml"], "--out", out], "binary.toml: not UTF-8"),
        "realism binary": ([*SIMULATE, "--realism", p["binary.toml"], "--out", out], "binary.toml: not UTF-8"),
        "scenario deep JSON": ([*SIMULATE, "--scenario", p["deep.json"], "--out", out], "deep.json: nested too deeply"),
        "gains deep JSON": ([*TUNE, "--gains", p["deep.json"], "--out", out], "deep.json: nested too deeply"),
        "robot deep TOML": (["info", "--robot", p["deep.toml"]], "deep.toml: nested too deeply"),
        "simulate missing scenario": (
            [*SIMULATE, "--scenario", p["missing"], "--out", out],
            "missing.toml: no such file",
        ),
        "info missing robot": (["info", "--robot", p["missing"]], "missing.toml: no such file"),
        "info robot folder": (["info", "--robot", p["a_folder"]], "a_folder: is a folder"),
        "info urdf exists": (["info", "--urdf", p["binary.toml"]], "binary.toml exists; name a new file"),
        "info urdf under a file": (["info", "--urdf", f"{p['binary.toml']}/arm.urdf"], "binary.toml is not a folder"),
        "info urdf empty name": (["info", "--urdf", ""], "argument --urdf: empty; expected FILE"),
        "simulate gains folder": ([*SIMULATE, "--gains", p["a_folder"], "--out", out], "a_folder: is a folder"),
        "montecarlo gains folder": ([*MONTECARLO, "--gains", p["a_folder"], "--out", out], "a_folder: is a folder"),
        "tune scenario folder": ([*TUNE, "--scenario", p["a_folder"], "--out", out], "a_folder: is a folder"),
        # a top level that is not a table
        "scenario list": ([*SIMULATE, "--scenario", p["list.json"], "--out", out], "list.json: expected a JSON object"),
        "scenario number": ([*SIMULATE, "--scenario", p["number.json"], "--out", out], "number.json: expected a JSON"),
        "scenario null": ([*SIMULATE, "--scenario", p["null.json"], "--out", out], "null.json: expected a JSON object"),
        "gains list": ([*MONTECARLO, "--gains", p["list.json"], "--out", out], "list.json: expected a JSON object"),
        "realism null": ([*SIMULATE, "--realism", p["null.json"], "--out", out], "null.json: expected a JSON object"),
        # wrong types are refused, not coerced
        "gains kp string": (
            [*SIMULATE, "--gains", p["kp_string.json"], "--fill-from", "paper", "--out", out],
            "kp_string.json: kp: expected",
        ),
        "gains kp true": (
            [*SIMULATE, "--gains", p["kp_true.json"], "--fill-from", "paper", "--out", out],
            "kp_true.json: kp: expected",
        ),
        "gains nested string": (
            [*TUNE, "--gains", p["Md_nested_string.json"], "--fill-from", "paper", "--out", out],
            ": Md: expected",
        ),
        "scenario duration string": (
            [*SIMULATE, "--scenario", p["duration_string.toml"], "--out", out],
            "duration_string.toml: duration: expected numbers",
        ),
        "scenario duration true": (
            [*MONTECARLO, "--scenario", p["duration_true.toml"], "--out", out],
            "duration_true.toml: duration: expected numbers",
        ),
        "scenario dt string": ([*SIMULATE, "--scenario", p["dt_string.json"], "--out", out], "dt_string.json: dt:"),
        "scenario ragged": ([*SIMULATE, "--scenario", p["ragged.json"], "--out", out], "ragged.json: q_init:"),
        "scenario table not a table": ([*SIMULATE, "--scenario", p["lar_not_table.toml"], "--out", out], ": lar:"),
        "target mass true": (
            [*SIMULATE, "--scenario", p["target_mass_true.toml"], "--out", out],
            "target_mass_true.toml: target.mass: expected numbers",
        ),
        "robot mass string": (["info", "--robot", p["satellite_mass_string.toml"]], ": satellite.mass: expected"),
        # absurd values
        "duration 1e300": ([*SIMULATE, "--scenario", p["duration_huge.toml"], "--out", out], ": duration:"),
        "dt 1e-300": ([*SIMULATE, "--scenario", p["dt_tiny.toml"], "--out", out], "dt_tiny.toml: dt: must be in"),
        "n 1e30": (["montecarlo", "--n", "1e30", "--out", out], "argument --n:"),
        "n 10^21": (["montecarlo", "--n", str(10**21), "--out", out], "argument --n:"),
        "batch 1e12": ([*TUNE, "--batch", str(10**12), "--out", out], "argument --batch:"),
        "holdout 1e30": ([*TUNE, "--holdout", "1e30", "--out", out], "argument --holdout:"),
        "seed 2^64": ([*SIMULATE, "--seed", str(2**64), "--out", out], "argument --seed:"),
        "montecarlo seed negative": ([*MONTECARLO, "--seed", "-1", "--out", out], "argument --seed:"),
        # explicit gains: what a file leaves out is refused unless --fill-from says where it comes from
        "gains without Kd": (
            [*SIMULATE, "--gains", p["no_Kd.json"], "--out", out],
            "no_Kd.json: Kd: missing; give every group the law uses, or say where the rest comes from "
            "(--fill-from paper|FILE",
        ),
        "tune gains without Kd": ([*TUNE, "--gains", p["no_Kd.json"], "--out", out], "no_Kd.json: Kd: missing;"),
        "montecarlo gains without Kd": (  # both laws: the Cartesian law's groups too
            [*MONTECARLO, "--gains", p["no_Kd.json"], "--out", out],
            "no_Kd.json: Kd, K_lin, K_eul: missing",
        ),
        "fill from without a file": (
            [*SIMULATE, "--fill-from", "paper", "--out", out],
            "--fill-from: completes a gains",
        ),
        "fill from with a shipped set": (
            [*SIMULATE, "--gains", "flight", "--fill-from", "paper", "--out", out],
            "--fill-from: completes a gains file given with --gains; flight's gains are whole",
        ),
        "montecarlo fill from without a file": ([*MONTECARLO, "--fill-from", "paper", "--out", out], "--fill-from:"),
        "tune fill from without a file": ([*TUNE, "--fill-from", "paper", "--out", out], "--fill-from: completes a"),
        "fill from a missing file": (
            [*SIMULATE, "--gains", p["no_Kd.json"], "--fill-from", p["missing"], "--out", out],
            "missing.toml: no such file",
        ),
        "fill from a file without it": (
            [*SIMULATE, "--gains", p["no_Kd.json"], "--fill-from", p["kp_true.json"], "--out", out],
            "kp_true.json: Kd: missing, and",
        ),
        "a shipped set on another arm": (
            [
                *SIMULATE,
                "--robot",
                str(CONFIGS / "ur5_on_satellite.toml"),
                "--scenario",
                str(CONFIGS / "ur5_scenario.toml"),
            ]
            + ["--gains", "flight", "--out", out],
            "--gains flight: the shipped tuned sets are for the paper's 7-joint arm, not this 6-joint one",
        ),
        "the paper's gains on another arm": (
            [
                *SIMULATE,
                "--robot",
                str(CONFIGS / "ur5_on_satellite.toml"),
                "--scenario",
                str(CONFIGS / "ur5_scenario.toml"),
            ]
            + ["--gains", "paper", "--out", out],
            "--gains paper: the paper's Table 4 gains are for its 7-joint arm, not this 6-joint one",
        ),
        # a misspelt name: the name meant, suggested
        "gain key in another case": (
            [*SIMULATE, "--gains", p["Kp.json"], "--fill-from", "paper", "--out", out],
            "Kp.json: unknown gain(s): Kp (did you mean kp?)",
        ),
        "baseline missing": ([*MONTECARLO, "--baseline", p["missing"], "--out", out], "missing.toml"),
        "check without a run": (["tune", "--check", "--out", p["a_folder"]], "--check: "),
        "check with a setting": (["tune", "--check", "--batch", "4", "--out", p["a_folder"]], "not --batch"),
        "misspelt option": (
            [*MONTECARLO, "--basline", "flight", "--out", out],
            "--basline flight (did you mean --baseline?)",
        ),
        # a stock URDF arm: a chain with several leaves, a start outside its ranges
        "urdf with several leaves": (
            ["info", "--robot", str(CONFIGS / "arms" / "panda.urdf")],
            "name the tip link (--tip-link on the command line, tip_link in a mounting TOML)",
        ),
        "q_init outside the joint ranges": (
            [*SIMULATE, "--robot", str(ARMS / "xarm7.urdf"), "--tip-link", "link7", "--mount", "paper", "--out", out],
            "q_init: the scenario's initial joint angles lie outside the robot's joint ranges: joint 2 at -2.386",
        ),
        "tune q_init outside the joint ranges": (
            [*TUNE, "--robot", str(ARMS / "xarm7.urdf"), "--tip-link", "link7", "--mount", "paper", "--out", out],
            "(choose angles inside them, or pass --allow-outside-limits)",
        ),
        "mount without a urdf": ([*SIMULATE, "--mount", "urdf", "--out", out], "--mount: for a URDF arm given"),
        # a cache is code: a folder others can write is not loaded from
        "compile cache writable by others": (
            [*SIMULATE, "--compile-cache", p["shared_cache"], "--out", out],
            f"--compile-cache: compilation cache {p['shared_cache']}: {p['shared_cache']} is writable by others "
            f"(mode 0777), who could put programs there that this process would run: make it yours alone "
            f"(chmod go-w {p['shared_cache']}), or pass --compile-cache none",
        ),
        # an option is named whole: an abbreviation is not read as the option it starts
        "abbreviated --controller": (
            [*SIMULATE, "--contr", "cartesian", "--out", out],
            "unrecognized arguments: --contr",
        ),
        "abbreviated --realism": ([*TUNE, "--real", "flight", "--out", out], "unrecognized arguments: --real flight"),
        # options that used to be checked late or not at all
        "freeze unknown group": ([*TUNE, "--freeze", "kd,zz", "--out", out], "--freeze: zz"),
        "freeze a group the law lacks": ([*TUNE, "--freeze", "K_lin", "--out", out], "--freeze: K_lin"),
        "pinv-damping nan": ([*SIMULATE, "--pinv-damping", "nan", "--out", out], "argument --pinv-damping:"),
        "pinv-damping inf": ([*MONTECARLO, "--pinv-damping", "inf", "--out", out], "argument --pinv-damping:"),
        "torque-threshold nan": (
            [*MONTECARLO, "--torque-threshold", "nan", "--out", out],
            "argument --torque-threshold:",
        ),
        "torque-threshold negative": (
            [*MONTECARLO, "--torque-threshold", "-5", "--out", out],
            "argument --torque-threshold:",
        ),
        "torque-limit (its old name) nan": (
            [*MONTECARLO, "--torque-limit", "nan", "--out", out],
            "argument --torque-limit:",
        ),
        "optimizer not an optimiser": ([*TUNE, "--optimizer", "clip", "--out", out], "--optimizer: 'clip'"),
        "optimizer a module": ([*TUNE, "--optimizer", "tree_utils", "--out", out], "--optimizer:"),
        "lr nan": ([*TUNE, "--lr", "nan", "--out", out], "argument --lr:"),
        "cvar above 1": ([*TUNE, "--cvar", "2", "--out", out], "argument --cvar:"),
        "torque-cap 0": ([*TUNE, "--torque-cap", "0", "--out", out], "argument --torque-cap:"),
        "torque-cap with weighted": (
            [*TUNE, "--objective", "weighted", "--torque-cap", "4", "--out", out],
            "--torque-cap: the capture objective's torque constraint",
        ),
        "torque-fraction with weighted": (
            [*TUNE, "--objective", "weighted", "--torque-fraction", "0.5", "--out", out],
            "--torque-fraction: the capture objective's torque constraint",
        ),
        "process id beyond count": (
            [*MONTECARLO, "--num-processes", "2", "--process-id", "2", "--out", out],
            "--process-id: must be below --num-processes",
        ),
        "realism int beyond float64": (
            [*SIMULATE, "--realism", p["noise_huge_int.toml"], "--out", out],
            "force_torque_sensor.force_noise_std: 99999",
        ),
        "realism period int beyond float64": (
            [*TUNE, "--realism", p["period_huge_int.toml"], "--out", out],
            "timing.control_period: must be a number of seconds",
        ),
        "ranges int beyond float64": (
            [*MONTECARLO, "--ranges", p["range_huge_int.toml"], "--out", out],
            "q_init_rad: must be a finite number",
        ),
        "servo period below the step": (  # the scenario's dt = 1 ms
            [*SIMULATE, "--realism", p["servo_below_dt.toml"], "--out", out],
            "timing.servo_period: 0.0005 s is not a whole multiple of the scenario's dt",
        ),
        "montecarlo servo period below the step": (
            [*MONTECARLO, "--realism", p["servo_below_dt.toml"], "--out", out],
            "timing.servo_period: 0.0005 s",
        ),
        # tuning options the chosen method or loop would not read
        "tune aggregate clip in the ideal loop": (
            [*TUNE, "--method", "gradient", "--aggregate", "clip", "--out", out],
            "--aggregate: clip combines the samples' separate gradients of a run under a realism",
        ),
        "tune aggregate under CMA-ES": (
            [*TUNE, "--method", "cmaes", "--realism", "flight", "--aggregate", "clip", "--out", out],
            "--aggregate: a setting of the gradient method; CMA-ES does not use it",
        ),
        "tune CMA-ES's population under the flight recipe": (
            [*TUNE, "--realism", "flight", "--population", "8", "--out", out],
            "--population: a setting of CMA-ES; without --method, tune in a flight-like loop runs the gradient method",
        ),
        "tune CMA-ES's step size under the flight recipe": (
            [*TUNE, "--realism", "flight", "--step-size", "0.1", "--out", out],
            "--step-size: a setting of CMA-ES",
        ),
        "tune gradient cut under CMA-ES": (
            [*TUNE, "--method", "cmaes", "--gradient-from", "3", "--out", out],
            "--gradient-from: a setting of the gradient method; CMA-ES does not use it",
        ),
        "tune gradient cut past the capture": (
            [*TUNE, "--method", "gradient", "--gradient-from", "30", "--out", out],
            "--gradient-from: 30 s is at or past the run's end (17 s): nothing would be differentiated",
        ),
        "tune lr under CMA-ES": ([*TUNE, "--lr", "0.3", "--out", out], "--lr: a setting of the gradient method"),
        "tune torque guard under CMA-ES": (
            [*TUNE, "--torque-guard", "50", "--out", out],
            "--torque-guard: a setting of the gradient method",
        ),
        "tune forward mode under a realism": (
            [*TUNE, "--method", "gradient", "--gradient", "forward", "--realism", "flight", "--out", out],
            "--gradient: tuning under a realism takes each sample's reverse-mode gradient",
        ),
        # export
        "export prefix not a C identifier": (
            ["export", "--format", "c-header", "--prefix", "9x", "--out", out],
            "argument --prefix: expected a C identifier",
        ),
        "export unknown format": (["export", "--format", "xml", "--out", out], "argument --format: invalid choice"),
        "export out a folder": (["export", "--format", "json", "--out", p["a_folder"]], "a_folder: is a folder"),
        "export out an existing file": (
            ["export", "--format", "json", "--out", p["list.json"]],
            "list.json: exists; pass --overwrite to replace it",
        ),
        "export gains kp string": (
            ["export", "--format", "yaml", "--gains", p["kp_string.json"], "--fill-from", "paper"],
            ": kp: expected",
        ),
        # output folders that cannot be created
        "simulate out under a file": ([*SIMULATE, "--out", p["under_a_file"]], "a_file/results: cannot write"),
        "reproduce out under a file": (["reproduce", "--out", p["under_a_file"]], "a_file/results: cannot write"),
        "montecarlo out under a file": ([*MONTECARLO, "--out", p["under_a_file"]], "a_file/results: cannot write"),
        "tune out under a file": ([*TUNE, "--out", p["under_a_file"]], "a_file/results: cannot write"),
        "gradients out under a file": (["gradients", "--n", "2", "--out", p["under_a_file"]], "a_file/results: cannot"),
        "benchmark out under a file": (["benchmark", "--quick", "--out", p["under_a_file"]], "a_file/results: cannot"),
        "margins out under a file": ([*MARGINS, "--out", p["under_a_file"]], "a_file/results: cannot write"),
        # occupied output folders, the same rule and message for every command
        **{
            f"{argv[0]} out occupied": (
                [*argv, "--out", p["occupied"]],
                "occupied already holds a tune run (started 2026-01-01",
            )
            for argv in (
                SIMULATE,
                ["reproduce"],
                TUNE,
                MONTECARLO,
                ["gradients", "--n", "2"],
                ["benchmark", "--quick"],
                MARGINS,
            )
        },
        **{
            f"{argv[0]} out foreign": (
                [*argv, "--out", p["foreign"]],
                "foreign already holds files this tool did not write (notes.txt)",
            )
            for argv in (
                SIMULATE,
                ["reproduce"],
                TUNE,
                MONTECARLO,
                ["gradients", "--n", "2"],
                ["benchmark", "--quick"],
                MARGINS,
            )
        },
        "tune resume another command's run": (
            ["tune", "--out", p["occupied"].replace("occupied", "foreign"), "--resume"],
            "holds no tuning run",
        ),
        "montecarlo resume and overwrite": (
            [*MONTECARLO, "--resume", "--overwrite", "--out", p["occupied"]],
            "--resume continues the run there and --overwrite replaces it: give one",
        ),
        "tune resume a simulate run": (
            ["tune", "--resume", "--out", p["simulated"]],
            "--resume: it holds a simulate run",
        ),
        "replay no campaign": (
            ["replay", p["a_folder"], "--sample", "0", "--out", out],
            "a_folder: holds no readable campaign",
        ),
        "replay negative sample": (["replay", p["a_folder"], "--sample", "-1", "--out", out], "argument --sample:"),
        "compare not run folders": (
            ["compare", p["a_folder"], p["a_folder"], "--out", out],
            "a_folder: not a run folder",
        ),
        "gradients horizons": (["gradients", "--n", "2", "--horizons", "0.5,0.25", "--out", out], "--horizons"),
        "gradients n 0": (["gradients", "--n", "0", "--out", out], "argument --n:"),
        "margins samples 0": (["margins", "--samples", "0", "--out", out], "argument --samples:"),
        "margins resolution 1": ([*MARGINS, "--factor-resolution", "1", "--out", out], "argument --factor-resolution:"),
        "margins resolution above the factor": (
            [*MARGINS, "--max-factor", "2", "--factor-resolution", "3", "--out", out],
            "factor_resolution: must be a ratio above 1 and below max_factor",
        ),
        "margins max delay 0": ([*MARGINS, "--max-delay", "0", "--out", out], "argument --max-delay:"),
        "margins max servo delay 0": (
            [*MARGINS, "--max-servo-delay", "0", "--out", out],
            "argument --max-servo-delay:",
        ),
        "margins growth limit negative": (
            [*MARGINS, "--growth-limit", "-1", "--out", out],
            "argument --growth-limit:",
        ),
        "margins law": ([*MARGINS, "--controller", "pid", "--out", out], "argument --controller:"),
        "margins torque law": (
            [*MARGINS, "--controller", "impedance", "--gains", str(CONFIGS / "impedance_gains.json"), "--out", out],
            "the impedance law commands joint torques; margins are searched for laws that command joint rates",
        ),
        "simulate a law outside the paper without gains": (
            ["simulate", "--controller", "impedance", "--out", out],
            "--gains: required for the impedance law",
        ),
        "montecarlo a law outside the paper without gains": (
            [*MONTECARLO, "--controller", "impedance", "--out", out],
            "--gains: required for the impedance law",
        ),
        "simulate a damping the law has not": (
            ["simulate", "--controller", "impedance", "--gains", str(CONFIGS / "impedance_gains.json")]
            + ["--pinv-damping", "0.1", "--out", out],
            "--pinv-damping: pinv_damping: the impedance law has no pseudoinverse to damp",
        ),
        "worstcase a damping the law has not": (
            [*WORSTCASE, "--controller", "impedance", "--gains", str(CONFIGS / "impedance_gains.json")]
            + ["--pinv-damping", "0.1", "--out", out],
            "--pinv-damping: pinv_damping: the impedance law has no pseudoinverse to damp",
        ),
        "tune a law outside the paper without gains": (
            [*TUNE, "--controller", "impedance", "--out", out],
            "--gains: required for the impedance law",
        ),
        "margins gains kp string": (
            [*MARGINS, "--gains", p["kp_string.json"], "--fill-from=paper", "--out", out],
            ": kp: expected",
        ),
        "margins servo below dt": (
            [*MARGINS, "--realism", p["servo_below_dt.toml"], "--out", out],
            "timing.servo_period: 0.0005 s is not a whole multiple",
        ),
        "margins range huge int": ([*MARGINS, "--ranges", p["range_huge_int.toml"], "--out", out], "range_huge_int"),
        "worstcase budget below one step": (
            ["worstcase", "--budget", "10", "--out", out],
            "budget: must be an integer of at least 12 rollouts",
        ),
        "worstcase starts of a search without": (
            [*WORSTCASE, "--starts", "2", "--out", out],
            "--starts: the gradient ascent's starts; --method cem has none",
        ),
        "worstcase measure": ([*WORSTCASE, "--measure", "energy", "--out", out], "argument --measure:"),
        "worstcase starts 0": ([*WORSTCASE, "--starts", "0", "--out", out], "argument --starts:"),
        "worstcase gains kp string": (
            [*WORSTCASE, "--gains", p["kp_string.json"], "--fill-from=paper", "--out", out],
            ": kp: expected",
        ),
        "simulate perturbation list": (
            [*SIMULATE, "--perturbation", p["list.json"], "--out", out],
            "list.json: expected a JSON object of settings at the top level",
        ),
        "simulate perturbation missing": ([*SIMULATE, "--perturbation", p["missing"], "--out", out], "missing"),
        "margins tolerance 0": ([*MARGINS, "--tolerance-mm", "0", "--out", out], "argument --tolerance-mm:"),
        # a servo period so small that control_period / servo_period overflows a float
        "gradients servo period denormal": (
            ["gradients", "--n", "2", "--realism", p["servo_denormal.toml"], "--out", out],
            "servo_denormal.toml: timing.servo_period: must be a number of seconds in [1e-06, control_period]",
        ),
        "simulate servo period denormal": (
            [*SIMULATE, "--realism", p["servo_denormal.toml"], "--out", out],
            "timing.servo_period: must be a number of seconds in [1e-06",
        ),
        # null where a table belongs is not "no target"
        "gradients target null": (
            ["gradients", "--n", "2", "--scenario", p["target_null.json"], "--out", out],
            "target_null.json: target: expected a table of mass, inertia",
        ),
        "simulate target null": ([*SIMULATE, "--scenario", p["target_null.json"], "--out", out], ": target: expected"),
        "tune target null": ([*TUNE, "--scenario", p["target_null.json"], "--out", out], ": target: expected a table"),
        # envelopes past the nominal: named, scaled, drawn only where the scenario allows
        "montecarlo fast targets without a target": (
            [*MONTECARLO, "--ranges", "free_target_fast", "--out", out],
            "--ranges free_target_fast: needs a scenario with a free-floating [target]",
        ),
        "montecarlo scale reaching a fraction of 1": (
            [*MONTECARLO, "--scale", "12", "--out", out],
            "--scale 12: radius_fraction: 0.1 times 12 reaches 1.2",
        ),
        "requirements unknown group": (
            ["requirements", "--groups", "gravity", "--out", out],
            "--groups: distinct names of lar_pose",
        ),
        "requirements widths not increasing": (
            ["requirements", "--widths", "2,1", "--out", out],
            "--widths: positive multiples, increasing",
        ),
        "requirements sobol not a power of two": (
            ["requirements", "--sobol", "12", "--out", out],
            "--sobol: a power of two",
        ),
        "requirements widest point past a fraction": (
            ["requirements", "--widths", "1,12", "--out", out],
            "--widths 1,12: radius_fraction: 0.1 times 12 reaches 1.2; a fraction must stay below 1",
        ),
        "requirements unknown range": (
            ["requirements", "--range", "lar_pos=0.01", "--out", out],
            "unknown perturbation range 'lar_pos'",
        ),
        "ceiling without a campaign": (
            ["ceiling", p["a_folder"], "--out", out],
            "a_folder: holds no readable campaign",
        ),
        "ceiling no failures": (["ceiling", p["a_folder"], "--failures", "0", "--out", out], "argument --failures:"),
        "montecarlo approach offset past the approach": (
            [*MONTECARLO, "--range", "approach_offset_m=0.2", "--out", out],
            "approach_offset_m: 0.2 m needs an approach along the LAR z axis longer than that",
        ),
        # gradients and tune agree: a target's speed is weighed only where a target floats
        "gradients target speed weight without a target": (
            ["gradients", "--n", "2", "--objective", "weighted", "--weights", "target_speed=1", "--out", out],
            "--weights target_speed: needs a scenario with a free-floating [target]",
        ),
        "tune target speed weight without a target": (
            [*TUNE, "--objective", "weighted", "--weights", "target_speed=1", "--out", out],
            "--weights target_speed: needs a scenario with a free-floating [target]",
        ),
        # gradients builds the objective as tune does, with its checks
        "gradients weights with the capture objective": (
            ["gradients", "--n", "2", "--weights", "peak_torque=2", "--out", out],
            "--weights: they weigh the weighted objective's parts; choose it (--objective weighted)",
        ),
        "gradients torque-cap with weighted": (
            ["gradients", "--n", "2", "--objective", "weighted", "--torque-cap", "4", "--out", out],
            "--torque-cap: the capture objective's torque constraint",
        ),
        # an empty value is never the option's absence nor the current folder
        "simulate realism empty": (
            [*SIMULATE, "--realism", "", "--out", out],
            "--realism: empty; expected ideal|flight|FILE",
        ),
        "tune ranges= empty": (
            [*TUNE, "--ranges=", "--out", out],
            "argument --ranges: empty; expected montecarlo|tuning",
        ),
        "gradients ranges= empty": (
            ["gradients", "--n", "2", "--ranges=", "--out", out],
            "argument --ranges: empty; expected montecarlo|tuning",
        ),
        **empty_value_cases(out),
    }


def empty_value_cases(out: str) -> dict:
    """Case name -> (argv, error text): an empty string for every option or argument of every
    command that takes a name, a file or a list of them (those without a numeric type, whose
    own type refuses an empty string), as ``--option ''`` and as ``--option=``."""
    from spacegrasp_jax.cli import build_parser

    table = {}
    for command, parser in build_parser().commands.items():
        # where the command writes a folder or file, a named one: nothing lands in the working folder
        out_option = ["--out", out] if any("--out" in action.option_strings for action in parser._actions) else []
        for action in parser._actions:
            if action.nargs == 0 or action.type is not None or action.dest == "help":
                continue
            if not action.option_strings:  # a positional: the empty string stands where it belongs
                table[f"{command} {action.metavar or action.dest} empty"] = (
                    [command, ""],
                    f"argument {action.metavar or action.dest}: empty; expected",
                )
                continue
            option = action.option_strings[-1]
            rest = [] if option == "--out" else out_option
            table[f"{command} {option} empty"] = ([command, option, "", *rest], f"argument {option}: empty")
            table[f"{command} {option}= empty"] = ([command, f"{option}=", *rest], f"argument {option}: empty")
    return table


@pytest.fixture(scope="module")
def rejected(tmp_path_factory):
    """``(cases, results, out)``: every case run by the driver in one fresh process."""
    folder = tmp_path_factory.mktemp("bad_input")
    out = str(folder / "out")
    table = cases(files(folder), out)
    (folder / "cases.json").write_text(json.dumps({name: argv for name, (argv, _) in table.items()}))
    (folder / "driver.py").write_text(DRIVER)
    subprocess.run(
        [sys.executable, str(folder / "driver.py"), str(folder / "cases.json"), str(folder / "results.json")],
        check=True,
        timeout=600,
        cwd=folder,
    )
    return table, json.loads((folder / "results.json").read_text()), folder / "out"


_FILE_NAMES = (
    "binary.json binary.toml deep.json deep.toml list.json number.json null.json kp_string.json kp_true.json Kp.json no_Kd.json "
    "Md_nested_string.json duration_string.toml duration_true.toml dt_string.json target_mass_true.toml "
    "duration_huge.toml dt_tiny.toml ragged.json lar_not_table.toml noise_huge_int.toml period_huge_int.toml "
    "range_huge_int.toml servo_below_dt.toml servo_denormal.toml target_null.json satellite_mass_string.toml a_folder missing "
    "under_a_file occupied foreign simulated shared_cache"
).split()


@pytest.mark.parametrize("case", list(cases({name: name for name in _FILE_NAMES}, "out")))
def test_bad_input_is_refused_in_one_line_before_compiling(rejected, case):
    table, results, _ = rejected
    result, (argv, expected) = results[case], table[case]
    assert result["crashed"] is None, result["crashed"]
    assert result["code"] == 2, (argv, result)
    assert "Traceback" not in result["stderr"]
    lines = [line for line in result["stderr"].splitlines() if not line.startswith("compilation cache:")]
    assert len(lines) == 1, lines
    assert lines[0].startswith("spacegrasp") and "error:" in lines[0], lines
    assert expected in lines[0], (expected, lines[0])
    assert result["built"] == [], f"built {result['built']} before refusing"


def test_a_refused_run_leaves_no_files(rejected):
    """Nothing is written for a refused run: in particular no ``run.json`` that would make the
    corrected re-run of ``tune`` refuse the folder; the occupied folders are as they were."""
    _, _, out = rejected
    assert not out.exists() or not any(out.rglob("*")), sorted(out.rglob("*"))
    folder = out.parent
    assert sorted(path.name for path in (folder / "occupied").iterdir()) == [".spacegrasp-run.json", "summary.json"]
    assert (folder / "occupied" / "summary.json").read_text() == "{}\n"
    assert [path.name for path in (folder / "foreign").iterdir()] == ["notes.txt"]


def test_an_option_under_its_old_name_still_works_and_says_its_new_name(capsys):
    """``--torque-limit`` (the success criterion's old name) sets the torque threshold, warns
    once naming ``--torque-threshold``, and is left out of the help."""
    from spacegrasp_jax.cli import build_parser

    parser = build_parser()
    args = parser.parse_args([*MONTECARLO, "--torque-limit", "50", "--out", "x"])
    assert args.torque_threshold == 50.0
    assert "--torque-limit is now --torque-threshold" in capsys.readouterr().err
    assert parser.parse_args([*MONTECARLO, "--torque-threshold", "60", "--out", "x"]).torque_threshold == 60.0
    assert capsys.readouterr().err == ""
    assert "--torque-limit" not in parser.commands["montecarlo"].format_help()
