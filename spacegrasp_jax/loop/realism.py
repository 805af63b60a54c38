"""The realism model: what separates a flight-like closed loop from the paper's ideal one.

The ideal loop (the paper's, and the default everywhere) has a controller that knows the
plant exactly, perfect sensors, unlimited motors and control at the plant's rate. A
[`Realism`][spacegrasp_jax.loop.realism.Realism] inserts, in this order (documentation, modelling notes):

plant state -> sensors (F/T: bias and white noise in sensor axes, then a first-order
low-pass; joints: encoder quantisation of q, white noise on qd) -> controller, run at the
start of each control period with its own model of the robot (believed satellite mass and
inertia) and its own estimate of the LAR pose -> delay (whole control periods) -> joint PID
with anti-windup -> torque saturation -> zero-order hold over the control period -> plant
(RK4 at the scenario's ``dt``). The joint PID may run faster than the controller, at its own
servo period, reading the joint sensors at each of its ticks (``timing.servo_period``; by
default it runs with the controller, once per control period).

Array leaves (noise levels, biases, limits, factors, estimate errors) are differentiable and
vmappable; the choices that fix the program's shape are static: the control period, the
delay, the filter's cutoff, the saturation law, the anti-windup, and which stages are on
(``Realism.stages``, decided by [`make_realism()`][spacegrasp_jax.loop.realism.make_realism] from the values).

TOML (``--realism FILE``; every key optional, unknown keys rejected)::

    [timing]
    control_period = 0.001          # s, a whole multiple of the scenario's dt; zero-order hold
    delay_periods = 0               # whole control periods between measurement and actuation
    servo_period = 0.001            # s, the joint PID's period: divides control_period (default: equal)
    [force_torque_sensor]
    force_noise_std = [0.0, 0.0, 0.0]    # N, white Gaussian per axis, sensor axes
    torque_noise_std = [0.0, 0.0, 0.0]   # N m
    force_bias = [0.0, 0.0, 0.0]         # N
    torque_bias = [0.0, 0.0, 0.0]        # N m
    cutoff_hz = 0.0                      # first-order low-pass on the measured wrench; 0 = none
    [joint_sensors]
    angle_resolution_rad = 0.0      # encoder quantisation of q; 0 = exact
    rate_noise_std_radps = 0.0      # white Gaussian on qd
    [actuators]
    torque_limit_Nm = [inf, inf, inf, inf, inf, inf, inf]   # saturation
    saturation = "hard"             # or "smooth" (tanh, for gradients)
    anti_windup = true              # the PID's integrator stops while the torque saturates
    [controller_model]
    satellite_mass_factor = 1.0     # believed mass = factor * satellite mass
    satellite_inertia_factor = 1.0  # believed inertia = factor * satellite inertia
    [target_estimate]
    position_error_m = [0.0, 0.0, 0.0]   # constant error of the LAR pose the controller uses (LAR axes)
    angle_error_rad = [0.0, 0.0, 0.0]    # rotation vector
"""

from __future__ import annotations

import dataclasses
import enum
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from spacegrasp_jax.core.inputs import is_real, read_document, short
from spacegrasp_jax.core.precision import require_float64
from spacegrasp_jax.envelope.scenario import DT_LIMITS_S


class RealismError(ValueError):
    """Invalid realism settings; the message names the table and key."""


#: The TOML contract: table -> key -> (shape, default). Shape () is a scalar.
SCHEMA = {
    "timing": {"control_period": ((), None), "delay_periods": ((), 0), "servo_period": ((), None)},
    "force_torque_sensor": {
        "force_noise_std": ((3,), 0.0),
        "torque_noise_std": ((3,), 0.0),
        "force_bias": ((3,), 0.0),
        "torque_bias": ((3,), 0.0),
        "cutoff_hz": ((), 0.0),
    },
    "joint_sensors": {"angle_resolution_rad": ((), 0.0), "rate_noise_std_radps": ((), 0.0)},
    "actuators": {"torque_limit_Nm": ((7,), math.inf), "saturation": ((), "hard"), "anti_windup": ((), True)},
    "controller_model": {"satellite_mass_factor": ((), 1.0), "satellite_inertia_factor": ((), 1.0)},
    "target_estimate": {"position_error_m": ((3,), 0.0), "angle_error_rad": ((3,), 0.0)},
}


