"""One run record for every command: what a run folder, a campaign's sample and a tuning run
record runs them again, bit for bit, from the record alone (its robot, scenario, realism, gains
and noise key read back from JSON); records of older versions read as today's."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

import spacegrasp_jax as sg
from spacegrasp_jax import cli
from spacegrasp_jax.envelope.criteria import CaptureCriteria
from spacegrasp_jax.envelope.perturbations import PerturbationRanges
from spacegrasp_jax.envelope.scenario import load_scenario, paper_scenario, scenario_to_dict
from spacegrasp_jax.jobs import campaign, experiment, records
from spacegrasp_jax.jobs.records import RecordError, RunRecord, Variant
from spacegrasp_jax.loop.control import tuned_gains
from spacegrasp_jax.loop.realism import flight

SHORT = "duration = 0.2\n[trajectory]\nduration = 0.2\n"


def same_logs(a, b) -> None:
    for name, value in vars(a).items():
        if value is None:
            assert getattr(b, name) is None, name
        else:
            np.testing.assert_array_equal(np.asarray(value), np.asarray(getattr(b, name)), err_msg=name)


def same_trees(a, b) -> None:
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def through_json(record: RunRecord) -> RunRecord:
    return RunRecord.from_dict(json.loads(json.dumps(record.to_dict())))


def test_a_run_folders_record_runs_it_again_bit_for_bit(tmp_path):
    """``simulate`` in the flight-like loop with sensor noise (seed 3): the record in its
    config.json, read back alone, runs the log the folder holds, every field bit for bit."""
    (tmp_path / "short.toml").write_text(SHORT)
    out = tmp_path / "run"
    argv = ["simulate", "--compile-cache", "none", "--controller", "admittance", "--realism", "flight"]
    argv += ["--gains", "flight", "--seed", "3"]
    assert cli.main([*argv, "--scenario", str(tmp_path / "short.toml"), "--out", str(out)]) == 0
    document = json.loads((out / "config.json").read_text())["record"]
    assert document["command"] == ["spacegrasp", *argv, "--scenario", str(tmp_path / "short.toml"), "--out", str(out)]
    record = RunRecord.from_dict(document)
    assert record.noise_key == tuple(int(word) for word in np.asarray(jax.random.PRNGKey(3)))
    assert record.realism.to_dict() == flight().to_dict() and record.sources["realism"] == "flight"
    (result,) = records.replay(record, check=False).values()
    same_logs(result.log, experiment.read_log(out / "timeseries_admittance.npz"))


def test_a_campaign_samples_record_runs_the_sample_again(tmp_path):
    """A flight-like campaign's sample (a perturbed satellite, target estimate and noise): its
    record, through JSON, runs the same log as the record in memory, and its final error is the
    campaign's for that sample."""
    robot = sg.paper_robot()
    scenario = paper_scenario(robot, duration=0.2, move_duration=0.2)
    config = campaign.CampaignConfig(n=2, chunk=2, seed=5, realism=flight(), ranges=PerturbationRanges())
    variants = [Variant("admittance", tuned_gains("flight"), "flight")]
    result = campaign.run_campaign(robot, scenario, variants, config, tmp_path / "mc", progress=None)
    nominal, read_config = campaign.campaign_record(tmp_path / "mc")
    assert read_config.to_dict() == config.to_dict()
    same_trees((nominal.robot, nominal.scenario), (robot, scenario))
    sample = campaign.sample_record(nominal, read_config, 1)
    assert sample.model_robot is not None and float(sample.robot.satellite_mass) != float(robot.satellite_mass)
    again = records.replay(through_json(sample), check=False)["admittance/flight"]
    same_logs(again.log, records.replay(sample, check=False)["admittance/flight"].log)
    np.testing.assert_allclose(
        again.summary["final_position_error_m"],
        result.metrics["admittance/flight"]["final_position_error_m"][1],
        rtol=1e-9,
    )


