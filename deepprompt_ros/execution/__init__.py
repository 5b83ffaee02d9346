"""Execution at control rate: from a primitive's mean trajectory to limited joint commands.

Modules, from the bottom up:
  limits           per-joint position / velocity / acceleration / jerk limits, check_limits
  phase_clock      the phase x = τ(t) per control tick (temporal modulation, paper Sec. III-C)
  reference        the reference joint state (q, q̇, q̈) at a phase, by the chain rule
  braking          the closed-form, jerk-limited brake of one joint
  ruckig_streamer  RuckigStreamer: the next command within all limits, one call per tick
  settings         LoopSettings: the parameters the controller and the stream loop read
  plan             ExecutionReference and ExecutionPlan: what one Execute goal runs
  controller       ExecutionController: the tick-by-tick state machine of the command stream
  brake_tail       the brake to rest that ends every JointTrajectory message
  stream_loop      StreamLoop: runs the controller at the control rate (no rclpy)
  commands         the typed messages between the server and its control process

A streaming loop uses the first five like this (e.g. at 1 kHz)::

    clock = PhaseClock.linear(dt, duration)            # or rhythmic_clock / from_tau / ...
    streamer = RuckigStreamer(limits, dt)
    streamer.start(q_measured, qd_measured)
    reference = clock_reference(mean_fn, clock)        # reference(ahead) -> (q, qd, qdd)
    # every tick:
    out = streamer.track(reference)
    clock.tick()                                       # clock time = time of out
    publish(out.q, out.qd, out.qdd)                    # the limited command
"""