class Stage(enum.Flag):
    """The stages of the flight-like loop a realism can switch on (``Realism.stages``, a
    combination of them: ``Stage.SENSORS | Stage.ACTUATORS``; ``Stage(0)``: none). A flag, not
    a string: a misspelt stage is an ``AttributeError``, not a test that is silently false.

    Attributes:
        SENSORS: F/T sensor noise and bias, encoder quantum and joint-rate noise.
        ACTUATORS: joint torque saturation (with the PID's anti-windup).
        MODEL: the controller's own model of the satellite (mass and inertia it believes).
        ESTIMATE: the error of the LAR pose the controller believes.
    """

    SENSORS = enum.auto()
    ACTUATORS = enum.auto()
    MODEL = enum.auto()
    ESTIMATE = enum.auto()


def _static(default):
    return dataclasses.field(default=default, metadata=dict(static=True))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Realism:
    """The realism settings of a rollout (module docstring); build it with
    [`make_realism()`][spacegrasp_jax.loop.realism.make_realism], [`ideal()`][spacegrasp_jax.loop.realism.ideal], [`flight()`][spacegrasp_jax.loop.realism.flight] or [`load_realism()`][spacegrasp_jax.loop.realism.load_realism].

    Attributes:
        force_noise_std, torque_noise_std: (3,) N, N m, white noise std per sensor axis.
        force_bias, torque_bias: (3,) N, N m, constant sensor bias, sensor axes.
        angle_resolution_rad: () rad, encoder quantum of q (0: exact).
        rate_noise_std_radps: () rad/s, white noise std on each joint rate.
        torque_limit_Nm: (N,) N m, saturation of each joint torque (``inf``: none); a file's
            single number is one for each of the paper's 7 joints, and a list has one a joint
            of the arm it runs with ([`check_joints()`][spacegrasp_jax.loop.realism.Realism.check_joints]).
        satellite_mass_factor, satellite_inertia_factor: () the controller's belief over
            the satellite's true mass and inertia.
        lar_position_error_m: (3,) m, error of the LAR origin the controller uses, LAR axes.
        lar_angle_error_rad: (3,) rad, rotation vector of the LAR attitude error, LAR axes.
        control_period: s, the controller's period (``None``: the scenario's ``dt``; static).
        delay_periods: whole control periods between measurement and actuation (static).
        servo_period: s, the joint PID's period, a whole fraction of the control period;
            the joint sensors are read at each servo tick (``None``: the control period;
            static).
        cutoff_hz: Hz, cutoff of the first-order low-pass on the measured wrench (0: none;
            static).
        saturation: ``"hard"`` (clip) or ``"smooth"`` (``limit tanh(u / limit)``; static).
        anti_windup: stop the PID's integrator while the torque saturates (static).
        stages: the stages that are on ([`Stage`][spacegrasp_jax.loop.realism.Stage] flags; static).
    """

    force_noise_std: jax.Array
    torque_noise_std: jax.Array
    force_bias: jax.Array
    torque_bias: jax.Array
    angle_resolution_rad: jax.Array
    rate_noise_std_radps: jax.Array
    torque_limit_Nm: jax.Array
    satellite_mass_factor: jax.Array
    satellite_inertia_factor: jax.Array
    lar_position_error_m: jax.Array
    lar_angle_error_rad: jax.Array
    control_period: float | None = _static(None)
    delay_periods: int = _static(0)
    servo_period: float | None = _static(None)
    cutoff_hz: float = _static(0.0)
    saturation: str = _static("hard")
    anti_windup: bool = _static(True)
    stages: Stage = _static(Stage(0))

    def check_joints(self, n_joints: int) -> None:
        """Raise ``RealismError`` if the actuators saturate and ``torque_limit_Nm`` has not one
        limit a joint of an arm of ``n_joints`` joints (``flight()`` without a robot: the paper's
        arm's seven motors)."""
        limits = np.shape(self.torque_limit_Nm)[-1]
        if Stage.ACTUATORS in self.stages and limits != n_joints:
            raise RealismError(
                f"actuators.torque_limit_Nm: {limits} limits for an arm of {n_joints} joints; write a "
                "realism file with one limit a joint (flight() without a robot has the paper's arm's motors; "
                "flight(robot), the robot's)"
            )

    def is_ideal(self, dt: float) -> bool:
        """Whether this is the paper's loop for a scenario of step ``dt`` (s)."""
        return not self.stages and self.delay_periods == 0 and self.cutoff_hz == 0.0 and self.steps_per_period(dt) == 1

    def steps_per_period(self, dt: float) -> int:
        """Plant steps per control period, for a scenario of step ``dt`` (s)."""
        if self.control_period is None:
            return 1
        ratio = self.control_period / dt
        if round(ratio) < 1 or abs(ratio - round(ratio)) > 1e-9 * ratio:
            raise RealismError(
                f"timing.control_period: {self.control_period} s is not a whole multiple of the scenario's dt = {dt} s"
            )
        return int(round(ratio))

    def steps_per_servo(self, dt: float) -> int:
        """Plant steps per servo period (the joint PID's), for a scenario of step ``dt`` (s);
        a whole fraction of ``steps_per_period()``."""
        per_period = self.steps_per_period(dt)
        if self.servo_period is None:
            return per_period
        ratio = self.servo_period / dt
        per_servo = int(round(ratio))
        if per_servo < 1 or abs(ratio - per_servo) > 1e-9 * ratio or per_period % per_servo:
            raise RealismError(
                f"timing.servo_period: {self.servo_period} s is not a whole multiple of the scenario's dt = {dt} s "
                f"dividing the control period ({per_period * dt:g} s)"
            )
        return per_servo

    def check_timing(self, dt: float, n_steps: int) -> None:
        """Raise ``RealismError`` unless the control and servo periods suit a scenario of
        step ``dt`` (s) and ``n_steps`` steps: each a whole number of steps, the servo's
        dividing the control period, and the control period dividing the duration."""
        self.steps_per_servo(dt)
        if n_steps % self.steps_per_period(dt):
            raise RealismError(
                f"timing.control_period: {self.control_period} s does not divide the scenario's duration "
                f"({n_steps} steps of {dt} s)"
            )

    def to_dict(self) -> dict:
        """The settings as the TOML tables (JSON-ready; ``None`` for an infinite limit)."""
        values = {
            "timing": {
                "control_period": self.control_period,
                "delay_periods": self.delay_periods,
                "servo_period": self.servo_period,
            },
            "force_torque_sensor": {
                "force_noise_std": self.force_noise_std,
                "torque_noise_std": self.torque_noise_std,
                "force_bias": self.force_bias,
                "torque_bias": self.torque_bias,
                "cutoff_hz": self.cutoff_hz,
            },
            "joint_sensors": {
                "angle_resolution_rad": self.angle_resolution_rad,
                "rate_noise_std_radps": self.rate_noise_std_radps,
            },
            "actuators": {
                "torque_limit_Nm": self.torque_limit_Nm,
                "saturation": self.saturation,
                "anti_windup": self.anti_windup,
            },
            "controller_model": {
                "satellite_mass_factor": self.satellite_mass_factor,
                "satellite_inertia_factor": self.satellite_inertia_factor,
            },
            "target_estimate": {
                "position_error_m": self.lar_position_error_m,
                "angle_error_rad": self.lar_angle_error_rad,
            },
        }
        plain = lambda v: (
            v
            if isinstance(v, (str, bool, int, type(None)))
            else [x if math.isfinite(x) else None for x in np.ravel(v).tolist()]
            if np.ndim(v)
            else float(v)
        )
        return {table: {key: plain(value) for key, value in keys.items()} for table, keys in values.items()}


