"""The closed loop's stages: each a small object with its own memory, like an optax
transformation, chained on the signal it acts on.

A stage has a ``signal`` (a static field: where in the loop it sits), ``init(value)``, which
gives its memory for a signal shaped like ``value``, and ``apply(memory, value, noise) ->
(value, memory)``, which passes the signal on. The loop runs, in this order
([`loop_body()`][spacegrasp_jax.loop.simulate.loop_body]):

| signal | value | when |
| --- | --- | --- |
| ``"wrench"`` | (6,) the F/T reading ``[f (N); n (N m)]``, sensor axes | once a control period, at its start |
| ``"joints"`` | ``(q (N,) rad, qd (N,) rad/s)``, the controller's joint reading | once a control period, at its start |
| ``"lar"`` | ``(p (3,) m, R (3, 3))`` inertial, the LAR pose the controller believes | once a control period, at its start |
| ``"command"`` | (N,) the law's command (desired joint rates, rad/s, or a torque law's N m) | once a control period, from the law to the joint servo |
| ``"servo_joints"`` | ``(q, qd)``, the joint PID's reading | at every servo tick |
| ``"torque"`` | (N,) N m, the PID's torques (after its saturation), applied to the plant | at every servo tick, held over the tick's plant steps |

``noise`` holds the period's standard normals for the signal where the loop draws noise (a
realism with noisy sensors; zeros otherwise): (6,) for ``"wrench"``, (N,) for the two joint
signals (the servo tick's), ``None`` for the others. A stage with a ``signal`` among these
runs in [`simulate`][spacegrasp_jax.loop.simulate], campaigns and gradients when it is in the
run's ``RunSpec.stages`` (after the realism's own stages of the same signal): it must be a
pytree (a frozen dataclass under ``jax.tree_util.register_dataclass``, its numbers leaves,
its settings static), so that two runs that differ in its numbers share one program.

The realism's stages ([`realism_stages()`][spacegrasp_jax.loop.stages.realism_stages]) are these
classes, built from a [`Realism`][spacegrasp_jax.loop.realism.Realism]; a stage the realism leaves
off is not in the chain, at no cost in the compiled program. The actuators' saturation and
the anti-windup are the joint PID's own
([`PID.update()`][spacegrasp_jax.loop.control.pid.PID.update]); the controller's model is
[`believed_robot()`][spacegrasp_jax.loop.stages.believed_robot].
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Protocol

import jax
import jax.numpy as jnp

from spacegrasp_jax.core import spatial
from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.loop.realism import Realism, Stage

#: The signals a stage may act on, in the order the loop passes them (module docstring).
SIGNALS = ("wrench", "joints", "lar", "command", "servo_joints", "torque")
#: The signals of every servo tick (the others pass once a control period).
TICK_SIGNALS = ("servo_joints", "torque")


class LoopStage(Protocol):
    """A stage of the closed loop (module docstring).

    Attributes:
        signal: which of ``SIGNALS`` it acts on (static).
    """

    signal: str

    def init(self, value: Any) -> Any:
        """The stage's memory at the start of a run, for a signal shaped like ``value``."""
        ...

    def apply(self, memory: Any, value: Any, noise: jax.Array | None) -> tuple[Any, Any]:
        """``(the signal passed on, the memory after)``."""
        ...


def _static(default):
    return dataclasses.field(default=default, metadata=dict(static=True))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class WrenchSensor:
    """The F/T sensor's bias and white noise: ``reading + bias + std * noise``.

    Attributes:
        bias: (6,) ``[N; N m]``, constant, sensor axes.
        noise_std: (6,) ``[N; N m]``, white noise std per axis.
    """

    bias: jax.Array
    noise_std: jax.Array
    signal: str = _static("wrench")

    def init(self, value) -> tuple:
        return ()

    def apply(self, memory, value, noise):
        return value + self.bias + self.noise_std * noise, memory


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LowPass:
    """A first-order low-pass, discretised exactly at its sample period:
    ``filtered = previous + gain (reading - previous)``, from zero.

    Attributes:
        gain: the gain per sample, ``1 - exp(-2 pi f_c T)`` ([`low_pass_gain()`][spacegrasp_jax.loop.stages.low_pass_gain]; static).
    """

    gain: float = _static(1.0)
    signal: str = _static("wrench")

    def init(self, value) -> jax.Array:
        return jnp.zeros_like(value)

    def apply(self, memory, value, noise):
        filtered = memory + self.gain * (value - memory)
        return filtered, filtered


