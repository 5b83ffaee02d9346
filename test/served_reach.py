"""Execute goal durations for the reach primitive a running primitive_server serves, for the tests that
send it goals.

primitive_server refuses (LIMIT_VIOLATION) a goal whose executed mean trajectory y(x) would need more
than a joint's velocity limit: at duration T a joint moves at |y_j'(x)| / T, so the shortest duration
it accepts is max_j max_x |y_j'(x)| / v_max,j. The shipped reach model follows the speed of its
demonstrations, so that duration is a property of the trained model: it is read here from the server
itself (the preview of the reach's prior mean on the server's execution grid, the trajectory a goal
of that handle executes), never written into a test.

Imported by the test files as ``served_reach`` (pytest puts ``test/`` on ``sys.path``).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

ROBOT = "gen3_lite"
#: goal duration / shortest accepted duration of the tests' ordinary goals
MARGIN = 1.3
#: the same for goals meant to run near the top speed the limits allow (braking then takes about a second)
FAST_MARGIN = 1.1


def limit_ratios(y: np.ndarray, joint_names) -> np.ndarray:
    """The duration (s) at which the trajectory ``y`` (N, d; N evenly spaced phases on [0, 1], joints
    ``joint_names``) would reach a velocity limit at each phase, shape (N,):
    :meth:`~deepprompt_ros.execution.plan.ExecutionReference.velocity_limit_ratios` under the Gen3 lite's
    limits and the default ServerConfig (the server's velocity check)."""
    from deepprompt_ros.execution.plan import ExecutionReference
    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.server.config import ServerConfig, robot_limits

    config = ServerConfig()
    limits = robot_limits(load_robot(ROBOT), config)
    v_max = dict(zip(limits.names, limits.max_velocity))
    ref = ExecutionReference(np.asarray(y, dtype=np.float64), False, config.derivative_step)
    return ref.velocity_limit_ratios([v_max[name] for name in joint_names])


@dataclasses.dataclass(frozen=True)
class ReachTiming:
    """The timing of the served reach's prior mean (the handle of a Condition with no via-point and no
    context).

    Attributes
    ----------
    ratios : array, shape (N,)
        :func:`limit_ratios` of the prior mean on N evenly spaced phases.
    """

    ratios: np.ndarray

    @property
    def shortest(self) -> float:
        """Shortest duration (s) the server accepts."""
        return float(self.ratios.max())

    def duration(self, margin: float = MARGIN, step: float = 0.1) -> float:
        """``margin`` x :attr:`shortest`, rounded up to a multiple of ``step`` (s)."""
        if not margin >= 1.0:
            raise ValueError(f"margin = {margin!r}: expected >= 1 (a shorter goal is refused)")
        return round(math.ceil(self.shortest * margin / step - 1e-9) * step, 6)

    @property
    def ordinary(self) -> float:
        """The duration (s) of an ordinary goal (:data:`MARGIN`)."""
        return self.duration(MARGIN)

    @property
    def fast(self) -> float:
        """The duration (s) of a goal near the top speed the limits allow (:data:`FAST_MARGIN`)."""
        return self.duration(FAST_MARGIN)

    def fastest_phase(self, lo: float = 0.1, hi: float = 0.8) -> float:
        """The phase in [lo, hi] where the prior mean runs closest to a velocity limit: a goal canceled
        there brakes from its top speed (the phases outside leave room to start the goal and to brake
        before its end)."""
        x = np.linspace(0.0, 1.0, self.ratios.shape[0])
        inside = (x >= lo) & (x <= hi)
        return float(x[inside][np.argmax(self.ratios[inside])])


def reach_timing(client, server: str = "/primitive_server", timeout: float = 20.0) -> ReachTiming:
    """Ask the server ``server`` (through ``client``, a :class:`~deepprompt_ros.ros.testing.RosTestClient`)
    for the preview of its 'reach' prior mean on its execution grid (default ServerConfig) and time it."""
    from deepprompt_msgs.srv import Condition

    from deepprompt_ros.ros import conversions as conv
    from deepprompt_ros.server.config import ServerConfig

    req = Condition.Request(primitive="reach", preview_points=ServerConfig().execution_grid_points)
    # sent again after 5 s without a reply: the first call of a client can lose its reply while the server has
    # not yet matched the client's reply reader (RosTestClient.wait_for_service); a repeat stores one more handle
    r = client.call(Condition, f"{server}/condition", req, timeout=timeout, resend_after=5.0)
    assert r.success, r.message
    return ReachTiming(limit_ratios(conv.preview_from_msg(r.preview).mean, list(r.preview.joint_names)))
