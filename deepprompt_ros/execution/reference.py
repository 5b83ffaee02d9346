"""Reference (target) joint state of a primitive at a tick of the phase clock.

``mean_fn`` maps phases (k,) to joint positions (k, d) (e.g. a primitive's conditioned mean);
:func:`reference_state` turns it into the target position, velocity and acceleration at one
:class:`~deepprompt_ros.execution.phase_clock.PhaseSample`, by the chain rule through the
clock's phase rate, and :func:`clock_reference` makes the ``reference(ahead)`` callable that
:meth:`~deepprompt_ros.execution.ruckig_streamer.RuckigStreamer.track` follows.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from deepprompt_ros.execution.phase_clock import PhaseClock, PhaseSample

__all__ = ["ReferenceState", "ReferenceFn", "reference_state", "clock_reference"]


class ReferenceState(NamedTuple):
    """Target joint state of the primitive at one tick, arrays of shape (d,)."""

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray


#: ``reference(ahead)``: the reference state ``ahead`` seconds after the current tick.
ReferenceFn = Callable[[float], "ReferenceState | tuple[np.ndarray, np.ndarray, np.ndarray]"]


def reference_state(target_fn: Callable[[np.ndarray], np.ndarray], phase: PhaseSample, *,
                    periodic: bool = False, h: float = 1e-3) -> ReferenceState:
    """Target position, velocity and acceleration of a primitive at the phase of one tick.

    With y(x) the primitive (e.g. its mean μ_y(z, x)) and x = τ(t) (paper Sec. III-C), by the
    chain rule::

        qd  = y'(x) · dx/dt
        qdd = y''(x) · (dx/dt)² + y'(x) · d²x/dt²

    y' and y'' are central finite differences in phase with step h (second order; near the
    ends of [0, 1] a one-sided stencil inside [0, 1], or wrapped when ``periodic``). The three
    phases are evaluated in ONE call of ``target_fn``. Truncation error is O(h²); rounding error
    of y'' is O(eps·|y|/h²): h = 1e-3 suits float64 primitives, use h ≈ 1e-2 for float32 ones.
    When the primitive has analytic derivatives, compute qd and qdd yourself and pass them
    directly to :meth:`~deepprompt_ros.execution.ruckig_streamer.RuckigStreamer.step`.

    Parameters
    ----------
    target_fn : callable
        Maps phases, array shape (3,), to joint positions, array shape (3, d).
    phase : PhaseSample
        From :meth:`PhaseClock.tick`.
    periodic : bool
        The primitive is rhythmic (y(x) = y(x + 1)).
    h : float
        Phase step of the finite differences, 0 < h <= 0.25.

    Returns
    -------
    ReferenceState
        q, qd, qdd, each shape (d,).
    """
    if not (0.0 < h <= 0.25):
        raise ValueError(f"finite-difference step h must be in (0, 0.25]; got {h}")
    x = phase.x
    if periodic:
        xs = np.array([(x - h) % 1.0, x, (x + h) % 1.0])
        offset = 0  # centred stencil
    elif x - h < 0.0:
        xs = np.array([x, x + h, x + 2 * h])
        offset = -1
    elif x + h > 1.0:
        xs = np.array([x - 2 * h, x - h, x])
        offset = 1
    else:
        xs = np.array([x - h, x, x + h])
        offset = 0
    ys = np.asarray(target_fn(xs), dtype=float)
    if ys.ndim != 2 or ys.shape[0] != 3:
        raise ValueError(f"target_fn must map phases of shape (3,) to positions of shape (3, d); "
                         f"got shape {ys.shape}")
    y0, y1, y2 = ys
    d2 = (y0 - 2 * y1 + y2) / (h * h)
    if offset == 0:
        q = y1
        d1 = (y2 - y0) / (2 * h)
    elif offset < 0:  # x is the first point: second-order forward difference
        q = y0
        d1 = (-3 * y0 + 4 * y1 - y2) / (2 * h)
    else:  # x is the last point: second-order backward difference
        q = y2
        d1 = (3 * y2 - 4 * y1 + y0) / (2 * h)
    qd = d1 * phase.x_dot
    qdd = d2 * phase.x_dot ** 2 + d1 * phase.x_ddot
    return ReferenceState(q.copy(), qd, qdd)


def clock_reference(target_fn: Callable[[np.ndarray], np.ndarray], clock: PhaseClock, *,
                    periodic: bool | None = None, h: float = 1e-3
                    ) -> Callable[[float], ReferenceState]:
    """The ``reference(ahead)`` callable of
    :meth:`~deepprompt_ros.execution.ruckig_streamer.RuckigStreamer.track` for a primitive
    ``target_fn`` (phases (k,) -> positions (k, d)) driven by ``clock``: the reference state
    at the phase the clock predicts ``ahead`` seconds after its current tick
    (:meth:`PhaseClock.peek`), by :func:`reference_state`. ``periodic`` defaults to the
    clock's ``rhythmic``."""
    wrap = clock.rhythmic if periodic is None else bool(periodic)

    def reference(ahead: float) -> ReferenceState:
        return reference_state(target_fn, clock.peek(ahead), periodic=wrap, h=h)
    return reference
