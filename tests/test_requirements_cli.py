"""``spacegrasp requirements`` end to end on a short capture: every point of a curve is the
campaign of its envelope (the same captures ``montecarlo`` draws with those half-widths),
the failures' attribution runs, and the files say what the gains require."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

pytestmark = pytest.mark.slow  # compiles a campaign


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    folder = tmp_path_factory.mktemp("requirements")
    scenario = folder / "short.toml"
    scenario.write_text("duration = 1.0\n[trajectory]\nduration = 1.0\n")
    command = [sys.executable, "-m", "spacegrasp_jax.cli", "requirements", "--scenario", str(scenario)]
    command += ["--groups", "lar_estimate,approach_timing", "--widths", "1,3", "--n", "8", "--chunk", "8"]
    command += ["--sobol", "4", "--gains", "flight", "--compile-cache", "none", "--out", str(folder / "out")]
    result = subprocess.run(command, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    return folder, result


def test_each_point_is_the_campaign_of_its_envelope(study):
    folder, _ = study
    document = json.loads((folder / "out" / "requirements.json").read_text())
    entry = document["curves"]["lar_estimate"]
    assert entry["widths"] == [1.0, 3.0] and entry["half_widths"][1]["lar_estimate_position_m"] == pytest.approx(0.006)
    # The 3x point of the LAR estimate is montecarlo's campaign with those half-widths.
    command = [sys.executable, "-m", "spacegrasp_jax.cli", "montecarlo", "--n", "8", "--chunk", "8"]
    command += ["--scenario", str(folder / "short.toml"), "--controller", "admittance", "--gains", "flight"]
    command += ["--ranges", "montecarlo", "--range", "lar_estimate_position_m=0.006"]
    command += ["--range", "lar_estimate_angle_rad=0.015", "--range", "approach_offset_m=0.003"]
    command += ["--range", "ft_force_bias_N=0.25", "--range", "ft_torque_bias_Nm=0.0125"]
    command += ["--range", "ft_force_noise_std_N=0.05", "--range", "ft_torque_noise_std_Nm=0.0025"]
    command += ["--range", "actuator_torque_loss_fraction=0.1", "--compile-cache", "none", "--out", str(folder / "mc")]
    result = subprocess.run(command, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr
    with (
        np.load(folder / "mc" / "samples.npz") as direct,
        np.load(folder / "out" / "points" / "lar_estimate_x3" / "samples.npz") as point,
    ):
        for name in direct.files:
            if name.startswith("admittance/flight/"):
                np.testing.assert_array_equal(point[name], direct[name], err_msg=name)
    for label, curve in entry.items():
        if label not in ("widths", "half_widths"):
            assert curve["samples"] == 8 and set(curve["crossings"]) == {"0.99", "0.9"}


def test_the_study_states_its_requirements_and_attributes_its_failures(study):
    folder, result = study
    document = json.loads((folder / "out" / "requirements.json").read_text())
    assert set(document["curves"]) == {"lar_estimate", "approach_timing", "all"}
    labels = set(document["requirements"])
    assert labels == {"admittance/paper", "admittance/flight"}
    attribution = document["failure_attribution"]["admittance/flight"]
    assert attribution["groups"] == ["lar_estimate", "approach_timing", "sensor_noise"]
    assert attribution["evaluations"] == 4 * (2 + 3)
    assert "all perturbations together:" in result.stdout
    assert (folder / "out" / "curves.png").stat().st_size > 10_000