def test_a_campaign_record_of_an_older_version_reads_as_todays(tmp_path):
    """An older ``campaign.json`` (the robot by its file, the criteria among the settings, the
    gains' ``gains_label``) reads as the record and settings today's version writes for it,
    and resumes as the same campaign."""
    robot = sg.paper_robot()
    scenario = paper_scenario(robot, duration=0.2, move_duration=0.2)
    config = campaign.CampaignConfig(n=2, chunk=2, criteria=CaptureCriteria(torque_threshold_Nm=50.0))
    variants = [Variant("admittance", tuned_gains("flight"), "flight")]
    today = campaign.campaign_document(robot, scenario, variants, config)
    older = {
        "config": {k: v for k, v in config.to_dict().items() if k != "criteria"}
        | {"position_tolerance_m": 0.005, "orientation_tolerance_rad": np.radians(1.0), "torque_limit_Nm": 50.0}
        | {"target_speed_limit_mps": 0.005},
        "variants": [{"controller": "admittance", "gains_label": "flight", "gains": tuned_gains("flight").to_dict()}],
        "robot": "paper_robot()",
        "robot_file": None,
        "scenario": scenario_to_dict(scenario),
    }
    (tmp_path / "campaign.json").write_text(json.dumps(older))
    record, read_config = campaign.campaign_record(tmp_path)
    assert read_config == config and record.variants[0].key == "admittance/flight"  # the ideal loop: no arrays
    same_trees((record.robot, record.scenario, record.variants[0].gains), (robot, scenario, tuned_gains("flight")))
    campaign._check_resume(tmp_path, today, resume=True)  # the same campaign: no error
    other = campaign.campaign_document(robot, scenario, variants, campaign.CampaignConfig(n=2, chunk=2, seed=1))
    with pytest.raises(campaign.CampaignError, match=r"the config differs .*\(criteria, seed\)"):
        campaign._check_resume(tmp_path, other, resume=True)


def test_a_tuning_runs_record_holds_what_it_tunes_and_an_older_one_reads_the_same(tmp_path):
    from spacegrasp_jax.tuning import TuneConfig
    from spacegrasp_jax.tuning.run import new_record, run_record

    scenario_file = tmp_path / "short.toml"
    scenario_file.write_text(SHORT)
    config = TuneConfig(realism=flight().to_dict(), batch=2, seed=4)
    document = json.loads(json.dumps(new_record(config, "flight", str(scenario_file), None, 3, command=["x"])))
    record = run_record(document)
    robot = sg.paper_robot()
    same_trees((record.robot, record.scenario), (robot, load_scenario(robot, scenario_file)))
    same_trees(record.variants[0].gains, tuned_gains("flight"))
    assert record.realism.to_dict() == flight().to_dict() and record.command == ("x",)
    assert record.noise_key == tuple(int(word) for word in np.asarray(jax.random.PRNGKey(4)))
    assert record.sources["gains"] == "flight" and record.sources["scenario"] == str(scenario_file)
    older = {
        "config": config.to_dict(),
        "base_gains": tuned_gains("flight").to_dict(),
        "gains_source": "flight",
        "gains_fill_from": None,
        "gains_filled": [],
        "scenario_source": str(scenario_file),
        "scenario_text": SHORT,
        "scenario_is_json": False,
        "robot_source": "paper_robot()",
        "robot_toml": None,
        "robot_links": None,
        "robot_frames": None,
        "holdout": 3,
    }
    read = run_record(older)
    same_trees(
        (read.robot, read.scenario, read.variants[0].gains), (record.robot, record.scenario, tuned_gains("flight"))
    )
    assert read.realism.to_dict() == record.realism.to_dict() and read.noise_key == record.noise_key


def test_a_record_that_is_not_one_is_refused_naming_it():
    with pytest.raises(RecordError, match=r"config.json: not a run record of format 1 \(format None\)"):
        RunRecord.from_dict({"robot": None}, source="config.json")
    record = records.make_record(
        sg.paper_robot(), paper_scenario(sg.paper_robot()), [Variant("admittance", tuned_gains())]
    )
    broken = record.to_dict() | {"realism": {"timing": {"control_period": -1.0}}}
    with pytest.raises(RecordError, match="config.json: "):
        RunRecord.from_dict(broken, source="config.json")
    with pytest.raises(RecordError, match=r"config.json: incomplete record \('scenario'\)"):
        RunRecord.from_dict({k: v for k, v in record.to_dict().items() if k != "scenario"}, source="config.json")
