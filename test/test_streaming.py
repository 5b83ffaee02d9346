"""Tests of deepprompt_ros.execution (limits, phase_clock, reference, braking, ruckig_streamer):
phase clock, reference derivatives, and the Ruckig
streamer with real ruckig (no mocks). Limits are checked on every produced sample with
check_limits: |qd| <= v, |qdd| <= a per sample and |Δq|/dt <= v, |Δqd|/dt <= a,
|Δqdd|/dt <= j between successive samples (finite-difference jerk of the reported
accelerations), relative tolerance 1e-6, positions within [lower, upper] up to 1e-9 rad; with
sample times, across gaps by their length (a displaced command and a jump across missing samples
are found)."""
import math

import numpy as np
import pytest

from deepprompt_ros.execution.braking import brake_joint
from deepprompt_ros.execution.limits import JointLimits, check_limits
from deepprompt_ros.execution.phase_clock import PhaseClock
from deepprompt_ros.execution.reference import clock_reference, reference_state
from deepprompt_ros.execution.ruckig_streamer import RuckigStreamer, StreamStatus

DT = 0.001
LIMITS = JointLimits(lower=[-1.0, -2.0, -0.5], upper=[1.0, 2.0, 0.5],
                     max_velocity=[1.0, 1.5, 0.8], max_acceleration=[3.0, 4.0, 2.0],
                     max_jerk=[30.0, 40.0, 20.0])


def sine_family(amp, off, phase=0.0):
    amp, off = np.asarray(amp, float), np.asarray(off, float)

    def fn(x):
        return off + amp * np.sin(2 * np.pi * (np.atleast_1d(x)[:, None] + phase))
    return fn


class Recorder:
    """Collects the streamed samples, starting with the state given to start()."""

    def __init__(self, q0, qd0=None, qdd0=None):
        d = len(q0)
        self.q = [np.asarray(q0, float)]
        self.qd = [np.zeros(d) if qd0 is None else np.asarray(qd0, float)]
        self.qdd = [np.zeros(d) if qdd0 is None else np.asarray(qdd0, float)]
        self.status = []

    def add(self, s):
        self.q.append(s.q)
        self.qd.append(s.qd)
        self.qdd.append(s.qdd)
        self.status.append(s.status)

    def report(self, limits=LIMITS):
        return check_limits(np.array(self.q), np.array(self.qd), np.array(self.qdd), DT, limits)


def run_track(streamer, clock, fn, rec, n=None):
    errors = []
    k = 0
    reference = clock_reference(fn, clock)
    while not clock.done and (n is None or k < n):
        s = streamer.track(reference)
        ph = clock.tick()
        rec.add(s)
        errors.append(np.abs(s.q - fn(ph.x)[0]))
        k += 1
    return np.array(errors)


# ------------------------------------------------------------------------------------------
# PhaseClock
# ------------------------------------------------------------------------------------------
def test_linear_clock_maps_ticks_to_t_over_T_and_finishes():
    clock = PhaseClock.linear(0.01, 2.0)
    xs = [clock.tick() for _ in range(250)]
    for k, s in enumerate(xs[:199], start=1):
        assert s.x == pytest.approx(k * 0.01 / 2.0, abs=1e-12)
        assert s.x_dot == pytest.approx(0.5) and not s.done
    assert xs[199].done and xs[199].x == 1.0
    assert all(s.done and s.x == 1.0 and s.x_dot == 0.0 for s in xs[200:])
    by_rate = PhaseClock.from_rate(0.01, 0.5)
    assert [by_rate.tick().x for _ in range(50)] == pytest.approx([s.x for s in xs[:50]], abs=1e-12)


def test_monotone_tau_callable_and_knots():
    T = 2.0
    clock = PhaseClock.from_tau(0.01, lambda t: (t / T) ** 2, T)
    samples = [clock.tick() for _ in range(200)]
    t = np.arange(1, 201) * 0.01
    assert [s.x for s in samples] == pytest.approx((t / T) ** 2, abs=1e-12)
    # dx/dt = 2t/T² (one-sided stencil at the very end is first-order)
    assert [s.x_dot for s in samples[:-1]] == pytest.approx(2 * t[:-1] / T ** 2, abs=1e-6)
    assert samples[-1].done
    knots_t, knots_x = [0.0, 0.5, 1.5, 2.0], [0.0, 0.1, 0.9, 1.0]
    clock = PhaseClock.from_knots(0.001, knots_t, knots_x)
    xs, rates = [clock.sample.x], [clock.sample.x_dot]
    for _ in range(2000):
        s = clock.tick()
        xs.append(s.x)
        rates.append(s.x_dot)
    xs = np.array(xs)
    for tk, xk in zip(knots_t, knots_x):
        assert xs[int(round(tk / 0.001))] == pytest.approx(xk, abs=1e-12)
    assert np.all(np.diff(xs) >= 0)                       # monotone knots -> monotone τ
    assert np.max(np.abs(np.diff(rates[:-1]))) < 0.01     # C¹: no jump of the phase rate


