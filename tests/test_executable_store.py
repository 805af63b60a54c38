"""The store of compiled programs under the package's own keys: a later process loads a
program without tracing it, and only keys whose every object is described by its value (and
the package's code) are stored."""

from __future__ import annotations

import dataclasses
import functools
import os
import subprocess
import sys

import numpy as np
import pytest

from spacegrasp_jax import compilation, executable_store
from spacegrasp_jax.simulate import FullLog, closed_loop
from spacegrasp_jax.stages import Stage


@pytest.fixture
def cache_folder(tmp_path, monkeypatch):
    """The store in a fresh folder (where JAX's cache folder would put it)."""
    monkeypatch.setattr(executable_store, "_cache_folder", lambda: str(tmp_path))
    return tmp_path


@dataclasses.dataclass(frozen=True)
class UsersLaw:  # a class defined outside the package: its code is not in the fingerprint
    gain: float = 1.0


def users_function(x):
    return x


def test_keys_described_by_their_values_are_stored_and_others_are_not(cache_folder):
    signature = compilation.argument_signature((np.zeros(3), {"a": np.zeros((2, 2))}))
    package_key = ("batch", "job", (closed_loop, (), (("stage", Stage.ESTIMATE),)), 8, FullLog(4), signature)
    path = executable_store.path_for(package_key)
    assert path is not None and path.parent == cache_folder / executable_store.FOLDER
    assert executable_store.path_for(package_key) == path  # the same name each time
    assert executable_store.path_for(package_key[:-1] + (FullLog(8), signature)) != path

    def local_function(x):
        return x

    not_described = [
        ("job", users_function),  # a function outside the package
        ("job", local_function),  # a closure: its captured values are not in its name
        ("job", lambda x: x),
        ("job", UsersLaw()),  # a user's class
        ("job", functools.partial(closed_loop, observer=UsersLaw())),
        ("job", object()),  # described by its address only
    ]
    for key in not_described:
        assert executable_store.path_for(key) is None, key


def test_another_version_of_the_code_or_of_the_flags_is_another_program(cache_folder, monkeypatch):
    key = ("program", closed_loop, 3)
    path = executable_store.path_for(key)
    monkeypatch.setattr(executable_store, "_source_digest", lambda: "edited")
    edited = executable_store.path_for(key)
    monkeypatch.undo()
    monkeypatch.setattr(executable_store, "_cache_folder", lambda: str(cache_folder))
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_fast_math=false")
    other_flags = executable_store.path_for(key)
    assert len({path, edited, other_flags}) == 3


def test_no_folder_no_store(monkeypatch):
    monkeypatch.setattr(executable_store, "_cache_folder", lambda: None)
    assert executable_store.path_for(("program", 1)) is None


RUN_A_SHORT_ROLLOUT = """
import sys
import numpy as np
import spacegrasp_jax as sg
from spacegrasp_jax import compilation, experiment
from spacegrasp_jax.control import paper_gains
from spacegrasp_jax.scenario import paper_scenario
from spacegrasp_jax.simulate import RunSpec

sg.configure(compile_cache=sys.argv[1])
if sys.argv[2] == "load":  # a later process: the program must come from the store, untraced
    def compile_once_without_lowering(key, lower, label=None):
        def refuse():
            raise AssertionError(f"{label} was traced again")
        return original(key, refuse, label)
    original = compilation.compile_once
    compilation.compile_once = compile_once_without_lowering
robot = sg.paper_robot()
scenario = paper_scenario(robot, duration=0.05)
if sys.argv[4] == "rollout":
    log = experiment.run(RunSpec(robot, scenario, "admittance"), paper_gains()).log
    np.savez(sys.argv[3], pose=log.pose_ee, torque=log.u)
else:  # a chunk run in sub-batches: a loop over runs (compilation.map_one_at_a_time)
    from spacegrasp_jax import campaign
    config = campaign.CampaignConfig(n=4, chunk=4, device_batch=2)
    metrics = campaign.evaluate_indices(robot, scenario, campaign.Variant("admittance", paper_gains()), config, np.arange(4))
    np.savez(sys.argv[3], **{name: np.asarray(value) for name, value in metrics.items()})
"""


@pytest.mark.parametrize("program", ["rollout", "chunk_in_sub_batches"])
def test_a_later_process_loads_the_program_without_tracing_it_and_gets_the_same_log(tmp_path, program):
    # The chunk's loop over its sub-batches once made a LAPACK call to keep it from being
    # compiled whole, which JAX sets up only while tracing: loaded untraced, it crashed.
    cache = tmp_path / "cache"
    logs = []
    for step in ("compile", "load"):
        path = tmp_path / f"{step}.npz"
        result = subprocess.run(
            [sys.executable, "-c", RUN_A_SHORT_ROLLOUT, str(cache), step, str(path), program],
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert result.returncode == 0, result.stderr[-3000:]
        logs.append(dict(np.load(path)))
        if step == "compile":
            assert len(list((cache / executable_store.FOLDER).iterdir())) == 1
    assert logs[0].keys() == logs[1].keys()
    for name in logs[0]:
        np.testing.assert_array_equal(logs[0][name], logs[1][name])


SOLVE_BY_LAPACK = """
import sys
import jax
import jax.numpy as jnp
import numpy as np
import spacegrasp_jax as sg
from spacegrasp_jax import compilation

sg.configure(compile_cache=sys.argv[1])
matrix = np.array([[4.0, 1.0], [1.0, 3.0]])
factor = lambda a: jnp.linalg.cholesky(a)  # a LAPACK call (potrf) on a CPU
executable, _ = compilation.compile_once(("lapack-probe", 2), lambda: jax.jit(factor).lower(matrix))
np.save(sys.argv[2], np.asarray(executable(matrix)))
"""


def test_a_program_that_calls_lapack_is_not_stored_and_a_later_process_gets_it_right(tmp_path):
    # JAX sets up its LAPACK kernels while lowering: stored and loaded untraced, such a
    # program crashed the process at its first call.
    cache = tmp_path / "cache"
    factors = []
    for step in ("first", "later"):
        path = tmp_path / f"{step}.npy"
        result = subprocess.run(
            [sys.executable, "-c", SOLVE_BY_LAPACK, str(cache), str(path)], capture_output=True, text=True, timeout=600
        )
        assert result.returncode == 0, result.stderr[-3000:]
        stored = cache / executable_store.FOLDER
        assert not stored.exists() or not any(stored.iterdir())
        factors.append(np.load(path))
    np.testing.assert_allclose(factors[1], np.linalg.cholesky([[4.0, 1.0], [1.0, 3.0]]), rtol=1e-15)
    np.testing.assert_array_equal(factors[0], factors[1])


def test_an_unreadable_file_is_removed_and_not_loaded(tmp_path):
    broken = tmp_path / "broken.pickle"
    broken.write_bytes(b"not a stored program")
    assert executable_store.load(broken) is None
    assert not broken.exists()
    assert executable_store.load(tmp_path / "absent.pickle") is None