def low_pass_gain(cutoff_hz: float, period: float) -> float:
    """The first-order low-pass's gain per sample of ``period`` (s) at ``cutoff_hz`` (Hz),
    discretised exactly: ``1 - exp(-2 pi f_c period)``."""
    return 1.0 - math.exp(-2.0 * math.pi * cutoff_hz * period)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class JointSensors:
    """The joint sensors: the encoder's grid on ``q`` and white noise on ``qd``.

    The grid has a straight-through gradient: ``round()`` is flat between steps, so its exact
    derivative would cut the position feedback out of every gradient (an open loop whose
    sensitivity grows without bound). Averaged over where the grid falls, ``d E[reading] /
    dq = 1``.

    Attributes:
        angle_resolution_rad: () rad, the encoder's quantum (0: exact).
        rate_noise_std_radps: () rad/s, white noise std on each joint rate.
        signal: ``"joints"`` (the controller's reading) or ``"servo_joints"`` (the PID's).
    """

    angle_resolution_rad: jax.Array
    rate_noise_std_radps: jax.Array
    signal: str = _static("joints")

    def init(self, value) -> tuple:
        return ()

    def apply(self, memory, value, noise):
        q, qd = value
        quantum = self.angle_resolution_rad
        safe = jnp.where(quantum > 0.0, quantum, 1.0)
        grid_error = jnp.round(q / safe) * safe - q
        q = q + jnp.where(quantum > 0.0, jax.lax.stop_gradient(grid_error), 0.0)
        qd = qd + self.rate_noise_std_radps * noise
        return (q, qd), memory


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LarEstimate:
    """The LAR pose the controller believes: the true one moved by constant errors.

    Attributes:
        position_error_m: (3,) m, LAR axes.
        angle_error_rad: (3,) rad, a rotation vector in LAR axes.
    """

    position_error_m: jax.Array
    angle_error_rad: jax.Array
    signal: str = _static("lar")

    def init(self, value) -> tuple:
        return ()

    def apply(self, memory, value, noise):
        p_lar, R_lar = value
        p_lar = p_lar + spatial.matvec(R_lar, self.position_error_m)
        R_lar = spatial.matmul(R_lar, spatial.rotation_exp(self.angle_error_rad))
        return (p_lar, R_lar), memory


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DelayLine:
    """A delay of whole samples: the value passed on is the one that came in ``length``
    samples before (zeros before the first). The realism's delay of the commands and the
    margins' extra delays at the law's output and at the servo's input are each one.

    Its memory is the last ``capacity`` values, oldest first (each leaf of the signal with a
    leading axis of ``capacity``): the realism's line of ``delay_periods`` holds exactly the
    commands in flight.

    Attributes:
        capacity: the line's length (static); ``length`` must be at most it.
        length: () int, the delay in samples, 0 to ``capacity`` (a value: every delay up to
            ``capacity`` runs the same program).
        signal: where it sits (``"command"``: control periods; ``"servo_joints"``: servo
            ticks; any of ``SIGNALS``).
    """

    capacity: int = _static(1)
    length: jax.Array = 0
    signal: str = _static("command")

    def init(self, value):
        return jax.tree.map(lambda x: jnp.zeros((self.capacity,) + jnp.shape(x), jnp.result_type(x)), value)

    def apply(self, memory, value, noise):
        at = (self.capacity - self.length) % self.capacity  # the value of ``length`` samples before
        values, structure = jax.tree.flatten(value)
        passed, kept = [], []
        for line, now in zip(structure.flatten_up_to(memory), values, strict=True):
            passed.append(jnp.where(self.length == 0, now, line[at]))
            kept.append(jnp.concatenate([line[1:], now[None]]))
        return structure.unflatten(passed), structure.unflatten(kept)


def realism_stages(realism: Realism, period: float) -> tuple:
    """The stages ``realism`` switches on, in the loop's order, for a control period of
    ``period`` (s): the F/T sensor's bias and noise and its low-pass, the joint sensors (for
    the controller and for the servo), the LAR estimate and the commands' delay line."""
    chain = []
    if Stage.SENSORS in realism.stages:
        chain.append(
            WrenchSensor(
                jnp.concatenate([realism.force_bias, realism.torque_bias], axis=-1),
                jnp.concatenate([realism.force_noise_std, realism.torque_noise_std], axis=-1),
            )
        )
    if realism.cutoff_hz > 0.0:
        chain.append(LowPass(low_pass_gain(realism.cutoff_hz, period)))
    if Stage.SENSORS in realism.stages:
        for signal in ("joints", "servo_joints"):
            chain.append(JointSensors(realism.angle_resolution_rad, realism.rate_noise_std_radps, signal))
    if Stage.ESTIMATE in realism.stages:
        chain.append(LarEstimate(realism.lar_position_error_m, realism.lar_angle_error_rad))
    if realism.delay_periods:
        chain.append(DelayLine(realism.delay_periods, realism.delay_periods))
    return tuple(chain)


def check_chain(chain: tuple) -> None:
    """Raise ``ValueError`` unless every stage of ``chain`` names one of ``SIGNALS``."""
    for stage in chain:
        signal = getattr(stage, "signal", None)
        if signal not in SIGNALS:
            raise ValueError(f"stages: {type(stage).__name__}'s signal must be one of {SIGNALS}, got {signal!r}")


def init_chain(chain: tuple, values: dict[str, Any]) -> tuple:
    """Each stage's memory at the start of a run (``values``: a value of each signal)."""
    return tuple(stage.init(values[stage.signal]) for stage in chain)


def run_chain(chain: tuple, memories: tuple, signal: str, value, noise=None) -> tuple[Any, tuple]:
    """``value`` through ``chain``'s stages of ``signal`` in order: ``(the value passed on,
    the memories after)``."""
    memories = list(memories)
    for i, stage in enumerate(chain):
        if stage.signal == signal:
            value, memories[i] = stage.apply(memories[i], value, noise)
    return value, tuple(memories)


def acts_on(chain: tuple, *signals: str) -> bool:
    """Whether a stage of ``chain`` acts on one of ``signals``."""
    return any(stage.signal in signals for stage in chain)


def believed_robot(robot: Robot, realism: Realism) -> Robot:
    """The robot the controller believes: ``robot`` with the satellite's mass and inertia
    times the realism's factors."""
    return dataclasses.replace(
        robot,
        satellite_mass=robot.satellite_mass * realism.satellite_mass_factor,
        satellite_inertia=robot.satellite_inertia * realism.satellite_inertia_factor,
    )


__all__ = [
    "DelayLine",
    "JointSensors",
    "LarEstimate",
    "LoopStage",
    "LowPass",
    "SIGNALS",
    "TICK_SIGNALS",
    "WrenchSensor",
    "acts_on",
    "believed_robot",
    "check_chain",
    "init_chain",
    "low_pass_gain",
    "realism_stages",
    "run_chain",
]
