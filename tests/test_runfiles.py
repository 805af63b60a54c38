"""The output-folder rule every command follows (``runfiles.claim_output_folder``): a folder
that holds anything is refused, naming what it holds; ``--overwrite`` deletes a previous
run's files and nothing else; ``--resume`` continues a run of the same command."""

from __future__ import annotations

import io
import json

import pytest

from spacegrasp_jax.jobs import runfiles
from spacegrasp_jax.jobs.runfiles import OutputFolderError, claim_output_folder, read_run_marker


def test_a_new_or_empty_folder_is_claimed_with_a_marker(tmp_path):
    claim_output_folder(tmp_path / "new" / "run", "simulate")
    marker = read_run_marker(tmp_path / "new" / "run")
    assert marker["command"] == "simulate" and marker["kept_files"] == [] and "started" in marker
    (tmp_path / "empty").mkdir()
    claim_output_folder(tmp_path / "empty", "tune")
    assert [p.name for p in (tmp_path / "empty").iterdir()] == [runfiles.RUN_MARKER]


def test_a_folder_holding_a_run_is_refused_then_replaced_with_overwrite(tmp_path):
    out = tmp_path / "run"
    claim_output_folder(out, "tune")
    (out / "summary.json").write_text("{}")
    (out / "chunks").mkdir()
    (out / "chunks" / "000.npz").write_bytes(b"x")
    with pytest.raises(OutputFolderError, match=r"run already holds a tune run \(started .*--overwrite"):
        claim_output_folder(out, "simulate")
    assert (out / "summary.json").exists()  # refused: untouched
    claim_output_folder(out, "simulate", overwrite=True)
    assert sorted(p.name for p in out.iterdir()) == [runfiles.RUN_MARKER]
    assert read_run_marker(out)["command"] == "simulate"