def test_reverse_runs_phase_from_one_to_zero():
    clock = PhaseClock.linear(0.01, 1.0, reverse=True)
    assert clock.x == 1.0
    s = [clock.tick() for _ in range(100)]
    assert [v.x for v in s] == pytest.approx(1.0 - np.arange(1, 101) * 0.01, abs=1e-12)
    assert s[50].x_dot == pytest.approx(-1.0)
    assert s[-1].done and s[-1].x == 0.0


def test_rhythmic_clock_wraps_seamlessly_for_n_cycles():
    clock = PhaseClock.rhythmic_clock(DT, 1.0, cycles=3)
    samples = [clock.sample]
    while not clock.done:
        samples.append(clock.tick())
    assert len(samples) == 3001
    x = np.array([s.x for s in samples])
    assert x.min() >= 0.0 and x.max() < 1.0
    assert [s.cycle for s in samples[999:1002]] == [0, 1, 1]
    enc = np.stack([np.sin(2 * np.pi * x), np.cos(2 * np.pi * x)], axis=1)
    # the decoder input moves by at most 2π·rate·dt per tick, also across the wraps
    assert np.max(np.linalg.norm(np.diff(enc, axis=0), axis=1)) <= 2 * np.pi * DT * (1 + 1e-6)
    endless = PhaseClock.rhythmic_clock(DT, 0.1)
    for _ in range(5000):
        s = endless.tick()
    assert not s.done and s.cycle == 50


def test_live_rate_change_keeps_phase_continuous():
    clock = PhaseClock.linear(DT, 2.0)
    for _ in range(500):
        clock.tick()
    before = clock.x
    clock.set_rate(2.0)
    assert clock.x == before                               # the call itself moves nothing
    s = clock.tick()
    assert s.x - before == pytest.approx(2.0 * DT, abs=1e-12)
    n = 1
    while not clock.done:
        clock.tick()
        n += 1
    assert n == pytest.approx((1.0 - 0.25) / (2.0 * DT), abs=1)
    # ramped change: dx/dt continuous, d²x/dt² = slope during the ramp
    clock = PhaseClock.rhythmic_clock(DT, 1.0)
    for _ in range(100):
        clock.tick()
    clock.set_rate(3.0, ramp_time=0.2)
    rates, accs, xs = [], [], []
    for _ in range(400):
        s = clock.tick()
        rates.append(s.x_dot)
        accs.append(s.x_ddot)
        xs.append(s.x)
    assert np.max(np.abs(np.diff(rates))) <= 10.0 * DT * (1 + 1e-9)
    assert accs[50] == pytest.approx(10.0) and accs[-1] == 0.0 and rates[-1] == pytest.approx(3.0)
    steps = np.diff(np.unwrap(np.array(xs) * 2 * np.pi)) / (2 * np.pi)
    assert np.all(steps > 0) and np.max(steps) <= 3.0 * DT * (1 + 1e-9)


def test_peek_predicts_the_phase_of_later_ticks():
    clock = PhaseClock.rhythmic_clock(DT, 1.3)
    clock.set_rate(2.0, ramp_time=0.05)
    predicted = [clock.peek(k * DT) for k in (1, 10, 40, 80)]
    ticks = [clock.tick() for _ in range(80)]
    for k, p in zip((1, 10, 40, 80), predicted):
        assert p.x == pytest.approx(ticks[k - 1].x, abs=1e-12)
        assert p.x_dot == pytest.approx(ticks[k - 1].x_dot, abs=1e-12)


