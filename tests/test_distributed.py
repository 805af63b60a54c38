"""``spacegrasp montecarlo --distributed`` with two processes on this machine
(``jax.distributed`` on localhost, JAX's CPU collectives): an interrupt sent to both stops
them after the same chunk, ``--resume`` completes the campaign, and its ``samples.npz`` is
the one process's run over the same four devices, bit for bit."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

pytestmark = pytest.mark.slow  # two processes compiling and running a campaign each

N, CHUNK = 32, 4  # eight chunks of four samples, one per device
SCENARIO = "duration = 1.0\n[trajectory]\nduration = 1.0\n"


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("localhost", 0))
        return probe.getsockname()[1]


def _command(tmp_path, out, *extra):
    return [
        sys.executable,
        "-m",
        "spacegrasp_jax.cli",
        "montecarlo",
        "--n",
        str(N),
        "--chunk",
        str(CHUNK),
        "--controller",
        "admittance",
        "--scenario",
        str(tmp_path / "scenario.toml"),
        "--out",
        str(out),
        *extra,
    ]


def _two_processes(tmp_path, out, *extra):
    """Both processes of a two-process campaign (two CPU devices each), started."""
    port = _free_port()
    environment = os.environ | {"JAX_NUM_CPU_DEVICES": "2"}
    cluster = ["--distributed", "--coordinator", f"localhost:{port}", "--num-processes", "2"]
    cache = ["--compile-cache", str(tmp_path / "cache")]  # the resumed run loads the first's programs
    return [
        subprocess.Popen(
            _command(tmp_path, out, *cluster, "--process-id", str(rank), *cache, *extra),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=environment,
        )
        for rank in range(2)
    ]


def _wait(processes, timeout=600):
    finished = [process.communicate(timeout=timeout) for process in processes]
    return [process.returncode for process in processes], [stderr for _, stderr in finished]


def test_two_process_campaign_interrupted_and_resumed_equals_one_process(tmp_path):
    (tmp_path / "scenario.toml").write_text(SCENARIO)
    out = tmp_path / "two"
    chunks = out / "chunks" / "admittance" / "paper"

    processes = _two_processes(tmp_path, out)
    deadline = time.monotonic() + 600
    while not (chunks / f"{0:09d}.npz").exists():  # the first chunk done: both are in the loop
        assert all(process.poll() is None for process in processes), _wait(processes)
        assert time.monotonic() < deadline
        time.sleep(0.05)
    processes[0].send_signal(signal.SIGINT)
    time.sleep(0.3)  # the two signals land at different moments
    processes[1].send_signal(signal.SIGINT)
    codes, errors = _wait(processes)
    assert codes == [130, 130], errors
    stopped = [re.search(r"interrupted after chunk (\d+)/(\d+)", error) for error in errors]
    assert all(stopped), errors
    done = {int(match.group(1)) for match in stopped}
    assert len(done) == 1, f"the processes stopped after different chunks: {errors}"
    (done,) = done
    assert 1 <= done < N // CHUNK
    assert sorted(path.name for path in chunks.iterdir()) == [
        f"{first:09d}.npz" for first in range(0, done * CHUNK, CHUNK)
    ]

    codes, errors = _wait(_two_processes(tmp_path, out, "--resume", "--csv"))  # --csv: safe to add on resume
    assert codes == [0, 0], errors
    assert (out / "samples.csv").stat().st_size > 0

    one = tmp_path / "one"
    single = subprocess.run(
        _command(tmp_path, one, "--compile-cache", "none"),
        capture_output=True,
        text=True,
        timeout=600,
        env=os.environ | {"JAX_NUM_CPU_DEVICES": "4"},
    )
    assert single.returncode == 0, single.stderr
    two_processes, one_process = np.load(out / "samples.npz"), np.load(one / "samples.npz")
    assert sorted(two_processes.files) == sorted(one_process.files)
    for name in one_process.files:
        np.testing.assert_array_equal(two_processes[name], one_process[name], err_msg=name)
