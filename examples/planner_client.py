"""Task-planner example: condition the shipped Gen3 lite 'reach' primitive on an object position and
one via-point, execute it on the simulated arm, and print the via-point error the arm achieved.

Start the robot side first (`make run`), then: `.venv/bin/python examples/planner_client.py`.
"""
from __future__ import annotations

import argparse
import sys
import threading
import time

import numpy as np
import rclpy
from rclpy.action import ActionClient
from rclpy.executors import MultiThreadedExecutor
from sensor_msgs.msg import JointState

from deepprompt_msgs.action import Execute
from deepprompt_msgs.msg import Context, ViaPoint
from deepprompt_msgs.srv import Condition


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--object", type=float, nargs=3, default=[0.35, 0.1, 0.05], help="object position (m)")
    ap.add_argument("--via-phase", type=float, default=0.5)
    ap.add_argument("--via-offset", type=float, default=0.05, help="rad added to joint_1 of the preview at the via phase")
    # the reach follows its demonstrations' speed: the server refuses (LIMIT_VIOLATION, naming the shortest
    # duration it accepts) a goal faster than the Gen3 lite's velocity limits allow; 8 s is well above that
    ap.add_argument("--duration", type=float, default=8.0,
                    help="s from phase 0 to 1 (at least the shortest the velocity limits allow for this motion)")
    ap.add_argument("--server", default="/primitive_server")
    args = ap.parse_args(argv)

    rclpy.init()
    node = rclpy.create_node("planner_client")
    ex = MultiThreadedExecutor()
    ex.add_node(node)
    spinner = threading.Thread(target=ex.spin, daemon=True)
    spinner.start()
    # joint_states and feedback arrive in the executor's threads while this thread reads them: both
    # lists are appended and copied under one lock, and read only from a copy
    lock = threading.Lock()
    states: list[tuple[float, dict]] = []

    def on_state(m: JointState) -> None:
        sample = (time.monotonic(), dict(zip(m.name, m.position)))
        with lock:
            states.append(sample)

    # 2 s of 1 kHz states kept: an executor that stalls (a loaded machine) takes them late, not never
    node.create_subscription(JointState, "joint_states", on_state, 2000)
    cond = node.create_client(Condition, f"{args.server}/condition")
    act = ActionClient(node, Execute, f"{args.server}/execute")
    try:
        if not cond.wait_for_service(timeout_sec=20.0) or not act.wait_for_server(timeout_sec=20.0):
            print("primitive_server not found: start it with `make run`", file=sys.stderr)
            return 2
        ctx = Context(modality="object", values=list(args.object))
        # 1) context only: where would the primitive go?
        r = cond.call(Condition.Request(primitive="reach", contexts=[ctx], preview_points=101))
        if not r.success:
            print(f"condition failed: {r.message}", file=sys.stderr)
            return 1
        T, d = r.preview.n_points, r.preview.n_joints
        mean = np.array(r.preview.mean).reshape(T, d)
        phases = np.array(r.preview.phases)
        via = mean[int(np.argmin(np.abs(phases - args.via_phase)))].copy()
        via[0] += args.via_offset
        # 2) context + via-point, refined so the executed trajectory meets it
        req = Condition.Request(primitive="reach", contexts=[ctx], refine=True, preview_points=101,
                                via_points=[ViaPoint(phase=args.via_phase, positions=via.tolist())])
        r = cond.call(req)
        print(f"condition: success={r.success} code={r.code.value} '{r.message}' handle={r.handle} "
              f"refine_max_error={r.refine_max_error:.2e} rad reachable={r.reachable}")
        if not r.handle:
            return 1
        joint_names = list(r.preview.joint_names)
        # 3) execute, logging the phase feedback with its arrival time
        feedback: list[tuple[float, float]] = []

        def on_feedback(f) -> None:
            sample = (time.monotonic(), f.feedback.phase)
            with lock:
                feedback.append(sample)

        goal = Execute.Goal(handle=r.handle, duration=args.duration)
        fut = act.send_goal_async(goal, feedback_callback=on_feedback)
        while not fut.done():
            time.sleep(0.01)
        handle = fut.result()
        if not handle.accepted:
            print("execute goal rejected", file=sys.stderr)
            return 1
        res_fut = handle.get_result_async()
        while not res_fut.done():
            time.sleep(0.05)
        res = res_fut.result().result
        print(f"execute: success={res.success} code={res.code.value} '{res.message}' "
              f"max_tracking_error={res.max_tracking_error:.2e} rad")
        # 4) the arm's closest approach to the via-point: the measured joint_states sample whose largest joint
        # error is the smallest (one snapshot of each list, in time order: the executor's threads may have run
        # callbacks out of order); the feedback phase at that time says where in the motion it was
        with lock:
            feedback_seen, states_seen = sorted(feedback), sorted(states, key=lambda s: s[0])
        if not feedback_seen or not states_seen:
            print("no feedback/joint_states received during the execution", file=sys.stderr)
            return 1
        t0, t1 = feedback_seen[0][0], feedback_seen[-1][0]
        during = [(t, [s.get(j, np.nan) for j in joint_names]) for t, s in states_seen if t0 - 0.5 <= t <= t1 + 0.5]
        during = [(t, q) for t, q in during if np.all(np.isfinite(q))]  # (a state naming other joints: skipped)
        qs = np.array([q for _, q in during]).reshape(-1, len(joint_names))
        if not len(qs):
            print("no joint_states received during the execution", file=sys.stderr)
            return 1
        k = int(np.argmin(np.abs(qs - via).max(1)))
        err = np.abs(qs[k] - via)
        phase_at = np.interp(during[k][0], [t for t, _ in feedback_seen], [ph for _, ph in feedback_seen])
        print("via-point error achieved by the simulated arm (rad): "
              + ", ".join(f"{j}={e:.5f}" for j, e in zip(joint_names, err)) + f"; max {err.max():.5f}")
        print(f"(the measured joint_states sample closest to the via-point, at feedback phase {phase_at:.3f}; "
              f"the via phase is {args.via_phase:g})")
        return 0 if res.success else 1
    finally:
        # the spinning thread must have left rclpy before the interpreter exits: a thread still waiting in
        # the executor then aborts the process ("terminate called without an active exception")
        ex.shutdown()
        spinner.join(timeout=5.0)
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
