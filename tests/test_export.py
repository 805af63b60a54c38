"""Exported gains read back to the same numbers, bit for bit, by readers that are not ours:
Python's json and csv modules, PyYAML, and a C compiler compiling the header into a program
that prints every array. The settings written are the loop's."""

from __future__ import annotations

import csv
import io
import json
import math
import shutil
import subprocess

import numpy as np
import pytest
import yaml

from spacegrasp_jax.analysis.export import FORMATS, GROUPS, export_text, loop_settings
from spacegrasp_jax.loop.control import make_gains, paper_gains, tuned_gains
from spacegrasp_jax.loop.control.gains import GAINS_USED
from spacegrasp_jax.loop.realism import flight

#: Gains whose numbers need every digit (tuned), and the paper's for the Cartesian law.
CASES = {"admittance": tuned_gains("flight"), "cartesian": paper_gains()}


def _same_gains(read: dict, gains, controller: str) -> None:
    assert set(read) == set(GAINS_USED[controller])
    for name in GAINS_USED[controller]:
        expected = np.asarray(getattr(gains, name)).tolist()
        assert [float(x) for x in read[name]] == expected, name  # exact: the shortest round-trip decimals


@pytest.fixture(scope="module")
def flight_settings():
    return loop_settings(flight(), 0.001)


def test_the_settings_are_the_loops(flight_settings):
    preset = flight()
    assert flight_settings.control_period_s == pytest.approx(0.01) and flight_settings.delay_periods == 1
    assert flight_settings.servo_period_s == pytest.approx(0.001)
    assert flight_settings.torque_limit_Nm == tuple(float(x) for x in np.asarray(preset.torque_limit_Nm))
    assert flight_settings.saturation == preset.saturation and flight_settings.ft_cutoff_hz == preset.cutoff_hz
    ideal = loop_settings(None, 0.001)
    assert (ideal.control_period_s, ideal.servo_period_s, ideal.delay_periods) == (0.001, 0.001, 0)
    assert all(math.isinf(x) for x in ideal.torque_limit_Nm)


@pytest.mark.parametrize("controller", list(CASES))
def test_json_reads_back_to_the_same_gains(controller, flight_settings):
    document = json.loads(export_text(CASES[controller], controller, flight_settings, "json"))
    _same_gains(document["gains"], CASES[controller], controller)
    assert make_gains(**(paper_gains().to_dict() | document["gains"])).kp.tolist() == document["gains"]["kp"]
    assert document["settings"]["control_period_s"] == flight_settings.control_period_s
    assert document["equations"]["kp"] == "Table 4" and set(document["units"]) == set(GAINS_USED[controller])


@pytest.mark.parametrize("controller", list(CASES))
def test_yaml_reads_back_to_the_same_gains(controller, flight_settings):
    text = export_text(CASES[controller], controller, flight_settings, "yaml")
    document = yaml.safe_load(text)  # PyYAML: a YAML 1.1 reader, strict about floats
    _same_gains(document["gains"], CASES[controller], controller)
    assert document["settings"]["torque_limit_Nm"] == list(flight_settings.torque_limit_Nm)
    assert document["settings"]["anti_windup"] is flight_settings.anti_windup
    ideal = yaml.safe_load(export_text(CASES[controller], controller, loop_settings(None, 0.001), "yaml"))
    assert ideal["settings"]["torque_limit_Nm"] == [math.inf] * 7
    for name in GAINS_USED[controller]:
        assert GROUPS[name].equation in text and GROUPS[name].unit in text  # the comments


def test_yaml_floats_without_a_point_are_still_floats():
    gains = make_gains(**(paper_gains().to_dict() | {"pinv_damping": [1e-5], "kd": [1e-20] * 7}))
    document = yaml.safe_load(export_text(gains, "admittance", loop_settings(None, 0.001), "yaml"))
    assert document["gains"]["pinv_damping"] == [1e-5] and document["gains"]["kd"] == [1e-20] * 7


@pytest.mark.parametrize("controller", list(CASES))
def test_csv_reads_back_to_the_same_gains(controller, flight_settings):
    rows = list(csv.DictReader(io.StringIO(export_text(CASES[controller], controller, flight_settings, "csv"))))
    read: dict[str, list[float]] = {}
    for row in rows:
        if row["kind"] == "gain":
            assert int(row["index"]) == len(read.setdefault(row["name"], []))
            read[row["name"]].append(float(row["value"]))
    _same_gains(read, CASES[controller], controller)
    settings = {(row["name"], int(row["index"])): row["value"] for row in rows if row["kind"] == "setting"}
    assert float(settings[("servo_period_s", 0)]) == flight_settings.servo_period_s
    assert settings[("saturation", 0)] == flight_settings.saturation


