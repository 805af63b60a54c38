"""Linear stability of the closed loop where a capture settles: its modes, how they move
with each loop's gain, and the gain at which one starts to grow.

The closed loop advanced by one control period is a map ``x_{k+1} = Phi(x_k)`` of its whole
state: the plant, the law's and the PID's memory, the F/T sensor's low-pass and the delay
line (the loop's [`LoopState`][spacegrasp_jax.loop.simulate.LoopState]; the paper's loop is
the loop with every stage off and a period of one step, whose state is the plant's and the
controller's only). Its
Jacobian at an operating point, by ``jax.jacfwd``, is the loop's linearisation; each
eigenvalue ``lambda`` of it is a mode (stable inside the unit circle) and a continuous-time
pole ``s = log(lambda) / T``: a growth rate ``Re s`` (1/s), a natural frequency
``|s| / 2 pi`` (Hz) and a damping ratio ``-Re s / |s|``. How each eigenvalue moves with a
loop's gain factor ``c`` (``d lambda / d ln c``) comes from the Jacobian's derivative with
respect to ``ln c``, by forward-mode autodiff, and first-order perturbation theory.

**The loop linearised** is the small-signal loop ([`small_signal()`][spacegrasp_jax.analysis.stability.small_signal]): the sensors'
noise and the encoder's grid off (the grid's linearisation is the identity), the motors'
saturation off (not active at rest; with it, an unstable loop settles into a limit cycle),
biases, delays, filters and the controller's model as the realism has them.

**The operating point** is the state at the end of the nominal capture, with the desired
pose held at the EE's pose there ([`holding()`][spacegrasp_jax.analysis.stability.holding]): no law gain then changes what the law
commands at the point. With the target fixed in inertial space and the chaser
free-floating, no steady contact force can exist (it would accelerate the whole chaser): a
capture settles pressing with zero force, touching the sphere or just off it. The point is
not an exact fixed point (a redundant arm's joints keep drifting slowly): ``residual``
says how far it is.

**Coordinates.** Every field of the state is a coordinate except the satellite's attitude
quaternion, replaced by a rotation vector (3,) rad, inertial axes, about the operating
point's attitude (the quaternion's norm is not a state).

**Neutral modes.** Out of contact no external force acts on the chaser: its linear and
angular momentum are conserved and its centre of mass drifts with the linear momentum.
These 9 directions span a subspace that the map's transpose leaves invariant (eigenvalue 1,
with Jordan blocks that numerical eigenvalues split into ``1 +- sqrt(eps)``): they say
nothing of the loop's stability, and [`modes()`][spacegrasp_jax.analysis.stability.modes] removes them (the eigenvalues of the map
restricted to the perturbations that keep the momentum and the centre of mass).

**The linear gain margins** scale a loop's gain as ``spacegrasp_jax.analysis.margins`` does and
bisect the same way (``margins.gain_margin()``) on whether a mode grows faster than
``growth_limit_per_s`` (1/s; the redundant arm's self-motion drifts at about 0.1 1/s and is
not what a gain margin is about). [`HoldProber`][spacegrasp_jax.analysis.stability.HoldProber] is their time-domain check on the same
loop and point. A free-floating target is not supported here.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from spacegrasp_jax.analysis import frequency
from spacegrasp_jax.analysis.margins import (
    LOOPS,
    MarginSettings,
    control_period,
    gain_margin,
    loop_groups,
    require_joint_servo,
)
from spacegrasp_jax.core import spatial
from spacegrasp_jax.core.dynamics import system_com, system_momentum
from spacegrasp_jax.core.model import Robot
from spacegrasp_jax.envelope.scenario import Scenario
from spacegrasp_jax.jobs import compilation, experiment
from spacegrasp_jax.loop.control.gains import Gains
from spacegrasp_jax.loop.control.registry import as_controller
from spacegrasp_jax.loop.realism import Realism, Stage, ideal
from spacegrasp_jax.loop.simulate import FullLog, LoopState, RunSpec, loop_body, observe, plant_kinematics


def _key() -> jax.Array:
    """The noise key of the linearised loop: its noise is off, so no stage draws from it.
    (Made when needed: an array made at import would start JAX's backend.)"""
    return jax.random.PRNGKey(0)


class StabilityError(ValueError):
    """A loop this analysis does not cover; names the cause."""


def quiet(realism: Realism | None) -> Realism:
    """``realism`` (``None``: the paper's loop) with the sensors' noise and the encoder's grid
    off; biases, the delay and the filter stay."""
    realism = ideal() if realism is None else realism
    return dataclasses.replace(
        realism,
        force_noise_std=0.0 * realism.force_noise_std,
        torque_noise_std=0.0 * realism.torque_noise_std,
        rate_noise_std_radps=0.0 * realism.rate_noise_std_radps,
        angle_resolution_rad=0.0 * realism.angle_resolution_rad,
    )


def _with_attitude(state: LoopState, attitude) -> LoopState:
    """``state`` as its coordinates see it: the satellite's attitude replaced by ``attitude``
    and the fixed target left out (it never moves: a constant, not a coordinate)."""
    return dataclasses.replace(state, plant=dataclasses.replace(state.plant, quat_base=attitude, target=()))


@dataclasses.dataclass(frozen=True)
class Coordinates:
    """Local coordinates of the loop's state about ``reference`` (module docstring).

    Attributes:
        reference: the operating point, a [`LoopState`][spacegrasp_jax.loop.simulate.LoopState].
        names: one name per coordinate, e.g. ``plant.q[3]``, ``plant.attitude[0]``.
    """

    reference: LoopState
    names: tuple[str, ...]

    @classmethod
    def about(cls, reference: LoopState) -> Coordinates:
        if reference.plant.target.free:
            raise StabilityError("target: the linear analysis covers the paper's stationary target only")
        template = _with_attitude(reference, jnp.zeros(3))
        names = []
        for path, leaf in jax.tree_util.tree_flatten_with_path(template)[0]:
            name = jax.tree_util.keystr(path, simple=True, separator=".").replace("quat_base", "attitude")
            names += [f"{name}[{i}]" for i in range(int(np.size(leaf)))] if np.ndim(leaf) else [name]
        return cls(reference, tuple(names))

    @property
    def size(self) -> int:
        return len(self.names)

    def _flat_reference(self):
        return ravel_pytree(_with_attitude(self.reference, jnp.zeros(3)))

    def to_local(self, state: LoopState) -> jax.Array:
        """(n,) the coordinates of ``state``."""
        attitude = spatial.rotation_log(spatial.matmul(state.plant.R_base, self.reference.plant.R_base.T))
        return ravel_pytree(_with_attitude(state, attitude))[0] - self._flat_reference()[0]

    def from_local(self, delta: jax.Array) -> LoopState:
        """The state at coordinates ``delta`` (n,)."""
        flat, unravel = self._flat_reference()
        state = unravel(flat + delta)
        R_base = spatial.matmul(spatial.rotation_exp(state.plant.quat_base), self.reference.plant.R_base)
        plant = dataclasses.replace(
            state.plant, quat_base=spatial.rotation_to_quat(R_base), target=self.reference.plant.target
        )
        return dataclasses.replace(state, plant=plant)


def small_signal(realism: Realism | None) -> Realism:
    """[`quiet()`][spacegrasp_jax.analysis.stability.quiet] with the motors' saturation off: the loop
    the linearisation describes. (With saturation, an unstable loop settles into a limit
    cycle that stops growing, and a saturated motor cuts its joint out of the loop.)"""
    realism = quiet(realism)
    return dataclasses.replace(realism, stages=realism.stages & ~Stage.ACTUATORS)


def settled_state(spec: RunSpec, gains: Gains) -> tuple[LoopState, int]:
    """``(state, periods)``: the state of the loop of ``spec`` after its scenario's
    ``periods`` control periods (the nominal capture, noise off:
    [`quiet()`][spacegrasp_jax.analysis.stability.quiet])."""
    _check_spec(spec)
    scenario, realism = spec.scenario, quiet(spec.realism)
    spec = dataclasses.replace(spec, realism=realism, observer=FullLog())
    loop, _ = experiment.compiled_loop(spec, gains, _key())
    final, _ = loop(spec, gains, _key())
    return final, scenario.n_steps // realism.steps_per_period(scenario.dt)


def _check_spec(spec: RunSpec) -> None:
    """Refuse what the linear analysis does not cover, rather than ignore it."""
    if spec.scenario.free_target:
        raise StabilityError("target: the linear analysis covers the paper's stationary target only")
    if spec.model_robot is not None or spec.stages:
        raise StabilityError(
            "the linear analysis runs the nominal loop: the spec's model_robot must be None and it must add no stages"
        )


def holding(robot: Robot, scenario: Scenario, state: LoopState) -> Scenario:
    """``scenario`` with its desired EE pose held, from the start, at the EE's pose (LAR) in
    ``state``: the reference of the loop at rest where the capture settled, so that no
    gain of the law changes what the law commands there."""
    pose = _observed_pose(robot, scenario, state.plant)
    return dataclasses.replace(
        scenario, trajectory=dataclasses.replace(scenario.trajectory, start_pose=pose, end_pose=pose)
    )


# One program each instead of dozens of single operations (seconds of compiles on a first
# run); their numbers are the operations' to the last unit in the last place.
@jax.jit
def _observed_pose(robot: Robot, scenario: Scenario, plant):
    """The EE's pose in the LAR frame as the law observes it in ``plant``."""
    return observe(robot, scenario, plant, plant_kinematics(robot, scenario, plant), 0.0).pose


@jax.jit
def _contact_at(robot: Robot, scenario: Scenario, plant) -> dict:
    """The contact force's magnitude (N), the EE point's clearance outside the sphere (m) and
    the largest joint rate (rad/s) in ``plant``."""
    kinematics = plant_kinematics(robot, scenario, plant)
    p_ee = plant.p_base + kinematics.frames.p_ee
    from_centre = spatial.matvec(kinematics.R_lar.T, p_ee - kinematics.p_lar) - scenario.sphere_centre
    return {
        "contact_force_N": jnp.linalg.norm(kinematics.contact_force_lar),
        "clearance_m": jnp.linalg.norm(from_centre) - scenario.sphere_radius,
        "largest_rate_radps": jnp.max(jnp.abs(plant.qd)),
    }


def invariants(robot: Robot, coordinates: Coordinates) -> Callable[[jax.Array], jax.Array]:
    """``g(delta) -> (9,)``: the chaser's linear momentum (N s), angular momentum about the
    inertial origin (N m s) and centre of mass (m), inertial frame, at coordinates ``delta``."""

    def g(delta):
        plant = coordinates.from_local(delta).plant
        R_base = plant.R_base
        momentum = system_momentum(robot, plant.p_base, R_base, plant.q, plant.V_base, plant.qd)
        return jnp.concatenate([momentum, system_com(robot, plant.p_base, R_base, plant.q)])

    return g


def scaled_gains(gains: Gains, controller, log_factors) -> Gains:
    """``gains`` with each loop's gain (``margins.LOOPS``: the joint PID, the law) times
    ``exp(log_factors[i])``, traceable (``margins.scaled_loop()``'s scaling)."""
    changes = {}
    for log_factor, loop in zip(log_factors, LOOPS, strict=True):
        groups = loop_groups(controller, loop)
        changes |= {name: getattr(gains, name) * jnp.exp(power * log_factor) for name, power in groups.items()}
    return dataclasses.replace(gains, **changes)


def factors(loop: str, factor: float) -> np.ndarray:
    """The ``log_factors`` of [`scaled_gains()`][spacegrasp_jax.analysis.stability.scaled_gains] that scale ``loop``'s gain by ``factor``."""
    return np.array([math.log(factor) if name == loop else 0.0 for name in LOOPS])


@dataclasses.dataclass(frozen=True)
class Linearisation:
    """The period map's Jacobian at an operating point, its derivative with respect to each
    loop's gain, and what it is taken about.

    Attributes:
        jacobian: (n, n) ``d Phi / d x`` in the coordinates ``names``.
        sensitivity: (len(LOOPS), n, n) ``d jacobian / d ln c`` for each loop's gain factor
            ``c`` (``margins.LOOPS``: the joint PID, the law), by forward-mode autodiff.
        names: the n coordinates' names.
        period_s: the control period (s).
        residual: ``max |Phi(x0) - x0|`` over the coordinates (each in its own unit): zero
            at an exact fixed point.
        invariant_rows: (9, n) the gradients of the momentum and the centre of mass
            ([`invariants()`][spacegrasp_jax.analysis.stability.invariants]).
        contact_force_N: the contact force's magnitude at the operating point (N).
        clearance_m: the EE point's distance outside the contact sphere (m; negative inside).
        free: whether no external force acts near the operating point (the EE outside the
            sphere, by at least five widths ``1 / sharpness`` of the smooth contact law's
            boundary): the momentum and the centre of mass are then conserved.
        largest_rate_radps: the largest joint rate at the operating point (rad/s): how far
            from rest the arm is there.
    """

    jacobian: np.ndarray
    sensitivity: np.ndarray
    names: tuple[str, ...]
    period_s: float
    residual: float
    invariant_rows: np.ndarray
    contact_force_N: float
    clearance_m: float
    free: bool
    largest_rate_radps: float

    @property
    def finite(self) -> bool:
        """Whether the Jacobian is finite (the loop is defined around the point)."""
        return bool(np.all(np.isfinite(self.jacobian)))


class Linearizer:
    """Linearises the small-signal loop ([`small_signal()`][spacegrasp_jax.analysis.stability.small_signal]) of ``scenario`` over control
    period ``period_index`` at ``point`` under any gains, with one compiled program: its
    arguments are the gains, the point, the period and the scenario's numbers, so every
    point of the same loop (law, realism settings, state shapes) reuses it, and a later
    process loads it ([`compile_once()`][spacegrasp_jax.jobs.compilation.compile_once]).

    Attributes:
        names: the coordinates' names. period_s: the control period (s).
        time_s: the operating point's time (s).
        advance: ``advance(delta, gains) -> delta'``, the period map in the coordinates,
            (n,) -> (n,) (traceable).
    """

    def __init__(
        self,
        robot: Robot,
        scenario: Scenario,
        controller,
        realism: Realism | None,
        point: LoopState,
        period_index: int,
    ):
        realism = small_signal(realism)
        coordinates = Coordinates.about(point)
        self.names = coordinates.names
        self.period_s = control_period(scenario, realism)
        self.time_s = period_index * self.period_s
        self._boundary = 5.0 / float(scenario.contact_sharpness) if scenario.contact_law == "smooth" else 0.0
        k = jnp.asarray(float(period_index))
        zero = jnp.zeros(len(self.names))
        self.advance = _period_map(robot, scenario, controller, realism, coordinates, k)
        self._controller = controller
        self._arguments = (robot, scenario, realism, point, k)
        self._label = f"the linearisation of the {as_controller(controller).name} law's loop"
        # What depends on the point alone, once.
        self._invariant_rows = np.asarray(jax.jit(jax.jacfwd(invariants(robot, coordinates)))(zero))
        contact = {name: float(value) for name, value in _contact_at(robot, scenario, point.plant).items()}
        self._contact_force = contact["contact_force_N"]
        self._clearance = contact["clearance_m"]
        self._largest_rate = contact["largest_rate_radps"]

    def __call__(self, gains: Gains) -> Linearisation:
        arguments = (gains, *self._arguments)
        key = ("linearisation", self._controller, compilation.argument_signature(arguments))
        program, _ = compilation.compile_once(
            key, lambda: _LINEARISATION.lower(self._controller, *arguments), label=self._label
        )
        out = {name: np.asarray(value) for name, value in program(*arguments).items()}
        return Linearisation(
            jacobian=out["jacobian"],
            sensitivity=out["sensitivity"],
            names=self.names,
            period_s=self.period_s,
            residual=float(np.max(np.abs(out["moved"]))),
            invariant_rows=self._invariant_rows,
            contact_force_N=self._contact_force,
            clearance_m=self._clearance,
            free=self._clearance > self._boundary,
            largest_rate_radps=self._largest_rate,
        )


def _period_map(robot, scenario, controller, realism, coordinates: Coordinates, k) -> Callable:
    """``advance(delta, gains) -> delta'``: the loop's control period ``k`` in the local
    ``coordinates``, (n,) -> (n,) (traceable)."""

    def advance(delta, gains):
        period = loop_body(RunSpec(robot, scenario, controller, realism=realism), gains, _key()).period
        return coordinates.to_local(period(coordinates.from_local(delta), k)[0])

    return advance


def _linearisation(controller, gains, robot, scenario, realism, point, k) -> dict:
    """The Jacobian of the period map of [`Linearizer`][spacegrasp_jax.analysis.stability.Linearizer]'s loop at ``point``, its
    derivative with respect to each loop's log gain factor, and where the map moves the
    point (``Linearisation``'s fields), as one program of values only: every point, scenario
    and gains of the same shapes and settings share it."""
    coordinates = Coordinates.about(point)
    zero = jnp.zeros(coordinates.size)
    advance = _period_map(robot, scenario, controller, realism, coordinates, k)

    def jacobian_at(log_factors):
        return jax.jacfwd(advance)(zero, scaled_gains(gains, controller, log_factors))

    origin = jnp.zeros(len(LOOPS))
    # One forward pass per loop gives the Jacobian (the primal) and its derivative.
    jacobians, sensitivity = jax.vmap(lambda d: jax.jvp(jacobian_at, (origin,), (d,)))(jnp.eye(len(LOOPS)))
    return {"jacobian": jacobians[0], "sensitivity": sensitivity, "moved": advance(zero, gains)}


_LINEARISATION = jax.jit(_linearisation, static_argnums=0)


@dataclasses.dataclass(frozen=True)
class Modes:
    """The loop's modes: the period map's eigenvalues, the neutral ones removed.

    Attributes:
        eigenvalues: (m,) complex, by decreasing magnitude.
        sensitivity: (len(LOOPS), m) complex, ``d lambda / d ln c`` of each eigenvalue for
            each loop's gain factor ``c`` (first-order perturbation with the left and right
            eigenvectors).
        period_s: the control period T (s).
        neutral_removed: how many neutral modes were removed (9 out of contact, else 0).
        invariance_residual: how far the momentum and centre-of-mass rows are from an
            invariant subspace of the map (relative; 0 when conserved exactly).
        shapes: (n, m) complex, each mode's right eigenvector in the n coordinates.
    """

    eigenvalues: np.ndarray
    sensitivity: np.ndarray
    shapes: np.ndarray
    period_s: float
    neutral_removed: int
    invariance_residual: float

    @property
    def spectral_radius(self) -> float:
        return float(np.max(np.abs(self.eigenvalues)))

    @property
    def poles(self) -> np.ndarray:
        """(m,) complex 1/s, ``s = log(lambda) / T`` (``-inf`` for ``lambda = 0``)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.log(self.eigenvalues.astype(complex)) / self.period_s

    @property
    def growth_rate_per_s(self) -> np.ndarray:
        """(m,) 1/s, ``Re s``: positive for a mode that grows."""
        return self.poles.real

    @property
    def frequency_hz(self) -> np.ndarray:
        """(m,) Hz, the undamped natural frequency ``|s| / 2 pi``."""
        return np.abs(self.poles) / (2.0 * math.pi)

    @property
    def damping_ratio(self) -> np.ndarray:
        """(m,) ``-Re s / |s|`` (1 for a real decaying mode, negative when it grows)."""
        poles = self.poles
        with np.errstate(invalid="ignore"):
            return np.where(np.isfinite(poles.real), -poles.real / np.abs(poles), 1.0)

    @property
    def fastest_growth_per_s(self) -> float:
        """The largest ``Re s`` (1/s): the loop is unstable where it is above 0."""
        return float(np.max(self.growth_rate_per_s))


def kept_subspace(linearisation: Linearisation) -> np.ndarray:
    """(n, k) an orthonormal basis of the perturbations that keep the momentum and the centre
    of mass where no external force acts (``linearisation.free``: k = n - 9), else of all
    (k = n): the loop's map restricted to it has no neutral mode (module docstring)."""
    import scipy.linalg  # imported on first use: a fifth of a second at every command's start

    n = linearisation.jacobian.shape[0]
    return scipy.linalg.null_space(linearisation.invariant_rows) if linearisation.free else np.eye(n)


def broken_loops(linearisation: Linearisation, growth_limit_per_s: float) -> dict:
    """Each loop (``margins.LOOPS``) of the linearised loop broken at its gain, on the
    perturbations that keep the momentum and the centre of mass
    ([`kept_subspace()`][spacegrasp_jax.analysis.stability.kept_subspace]), its response to be
    taken on ``|z| = e^{sigma T}``, ``sigma = growth_limit_per_s``
    ([`spacegrasp_jax.analysis.frequency`][spacegrasp_jax.analysis.frequency])."""
    basis = kept_subspace(linearisation)
    restricted = basis.T @ linearisation.jacobian @ basis
    radius = math.exp(growth_limit_per_s * linearisation.period_s)
    return {
        loop: frequency.break_loop(
            restricted, basis.T @ linearisation.sensitivity[i] @ basis, loop, linearisation.period_s, radius
        )
        for i, loop in enumerate(LOOPS)
    }


def modes(linearisation: Linearisation) -> Modes:
    """The [`Modes`][spacegrasp_jax.analysis.stability.Modes] of a linearisation, with the 9 neutral
    modes of the momentum and the centre of mass removed where no external force acts
    (``linearisation.free``; module docstring)."""
    A, W = linearisation.jacobian, linearisation.invariant_rows
    WA = W @ A
    # Conserved quantities: W A = M W for some (9, 9) M (the rows span an invariant
    # subspace of A^T); the residual says how exactly the map conserves them.
    M = WA @ np.linalg.pinv(W)
    residual = float(np.linalg.norm(WA - M @ W) / max(np.linalg.norm(WA), 1e-300))
    # The perturbations that keep the momentum and the centre of mass are then an
    # invariant subspace of A; its eigenvalues are A's less the 9 neutral ones.
    import scipy.linalg  # imported on first use: a fifth of a second at every command's start

    basis = kept_subspace(linearisation)
    restricted = basis.T @ A @ basis
    eigenvalues, left, right = scipy.linalg.eig(restricted, left=True, right=True)
    order = np.argsort(-np.abs(eigenvalues), kind="stable")
    eigenvalues, left, right = eigenvalues[order], left[:, order], right[:, order]
    projected = np.einsum("ij,ljk,kn->lin", basis.T, linearisation.sensitivity, basis)
    numerator = np.einsum("im,lij,jm->lm", left.conj(), projected, right)
    sensitivity = numerator / np.einsum("im,im->m", left.conj(), right)
    return Modes(eigenvalues, sensitivity, basis @ right, linearisation.period_s, A.shape[0] - basis.shape[1], residual)


@dataclasses.dataclass
class LinearProber:
    """The linear counterpart of ``margins.Prober``: a probe holds when the small-signal
    loop at the scaled gains reaches its operating point without diverging and no mode
    there grows faster than ``growth_limit_per_s``.

    Attributes:
        probes: one dict a probe: ``loop``, ``value`` (the factor), ``holds``, ``diverged``,
            ``spectral_radius``, ``fastest_growth_per_s``, ``eigenvalues`` (``[re, im]``).
    """

    linearizer: Linearizer
    gains: Gains
    controller: str
    settings: MarginSettings = MarginSettings()
    growth_limit_per_s: float = 1.0
    probes: list = dataclasses.field(default_factory=list)

    def linearisation_at(self, loop: str, factor: float) -> Linearisation:
        """The linearisation with ``loop``'s gain times ``factor``."""
        return self.linearizer(scaled_gains(self.gains, self.controller, factors(loop, factor)))

    def holds(self, loop: str, factor: float) -> bool:
        linearisation = self.linearisation_at(loop, factor)
        probe = {"loop": loop, "value": float(factor), "holds": False, "diverged": not linearisation.finite}
        if linearisation.finite:
            found = modes(linearisation)
            probe |= {
                "holds": found.fastest_growth_per_s < self.growth_limit_per_s,
                "spectral_radius": found.spectral_radius,
                "fastest_growth_per_s": found.fastest_growth_per_s,
                "eigenvalues": eigenvalue_pairs(found.eigenvalues),
            }
        self.probes.append(probe)
        return probe["holds"]


def eigenvalue_pairs(eigenvalues: np.ndarray) -> list[list[float]]:
    """``[[re, im], ...]`` of complex eigenvalues, for JSON."""
    return [[float(z.real), float(z.imag)] for z in eigenvalues]


@dataclasses.dataclass
class HoldProber:
    """The time-domain check of ``LinearProber``: the same small-signal loop from the same
    operating point, run instead of linearised.

    A probe runs the loop of ``scenario`` at the scaled gains from ``point`` (control
    period ``period_index``) twice for ``hold_s`` seconds, once with the joint rates nudged
    by ``kick_radps`` times a fixed direction drawn once (every joint a different amount).
    The nudge's effect, the largest difference of the two runs' joint rates over the last
    tenth of each half of the hold, grows at ``log(late / middle) / (hold_s / 2)`` 1/s: the
    probe holds while that is below ``growth_limit_per_s`` (the linear prober's criterion)
    and the runs stay finite.

    Attributes:
        probes: one dict a probe: ``loop``, ``value``, ``holds``, ``growth_rate_per_s``.
    """

    robot: Robot
    scenario: Scenario
    controller: str
    realism: Realism | None
    point: LoopState
    period_index: int
    gains: Gains
    settings: MarginSettings = MarginSettings()
    growth_limit_per_s: float = 1.0
    hold_s: float = 4.0
    kick_radps: float = 1e-6
    probes: list = dataclasses.field(default_factory=list)

    def __post_init__(self):
        realism = small_signal(self.realism)
        half = max(10, round(0.5 * self.hold_s / control_period(self.scenario, realism)))
        point = self.point
        nudge = self.kick_radps * np.random.default_rng(0).uniform(0.5, 1.0, point.plant.qd.shape)
        kicked = dataclasses.replace(point, plant=dataclasses.replace(point.plant, qd=point.plant.qd + nudge))
        starts = jax.tree.map(lambda *pair: jnp.stack(pair), point, kicked)
        ks = self.period_index + jnp.arange(2 * half, dtype=jnp.float64)
        window = half // 10

        def growth_rate(gains):
            one_period = loop_body(
                RunSpec(self.robot, self.scenario, self.controller, realism=realism), gains, _key()
            ).period
            _, rows = jax.vmap(lambda start: jax.lax.scan(one_period, start, ks))(starts)
            difference = jnp.abs(rows.qd[1] - rows.qd[0])  # (periods, steps a period, 7)
            middle = jnp.max(difference[half - window : half])
            late = jnp.max(difference[2 * half - window :])
            rate = jnp.log(late / middle) / (half * control_period(self.scenario, realism))
            return jnp.where(jnp.all(jnp.isfinite(rows.qd)) & (middle > 0.0), rate, jnp.inf)

        self._program = jax.jit(growth_rate)

    def holds(self, loop: str, factor: float) -> bool:
        rate = float(self._program(scaled_gains(self.gains, self.controller, factors(loop, factor))))
        held = rate < self.growth_limit_per_s
        self.probes.append({"loop": loop, "value": float(factor), "holds": held, "growth_rate_per_s": rate})
        return held


def mode_table(found: Modes, names: tuple[str, ...], largest: int = 3) -> list[dict]:
    """One JSON-ready dict a mode: its eigenvalue, magnitude, growth rate (1/s), natural
    frequency (Hz), damping ratio, the sensitivity of its eigenvalue and of its growth rate
    to each loop's gain (``d / d ln c``), and the ``largest`` coordinates of its shape."""
    rows = []
    for i, value in enumerate(found.eigenvalues):
        shape = np.abs(found.shapes[:, i])
        growth_sensitivity = np.real(found.sensitivity[:, i] / value) / found.period_s if value != 0 else [0.0] * 2
        rows.append(
            {
                "eigenvalue": [float(value.real), float(value.imag)],
                "magnitude": float(abs(value)),
                "growth_rate_per_s": _finite_or_none(found.growth_rate_per_s[i]),
                "frequency_hz": _finite_or_none(found.frequency_hz[i]),
                "damping_ratio": _finite_or_none(found.damping_ratio[i]),
                "sensitivity": {
                    loop: [float(found.sensitivity[j, i].real), float(found.sensitivity[j, i].imag)]
                    for j, loop in enumerate(LOOPS)
                },
                "growth_sensitivity_per_s": {loop: float(growth_sensitivity[j]) for j, loop in enumerate(LOOPS)},
                "largest_coordinates": [names[j] for j in np.argsort(-shape, kind="stable")[:largest]],
            }
        )
    return rows


def _finite_or_none(x) -> float | None:
    return float(x) if np.isfinite(x) else None


def linear_analysis(
    spec: RunSpec,
    gains: Gains,
    settings: MarginSettings = MarginSettings(),
    growth_limit_per_s: float = 1.0,
) -> dict:
    """The loop's modes where the nominal capture settles, and the linear gain margins: the
    factors on each loop's gain (``margins.gain_margin()``'s search, both directions) at
    which a mode of the loop there starts to grow faster than ``growth_limit_per_s`` (1/s).
    The operating point is the end of the nominal capture of ``spec`` (its robot, scenario,
    controller and realism; the controller a law's name or a law object with its settings,
    ``control.Admittance(pinv_damping=0.01)``), its pose held
    ([`holding()`][spacegrasp_jax.analysis.stability.holding]).

    Returns:
        A JSON-ready dict: ``operating_point`` (``time_s``, ``residual``,
        ``contact_force_N``, ``clearance_m``, ``largest_rate_radps``, ``coordinates``,
        ``neutral_modes_removed``, ``invariance_residual``), ``growth_limit_per_s``, ``spectral_radius`` and
        ``fastest_growth_per_s`` of the nominal loop, ``modes`` (``mode_table()``),
        ``gain_margins`` (loop -> direction -> ``gain_margin()``'s result),
        ``eigenvalues_at_margins`` (loop -> direction -> the eigenvalues at the first
        failing factor, or ``None``), ``verdict`` ([`verdict()`][spacegrasp_jax.analysis.stability.verdict]),
        ``frequency_response`` (loop -> ``frequency.loop_margins()`` of the loop broken at
        its gain: the gain and phase margins from its frequency response, with its
        ``affine_residual``; where that is above ``frequency.AFFINE_TOLERANCE`` the loop
        cannot be broken at one gain and only the residual is given) and ``bode`` (loop ->
        ``frequency.bode()``'s arrays, for the loops broken; not JSON: a caller writes them apart),
        ``probes``, ``compile_s``, ``search_s``.
    """
    if not (math.isfinite(growth_limit_per_s) and growth_limit_per_s >= 0.0):
        raise StabilityError(f"growth_limit_per_s: must be finite and at least 0, got {growth_limit_per_s!r}")
    robot, scenario, controller, realism = spec.robot, spec.scenario, spec.controller, spec.realism
    require_joint_servo(controller)
    started = time.perf_counter()
    point, periods = settled_state(spec, gains)
    period_s = control_period(scenario, realism)
    linearizer = Linearizer(robot, holding(robot, scenario, point), controller, realism, point, periods)
    linearisation = linearizer(gains)
    compile_s = time.perf_counter() - started
    if not linearisation.finite:
        raise StabilityError("the loop diverged after the nominal capture: there is no operating point to linearise at")
    nominal = modes(linearisation)
    prober = LinearProber(linearizer, gains, controller, settings, growth_limit_per_s)
    gain_margins = {
        name: {direction: gain_margin(prober, name, direction) for direction in ("increase", "decrease")}
        for name in LOOPS
    }
    at_margins = {
        name: {
            direction: next(
                (p.get("eigenvalues") for p in prober.probes if p["loop"] == name and p["value"] == result["fails"]),
                None,
            )
            for direction, result in directions.items()
        }
        for name, directions in gain_margins.items()
    }
    table = mode_table(nominal, linearisation.names)
    broken = broken_loops(linearisation, growth_limit_per_s)
    basis = kept_subspace(linearisation)
    responses, bodes = {}, {}
    for name, loop in broken.items():
        doubled = linearizer(scaled_gains(gains, controller, factors(name, 2.0))).jacobian
        residual = frequency.affine_residual(loop, basis.T @ doubled @ basis, 2.0)
        if residual <= frequency.AFFINE_TOLERANCE:
            responses[name] = frequency.loop_margins(loop) | {"affine_residual": residual}
            bodes[name] = frequency.bode(loop)
        else:
            responses[name] = {"loop": name, "channels": loop.channels, "affine_residual": residual}
    return {
        "operating_point": {
            "time_s": linearizer.time_s,
            "residual": linearisation.residual,
            "contact_force_N": linearisation.contact_force_N,
            "clearance_m": linearisation.clearance_m,
            "largest_rate_radps": linearisation.largest_rate_radps,
            "coordinates": list(linearisation.names),
            "neutral_modes_removed": nominal.neutral_removed,
            "invariance_residual": nominal.invariance_residual,
        },
        "control_period_s": period_s,
        "growth_limit_per_s": growth_limit_per_s,
        "spectral_radius": nominal.spectral_radius,
        "fastest_growth_per_s": nominal.fastest_growth_per_s,
        "modes": table,
        "verdict": verdict(nominal.fastest_growth_per_s, growth_limit_per_s, table[0]),
        "gain_margins": gain_margins,
        "eigenvalues_at_margins": at_margins,
        "frequency_response": responses,
        "bode": bodes,
        "probes": prober.probes,
        "compile_s": compile_s,
        "search_s": time.perf_counter() - started - compile_s,
    }


def verdict(fastest_growth_per_s: float, growth_limit_per_s: float, slowest: dict) -> dict:
    """The linearised loop's verdict: ``"stable"`` (every mode decays), ``"stable within the
    growth limit"`` (the fastest mode grows, but more slowly than ``growth_limit_per_s``: a
    drift such as the redundant arm's self-motion, doubling in ``doubling_s``, not a loop
    going unstable) or ``"unstable"``; with ``words``, one line for the console."""
    growth = fastest_growth_per_s
    mostly = ", ".join(slowest["largest_coordinates"])
    if growth < 0.0:
        kind, words = "stable", f"stable: every mode decays (the slowest at {growth:+.3g} 1/s, mostly {mostly})"
    elif growth <= growth_limit_per_s:
        doubling = math.log(2.0) / growth if growth > 0.0 else math.inf
        kind = "stable within the growth limit"
        words = (
            f"stable within the growth limit: no mode grows faster than {growth_limit_per_s:g}/s; the slowest, "
            f"mostly {mostly}, grows at {growth:+.3g} 1/s (doubling in {doubling:.3g} s), a drift rather than "
            "a loop going unstable"
        )
    else:
        kind = "unstable"
        words = f"unstable: a mode grows at {growth:+.3g} 1/s, above the growth limit {growth_limit_per_s:g}/s (mostly {mostly})"
    return {"kind": kind, "words": words, "fastest_growth_per_s": growth}


def linear_lines(result: dict) -> list[str]:
    """The linear analysis in words, with units."""
    point = result["operating_point"]
    lines = [
        f"linearised at t = {point['time_s']:g} s (contact force {point['contact_force_N']:.3g} N, "
        f"{len(point['coordinates'])} states, {point['neutral_modes_removed']} neutral modes removed): "
        f"spectral radius {result['spectral_radius']:.6f}, fastest growth {result['fastest_growth_per_s']:+.3g} 1/s"
    ]
    slowest = result["modes"][0]
    lines.append(
        f"least stable mode: |lambda| = {slowest['magnitude']:.6f}, {slowest['frequency_hz']:.3g} Hz, "
        f"damping {slowest['damping_ratio']:.3g}, mostly {', '.join(slowest['largest_coordinates'])}"
    )
    for name, title in (("pid", "joint PID gain"), ("law", "law gain")):
        parts = []
        for direction in ("increase", "decrease"):
            entry = result["gain_margins"][name][direction]
            parts.append(
                f"{direction} to x{entry['holds']:.3g} (the search's limit)"
                if entry["fails"] is None
                else f"{direction} x{entry['holds']:.3g} ({entry['margin_db']:+.1f} dB)"
            )
        lines.append(
            f"linear {title} margin (a mode growing faster than {result['growth_limit_per_s']:g}/s): {', '.join(parts)}"
        )
    if "verdict" in result:
        lines.insert(1, f"linearised loop: {result['verdict']['words']}")
    for name, title in (("pid", "joint PID"), ("law", "law")):
        response = result.get("frequency_response", {}).get(name)
        if response is None:
            continue
        if "gain_margins" not in response:
            lines.append(
                f"frequency response broken at the {title}: not available: its gain does not enter the control "
                f"period's map linearly (||A(2) - A0 - 2 M|| / ||M|| = {response['affine_residual']:.2g}; "
                "a servo that ticks several times a period, or a loop the gain barely reaches); "
                "the eigenvalue margins above are the reference"
            )
            continue
        parts = []
        for direction in ("increase", "decrease"):
            entry = response["gain_margins"][direction]
            parts.append(
                f"{direction}: none"
                if entry is None
                else f"{direction} x{entry['factor']:.3g} ({entry['margin_db']:+.1f} dB at {entry['frequency_hz']:.3g} Hz)"
            )
        phase = response["phase_margin"]
        parts.append(
            "phase margin: no 0 dB crossing"
            if phase is None
            else f"phase margin {phase['phase_margin_deg']:.1f} deg at {phase['frequency_hz']:.3g} Hz"
        )
        lines.append(f"frequency response broken at the {title} ({response['channels']} channels): {', '.join(parts)}")
    lines.append(
        f"linear analysis: {len(result['probes'])} linearisations in {result['search_s']:.1f} s, after {result['compile_s']:.1f} s compiling"
    )
    return lines


__all__ = [
    "Coordinates",
    "HoldProber",
    "LinearProber",
    "Linearisation",
    "Linearizer",
    "Modes",
    "StabilityError",
    "factors",
    "holding",
    "invariants",
    "linear_analysis",
    "linear_lines",
    "kept_subspace",
    "broken_loops",
    "verdict",
    "mode_table",
    "modes",
    "quiet",
    "scaled_gains",
    "settled_state",
    "small_signal",
]