def test_reference_state_applies_the_chain_rule():
    fn = sine_family([0.4, -0.7], [0.1, 0.0])
    clock = PhaseClock.linear(DT, 2.0)
    clock.set_rate(0.5)
    clock.set_rate(0.8, ramp_time=0.5)
    for _ in range(100):
        clock.tick()
    s = clock.sample
    ref = reference_state(fn, s)
    w = 2 * np.pi
    amp = np.array([0.4, -0.7])
    dq = amp * w * np.cos(w * s.x)
    ddq = -amp * w * w * np.sin(w * s.x)
    assert ref.q == pytest.approx(fn(s.x)[0], abs=1e-12)
    assert ref.qd == pytest.approx(dq * s.x_dot, rel=1e-5, abs=1e-9)
    assert ref.qdd == pytest.approx(ddq * s.x_dot ** 2 + dq * s.x_ddot, rel=1e-4, abs=1e-6)
    # at the ends of [0, 1] the one-sided stencil stays inside and is second order
    for x in (0.0, 1.0):
        end = reference_state(fn, s._replace(x=x))
        assert end.qd == pytest.approx(amp * w * np.cos(w * x) * s.x_dot, rel=1e-4)


# ------------------------------------------------------------------------------------------
# brake used by the position guard and by stops
# ------------------------------------------------------------------------------------------
def test_brake_profile_stops_within_limits_and_its_extrema_bound_the_motion():
    rng = np.random.default_rng(0)
    A, J, V = 3.0, 30.0, 1.0
    for _ in range(100):
        a0 = rng.uniform(-A, A)
        vmax = V - a0 * a0 / (2 * J)
        v0 = rng.uniform(-vmax, vmax)
        q = rng.uniform(-1, 1)
        lo, hi, _, _, _ = brake_joint(q, v0, a0, A, J, 0.0)
        state = (q, v0, a0)
        qs, vs, accs = [q], [v0], [a0]
        for _ in range(800):
            lo_k, hi_k, *state = brake_joint(*state, A, J, DT)
            qs.append(state[0])
            vs.append(state[1])
            accs.append(state[2])
            # stepping along the brake never widens its predicted range (guard invariant)
            assert lo_k >= lo - 1e-12 and hi_k <= hi + 1e-12
        qs, vs, accs = map(np.array, (qs, vs, accs))
        assert vs[-1] == 0.0 and accs[-1] == 0.0
        assert qs.min() >= lo - 1e-12 and qs.max() <= hi + 1e-12
        assert min(qs.min() - lo, hi - qs.max()) > -1e-12
        assert np.max(np.abs(vs)) <= V * (1 + 1e-9) and np.max(np.abs(accs)) <= A * (1 + 1e-9)
        assert np.max(np.abs(np.diff(accs))) / DT <= J * (1 + 1e-9)


# ------------------------------------------------------------------------------------------
# RuckigStreamer
# ------------------------------------------------------------------------------------------
def test_track_converges_from_far_onto_moving_sine_then_tracks_within_limits():
    streamer = RuckigStreamer(LIMITS, DT, horizon=0.01)
    fn = sine_family([0.5, 0.8, 0.3], [0.2, -0.3, 0.0])
    clock = PhaseClock.rhythmic_clock(DT, 4.0, cycles=2)
    q0 = np.array([-0.9, 1.5, 0.3])
    streamer.start(q0)
    rec = Recorder(q0)
    err = run_track(streamer, clock, fn, rec, n=7000)
    assert err[0].max() > 1.0                                      # started far away
    assert rec.status[0] == StreamStatus.APPROACHING
    converged = int(np.argmax(err.max(axis=1) < 1e-5))
    assert 0 < converged < 3000                                    # onto the sine within 3 s
    assert err[converged:].max() < 1e-5                            # and stays on it
    tracking = rec.status.index(StreamStatus.TRACKING)  # the interception ended there
    assert abs(tracking - converged) < 50
    assert all(s == StreamStatus.TRACKING for s in rec.status[tracking:])
    report = rec.report()
    assert report.ok(rtol=1e-6), report


def test_limits_hold_when_reference_leaves_the_joint_range():
    # joint 3's reference (amplitude 0.8) leaves its range ±0.5; the others stay feasible
    streamer = RuckigStreamer(LIMITS, DT, position_margin=0.02)
    fn = sine_family([0.5, 0.8, 0.8], [0.2, -0.3, 0.0])
    clock = PhaseClock.rhythmic_clock(DT, 4.0, cycles=2)
    q0 = fn(0.0)[0]
    streamer.start(q0)
    rec = Recorder(q0)
    err = run_track(streamer, clock, fn, rec, n=5000)
    report = rec.report()
    assert report.ok(rtol=1e-6, position_tol=1e-9), report
    q = np.array(rec.q)
    assert q[:, 2].max() > 0.47 and q[:, 2].min() < -0.47          # it did go to the limits
    # the joints whose references are reachable keep tracking (joints are planned independently)
    assert err[1500:, :2].max() < 1e-5