PRINTER = """
#include <stdio.h>
#include "gains.h"
#define SHOW(name, array) do { printf("%s", name); \\
    for (int i = 0; i < (int)(sizeof(array) / sizeof(array[0])); ++i) printf(" %.17g", array[i]); \\
    printf("\\n"); } while (0)
int main(void) {
{shows}
    SHOW("torque_limit_Nm", FT_TORQUE_LIMIT_NM);
    printf("control_period_s %.17g\\n", (double)FT_CONTROL_PERIOD_S);
    printf("delay_periods %d\\n", FT_DELAY_PERIODS);
    printf("controller %s\\n", FT_CONTROLLER);
    return 0;
}
"""


@pytest.mark.parametrize("controller", list(CASES))
def test_the_c_header_compiles_and_holds_the_same_gains(controller, flight_settings, tmp_path):
    compiler = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if compiler is None:
        pytest.skip("no C compiler on this machine")
    gains = CASES[controller]
    (tmp_path / "gains.h").write_text(export_text(gains, controller, flight_settings, "c-header", prefix="FT"))
    shows = "\n".join(f'    SHOW("{name}", FT_{name});' for name in GAINS_USED[controller])
    (tmp_path / "main.c").write_text(PRINTER.replace("{shows}", shows))
    built = subprocess.run(
        [compiler, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "main.c", "-o", "show"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert built.returncode == 0, built.stderr
    printed = subprocess.run([str(tmp_path / "show")], capture_output=True, text=True, check=True).stdout
    read = {line.split()[0]: line.split()[1:] for line in printed.splitlines()}
    _same_gains({name: read[name] for name in GAINS_USED[controller]}, gains, controller)
    assert [float(x) for x in read["torque_limit_Nm"]] == list(flight_settings.torque_limit_Nm)
    assert float(read["control_period_s"][0]) == flight_settings.control_period_s
    assert read["delay_periods"] == ["1"] and read["controller"] == [controller]


def test_unknown_formats_controllers_and_prefixes_are_refused(flight_settings):
    gains = paper_gains()
    with pytest.raises(ValueError, match="format: expected one of json, yaml, c-header, csv"):
        export_text(gains, "admittance", flight_settings, "xml")
    with pytest.raises(ValueError, match="controller: expected one of"):
        export_text(gains, "pid", flight_settings, "json")
    with pytest.raises(ValueError, match="prefix: '9x' is not a C identifier"):
        export_text(gains, "admittance", flight_settings, "c-header", prefix="9x")
    assert set(FORMATS) == {"json", "yaml", "c-header", "csv"}


def test_the_command_writes_prints_and_keeps_an_existing_file(tmp_path, capsys):
    from spacegrasp_jax import cli

    gains_file = tmp_path / "gains.json"
    gains_file.write_text(json.dumps(CASES["admittance"].to_dict("admittance")))
    out = tmp_path / "gains.yaml"
    argv = ["export", "--gains", str(gains_file), "--realism", "flight", "--format", "yaml", "--out", str(out)]
    assert cli.main(argv) == 0
    document = yaml.safe_load(out.read_text())
    _same_gains(document["gains"], CASES["admittance"], "admittance")
    assert document["settings"]["control_period_s"] == 0.01 and document["settings"]["delay_periods"] == 1
    assert str(gains_file) in out.read_text().splitlines()[0]  # where the gains came from
    out.write_text("mine\n")
    assert cli.main(argv) == 2 and out.read_text() == "mine\n"
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert cli.main([*argv, "--overwrite"]) == 0 and yaml.safe_load(out.read_text())["controller"] == "admittance"
    capsys.readouterr()
    assert cli.main(["export", "--format", "json", "--controller", "cartesian"]) == 0  # printed: the paper's gains
    printed = json.loads(capsys.readouterr().out)
    _same_gains(printed["gains"], paper_gains(), "cartesian")
    assert printed["settings"]["control_period_s"] == 0.001  # the ideal loop on the paper's step
    assert printed["settings"]["torque_limit_Nm"] == [None] * 7  # no limit