def _number(where: str, value, shape, *, allow_null_as_inf: bool = False) -> np.ndarray:
    """``value`` as float64 of ``shape`` (a scalar broadcasts), booleans and strings refused."""
    items = value if isinstance(value, list) else [value]
    for item in items:
        if allow_null_as_inf and item is None:
            continue
        if isinstance(item, bool) or not isinstance(item, (int, float)):
            raise RealismError(f"{where}: expected numbers, got {value!r}")
        if isinstance(item, int) and not is_real(item):
            raise RealismError(f"{where}: {short(item)} is beyond float64's range")
    array = np.asarray(
        [math.inf if item is None else item for item in items]
        if isinstance(value, list)
        else (math.inf if value is None else value),
        dtype=np.float64,
    )
    if array.ndim == 0 and shape:
        array = np.full(shape, float(array))
    if array.shape != shape:
        raise RealismError(f"{where}: expected shape {shape}, got {array.shape}")
    if np.any(np.isnan(array)):
        raise RealismError(f"{where}: NaN is not a value")
    return array


def make_realism(document: dict | None = None, *, source: str = "realism") -> Realism:
    """A [`Realism`][spacegrasp_jax.loop.realism.Realism] from the TOML tables of the module docstring (every key optional,
    unknown keys rejected, every value checked; errors name ``source``, table and key)."""
    require_float64("a Realism")
    document = {} if document is None else document
    if not isinstance(document, dict):
        raise RealismError(f"{source}: expected tables of settings, got {type(document).__name__}")
    values = {}
    for table, content in document.items():
        if table not in SCHEMA:
            raise RealismError(f"{source}: unknown table [{table}]; expected {', '.join(SCHEMA)}")
        if not isinstance(content, dict):
            raise RealismError(f"{source}: [{table}] must be a table")
        for key, value in content.items():
            if key not in SCHEMA[table]:
                raise RealismError(f"{source}: unknown key {table}.{key}; expected {', '.join(SCHEMA[table])}")
            values[(table, key)] = value
    get = lambda table, key: values.get((table, key), SCHEMA[table][key][1])
    where = lambda table, key: f"{source}: {table}.{key}"
    arrays = {}
    for table, keys in SCHEMA.items():
        for key, (shape, _) in keys.items():
            if (table, key) in {
                ("timing", "control_period"),
                ("timing", "delay_periods"),
                ("timing", "servo_period"),
                ("force_torque_sensor", "cutoff_hz"),
                ("actuators", "saturation"),
                ("actuators", "anti_windup"),
            }:
                continue
            if key == "torque_limit_Nm" and isinstance(get(table, key), list):
                shape = (len(get(table, key)),)  # one a joint, for an arm of any number of joints
            arrays[(table, key)] = _number(
                where(table, key), get(table, key), shape, allow_null_as_inf=key == "torque_limit_Nm"
            )
    for key in ("force_noise_std", "torque_noise_std"):
        if np.any(arrays[("force_torque_sensor", key)] < 0) or not np.all(
            np.isfinite(arrays[("force_torque_sensor", key)])
        ):
            raise RealismError(f"{where('force_torque_sensor', key)}: must be finite and non-negative")
    for table, key in (
        ("force_torque_sensor", "force_bias"),
        ("force_torque_sensor", "torque_bias"),
        ("target_estimate", "position_error_m"),
        ("target_estimate", "angle_error_rad"),
    ):
        if not np.all(np.isfinite(arrays[(table, key)])):
            raise RealismError(f"{where(table, key)}: must be finite")
    for table, key in (("joint_sensors", "angle_resolution_rad"), ("joint_sensors", "rate_noise_std_radps")):
        value = float(arrays[(table, key)])
        if not (math.isfinite(value) and value >= 0.0):
            raise RealismError(f"{where(table, key)}: must be finite and non-negative, got {value}")
    limits = arrays[("actuators", "torque_limit_Nm")]
    if limits.size == 0:
        raise RealismError(f"{where('actuators', 'torque_limit_Nm')}: one limit a joint (or one for all), got none")
    if np.any(limits <= 0):
        raise RealismError(
            f"{where('actuators', 'torque_limit_Nm')}: limits must be positive (inf: none), got {limits.tolist()}"
        )
    for key in ("satellite_mass_factor", "satellite_inertia_factor"):
        value = float(arrays[("controller_model", key)])
        if not (math.isfinite(value) and 0.1 <= value <= 10.0):
            raise RealismError(f"{where('controller_model', key)}: must be between 0.1 and 10, got {value}")
    if float(np.linalg.norm(arrays[("target_estimate", "angle_error_rad")])) > 0.5:
        raise RealismError(
            f"{where('target_estimate', 'angle_error_rad')}: an estimate error above 0.5 rad is not an estimate"
        )

    # A period is a whole number of plant steps, so none is shorter than the shortest step a
    # scenario may have; that bound also keeps control_period / servo_period finite.
    shortest = DT_LIMITS_S[0]
    period = get("timing", "control_period")
    if period is not None and not (is_real(period) and shortest <= period <= 1.0):
        raise RealismError(
            f"{where('timing', 'control_period')}: must be a number of seconds in [{shortest:g}, 1], got {short(period)}"
        )
    servo = get("timing", "servo_period")
    if servo is not None and not (is_real(servo) and shortest <= servo <= (1.0 if period is None else period)):
        raise RealismError(
            f"{where('timing', 'servo_period')}: must be a number of seconds in [{shortest:g}, control_period], "
            f"got {short(servo)}"
        )
    if servo is not None and period is not None and abs(period / servo - round(period / servo)) > 1e-9 * period / servo:
        raise RealismError(
            f"{where('timing', 'servo_period')}: {servo} s does not divide timing.control_period = {period} s"
        )
    delay = get("timing", "delay_periods")
    if isinstance(delay, bool) or not isinstance(delay, int) or not 0 <= delay <= 100:
        raise RealismError(
            f"{where('timing', 'delay_periods')}: must be a whole number in [0, 100], got {short(delay)}"
        )
    cutoff = get("force_torque_sensor", "cutoff_hz")
    if not (is_real(cutoff) and cutoff >= 0):
        raise RealismError(
            f"{where('force_torque_sensor', 'cutoff_hz')}: must be a non-negative number of Hz, got {short(cutoff)}"
        )
    saturation = get("actuators", "saturation")
    if saturation not in ("hard", "smooth"):
        raise RealismError(f'{where("actuators", "saturation")}: expected "hard" or "smooth", got {saturation!r}')
    anti_windup = get("actuators", "anti_windup")
    if not isinstance(anti_windup, bool):
        raise RealismError(f"{where('actuators', 'anti_windup')}: expected true or false, got {anti_windup!r}")

    a = {key: arrays[(table, key)] for table, key in arrays}
    stages = Stage(0)
    if any(
        np.any(a[key] != 0)
        for key in (
            "force_noise_std",
            "torque_noise_std",
            "force_bias",
            "torque_bias",
            "angle_resolution_rad",
            "rate_noise_std_radps",
        )
    ):
        stages |= Stage.SENSORS
    if np.any(np.isfinite(a["torque_limit_Nm"])):
        stages |= Stage.ACTUATORS
    if a["satellite_mass_factor"] != 1.0 or a["satellite_inertia_factor"] != 1.0:
        stages |= Stage.MODEL
    if np.any(a["position_error_m"] != 0) or np.any(a["angle_error_rad"] != 0):
        stages |= Stage.ESTIMATE
    return Realism(
        force_noise_std=jnp.asarray(a["force_noise_std"]),
        torque_noise_std=jnp.asarray(a["torque_noise_std"]),
        force_bias=jnp.asarray(a["force_bias"]),
        torque_bias=jnp.asarray(a["torque_bias"]),
        angle_resolution_rad=jnp.asarray(a["angle_resolution_rad"]),
        rate_noise_std_radps=jnp.asarray(a["rate_noise_std_radps"]),
        torque_limit_Nm=jnp.asarray(a["torque_limit_Nm"]),
        satellite_mass_factor=jnp.asarray(a["satellite_mass_factor"]),
        satellite_inertia_factor=jnp.asarray(a["satellite_inertia_factor"]),
        lar_position_error_m=jnp.asarray(a["position_error_m"]),
        lar_angle_error_rad=jnp.asarray(a["angle_error_rad"]),
        control_period=None if period is None else float(period),
        delay_periods=delay,
        servo_period=None if servo is None else float(servo),
        cutoff_hz=float(cutoff),
        saturation=saturation,
        anti_windup=anti_windup,
        stages=stages,
    )


