"""Minimum-jerk interpolation (Flash & Hogan 1985): the rest-to-rest profile and the quintic Hermite
basis of a segment between two states with given velocities and zero accelerations.

The one minimum-jerk of the package: :class:`~deepprompt_ros.sim.tasks.trajectory.ViaTrajectory`
joins via-configurations with the basis, the kinematic reach generator
(:mod:`~deepprompt_ros.sim.tasks.kinematic_reach`) times its path with the profile.
"""
from __future__ import annotations

__all__ = ["min_jerk", "quintic_hermite"]


def min_jerk(s):
    """Rest-to-rest minimum-jerk profile 10s³ − 15s⁴ + 6s⁵ (0 → 1 with zero velocity and
    acceleration at both ends), of a scalar or an array of s in [0, 1]."""
    return 10 * s**3 - 15 * s**4 + 6 * s**5


def quintic_hermite(u):
    """Quintic Hermite basis on u in [0, 1] (scalar or array) and its derivatives.

    The minimum-jerk curve from (q₀, v₀, 0) to (q₁, v₁, 0) over a segment of duration h is
    q(u) = H₀ q₀ + h H₁ v₀ + h H₂ v₁ + H₃ q₁ with H₀ = 1 − 10u³ + 15u⁴ − 6u⁵,
    H₁ = u − 6u³ + 8u⁴ − 3u⁵, H₂ = −4u³ + 7u⁴ − 3u⁵ and H₃ = 1 − H₀ = :func:`min_jerk` (u).

    Returns
    -------
    H : tuple (H₀, H₁, H₂, H₃)
    dH : tuple (H₀', H₁', H₂')
        d/du (H₃' = −H₀').
    ddH : tuple (H₀'', H₁'', H₂'')
        d²/du² (H₃'' = −H₀'').
    """
    u2, u3, u4, u5 = u**2, u**3, u**4, u**5
    H = (1 - 10 * u3 + 15 * u4 - 6 * u5, u - 6 * u3 + 8 * u4 - 3 * u5, -4 * u3 + 7 * u4 - 3 * u5, min_jerk(u))
    dH = (-30 * u2 + 60 * u3 - 30 * u4, 1 - 18 * u2 + 32 * u3 - 15 * u4, -12 * u2 + 28 * u3 - 15 * u4)
    ddH = (-60 * u + 180 * u2 - 120 * u3, -36 * u + 96 * u2 - 60 * u3, -24 * u + 84 * u2 - 60 * u3)
    return H, dH, ddH