def test_position_guard_keeps_joint_inside_when_clamping_alone_would_overshoot():
    limits = JointLimits(lower=[-0.5, -1.0], upper=[0.5, 1.0], max_velocity=[1.0, 1.0],
                         max_acceleration=[2.0, 2.0], max_jerk=[20.0, 20.0])
    amp = np.array([0.6, 0.3])
    fn = sine_family(amp, [0.0, 0.0])

    def run(guard: bool):
        streamer = RuckigStreamer(limits, DT, position_margin=0.005)
        if not guard:
            streamer._guard_zone = [-1.0, -1.0]  # no joint ever counts as near a limit
        clock = PhaseClock.rhythmic_clock(DT, 4.0, cycles=1)
        q0, qd0 = fn(0.0)[0], amp * 2 * np.pi / 4.0
        streamer.start(q0, qd0)
        rec = Recorder(q0, qd0)
        run_track(streamer, clock, fn, rec)
        return rec

    unguarded = run(False)
    assert np.array(unguarded.q)[:, 0].max() > 0.55       # clamping the target alone overshoots
    rec = run(True)
    assert StreamStatus.POSITION_GUARD in rec.status
    report = rec.report(limits)
    assert report.ok(rtol=1e-6, position_tol=1e-9), report


def test_switching_reference_mid_motion_keeps_position_and_velocity_continuous():
    streamer = RuckigStreamer(LIMITS, DT)
    fa = sine_family([0.5, 0.8, 0.3], [0.2, -0.3, 0.0])
    fb = sine_family([0.3, 0.5, 0.2], [-0.2, 0.3, 0.1], phase=0.25)
    clock = PhaseClock.rhythmic_clock(DT, 3.0)
    q0 = fa(0.0)[0]
    streamer.start(q0)
    rec = Recorder(q0)
    run_track(streamer, clock, fa, rec, n=1500)
    k_switch = len(rec.q) - 1
    err_b = run_track(streamer, clock, fb, rec, n=4500)
    q, qd = np.array(rec.q), np.array(rec.qd)
    dq = np.abs(q[k_switch + 1] - q[k_switch]) / DT
    dqd = np.abs(qd[k_switch + 1] - qd[k_switch]) / DT
    assert np.all(dq <= LIMITS.max_velocity * (1 + 1e-6))
    assert np.all(dqd <= LIMITS.max_acceleration * (1 + 1e-6))
    report = rec.report()
    assert report.ok(rtol=1e-6), report
    assert err_b[0].max() > 0.1 and err_b[-1000:].max() < 1e-5   # it moved onto the new reference


def test_stop_brings_every_joint_to_rest_within_limits_and_holds():
    streamer = RuckigStreamer(LIMITS, DT)
    fn = sine_family([0.5, 0.8, 0.3], [0.2, -0.3, 0.0])
    clock = PhaseClock.rhythmic_clock(DT, 2.0)
    q0 = fn(0.0)[0]
    streamer.start(q0)
    rec = Recorder(q0)
    run_track(streamer, clock, fn, rec, n=1200)
    assert np.abs(rec.qd[-1]).max() > 0.5                  # moving fast when cancelled
    streamer.request_stop()
    n = 0
    while True:
        s = streamer.track(lambda ahead: reference_state(fn, clock.peek(ahead), periodic=True))
        rec.add(s)
        n += 1
        if s.status == StreamStatus.STOPPED:
            break
        assert s.status == StreamStatus.STOPPING and n < 2000
    # time-optimal brake from |v| <= 1.5 with a = 4, j = 40: well under a second
    assert n * DT < 1.0
    assert streamer.at_rest(vel_tol=0.0, acc_tol=0.0)
    held = streamer.step(np.zeros(3))
    assert held.status == StreamStatus.STOPPED and np.array_equal(held.q, rec.q[-1])
    report = rec.report()
    assert report.ok(rtol=1e-6), report
    streamer.resume()
    assert streamer.step(np.zeros(3)).status == StreamStatus.TRACKING


