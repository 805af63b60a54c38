"""Signals on the command line: a second SIGINT (or the first, for a command without safe
points) ends the process at once, even in the middle of a compile, with exit code 130, one
line and no traceback or crash; a campaign killed outright (SIGKILL) resumes to the same
samples."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

SHORT_SCENARIO = "duration = 0.2\n[trajectory]\nduration = 0.2\n"


def _start(arguments, tmp_path):
    (tmp_path / "short.toml").write_text(SHORT_SCENARIO)
    command = [sys.executable, "-m", "spacegrasp_jax.cli", *arguments, "--compile-cache", "none"]
    command += ["--scenario", str(tmp_path / "short.toml"), "--out", str(tmp_path / "out")]
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_line(process, prefix: str) -> list[str]:
    """stderr lines up to the one starting with ``prefix`` (printed just before compiling)."""
    lines = []
    while not (lines and lines[-1].startswith(prefix)):
        line = process.stderr.readline()
        assert line, f"the process ended before printing {prefix!r}: {lines}"
        lines.append(line)
    return lines


def _finish(process, sent_at: float):
    stdout, stderr = process.communicate(timeout=60)
    return process.returncode, time.monotonic() - sent_at, stderr


@pytest.mark.parametrize("second_signal", [signal.SIGINT, signal.SIGTERM])
def test_second_signal_during_compilation_exits_130_at_once(tmp_path, second_signal):
    process = _start(["montecarlo", "--n", "2", "--chunk", "2", "--controller", "admittance"], tmp_path)
    _wait_for_line(process, "Monte-Carlo:")
    time.sleep(1.0)  # inside the campaign's compile (tens of seconds on two cores)
    process.send_signal(signal.SIGINT)
    time.sleep(0.5)
    process.send_signal(second_signal)
    code, elapsed, stderr = _finish(process, time.monotonic())
    assert code == 130, stderr  # not -11 (segmentation fault) or -6 (abort): no crash
    assert elapsed < 10.0, f"took {elapsed:.1f} s to stop"
    assert "Traceback" not in stderr and "core dumped" not in stderr
    assert "stopping after this chunk" in stderr
    assert (
        stderr.strip().splitlines()[-1] == f"{second_signal.name} received: stopped at once; finished files are on disk"
    )
    assert not list((tmp_path / "out").rglob(".*.npz")), "a half-written file left behind"


def test_first_signal_ends_a_command_without_safe_points(tmp_path):
    process = _start(["simulate", "--controller", "cartesian"], tmp_path)
    _wait_for_line(process, "compilation cache:")
    time.sleep(2.0)  # validation done, in the compile
    process.send_signal(signal.SIGINT)
    code, elapsed, stderr = _finish(process, time.monotonic())
    assert code == 130 and elapsed < 10.0, (code, elapsed, stderr)
    assert "Traceback" not in stderr
    assert stderr.strip().splitlines()[-1] == "SIGINT received: stopped at once; finished files are on disk"


def test_in_a_library_call_the_second_signal_raises_keyboard_interrupt():
    """Outside the command line (a notebook calling ``tuning.run.tune``) nothing ends the
    process: the first signal asks for a clean stop, the second raises KeyboardInterrupt,
    and the previous handlers come back."""
    import os

    from spacegrasp_jax.jobs.runfiles import StopRequest

    before = signal.getsignal(signal.SIGINT)
    with StopRequest("step") as stop:
        assert not stop.hard_exit
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.1)
        assert stop.requested
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)
    assert signal.getsignal(signal.SIGINT) is before
    with StopRequest("run", patience=0, hard_exit=True) as outer, StopRequest("chunk") as inner:
        assert outer.hard_exit and inner.hard_exit  # the command line's choice holds inside
    assert signal.getsignal(signal.SIGINT) is before


@pytest.mark.slow
def test_a_campaign_killed_between_chunks_resumes_to_the_same_samples(tmp_path):
    """SIGKILL leaves no chance to clean up: the chunks finished before it stay on disk (each
    written whole), ``--resume`` computes only the others, and the campaign ends with the
    same samples, bit for bit, as one that ran without a stop."""
    command = [sys.executable, "-m", "spacegrasp_jax.cli", "montecarlo", "--n", "16", "--chunk", "2"]
    command += ["--controller", "admittance", "--compile-cache", str(tmp_path / "cache")]  # the 17 s capture
    whole = subprocess.run([*command, "--out", str(tmp_path / "whole")], capture_output=True, text=True, timeout=600)
    assert whole.returncode == 0, whole.stderr  # it also fills the compile cache the others load from
    killed = subprocess.Popen(
        [*command, "--out", str(tmp_path / "killed")], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    chunks = tmp_path / "killed" / "chunks" / "admittance" / "paper"
    finished = lambda: [path for path in chunks.glob("*.npz") if not path.name.startswith(".")]
    deadline = time.monotonic() + 300
    while len(finished()) < 2:  # a chunk of 2 takes about 0.2 s on two cores
        assert killed.poll() is None, "the campaign ended before it could be killed"
        assert time.monotonic() < deadline, "no chunk finished in 300 s"
        time.sleep(0.002)
    killed.send_signal(signal.SIGKILL)
    killed.wait(timeout=60)
    assert killed.returncode == -signal.SIGKILL
    kept = len(finished())
    assert 2 <= kept < 8 and not (tmp_path / "killed" / "samples.npz").exists(), kept

    resumed = subprocess.run(
        [*command, "--resume", "--out", str(tmp_path / "killed")], capture_output=True, text=True, timeout=600
    )
    assert resumed.returncode == 0, resumed.stderr
    throughput = json.loads((tmp_path / "killed" / "summary.json").read_text())["throughput"]
    assert throughput["rollouts_computed_this_run"] == 16 - 2 * kept  # the finished chunks were not run again
    with np.load(tmp_path / "whole" / "samples.npz") as expected, np.load(tmp_path / "killed" / "samples.npz") as got:
        assert sorted(got.files) == sorted(expected.files)
        for name in expected.files:
            np.testing.assert_array_equal(got[name], expected[name], err_msg=name)
