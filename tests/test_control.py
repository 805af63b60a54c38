"""Controllers: gains validation, PID, pseudoinverse, and the admittance and Cartesian laws."""

from __future__ import annotations

import dataclasses
import json
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax.loop.control import (
    Admittance,
    AdmittanceState,
    ControlInputs,
    GainsError,
    UnusedGainsWarning,
    admittance,
    cartesian,
    load_gains,
    make_gains,
    missing_groups,
    named_gains,
    paper_gains,
    required_groups,
)
from spacegrasp_jax.loop.control.gains import tuned_gains_file
from spacegrasp_jax.loop.control.pid import pid_init, pid_torque
from spacegrasp_jax.loop.control.pseudoinverse import pseudoinverse_apply


def test_paper_gains_match_the_paper():
    gains = paper_gains()
    np.testing.assert_array_equal(gains.Kd, np.full(6, 600.0))
    np.testing.assert_array_equal(gains.Bd, np.full(6, 500.0))
    np.testing.assert_array_equal(gains.Md, np.full(6, 800.0))
    np.testing.assert_array_equal(gains.K_lin, [3, 3, 3])
    np.testing.assert_array_equal(gains.kp, [140, 210, 140, 105, 105, 21, 21])  # Table 4
    np.testing.assert_array_equal(gains.ki, [10, 10, 10, 1, 1, 1, 1])
    np.testing.assert_array_equal(gains.kd, [0.01] * 7)


BAD_GAINS = [
    ({"Kd": -1.0}, r"Kd: gains must be positive"),
    ({"Md": 0.0}, r"Md: gains must be positive"),
    ({"ki": [-1.0] * 7}, r"ki: gains must be non-negative"),
    ({"kp": [1.0] * 6}, r"kp: expected 7 values"),
    ({"Bd": float("nan")}, r"Bd: must be finite"),
    ({"gain_x": 1.0}, r"unknown gain\(s\): gain_x"),
]


@pytest.mark.parametrize("change, message", BAD_GAINS)
def test_make_gains_rejects_bad_values(change, message):
    fields = paper_gains().to_dict()
    fields.update(change)
    with pytest.raises(GainsError, match=message):
        make_gains(**fields)


def test_gains_json_round_trip_and_errors(tmp_path):
    path = tmp_path / "gains.json"
    path.write_text(json.dumps(paper_gains().to_dict()))
    assert load_gains(path).to_dict() == paper_gains().to_dict()
    path.write_text(json.dumps({"kd": -1.0}))
    with pytest.raises(GainsError, match=r"gains.json: kd: gains must be non-negative"):
        load_gains(path, fill_from="paper")
    path.write_text(json.dumps({"kq": 1.0}))
    with pytest.raises(GainsError, match=r"gains.json: unknown gain\(s\): kq"):
        load_gains(path)
    path.write_text("{not json")
    with pytest.raises(GainsError, match="not valid JSON"):
        load_gains(path)


def test_a_gains_file_holds_what_its_controller_uses(tmp_path):
    # Written for one controller: only that law's groups and the PID's.
    tuned = make_gains(**(paper_gains().to_dict() | {"Kd": 300.0, "K_lin": 2.0}))
    assert set(tuned.to_dict("admittance")) == {"Md", "Bd", "Kd", "kp", "ki", "kd", "pinv_damping"}
    assert set(tuned.to_dict("cartesian")) == {"K_lin", "K_eul", "kp", "ki", "kd", "pinv_damping"}
    path = tmp_path / "admittance.json"
    path.write_text(json.dumps(tuned.to_dict("admittance")))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no notice for a file that holds the law's own groups
        read = load_gains(path, "admittance")
    assert read.to_dict("admittance") == tuned.to_dict("admittance")
    assert read.K_lin.tolist() == [3.0] * 3  # the groups the file leaves out are the paper's
    # The other law's groups are accepted, and named; the law's own must come from somewhere.
    with pytest.warns(UnusedGainsWarning, match=r"admittance.json: Md, Bd, Kd not used by the cartesian controller"):
        read = load_gains(path, "cartesian", fill_from="paper")
    assert read.Kd.tolist() == [300.0] * 6 and read.K_lin.tolist() == [3.0] * 3