def test_files_the_tool_did_not_write_are_named_and_never_deleted(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    for name in ("a.txt", "b.txt", "c.txt", "d.txt"):
        (out / name).write_text(name)
    with pytest.raises(OutputFolderError, match=r"files this tool did not write \(a.txt, b.txt, c.txt and 1 more\)"):
        claim_output_folder(out, "reproduce")
    claim_output_folder(out, "reproduce", overwrite=True)
    assert read_run_marker(out)["kept_files"] == ["a.txt", "b.txt", "c.txt", "d.txt"]
    (out / "table5.csv").write_text("run output")
    claim_output_folder(out, "reproduce", overwrite=True)  # the run's file goes, the user's stay
    assert sorted(p.name for p in out.iterdir()) == [runfiles.RUN_MARKER, "a.txt", "b.txt", "c.txt", "d.txt"]
    assert all((out / name).read_text() == name for name in ("a.txt", "b.txt", "c.txt", "d.txt"))


def test_resume_continues_the_same_command_only(tmp_path):
    out = tmp_path / "campaign"
    claim_output_folder(out, "montecarlo")
    started = read_run_marker(out)["started"]
    (out / "campaign.json").write_text("{}")
    claim_output_folder(out, "montecarlo", resume=True)  # nothing deleted, the marker kept
    assert (out / "campaign.json").exists() and read_run_marker(out)["started"] == started
    with pytest.raises(OutputFolderError, match="--resume: it holds a montecarlo run .*not a tune run"):
        claim_output_folder(out, "tune", resume=True)
    with pytest.raises(OutputFolderError, match="give one"):
        claim_output_folder(out, "montecarlo", resume=True, overwrite=True)


def test_a_check_only_claim_writes_nothing(tmp_path):
    claim_output_folder(tmp_path / "x", "montecarlo", write=False)
    assert not (tmp_path / "x").exists()
    (tmp_path / "y").mkdir()
    (tmp_path / "y" / "f").write_text("")
    with pytest.raises(OutputFolderError):
        claim_output_folder(tmp_path / "y", "montecarlo", write=False)


def test_a_file_is_not_a_folder(tmp_path):
    (tmp_path / "f").write_text("")
    with pytest.raises(OutputFolderError, match="is a file"):
        claim_output_folder(tmp_path / "f", "simulate")
    assert json.loads((tmp_path / "f").read_text() or "null") is None


def test_a_log_is_written_and_read_back_field_for_field(tmp_path):
    # What `spacegrasp animate` and `compare` read: the same arrays, bit for bit; a field the
    # file does not hold (a log written before the field existed) comes back as None.
    import dataclasses

    import numpy as np
    from hand_logs import log_of

    from spacegrasp_jax.jobs.experiment import read_log

    rng = np.random.default_rng(3)
    log = log_of(np.arange(5) * 1e-3, u=rng.normal(size=(5, 7)), target_position=rng.normal(size=(5, 3)))
    runfiles.write_timeseries(tmp_path / "timeseries_admittance.npz", log)
    again = read_log(tmp_path / "timeseries_admittance.npz")
    for field in dataclasses.fields(log):
        written, read = getattr(log, field.name), getattr(again, field.name)
        assert (read is None) if written is None else np.array_equal(read, written), field.name
    older = {name: value for name, value in vars(log).items() if value is not None and "target" not in name}
    np.savez(tmp_path / "older.npz", **older)
    assert read_log(tmp_path / "older.npz").target_position is None
    np.testing.assert_array_equal(read_log(tmp_path / "older.npz").u, log.u)


def test_a_run_folders_robot_and_scenario_are_read_back_or_the_cause_is_named(tmp_path):
    # What `spacegrasp animate` films: the robot and scenario config.json says the run ran.
    import jax
    import numpy as np

    import spacegrasp_jax as sg
    from spacegrasp_jax.envelope.scenario import paper_scenario, scenario_to_dict
    from spacegrasp_jax.jobs.campaign import robot_and_scenario_of_run
    from spacegrasp_jax.jobs.experiment import RunFolderError

    robot = sg.paper_robot()
    scenario = paper_scenario(robot, duration=0.5, move_duration=0.5, contact_law="smooth")
    config = {"robot": "paper_robot()", "scenario": scenario_to_dict(scenario)}
    read_robot, read_scenario = robot_and_scenario_of_run(tmp_path, config)
    for a, b in zip(jax.tree.leaves((robot, scenario)), jax.tree.leaves((read_robot, read_scenario)), strict=True):
        np.testing.assert_array_equal(a, b)
    assert (read_scenario.n_steps, read_scenario.contact_law) == (500, "smooth")
    with pytest.raises(RunFolderError, match=rf"{tmp_path}: its robot {tmp_path}/gone.toml"):
        robot_and_scenario_of_run(tmp_path, config | {"robot": str(tmp_path / "gone.toml")})
    replay = config | {"campaign_record": "campaign.json", "campaign": str(tmp_path / "nowhere"), "sample": 3}
    with pytest.raises(RunFolderError, match=rf"{tmp_path}: a replay of {tmp_path}/nowhere, which cannot be read"):
        robot_and_scenario_of_run(tmp_path, replay)


class _Stream(io.StringIO):
    def __init__(self, terminal: bool):
        super().__init__()
        self.terminal = terminal

    def isatty(self) -> bool:
        return self.terminal


def test_progress_rewrites_its_line_on_a_terminal_and_writes_whole_lines_into_a_pipe():
    """On a terminal each update rewrites the line (a carriage return before it, one newline at
    the end); into a pipe or a log file, where carriage returns run the updates together,
    each is a line of its own."""
    updates = [runfiles.progress_bar(done, 3, f"step {done}/3") for done in (1, 2, 3)]
    terminal, pipe = _Stream(True), _Stream(False)
    for stream in (terminal, pipe):
        for line in updates:
            runfiles.show_progress(stream, line)
        runfiles.end_progress(stream)
    assert terminal.getvalue() == "".join(updates) + "\n" and terminal.getvalue().count("\n") == 1
    assert pipe.getvalue().splitlines() == [line.lstrip("\r") for line in updates] and "\r" not in pipe.getvalue()
    assert pipe.getvalue().splitlines()[0] == "[########................] step 1/3"