def ideal() -> Realism:
    """The paper's loop: every stage off (the default everywhere)."""
    return make_realism({}, source="ideal")


#: The ``flight`` preset's tables; each value's reasoning is in the documentation's
#: modelling notes ("The flight preset").
FLIGHT = {
    "timing": {"control_period": 0.01, "delay_periods": 1, "servo_period": 0.001},
    "force_torque_sensor": {
        "force_noise_std": [0.05, 0.05, 0.05],
        "torque_noise_std": [0.0025, 0.0025, 0.0025],
        "force_bias": [0.2, -0.15, 0.25],
        "torque_bias": [0.01, -0.008, 0.005],
        "cutoff_hz": 20.0,
    },
    "joint_sensors": {"angle_resolution_rad": 2 * math.pi / 2**16, "rate_noise_std_radps": 1e-3},
    "actuators": {"torque_limit_Nm": [10.0, 10.0, 10.0, 5.0, 5.0, 2.0, 2.0], "saturation": "hard", "anti_windup": True},
    "controller_model": {"satellite_mass_factor": 0.95, "satellite_inertia_factor": 1.1},
    "target_estimate": {"position_error_m": [0.002, -0.002, 0.001], "angle_error_rad": [0.005, -0.005, 0.003]},
}


def flight(robot=None) -> Realism:
    """Typical values for a 7-joint space arm with a 6-axis F/T sensor (``FLIGHT``); with a
    ``robot``, its actuators saturate at the robot's own motor limits
    (``Robot.joint_torque_limit``, one a joint: the preset for an arm of any number of
    joints). The paper's arm's limits are the preset's own."""
    if robot is None:
        return make_realism(FLIGHT, source="flight")
    limits = np.asarray(robot.joint_torque_limit, dtype=np.float64).tolist()
    actuators = FLIGHT["actuators"] | {"torque_limit_Nm": limits}
    return make_realism(FLIGHT | {"actuators": actuators}, source="flight")