def test_a_gains_file_that_leaves_out_a_group_is_refused_unless_told_where_it_comes_from(tmp_path):
    """Explicit gains: a file missing a group its law uses is refused naming the group; with
    ``fill_from`` the group comes from the paper, another file or a gain set, and
    ``missing_groups`` names what was filled. ``pinv_damping`` is optional (the exact law)."""
    assert required_groups("admittance") == ("Md", "Bd", "Kd", "kp", "ki", "kd")
    assert required_groups(["admittance", "cartesian"]) == ("Md", "Bd", "Kd", "K_lin", "K_eul", "kp", "ki", "kd")
    no_Kd = {name: value for name, value in paper_gains().to_dict("admittance").items() if name != "Kd"}
    no_Kd["Md"] = [900.0] * 6
    path = tmp_path / "no_Kd.json"
    path.write_text(json.dumps(no_Kd))
    with pytest.raises(GainsError, match=r"no_Kd.json: Kd: missing; give every group the law uses, or say where"):
        load_gains(path, "admittance")
    assert missing_groups(path, "admittance") == ["Kd"]
    from_paper = load_gains(path, "admittance", fill_from="paper")
    assert from_paper.Kd.tolist() == [600.0] * 6 and from_paper.Md.tolist() == [900.0] * 6
    other = tmp_path / "stiff.json"
    other.write_text(json.dumps({"Kd": 1200.0}))
    assert load_gains(path, "admittance", fill_from=other).Kd.tolist() == [1200.0] * 6
    given = dataclasses.replace(paper_gains(), Kd=paper_gains().Kd * 0.5)
    assert load_gains(path, "admittance", fill_from=given).Kd.tolist() == [300.0] * 6
    with pytest.raises(
        GainsError, match=r"stiff.json: Md, Bd, kp, ki, kd: missing, and .*empty.json leaves them to this file"
    ):
        empty = tmp_path / "empty.json"
        empty.write_text("{}")
        load_gains(empty, "admittance", fill_from=other)
    # The paper's joint gains are for its 7 joints: a 6-joint arm's file must give its own.
    six = tmp_path / "six.json"
    six.write_text(json.dumps({"Md": 800.0, "Bd": 500.0, "Kd": 600.0}))
    with pytest.raises(GainsError, match=r"six.json: kp, ki, kd: missing, and the paper's Table 4 is for its 7"):
        load_gains(six, "admittance", n_joints=6, fill_from="paper")
    # Named sets: the paper's and the shipped tuned ones, the tuned sets' other groups the paper's.
    assert named_gains("paper").to_dict() == paper_gains().to_dict()
    flight = named_gains("flight")
    assert flight.to_dict("admittance") == load_gains(tuned_gains_file("flight"), "admittance").to_dict("admittance")
    assert flight.K_lin.tolist() == [3.0] * 3
    with pytest.raises(ValueError, match="named_gains: name must be one of paper, ideal, flight, free_target"):
        named_gains("fast")


def test_pid_hand_computed():
    gains = paper_gains()
    state = pid_init(7)
    error = jnp.arange(1.0, 8.0)
    dt = 1e-3
    # At t = 0.5 s the ramp is 0.25; first step: integral = e dt, derivative = e / dt.
    torque, state = pid_torque(gains, state, error, 0.5, dt)
    expected = 0.25 * (gains.kp * error + gains.ki * error * dt + gains.kd * error / dt)
    np.testing.assert_allclose(torque, expected, rtol=1e-14)
    # Second step after the ramp: integral accumulates, derivative is the difference.
    torque, state = pid_torque(gains, state, 2 * error, 1.5, dt)
    expected = gains.kp * 2 * error + gains.ki * 3 * error * dt + gains.kd * error / dt
    np.testing.assert_allclose(torque, expected, rtol=1e-14)
    # At t = 0 every gain is ramped to zero.
    torque, _ = pid_torque(gains, pid_init(7), error, 0.0, dt)
    np.testing.assert_array_equal(torque, 0.0)


def test_pseudoinverse_exact_and_damped():
    rng = np.random.default_rng(0)
    J, twist = rng.normal(size=(6, 7)), rng.normal(size=6)
    np.testing.assert_allclose(pseudoinverse_apply(J, twist), np.linalg.pinv(J) @ twist, rtol=1e-10)
    np.testing.assert_allclose(J @ pseudoinverse_apply(J, twist), twist, rtol=1e-10)
    # Damped least squares: argmin |J x - v|^2 + lambda^2 |x|^2, closed form via numpy.
    lam = 0.1
    expected = np.linalg.solve(J.T @ J + lam**2 * np.eye(7), J.T @ twist)
    np.testing.assert_allclose(pseudoinverse_apply(J, twist, lam), expected, rtol=1e-10)
    # At a singular J (rank 5) the damped inverse stays finite, gradients too.
    J_singular = J.copy()
    J_singular[5] = J_singular[4]
    assert np.all(np.isfinite(pseudoinverse_apply(J_singular, twist, lam)))
    gradient = jax.grad(lambda M: jnp.sum(pseudoinverse_apply(M, twist, lam)))(jnp.asarray(J_singular))
    assert np.all(np.isfinite(gradient))


