"""Shared fixtures: the process settings, the paper robot, its Pinocchio twin and random states."""

from __future__ import annotations

import os
import shutil
import tempfile

import pytest
from random_states import RandomState, make_random_states

import spacegrasp_jax as sg
from spacegrasp_jax.loop.simulate import RunSpec

#: The test run's own persistent compilation cache: a program compiled by one process of the
#: run (a worker, a command run as a subprocess, a notebook's kernel, which all inherit this
#: variable) is loaded by the others instead of compiled again. The run's first process makes
#: a fresh, empty folder (never the user's cache) and removes it at the end, so no run loads a
#: program an earlier run compiled. Tests of the cache itself give their processes their own folder.
RUN_CACHE_VARIABLE = "JAX_COMPILATION_CACHE_DIR"
_RUN_CACHE_OWNER = "PYTEST_XDIST_WORKER" not in os.environ
if _RUN_CACHE_OWNER:
    _USERS_CACHE = os.environ.get(RUN_CACHE_VARIABLE)
    os.environ[RUN_CACHE_VARIABLE] = tempfile.mkdtemp(prefix="spacegrasp-test-run-xla-")

#: The run's XLA compiles its programs with LLVM's -O0, not the -O3 users get: most of the
#: suite's time is LLVM optimising the closed loop's kernels. At -O0 a gradient program
#: compiles about 4x faster and runs up to 5x slower, which the tests' short scenarios barely
#: feel: the whole suite takes half the time (docs/testing.md). Results agree with -O3 to
#: rounding: ``tests/test_compilation.py::test_the_suites_compiler_level_gives_the_users_results``
#: compares the two. Setting ``xla_backend_optimization_level`` in ``XLA_FLAGS`` overrides it.
#: Like the cache's folder, every process of the run inherits it.
SUITE_XLA_FLAG = "--xla_backend_optimization_level=0"
_USERS_XLA_FLAGS = os.environ.get("XLA_FLAGS")
if "xla_backend_optimization_level" not in (_USERS_XLA_FLAGS or ""):
    os.environ["XLA_FLAGS"] = f"{_USERS_XLA_FLAGS or ''} {SUITE_XLA_FLAG}".strip()

# As the command line does: float64, loops compiled whole (before anything compiles), and the
# run's compilation cache.
sg.configure(compile_cache=os.environ[RUN_CACHE_VARIABLE])


def pytest_unconfigure(config):
    if _RUN_CACHE_OWNER:
        shutil.rmtree(os.environ.pop(RUN_CACHE_VARIABLE), ignore_errors=True)
        if _USERS_CACHE is not None:
            os.environ[RUN_CACHE_VARIABLE] = _USERS_CACHE
    os.environ.pop("XLA_FLAGS", None)
    if _USERS_XLA_FLAGS is not None:
        os.environ["XLA_FLAGS"] = _USERS_XLA_FLAGS


N_RANDOM_STATES = 20


@pytest.fixture(scope="session")
def robot() -> sg.Robot:
    return sg.paper_robot()


@pytest.fixture(scope="session")
def random_states() -> list[RandomState]:
    return make_random_states(seed=20261123, count=N_RANDOM_STATES)


@pytest.fixture(scope="session", params=["tables", "urdf"])
def pinocchio_model(request, robot):
    """``(model, data, ee_frame_id)`` of the paper robot in Pinocchio, two ways: built from the
    paper's tables independently of this package (``tests/pinocchio_reference.py``), and read
    by Pinocchio's URDF parser from the URDF ``spacegrasp_jax.core.urdf`` writes, with a free-flyer
    root and no gravity (a URDF gives none; Pinocchio's default is the Earth's)."""
    import pinocchio as pin
    import pinocchio_reference

    if request.param == "tables":
        model, ee_frame = pinocchio_reference.build_model()
    else:
        from spacegrasp_jax.core.urdf import robot_to_urdf

        model = pin.buildModelFromXML(robot_to_urdf(robot), pin.JointModelFreeFlyer())
        model.gravity = pin.Motion.Zero()
        ee_frame = model.getFrameId("ee")
    return model, model.createData(), ee_frame


# ---- closed loop: each compiled once per session (experiment.run caches executables) ----


@pytest.fixture(scope="session")
def gains():
    from spacegrasp_jax.loop.control import paper_gains

    return paper_gains()


@pytest.fixture(scope="session")
def full_runs(robot, gains):
    """The paper's 17 s scenario with both controllers (exact contact law)."""
    from spacegrasp_jax.envelope.scenario import paper_scenario
    from spacegrasp_jax.jobs import experiment

    scenario = paper_scenario(robot)
    return {
        controller: experiment.run(RunSpec(robot, scenario, controller), gains)
        for controller in ("admittance", "cartesian")
    }


@pytest.fixture(scope="session")
def short_scenario(robot):
    """2 s with the whole approach compressed into it: contact starts at about 0.9 s."""
    from spacegrasp_jax.envelope.scenario import paper_scenario

    return paper_scenario(robot, duration=2.0, move_duration=2.0, contact_law="smooth")


# ---- scheduling: the longest files first --------------------------------------------------

#: The files that take longest (about 40-250 s each on 2 cores, measured), started first, the
#: longest first: the two workers take whole files in collection order, so long files left to
#: the end (the notebooks come last alphabetically) would leave one worker running them alone.
LONGEST_FIRST = (
    "tests/test_tune_cli.py",
    "tests/test_schedule.py",
    "tests/test_margins.py",
    "tests/test_cli.py",
    "tests/test_benchmark.py",
    "tests/test_docs_examples.py",
    "tests/test_compilation.py",
    "tests/test_tuning.py",
    "tests/test_tuner_reference.py",
    "tests/test_realism.py",
    "tests/test_target.py",
    "tests/test_simulate.py",
    "tests/test_stability.py",
    "tests/test_distributed.py",
    "tests/test_montecarlo.py",
    "tests/test_worstcase.py",
    "tests/test_dynamics.py",
    "tests/test_six_joint_arm.py",
    "tests/test_tuning_batch.py",
    "tests/test_gradients_cli.py",
    "tests/test_truncation.py",
    "notebooks/03_tuning.ipynb",
    "notebooks/06_free_target.ipynb",
    "tests/test_loop_compilation.py",
    "tests/test_urdf_arms.py",
    "tests/test_animation.py",
    "notebooks/04_monte_carlo.ipynb",
)


def pytest_collection_modifyitems(config, items):
    """Reorder whole files, the longest first; a file's tests keep their order."""
    rank = {name: position for position, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))