PRESETS = {"ideal": ideal, "flight": flight}


def load_realism(name_or_path: str | Path, robot=None) -> Realism:
    """A preset (``"ideal"``, ``"flight"``: with a ``robot``, [`flight(robot)`][spacegrasp_jax.loop.realism.flight],
    its actuators the robot's motors) or a TOML file of the module docstring's tables.
    A JSON file with the same tables is read too, and so is a run's ``config.json`` or a
    campaign's ``campaign.json`` that holds them in its record (``"record"``'s
    ``"realism"``; an older version's: ``"realism"``; ``null`` torque limits meaning none)."""
    if str(name_or_path) == "flight":
        return flight(robot)
    if str(name_or_path) in PRESETS:
        return PRESETS[str(name_or_path)]()
    if str(name_or_path) == "":
        raise RealismError("expected ideal, flight or a TOML file, got an empty name")
    path = Path(name_or_path)
    try:
        document = read_document(path, RealismError)
    except RealismError as error:
        if path.exists():
            raise
        raise RealismError(f"{error}; expected ideal, flight or a TOML file") from None
    if isinstance(document.get("record"), dict) and path.suffix.lower() == ".json":
        document = document["record"]
    if isinstance(document.get("realism"), dict) and path.suffix.lower() == ".json":
        document = document["realism"]
    return make_realism(document, source=str(path))


__all__ = ["FLIGHT", "PRESETS", "Realism", "RealismError", "Stage", "flight", "ideal", "load_realism", "make_realism"]
