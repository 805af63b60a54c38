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

from spacegrasp_jax.jobs import compilation, executable_store
from spacegrasp_jax.loop.simulate import FullLog, closed_loop
from spacegrasp_jax.loop.stages import Stage


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
from spacegrasp_jax.loop.control import paper_gains
from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.loop.simulate import RunSpec

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


@pytest.mark.slow
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


def test_a_cache_folder_that_others_can_write_is_refused_before_anything_is_loaded(tmp_path, monkeypatch):
    """A cache is code (its pickles hold executables): a folder another user can write, or one
    under such a folder, is neither loaded from nor written to, and ``use_compile_cache``
    refuses it naming the folder and the fix; a sticky folder above (``/tmp``) is no threat."""
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    (shared / executable_store.FOLDER).mkdir()
    planted = shared / executable_store.FOLDER / "planted.pickle"
    planted.write_bytes(b"not ours")
    reason = executable_store.unsafe_folder_reason(shared)
    assert reason == (
        f"{shared} is writable by others (mode 0777), who could put programs there that this process "
        f"would run: make it yours alone (chmod go-w {shared})"
    )
    monkeypatch.setattr(executable_store, "_cache_folder", lambda: str(shared))
    assert executable_store.path_for(("program", closed_loop, 3)) is None  # nothing loaded, nothing stored
    before = compilation.jax.config.jax_compilation_cache_dir
    with pytest.raises(compilation.CacheFolderError, match=r"writable by others \(mode 0777\)"):
        compilation.use_compile_cache(shared)
    assert compilation.jax.config.jax_compilation_cache_dir == before  # the process's cache is as it was
    assert planted.read_bytes() == b"not ours"

    mine_under_shared = shared / "mine"
    mine_under_shared.mkdir(mode=0o700)
    assert str(shared) in executable_store.unsafe_folder_reason(mine_under_shared)  # its parent can swap it
    group_writable = tmp_path / "group"
    group_writable.mkdir()
    group_writable.chmod(0o770)
    assert "mode 0770" in executable_store.unsafe_folder_reason(group_writable)

    sticky = tmp_path / "sticky"
    sticky.mkdir()
    sticky.chmod(0o1777)
    assert executable_store.unsafe_folder_reason(sticky / "mine") is None  # not there yet: judged by those above
    assert "mode 1777" in executable_store.unsafe_folder_reason(sticky)  # but not as the cache itself


def test_a_new_cache_folder_is_made_private_whatever_the_umask(tmp_path):
    folder = tmp_path / "cache" / "spacegrasp-jax" / "xla"
    before = compilation.jax.config.jax_compilation_cache_dir
    umask = os.umask(0o002)  # a group-writable default, as on shared workstations
    try:
        assert compilation.use_compile_cache(folder) == folder
    finally:
        os.umask(umask)
        compilation.jax.config.update("jax_compilation_cache_dir", before)
    for path in (tmp_path / "cache", tmp_path / "cache" / "spacegrasp-jax", folder):
        assert path.stat().st_mode & 0o777 == 0o700, path
    assert executable_store.unsafe_folder_reason(folder) is None
