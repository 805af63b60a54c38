"""The loop's frequency response, one loop broken at a time: Bode and Nichols data, gain and
phase margins, at the operating point of the linear analysis
([`spacegrasp_jax.analysis.stability`][spacegrasp_jax.analysis.stability]).

**Breaking a loop.** A loop's gain factor ``c`` (the joint PID's ``kp, ki, kd`` times ``c``;
the law's loop gain times ``c``, ``margins.scaled_loop()``) enters the period map's
Jacobian as ``A(c) = A0 + c M``, where ``M = d A / d ln c`` at ``c = 1`` (the linear
analysis' sensitivity) and ``A0 = A - M`` is the loop with that gain at zero. ``M = B C``
factored by its singular values (rank ``m``: the loop's channels, 7 joint torques for the
paper's PID) gives the loop broken there: the signal ``y = C x`` fed back through
``x' = A0 x + B u``, ``u = c y``. Its transfer matrix is ``G(z) = C (z I - A0)^-1 B``, and
the closed loop at gain ``c`` has a pole at ``z`` exactly where ``det(I - c G(z)) = 0``.
This is exact where the gain enters the period map affinely: a PID or law that acts once a
control period (the paper's loop; any realism whose servos run at the control period) and
whose output at the operating point does not change the plant's Jacobian. Where the
servos tick several times a period the gain enters as a polynomial in ``c`` and the break
is first order (exact at ``c = 1``, wrong away from it): the loop is then not broken.
[`affine_residual()`][spacegrasp_jax.analysis.frequency.affine_residual] measures which case
holds by linearising the loop again at ``c = 2``; the eigenvalue margins, which linearise it
at each factor, are the reference either way.

**The response.** ``G`` is evaluated on the circle ``z = r e^{j w T}``, ``r = e^{sigma T}``,
``sigma`` the linear analysis' growth limit (1/s): the response of the loop shifted by
``sigma``, so that a closed-loop pole crossing the circle is a mode growing at ``sigma``, the
eigenvalue analysis' criterion (a mode that grows more slowly, as the redundant arm's
self-motion does, counts as stable). With ``sigma`` of 1/s against loop frequencies of Hz
this is the classical response but at the lowest frequencies. A multi-channel loop has
``m`` characteristic loci, the eigenvalues ``g_i`` of ``G`` at each frequency (MacFarlane
and Postlethwaite's generalised Nyquist criterion); each is shown as the open-loop
``L_i = -g_i`` of a negative-feedback loop, whose critical point is ``-1`` (0 dB, -180 deg).

**Margins.** The closed loop at gain ``c`` has a pole on the circle where a locus passes
through ``1 / c`` on the positive real axis of ``g`` (``L`` at -180 deg): each such crossing,
and each locus' ends (``w = 0`` and the Nyquist frequency, where ``G`` is real), gives a
critical factor ``c* = 1 / g``. The gain margins are the nearest to 1 on each side
(``increase``: the least ``c* > 1``; ``decrease``: the largest ``c* < 1``), the same factors
the eigenvalue analysis bisects for. The phase margin of a locus is its angle from ``-1``
where ``|L_i| = 1``: ``|arg g_i|``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

#: Singular values of ``M`` below this fraction of its largest are not channels of the loop.
RANK_TOLERANCE = 1e-9

#: The largest ``affine_residual()`` at which a loop counts as broken exactly at its gain
#: (measured: 1e-8 for the paper's joint PID, 1e-12 for the law under the flight-like loop;
#: 0.36 for the flight-like loop's PID, whose servo ticks ten times a control period).
AFFINE_TOLERANCE = 1e-4

#: Critical factors beyond this ratio from 1 (either way) are not margins: a loop whose gain
#: must change a millionfold to go unstable has none worth stating (and a locus that small
#: is rounding).
FACTOR_LIMIT = 1e6

#: Frequencies of the response, log-spaced from this fraction of the Nyquist frequency.
LOWEST_FRACTION = 1e-5


class FrequencyError(ValueError):
    """A loop that cannot be broken or a response that cannot be evaluated."""


@dataclasses.dataclass(frozen=True)
class BrokenLoop:
    """A loop of the period map broken at its gain: ``x' = A0 x + B u``, ``y = C x``,
    closed by ``u = c y`` (``c`` the loop's gain factor; ``c = 1`` the nominal loop).

    Attributes:
        loop: which loop (``margins.LOOPS``: ``"pid"``, ``"law"``), or a name of the caller's.
        A0: (n, n) the period map's Jacobian with the loop's gain at zero.
        B: (n, m) where the loop's signal enters. C: (m, n) what the loop's signal reads.
        period_s: the period T of the map (s).
        radius: the circle ``|z| = r`` the response is evaluated on (``e^{sigma T}``).
    """

    loop: str
    A0: np.ndarray
    B: np.ndarray
    C: np.ndarray
    period_s: float
    radius: float = 1.0

    @property
    def channels(self) -> int:
        return self.B.shape[1]

    def closed(self, factor: float) -> np.ndarray:
        """(n, n) the closed loop's map at gain ``factor``: ``A0 + factor B C``."""
        return self.A0 + factor * self.B @ self.C

    def transfer(self, frequency_hz: float) -> np.ndarray:
        """(m, m) complex ``G(z) = C (z I - A0)^-1 B`` at ``z = r e^{j 2 pi f T}``."""
        z = self.radius * np.exp(2j * math.pi * frequency_hz * self.period_s)
        n = self.A0.shape[0]
        return self.C @ np.linalg.solve(z * np.eye(n) - self.A0, self.B.astype(complex))


def break_loop(jacobian: np.ndarray, sensitivity: np.ndarray, loop: str, period_s: float, radius: float = 1.0):
    """The loop of gain sensitivity ``sensitivity`` (``d jacobian / d ln c`` at ``c = 1``)
    broken at its gain ([`BrokenLoop`][spacegrasp_jax.analysis.frequency.BrokenLoop]; module docstring)."""
    jacobian, sensitivity = np.asarray(jacobian, dtype=float), np.asarray(sensitivity, dtype=float)
    if jacobian.shape != sensitivity.shape or jacobian.ndim != 2 or jacobian.shape[0] != jacobian.shape[1]:
        raise FrequencyError(f"need two (n, n) matrices, got {jacobian.shape} and {sensitivity.shape}")
    U, s, Vt = np.linalg.svd(sensitivity)
    if s.size == 0 or s[0] == 0.0:
        raise FrequencyError(f"the {loop} loop's gain does not change the loop: there is no loop to break")
    rank = int(np.sum(s > RANK_TOLERANCE * s[0]))
    return BrokenLoop(loop, jacobian - sensitivity, U[:, :rank] * s[:rank], Vt[:rank], period_s, radius)


def affine_residual(broken: BrokenLoop, jacobian_at: np.ndarray, factor: float) -> float:
    """How far the loop's Jacobian at gain ``factor`` (``jacobian_at``, linearised again
    there) is from the broken loop closed at that factor, relative to ``M = B C``:
    ``||A(c) - A0 - c M|| / ||M||``; 0 where the gain enters the period map affinely
    (module docstring)."""
    M = broken.B @ broken.C
    return float(np.linalg.norm(jacobian_at - broken.closed(factor)) / np.linalg.norm(M))


def frequencies(period_s: float, count: int = 1500) -> np.ndarray:
    """(count,) Hz: log-spaced from ``LOWEST_FRACTION`` of the Nyquist frequency up to it."""
    nyquist = 0.5 / period_s
    return np.geomspace(LOWEST_FRACTION * nyquist, nyquist, count)


def loci(broken: BrokenLoop, frequencies_hz: np.ndarray) -> np.ndarray:
    """(F, m) complex: the characteristic loci ``g_i`` (eigenvalues of ``G``) at each
    frequency, each column one locus followed from one frequency to the next (each
    frequency's eigenvalues matched to the previous' by the least total distance)."""
    from scipy.optimize import linear_sum_assignment

    out = np.empty((len(frequencies_hz), broken.channels), dtype=complex)
    for i, f in enumerate(frequencies_hz):
        values = np.linalg.eigvals(broken.transfer(f))
        if i:
            rows, cols = linear_sum_assignment(np.abs(out[i - 1][:, None] - values[None, :]))
            values = values[cols[np.argsort(rows)]]
        out[i] = values
    return out


def _bisect_locus(broken: BrokenLoop, f0: float, f1: float, g0: complex, g1: complex, side, steps: int = 40):
    """The locus between two frequencies where ``side(g)`` (a bool) changes, by bisection on
    a log scale, following the eigenvalue of ``G`` nearest the locus: the last bracket
    ``(f0, g0, f1, g1)``."""
    start = side(g0)
    for _ in range(steps):
        middle = math.sqrt(f0 * f1)
        values = np.linalg.eigvals(broken.transfer(middle))
        g = values[np.argmin(np.abs(values - 0.5 * (g0 + g1)))]
        if side(g) == start:
            f0, g0 = middle, g
        else:
            f1, g1 = middle, g
    return f0, g0, f1, g1


def _refined_crossing(broken: BrokenLoop, f0: float, f1: float, g0: complex, g1: complex):
    """The locus' crossing of the real axis between two frequencies (``Im g`` changes sign):
    ``(frequency, g)``, ``g`` interpolated onto the axis."""
    f0, g0, f1, g1 = _bisect_locus(broken, f0, f1, g0, g1, lambda g: g.imag > 0.0)
    share = g0.imag / (g0.imag - g1.imag) if g0.imag != g1.imag else 0.5
    return math.sqrt(f0 * f1), complex(g0.real + share * (g1.real - g0.real), 0.0)


def _unity_crossing(broken: BrokenLoop, f0: float, f1: float, g0: complex, g1: complex):
    """Where the locus' magnitude passes 1 between two frequencies: ``(frequency, g)``."""
    f0, g0, f1, g1 = _bisect_locus(broken, f0, f1, g0, g1, lambda g: abs(g) > 1.0)
    return math.sqrt(f0 * f1), 0.5 * (g0 + g1)


def critical_factors(broken: BrokenLoop, frequencies_hz: np.ndarray, tracked: np.ndarray | None = None) -> list[dict]:
    """Every gain factor ``c* > 0`` at which a locus passes through ``1 / c*`` (module
    docstring): ``{"factor", "frequency_hz", "locus"}`` (``locus`` ``None`` at the ends,
    0 Hz and the Nyquist frequency, where each real eigenvalue of ``G`` is one), within
    ``FACTOR_LIMIT`` of 1, by increasing factor."""
    tracked = loci(broken, frequencies_hz) if tracked is None else tracked
    found = []
    for end in (0.0, 0.5 / broken.period_s):  # z = r and z = -r, where G is real: a real pole crossing
        try:
            at_end = np.linalg.eigvals(broken.transfer(end))
        except np.linalg.LinAlgError:  # an open-loop pole on the circle there: no crossing to count
            continue
        for g in at_end:
            if abs(g.imag) <= 1e-12 * abs(g) and g.real > 0.0:
                found.append({"factor": 1.0 / g.real, "frequency_hz": end, "locus": None})
    for locus in range(tracked.shape[1]):
        g = tracked[:, locus]
        for i in np.flatnonzero(np.sign(g[:-1].imag) * np.sign(g[1:].imag) < 0):
            if g[i].real <= 0.0 and g[i + 1].real <= 0.0:
                continue
            f, at = _refined_crossing(broken, frequencies_hz[i], frequencies_hz[i + 1], g[i], g[i + 1])
            if at.real > 0.0:
                found.append({"factor": 1.0 / at.real, "frequency_hz": f, "locus": locus})
    found = [
        item | {"factor": float(item["factor"])} for item in found if 1 / FACTOR_LIMIT < item["factor"] < FACTOR_LIMIT
    ]
    return sorted(found, key=lambda item: item["factor"])


def phase_margins(broken: BrokenLoop, frequencies_hz: np.ndarray, tracked: np.ndarray | None = None) -> list[dict]:
    """Each locus' crossings of ``|g| = 1``: ``{"phase_margin_deg", "frequency_hz", "locus"}``,
    the angle between ``L = -g`` and -1 there (``|arg g|``, deg), the least first."""
    tracked = loci(broken, frequencies_hz) if tracked is None else tracked
    found = []
    for locus in range(tracked.shape[1]):
        magnitude = np.abs(tracked[:, locus])
        for i in np.flatnonzero((magnitude[:-1] > 1.0) != (magnitude[1:] > 1.0)):
            f, g = _unity_crossing(
                broken, frequencies_hz[i], frequencies_hz[i + 1], tracked[i, locus], tracked[i + 1, locus]
            )
            found.append({"phase_margin_deg": abs(math.degrees(np.angle(g))), "frequency_hz": f, "locus": locus})
    return sorted(found, key=lambda item: item["phase_margin_deg"])


def loop_margins(broken: BrokenLoop, frequencies_hz: np.ndarray | None = None) -> dict:
    """The broken loop's gain and phase margins (module docstring), JSON-ready.

    Returns:
        ``channels``; ``gain_margins``: ``increase`` and ``decrease``, each ``None`` or
        ``{"factor", "margin_db", "frequency_hz"}`` (the nearest critical factor above and
        below 1); ``phase_margin``: ``None`` (no locus reaches 0 dB) or
        ``{"phase_margin_deg", "frequency_hz"}``, the least; ``critical_factors``, every
        one found; ``radius`` and ``frequencies_hz``' range.
    """
    frequencies_hz = frequencies(broken.period_s) if frequencies_hz is None else np.asarray(frequencies_hz)
    tracked = loci(broken, frequencies_hz)
    critical = critical_factors(broken, frequencies_hz, tracked)
    above = [item for item in critical if item["factor"] > 1.0]
    below = [item for item in critical if item["factor"] < 1.0]

    def margin(item):
        if item is None:
            return None
        return {
            "factor": item["factor"],
            "margin_db": 20.0 * math.log10(item["factor"]),
            "frequency_hz": item["frequency_hz"],
        }

    phases = phase_margins(broken, frequencies_hz, tracked)
    return {
        "loop": broken.loop,
        "channels": broken.channels,
        "radius": broken.radius,
        "frequency_range_hz": [float(frequencies_hz[0]), float(frequencies_hz[-1])],
        "gain_margins": {
            "increase": margin(above[0] if above else None),
            "decrease": margin(below[-1] if below else None),
        },
        "phase_margin": None
        if not phases
        else {"phase_margin_deg": phases[0]["phase_margin_deg"], "frequency_hz": phases[0]["frequency_hz"]},
        "critical_factors": critical,
    }


def bode(broken: BrokenLoop, frequencies_hz: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The Bode and Nichols data of the broken loop's loci, as the open loop ``L = -g`` of a
    negative-feedback loop: ``frequency_hz`` (F,), ``magnitude_db`` (F, m), ``phase_deg``
    (F, m, unwrapped along each locus, starting in (-360, 0])."""
    frequencies_hz = frequencies(broken.period_s) if frequencies_hz is None else np.asarray(frequencies_hz)
    L = -loci(broken, frequencies_hz)
    phase = np.degrees(np.unwrap(np.angle(L), axis=0))
    phase -= 360.0 * np.ceil(phase[0] / 360.0)  # the first point in (-360, 0]
    with np.errstate(divide="ignore"):
        magnitude = 20.0 * np.log10(np.abs(L))
    return {"frequency_hz": frequencies_hz, "magnitude_db": magnitude, "phase_deg": phase}


__all__ = [
    "BrokenLoop",
    "AFFINE_TOLERANCE",
    "FACTOR_LIMIT",
    "affine_residual",
    "FrequencyError",
    "RANK_TOLERANCE",
    "bode",
    "break_loop",
    "critical_factors",
    "frequencies",
    "loci",
    "loop_margins",
    "phase_margins",
]