def test_step_moves_time_optimally_to_a_static_target_and_clamps_it():
    streamer = RuckigStreamer(LIMITS, DT, position_margin=0.01)
    streamer.start([0.0, 0.0, 0.0])
    rec = Recorder([0.0, 0.0, 0.0])
    target = np.array([0.9, -1.5, 2.0])                    # joint 3 beyond its limit 0.5
    for _ in range(5000):
        s = streamer.step(target)
        rec.add(s)
        if s.status == StreamStatus.REACHED:
            break
    assert s.status == StreamStatus.REACHED
    assert s.q == pytest.approx([0.9, -1.5, 0.49], abs=1e-12)
    assert s.clamped.tolist() == [False, False, True]
    assert rec.report().ok(rtol=1e-6)


def test_start_and_targets_are_validated_with_actionable_messages():
    streamer = RuckigStreamer(LIMITS, DT)
    with pytest.raises(RuntimeError, match="start"):
        streamer.step(np.zeros(3))
    with pytest.raises(ValueError, match="joint_3.*outside its limits"):
        streamer.start([0.0, 0.0, 0.6])
    with pytest.raises(ValueError, match="3 values; expected 3|expected 3"):
        streamer.start([0.0, 0.0])
    with pytest.raises(ValueError, match="velocity of joint_2 .*limit"):
        streamer.start([0.0, 0.0, 0.0], [0.0, 2.0, 0.0])
    with pytest.raises(ValueError, match="cannot stop inside its limits"):
        streamer.start([0.0, 0.0, 0.49], [0.0, 0.0, 0.8])
    streamer.start([0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"expected \(3,\)"):
        streamer.step(np.zeros(2))
    with pytest.raises(ValueError, match="finite"):
        streamer.step([0.0, math.nan, 0.0])
    with pytest.raises(ValueError, match="lower limit"):
        JointLimits([1.0], [0.0], [1.0], [1.0], [1.0])


def test_check_limits_reports_violations():
    limits = JointLimits([-1.0], [1.0], [1.0], [2.0], [10.0])
    q = np.zeros((5, 1))
    qd = np.zeros((5, 1))
    qdd = np.zeros((5, 1))
    assert check_limits(q, qd, qdd, DT, limits).ok()
    qdd[3] = 0.02                                           # jump of 0.02 in 1 ms: jerk 20
    r = check_limits(q, qd, qdd, DT, limits)
    assert r.jerk_ratio == pytest.approx(2.0) and not r.ok() and r.worst[0] == "jerk"
    q[4] = 1.5
    r = check_limits(q, qd, np.zeros((5, 1)), DT, limits)
    assert r.position_excess == pytest.approx(0.5) and not r.ok()


def _cruise(n, v=1.0):
    """n samples of one joint moving at constant velocity v from 0 (period DT): q, qd of shape (n, 1)."""
    t = np.arange(n) * DT
    return (v * t)[:, None], np.full((n, 1), v)


def test_check_limits_finds_one_displaced_command():
    """A single command off the path by 10 periods of motion: its velocity is within the limit, only
    |Δq| to its neighbours shows the jump (in and out: two samples)."""
    limits = JointLimits([-1.0], [1.0], [1.0], [2.0], [10.0])
    q, qd = _cruise(50, 0.5)
    r = check_limits(q, qd, None, DT, limits)
    assert r.ok() and r.violations == 0 and r.fd_velocity_ratio == pytest.approx(0.5)
    q[20] += 0.01
    r = check_limits(q, qd, None, DT, limits)
    assert not r.ok() and r.violations == 2 and r.worst[:2] == ("fd_velocity", 19)
    assert r.fd_velocity_ratio == pytest.approx(10.5) and r.velocity_ratio == pytest.approx(0.5)
    # with the stream's stamps: the same jump, the same count
    r = check_limits(q, qd, None, DT, limits, t=np.arange(50) * DT)
    assert r.violations == 2 and r.fd_velocity_ratio == pytest.approx(10.5)


def test_check_limits_checks_across_gaps_by_their_length():
    """Samples 10..12 missing (a gap of 4 periods): at full speed 4 DT v_max of motion across it is
    within the limits; more is a jump, found although the samples on either side are fine. Without
    the times the gap would count as one period."""
    limits = JointLimits([-1.0], [1.0], [1.0], [2.0], [10.0])
    q, qd = _cruise(40, 1.0)
    t = np.arange(40) * DT
    keep = np.r_[0:10, 13:40]
    r = check_limits(q[keep], qd[keep], None, DT, limits, t=t[keep])
    assert r.ok() and r.violations == 0 and r.fd_velocity_ratio == pytest.approx(1.0)
    assert check_limits(q[keep], qd[keep], None, DT, limits).fd_velocity_ratio == pytest.approx(4.0)
    q[13:] += 0.002                                         # 6 DT v_max of motion in 4 periods
    r = check_limits(q[keep], qd[keep], None, DT, limits, t=t[keep])
    assert not r.ok() and r.violations == 1 and r.worst == ("fd_velocity", 9, 0)
    assert r.fd_velocity_ratio == pytest.approx(1.5)
    # a velocity change across the gap: a_max allows 4 DT a_max = 0.008 rad/s in 4 periods
    q, qd = _cruise(40, 0.5)
    qd[13:] += 0.008
    assert check_limits(q[keep], qd[keep], None, DT, limits, t=t[keep]).fd_acceleration_ratio == pytest.approx(1.0)
    qd[13:] += 0.004
    r = check_limits(q[keep], qd[keep], None, DT, limits, t=t[keep])
    assert r.fd_acceleration_ratio == pytest.approx(1.5) and r.violations >= 1 and not r.ok()
    with pytest.raises(ValueError, match="increase strictly"):
        check_limits(q[:3], qd[:3], None, DT, limits, t=[0.0, DT, DT])
    with pytest.raises(ValueError, match="one time per sample"):
        check_limits(q[:3], qd[:3], None, DT, limits, t=[0.0, DT])


def test_check_limits_without_accelerations_takes_the_jerk_between_one_period_intervals():
    """q = j t³ / 6 at the jerk limit, sampled with gaps: the mean accelerations of the one-period
    intervals differ by j_max times the distance of their midpoints, across gaps too, so the jerk
    ratio is exactly 1; 1 % more jerk is a violation at the end of every one-period interval but
    the first."""
    limits = JointLimits([-1.0], [1.0], [1.0], [2.0], [10.0])
    t = np.r_[0:10, 13:20, 21:30, 35:40] * DT               # 27 one-period intervals, 3 gaps
    for j, ok in ((10.0, True), (10.1, False)):
        q, qd = (j * t ** 3 / 6)[:, None], (j * t ** 2 / 2)[:, None]
        r = check_limits(q, qd, None, DT, limits, t=t)
        assert r.jerk_ratio == pytest.approx(j / 10.0, rel=1e-9) and r.ok() == ok
        assert r.violations == (0 if ok else 26)


def test_check_limits_accepts_a_skipped_tick_and_finds_a_jerk_across_it():
    """A tick that started late: the next command carries a stamp 2.5 periods later but one
    period of motion (the stream stretches in time). Position, velocity and acceleration keep their
    limits over the longer interval, and the one-period intervals on either side of it show no jerk
    (that interval's own mean acceleration drops without any jerk in the commands). An acceleration
    step across the same gap is a jerk violation."""
    limits = JointLimits([-1.0], [1.0], [1.0], [2.0], [10.0])

    def stream(acc):
        """40 commands, interval i with acceleration acc[i] over one period of motion."""
        qd = np.r_[0.0, np.cumsum(acc * DT)]
        q = np.r_[0.0, np.cumsum(0.5 * (qd[:-1] + qd[1:]) * DT)]
        return q[:, None], qd[:, None]

    t = np.arange(40) * DT + np.where(np.arange(40) >= 20, 1.5 * DT, 0.0)  # samples 19 -> 20: 2.5 periods
    q, qd = stream(np.full(39, 1.5))
    r = check_limits(q, qd, None, DT, limits, t=t)
    assert r.ok() and r.violations == 0 and r.jerk_ratio == pytest.approx(0.0, abs=1e-6)
    assert r.fd_acceleration_ratio == pytest.approx(0.75)
    q, qd = stream(np.r_[np.full(19, 1.0), np.full(20, 1.3)])  # a step of 0.3 rad/s² at the gap
    r = check_limits(q, qd, None, DT, limits, t=t)
    assert r.worst[:2] == ("jerk", 18) and r.violations == 1 and not r.ok()
    assert r.jerk_ratio == pytest.approx(0.3 / (3.5 * DT) / 10.0)  # midpoints 3.5 periods apart