def test_admittance_reference_rate_eq14_by_hand():
    gains = paper_gains()
    pose = jnp.array([0.001, -0.002, -0.05, 0.01, -0.02, 0.03])
    pose_des = jnp.array([0.0, 0.0, -0.049, 0.0, 0.0, 0.0])
    twist = jnp.array([0.001, 0.0, 0.01, 0.0, 0.02, 0.0])
    twist_des = jnp.array([0.0, 0.0, 0.011, 0.0, 0.0, 0.0])
    rate_des = jnp.array([0.0, 0.0, 0.001, 0.0, 0.0, 0.0])
    wrench = jnp.array([0.5, 0.0, -3.0, 0.0, 0.01, 0.0])
    rate = admittance.reference_twist_rate(gains, pose, twist, pose_des, twist_des, rate_des, wrench)
    expected = rate_des + (wrench + 500.0 * (twist_des - twist) + 600.0 * (pose_des - pose)) / 800.0
    np.testing.assert_allclose(rate, expected, rtol=1e-14)
    # Euler-angle errors wrap: a yaw error of 2 pi - 0.1 acts as -0.1.
    wrapped = admittance.pose_error(jnp.zeros(6), jnp.array([0, 0, 0, 0, 0, 2 * np.pi - 0.1]))
    np.testing.assert_allclose(wrapped[5], 0.1, atol=1e-12)
    # The law object: the command from V_ref(k), then eq 15 by forward Euler over dt.
    J = jnp.eye(6, 7) + 0.1
    inputs = ControlInputs(
        pose, twist, wrench, pose_des, twist_des, rate_des, J, jnp.eye(3), jnp.zeros(7), jnp.zeros(7), jnp.zeros(6)
    )
    law, dt = Admittance(), 1e-3
    state = AdmittanceState(V_ref=jnp.array([0.01, 0.0, 0.002, 0.0, 0.0, 0.001]))
    qd_des, after = law.update(gains, inputs, state, dt)
    np.testing.assert_allclose(after.V_ref, state.V_ref + dt * expected, rtol=1e-14)
    np.testing.assert_allclose(J @ qd_des, state.V_ref, atol=1e-14)  # a right inverse of J
    np.testing.assert_array_equal(law.init().V_ref, np.zeros(6))


def test_laws_drive_the_ee_towards_the_target():
    """With J = [I 0] the joint rates are the EE twist: the admittance law follows V_ref
    rotated into the EE frame, and the Cartesian law moves along the pose error."""
    J = jnp.concatenate([jnp.eye(6), jnp.zeros((6, 1))], axis=1)
    R_lar_ee = jnp.eye(3)
    V_ref = jnp.array([0.01, -0.02, 0.03, 0.1, 0.2, 0.3])
    np.testing.assert_allclose(admittance.desired_joint_rates(J, R_lar_ee, V_ref)[:6], V_ref, atol=1e-14)
    pose, pose_des = jnp.zeros(6), jnp.array([0.0, 0.0, 0.01, 0.0, 0.0, 0.02])
    qd = cartesian.desired_joint_rates(paper_gains(), J, R_lar_ee, pose, pose_des, jnp.zeros(6))
    np.testing.assert_allclose(qd[:6], 3.0 * (pose_des - pose), atol=1e-14)


def test_the_gains_damping_is_the_damped_least_squares_law_and_differentiable():
    rng = np.random.default_rng(4)
    J = jnp.asarray(rng.normal(size=(6, 7)))
    twist = jnp.asarray(rng.normal(size=6))
    inputs = ControlInputs(
        jnp.zeros(6),
        jnp.zeros(6),
        jnp.zeros(6),
        jnp.zeros(6),
        jnp.zeros(6),
        jnp.zeros(6),
        J,
        jnp.eye(3),
        jnp.zeros(7),
        jnp.zeros(7),
        jnp.zeros(6),
    )
    state = AdmittanceState(V_ref=twist)
    lam = 0.2
    damped = make_gains(**(paper_gains().to_dict() | {"pinv_damping": lam}))
    qd_des, _ = Admittance().update(damped, inputs, state, 1e-3)
    expected = np.linalg.solve(np.asarray(J.T @ J) + lam**2 * np.eye(7), np.asarray(J.T @ twist))
    np.testing.assert_allclose(qd_des, expected, rtol=1e-10)
    # The same as the law's own (static) damping; the two add up.
    np.testing.assert_allclose(qd_des, Admittance(pinv_damping=lam).update(paper_gains(), inputs, state, 1e-3)[0])
    half = make_gains(**(paper_gains().to_dict() | {"pinv_damping": lam / 2}))
    np.testing.assert_allclose(qd_des, Admittance(pinv_damping=lam / 2).update(half, inputs, state, 1e-3)[0])
    # The paper's gains: no damping, the exact pseudoinverse.
    assert paper_gains().pinv_damping.tolist() == [0.0]
    exact, _ = Admittance().update(paper_gains(), inputs, state, 1e-3)
    np.testing.assert_allclose(exact, np.linalg.pinv(np.asarray(J)) @ np.asarray(twist), rtol=1e-10)

    # d qd / d lambda against central differences.
    def f(damping):
        gains = dataclasses.replace(paper_gains(), pinv_damping=jnp.reshape(damping, (1,)))
        return jnp.sum(Admittance().update(gains, inputs, state, 1e-3)[0] ** 2)

    h = 1e-6
    np.testing.assert_allclose(jax.grad(f)(lam), (f(lam + h) - f(lam - h)) / (2 * h), rtol=1e-6)
