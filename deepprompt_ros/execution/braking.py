"""Time-optimal, jerk-limited brake of one joint to rest, in closed form.

The position guard of :class:`~deepprompt_ros.execution.ruckig_streamer.RuckigStreamer`
checks, for every joint near a limit, where this brake from the proposed next state would take
the joint, and executes the same brake when that leaves the limits; cancelling uses it too.
"""
from __future__ import annotations

import math

__all__ = ["brake_joint"]


def brake_joint(q: float, v: float, a: float, a_max: float, j_max: float,
                t: float) -> tuple[float, float, float, float, float]:
    """Time-optimal jerk-limited brake of one joint to v = 0, a = 0.

    Profile (for a joint whose velocity must decrease; the other case is mirrored): jerk
    -j_max until the acceleration reaches a_p, hold a_p (only when a_p hits -a_max), jerk
    +j_max until a = 0, reached exactly when v = 0. Without the hold, the velocity balance
    v0 + (a0² - a_p²)/(2j) - a_p²/(2j) = 0 gives a_p = -sqrt(j·v0 + a0²/2); with it, the hold
    lasts t2 = (v0 + (a0² - 2a²)/(2j)) / a. The speed stays within
    max(|v0|, |v0 + a0|a0|/(2j)|) and the acceleration within a_max, so the brake of a state
    inside the limits keeps them. Computed here rather than with ruckig's velocity interface
    (its ``position_extrema`` is wrong for velocity-interface trajectories in 0.19.4) so that
    the brake that is checked and the brake that is executed are the same function: stepping
    along it and recomputing gives the same profile, which the position guard relies on.
    Plain floats: for d <= 7 this is faster than numpy on (d,) arrays.

    Returns
    -------
    lo, hi : float
        Min / max position over the whole brake.
    q_t, v_t, a_t : float
        State after time t (at rest once the brake is over).
    """
    s = 1.0 if v + a * abs(a) / (2.0 * j_max) >= 0.0 else -1.0
    vf, af = s * v, s * a  # mirrored: the brake decelerates, vf + af|af|/(2j) >= 0
    ap = -math.sqrt(max(j_max * vf + 0.5 * af * af, 0.0))
    t2 = 0.0
    if ap < -a_max:
        ap = -a_max
        t2 = max((vf + (af * af - 2.0 * a_max * a_max) / (2.0 * j_max)) / a_max, 0.0)
    t1 = max((af - ap) / j_max, 0.0)
    t3 = -ap / j_max
    p1 = vf * t1 + af * t1 * t1 / 2.0 - j_max * t1 ** 3 / 6.0
    v1 = vf + af * t1 - j_max * t1 * t1 / 2.0
    p2 = p1 + v1 * t2 + ap * t2 * t2 / 2.0
    v2 = v1 + ap * t2
    p3 = p2 + v2 * t3 + ap * t3 * t3 / 2.0 + j_max * t3 ** 3 / 6.0
    lo_f, hi_f = min(0.0, p3), max(0.0, p3)
    if vf < 0.0:  # the velocity turns around during the first segment: a position extremum
        ts = (af - math.sqrt(max(af * af + 2.0 * j_max * vf, 0.0))) / j_max
        ps = vf * ts + af * ts * ts / 2.0 - j_max * ts ** 3 / 6.0
        lo_f, hi_f = min(lo_f, ps), max(hi_f, ps)
    if t <= t1:
        pt = vf * t + af * t * t / 2.0 - j_max * t ** 3 / 6.0
        vt = vf + af * t - j_max * t * t / 2.0
        at = af - j_max * t
    elif t <= t1 + t2:
        u = t - t1
        pt, vt, at = p1 + v1 * u + ap * u * u / 2.0, v1 + ap * u, ap
    elif t < t1 + t2 + t3:
        u = t - t1 - t2
        pt = p2 + v2 * u + ap * u * u / 2.0 + j_max * u ** 3 / 6.0
        vt = v2 + ap * u + j_max * u * u / 2.0
        at = ap + j_max * u
    else:
        pt, vt, at = p3, 0.0, 0.0
    if s > 0:
        return q + lo_f, q + hi_f, q + pt, vt, at
    return q - hi_f, q - lo_f, q - pt, -vt, -at
