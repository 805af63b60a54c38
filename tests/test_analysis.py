"""spacegrasp_jax.tuning.analysis on functions whose slopes are known in closed form."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from spacegrasp_jax.tuning import analysis


def _quartic(params):
    # loss = sum(a^4) + sum(3 b^2) + a0 b1; an aux dict as spacegrasp_jax.tuning.tune's loss returns.
    a, b = params["a"], params["b"]
    loss = jnp.sum(a**4) + 3.0 * jnp.sum(b**2) + a[0] * b[1]
    return loss, {"loss": loss}


VALUE_AND_GRAD = jax.jit(jax.value_and_grad(_quartic, has_aux=True))
PARAMS = {"a": jnp.array([0.3, -1.2]), "b": jnp.array([2.0, 0.5, -0.7])}


def _exact_slope(s, direction):
    """d/ds of the quartic along params + s d, by hand."""
    a = PARAMS["a"] + s * direction["a"]
    b = PARAMS["b"] + s * direction["b"]
    da, db = direction["a"], direction["b"]
    return float(np.sum(4 * a**3 * da) + np.sum(6 * b * db) + da[0] * b[1] + a[0] * db[1])


def test_descent_direction_is_the_unit_negative_gradient():
    _, gradient = VALUE_AND_GRAD(PARAMS)
    direction = analysis.descent_direction(gradient)
    flat_g = np.concatenate([np.asarray(gradient["a"]), np.asarray(gradient["b"])])
    flat_d = np.concatenate([direction["a"], direction["b"]])
    np.testing.assert_allclose(np.linalg.norm(flat_d), 1.0, rtol=1e-14)
    np.testing.assert_allclose(flat_d, -flat_g / np.linalg.norm(flat_g), rtol=1e-14)
    assert analysis.group_norms(gradient)["b"] == pytest.approx(np.linalg.norm(gradient["b"]))


def test_descent_direction_refuses_a_zero_gradient():
    with pytest.raises(ValueError, match="gradient norm is 0"):
        analysis.descent_direction({"a": np.zeros(2)})


def test_loss_slice_gives_the_loss_and_its_exact_slope_along_the_line():
    _, gradient = VALUE_AND_GRAD(PARAMS)
    direction = analysis.descent_direction(gradient)
    steps = [-0.5, 0.0, 0.25, 1.0]
    line = analysis.loss_slice(VALUE_AND_GRAD, PARAMS, direction, steps)
    for s, loss, slope in zip(line["step"], line["loss"], line["slope"]):
        point = {k: PARAMS[k] + s * direction[k] for k in PARAMS}
        assert loss == pytest.approx(float(_quartic(point)[0]), rel=1e-14)
        assert slope == pytest.approx(_exact_slope(s, direction), rel=1e-12)
    assert line["slope"][1] < 0.0  # descending at the origin


def test_slope_check_agrees_with_the_exact_slope():
    _, gradient = VALUE_AND_GRAD(PARAMS)
    direction = analysis.descent_direction(gradient)
    check = analysis.slope_check(VALUE_AND_GRAD, PARAMS, direction, h=1e-5)
    assert check["gradient_slope"] == pytest.approx(_exact_slope(0.0, direction), rel=1e-12)
    assert check["relative_error"] < 1e-8
