"""Each law owns its gains (``spacegrasp_jax.loop.control.groups``): the gain set is every law's
and the joint servo's declared groups, each law reads its own and nothing else, and a law
with a gain group of its own joins the set with no other change (checked on a joint-space
spring-damper law written here, against its analytic torques in a closed loop)."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from random_states import random_rotation

from spacegrasp_jax.envelope.scenario import paper_scenario
from spacegrasp_jax.loop import simulate
from spacegrasp_jax.loop.control import (
    GAIN_GROUPS,
    GAINS_USED,
    LAWS,
    PID,
    ControlInputs,
    GainGroup,
    Gains,
    Output,
    as_controller,
    chain,
    group,
    paper_gains,
)
from spacegrasp_jax.loop.control.groups import PER_JOINT, fields_of_groups, groups_of
from spacegrasp_jax.loop.control.registry import collect_gain_groups
from spacegrasp_jax.loop.simulate import RunSpec

N_JOINTS = 7


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class JointSpringGains:
    Kq: jax.Array = group(GainGroup(PER_JOINT, "N m/rad", "joint stiffness, one a joint", "none", default=2.0))
    Bq: jax.Array = group(GainGroup(PER_JOINT, "N m s/rad", "joint damping, one a joint", "none", default=1.0))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Memoryless:
    pass


@dataclasses.dataclass(frozen=True)
class JointSpring:
    """``u = Kq (q_rest - q) - Bq qd``: a torque law with two gain groups no other law has."""

    q_rest: tuple[float, ...] = (0.1,) * N_JOINTS
    name: ClassVar[str] = "joint_spring"
    title: ClassVar[str] = "joint spring"
    output: ClassVar[Output] = Output.JOINT_TORQUES
    gains_type: ClassVar[type] = JointSpringGains
    gain_groups: ClassVar[tuple[str, ...]] = tuple(groups_of(JointSpringGains))
    loop_gain: ClassVar[dict[str, int]] = {"Kq": 1, "Bq": 1}
    style: ClassVar[dict[str, str]] = dict(color="k", linestyle="-", label="joint spring")
    paper_max_abs_torque_Nm: ClassVar[None] = None

    def init(self, n_joints: int = N_JOINTS, dtype=jnp.float64) -> Memoryless:
        return Memoryless()

    def update(self, gains: JointSpringGains, inputs: ControlInputs, state, dt):
        return gains.Kq * (jnp.asarray(self.q_rest) - inputs.q) - gains.Bq * inputs.qd, state

    def log_fields(self, state) -> dict[str, jax.Array]:
        return {}


def _inputs(seed: int) -> ControlInputs:
    rng = np.random.default_rng(seed)
    vector = lambda n, scale=1.0: jnp.asarray(scale * rng.standard_normal(n))  # noqa: E731
    J = rng.standard_normal((6, N_JOINTS))
    return ControlInputs(
        pose=vector(6, 0.3),
        twist=vector(6, 0.1),
        wrench=vector(6, 5.0),
        pose_des=vector(6, 0.3),
        twist_des=vector(6, 0.1),
        twist_rate_des=vector(6, 0.05),
        J_dyn_ee=jnp.asarray(J),
        R_lar_ee=jnp.asarray(random_rotation(rng)),
        q=vector(N_JOINTS),
        qd=vector(N_JOINTS, 0.1),
        frame_twist=vector(6, 0.01),
    )


def test_the_gain_set_is_every_law_and_the_servo_groups_as_each_declares_them():
    declared = {}
    for law in (*LAWS.values(), PID):
        for name, declaration in groups_of(law.gains_type).items():
            assert declared.setdefault(name, declaration) == declaration, name
    assert GAIN_GROUPS == declared
    assert [field.name for field in dataclasses.fields(Gains)] == list(declared)
    assert groups_of(Gains) == declared
    for name, law in LAWS.items():
        servo = PID.gain_groups if law.output is Output.JOINT_RATES else ()
        assert GAINS_USED[name] == law.gain_groups + servo == tuple(groups_of(law.gains_type)) + servo


@pytest.mark.parametrize("name", list(LAWS))
def test_a_law_reads_its_own_groups_and_nothing_else(name):
    """With every group the controller does not use set to NaN, its command and torques are
    finite and bit for bit those of the law's and the servo's own gains pytrees."""
    controller = as_controller(name)
    gains = paper_gains()
    unused = {group: jnp.full_like(value, jnp.nan) for group, value in vars(gains).items()}
    poisoned = dataclasses.replace(gains, **{g: v for g, v in unused.items() if g not in GAINS_USED[name]})
    own = controller.law.gains_type(**{g: getattr(gains, g) for g in controller.law.gain_groups})
    inputs, state = _inputs(4), controller.init(N_JOINTS)
    command, _ = controller.command(poisoned, inputs, state.law, 1e-3)
    expected, _ = controller.law.update(own, inputs, state.law, 1e-3)
    assert np.all(np.isfinite(command))
    np.testing.assert_array_equal(command, expected)
    u, _ = controller.torque(poisoned, command, inputs.qd, state.pid, 0.5, 1e-3)
    if controller.servo is not None:
        servo_gains = PID.gains_type(**{g: getattr(gains, g) for g in PID.gain_groups})
        np.testing.assert_array_equal(
            u, controller.servo.update(servo_gains, command - inputs.qd, state.pid, 0.5, 1e-3)[0]
        )
    assert np.all(np.isfinite(u))


def test_a_law_with_gain_groups_of_its_own_joins_the_gain_set_and_runs_in_the_closed_loop(robot):
    """The registry's collection with the new law has its groups, a gain set made from it
    runs the law, and the logged torques are the law's analytic ones at the logged state."""
    groups = collect_gain_groups([*LAWS.values(), JointSpring])
    assert set(groups) == {*GAIN_GROUPS, "Kq", "Bq"}
    assert groups["Kq"] == groups_of(JointSpringGains)["Kq"]

    @jax.tree_util.register_dataclass
    @dataclasses.dataclass(frozen=True)
    class ExtendedGains(fields_of_groups(groups)):  # as control.gains makes Gains
        pass

    Kq = jnp.asarray([3.0, 4.0, 3.0, 2.0, 2.0, 0.5, 0.5])
    Bq = jnp.asarray([2.0, 3.0, 2.0, 1.0, 1.0, 0.2, 0.2])
    gains = ExtendedGains(**vars(paper_gains()), Kq=Kq, Bq=Bq)
    scenario = paper_scenario(robot, duration=0.1, move_duration=0.1)
    _, log = jax.jit(simulate.closed_loop)(RunSpec(robot, scenario, chain(JointSpring())), gains)
    q, qd, u = (np.asarray(x) for x in (log.q, log.qd, log.u))
    expected = np.asarray(Kq) * (0.1 - q) - np.asarray(Bq) * qd
    np.testing.assert_allclose(u, expected, rtol=1e-12, atol=1e-12)
    assert np.max(np.abs(qd[-1])) > 1e-4  # the spring moved the arm


def test_a_group_two_laws_declare_differently_is_refused():
    @jax.tree_util.register_dataclass
    @dataclasses.dataclass(frozen=True)
    class OtherKdGains:
        Kd: jax.Array = group(GainGroup(6, "N/mm", "another stiffness", "none", default=1.0))

    other = type("OtherKd", (JointSpring,), {"name": "other_kd", "gains_type": OtherKdGains, "gain_groups": ("Kd",)})
    with pytest.raises(ValueError, match="gain group 'Kd': the other_kd law declares it unlike the admittance law"):
        collect_gain_groups([*LAWS.values(), other])


def test_a_law_without_its_gains_declaration_is_refused_naming_what_it_lacks():
    without_gains = type("NoGains", (), {k: v for k, v in vars(JointSpring).items() if k != "gains_type"})
    with pytest.raises(ValueError, match="is not a control law: it has no gains_type"):
        chain(without_gains())
