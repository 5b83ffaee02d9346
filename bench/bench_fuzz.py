"""Fuzzer of primitive_server over real DDS: random and malformed requests from concurrent clients.

    python bench/bench_fuzz.py                  # full: 10 000 requests from 4 client processes
    python bench/bench_fuzz.py --quick          # 400 requests from 2 clients (test/test_ros_fuzz.py)
    python bench/bench_fuzz.py --seed 3 --requests 20000 --clients 4 --param fast_path:=false

Processes: sim_bridge (PyBullet Gen3 lite, camera off), primitive_server (and its control process)
serving the shipped ``models/gen3_lite_reach.safetensors`` as ``reach`` and an untrained rhythmic
6-joint primitive ``wave`` that takes 24x32 images (written here, so the image checks and
``cycles`` are reached), the client processes, and this orchestrator.

Each client (its own process and DDS participant, seeded with ``--seed`` and its index) sends its
share of the requests one after the other, as fast as they are answered, over every service
(Condition, Blend, Sample, ListPrimitives, SetPhaseRate) and the Execute action (goals that run,
are left to be preempted by the next goal of any client, have their phase rate changed, or are
canceled, at once or later, and cancels of finished goals). About a third of the requests are well formed (they give the handles
the others use); the rest break one or more fields: NaN / inf / huge / subnormal values, wrong
lengths, empty and 10 000-element arrays, phases outside [0, 1], unknown primitives and handles,
4-billion counts (uint32 max), images of the wrong size, step, data length and encoding, joint
masks of the wrong length, negative or NaN weights, contradictory timing. The largest requests the
server's shipped limits accept (:data:`LIMITS`: max_via_points via-points and blending knots,
max_preview_points preview points, max_sample_points sample points) are in the mix too, and so is
refinement with 10 000 iterations (ended by refine_time_budget), and so are blends of blends. At the end every client cancels its goals
that still run and waits for their results.

The clients are planners that do not lose answers on their side: before the run each has had one
answer from every service and one Execute result (a response sent before the server has discovered
the client's response reader is lost), and each of its service clients keeps 100 responses
(rmw_fastrtps sends every response of a service to every client of it; with the default 10, a client
lost responses among the other clients'). An answer that does not come is then not the client's doing.

Every answer is classified (:func:`classify`): ``ok`` (success and code SUCCESS), ``refused``
(success false with a code and a message), ``internal_error`` (code INTERNAL_ERROR: an exception
the server did not expect), ``no_message`` (a refusal with an empty message, a code SUCCESS with
success false or the reverse, a goal rejected without a result) or ``unanswered`` (no response
within ``--timeout`` s; for a goal: no acceptance or no result).

Figures (last line):

* ``fuzz_requests`` -- requests sent (service calls, goals, cancels);
* ``fuzz_unanswered`` -- of them not answered within the timeout (target 0);
* ``fuzz_crashes`` -- processes not alive at the end (sim_bridge, primitive_server, its control
  process; a restarted control process counts) plus failed final checks: afterwards a well-formed
  Condition must succeed with a full preview and an Execute of its handle must succeed (target 0);
* ``fuzz_no_message`` -- refusals without a code and a message (target 0);
* ``fuzz_internal_errors`` -- answers with code INTERNAL_ERROR (target 0);
* ``fuzz_longest_answer_s`` -- the longest time an answered request waited for its answer (a goal:
  for its acceptance), queueing behind the other clients' requests included;
* ``fuzz_wall_s``, ``fuzz_requests_per_s`` -- wall-clock time of the clients' run and its throughput.
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import pathlib
import re
import signal
import sys
import tempfile
import time
from typing import Any

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from bench.bench_ros import min_duration  # noqa: E402  (ROS-free, as this module: the test imports it)
from deepprompt_ros.common.results import Code  # noqa: E402
from deepprompt_ros.server.config import ServerConfig  # noqa: E402

#: the server's request limits: its defaults (a --param that changes one is not known to the clients)
LIMITS = ServerConfig()

SERVER = "/primitive_server"
NAN, INF = float("nan"), float("inf")
UINT32_MAX = 2**32 - 1
INT64_MIN, INT64_MAX = -2**63, 2**63 - 1
#: values that are not a usable number (or not a sane one) for any float field
BAD_FLOATS = (NAN, INF, -INF, 1e308, -1e308, 5e-324, -5e-324, 1e19, -1e19)
#: the image primitive written by this benchmark: (height, width)
WAVE_IMAGE = (24, 32)

OUTCOMES = ("ok", "refused", "internal_error", "no_message", "unanswered")


# ------------------------------------------------------------------------------------------------
# classification and figures (pure, unit-tested in test/test_ros_fuzz.py)
# ------------------------------------------------------------------------------------------------
def classify(answered: bool, success: bool | None = None, code: int | None = None, message: str = "") -> str:
    """The outcome of one request, one of :data:`OUTCOMES`.

    Parameters
    ----------
    answered : bool
        A response (for a goal: its result) arrived within the timeout.
    success, code, message
        The response's ``success``, ``code.value`` and ``message``.
    """
    if not answered:
        return "unanswered"
    if success is None or code is None or bool(success) != (int(code) == Code.SUCCESS):
        return "no_message"  # success and code disagree: a refusal that says SUCCESS, or the reverse
    if success:
        return "ok"
    if not str(message).strip():
        return "no_message"
    if int(code) == Code.INTERNAL_ERROR:
        return "internal_error"
    return "refused"


def figures(records, crashes: int, wall_s: float) -> dict:
    """The last line's figures from the clients' records (dicts with at least ``outcome``)."""
    counts = collections.Counter(r["outcome"] for r in records)
    unknown = set(counts) - set(OUTCOMES)
    if unknown:
        raise ValueError(f"records with unknown outcomes {sorted(unknown)}; expected one of {OUTCOMES}")
    n = len(records)
    longest = max((r["answer_s"] for r in records if r["outcome"] != "unanswered" and "answer_s" in r), default=0.0)
    return dict(fuzz_requests=n, fuzz_unanswered=counts["unanswered"], fuzz_crashes=int(crashes),
                fuzz_no_message=counts["no_message"], fuzz_internal_errors=counts["internal_error"],
                fuzz_longest_answer_s=float(longest), fuzz_wall_s=float(wall_s),
                fuzz_requests_per_s=float(n / wall_s) if wall_s > 0 else 0.0)


# ------------------------------------------------------------------------------------------------
# requests
# ------------------------------------------------------------------------------------------------
class Factory:
    """Random requests, well formed or broken, from a seeded generator.

    Parameters
    ----------
    rng : numpy Generator
    primitives : list of deepprompt_msgs/PrimitiveInfo (from ListPrimitives)
    home : array, shape (d,), a configuration inside the limits (via-points scatter around it)
    prior_durations : mapping primitive -> float
        Shortest duration (s) the velocity limits allow for each primitive's prior mean.

    Each builder returns ``(request, note)``; ``note`` names the broken fields ('' = none broken).

    Goal timing is relative to the handle's shortest duration (from the preview its Condition or Blend
    answer carried, else its primitive's prior): a well-formed duration or phase rate is 1.2-3 times
    slower than that, so such goals are mostly executable (a coarse preview misses some peaks); a
    broken one may be twice too fast (refused: LIMIT_VIOLATION), out of range or contradictory.
    SetPhaseRate is relative to the handle the client names (the one of its goals it believes is
    running, see Client.call; another client's goal may have preempted it): a well-formed rate is 0
    (hold) or, either way, 0.1-1 times the largest rate that handle's shortest duration allows; a
    broken one is twice that (refused: LIMIT_VIOLATION) or not a usable number.
    """

    P_VALID = 0.35   # share of requests built without breaking any field
    P_BREAK = 0.35   # per field of a broken request: the chance it is broken

    def __init__(self, rng, primitives, home, prior_durations):
        self.rng = rng
        self.prims = {p.name: p for p in primitives}
        self.home = np.asarray(home, dtype=np.float64)
        self.handles: dict[str, list[str]] = collections.defaultdict(list)  # primitive -> handles issued
        self.prior_durations = dict(prior_durations)
        self.durations: dict[str, float] = {}  # handle -> its shortest duration (s), where its preview told
        self._breaking = False
        self._notes: list[str] = []

    # -- helpers -----------------------------------------------------------------------------------
    def _start(self) -> None:
        self._breaking = self.rng.random() > self.P_VALID
        self._notes = []

    def _note(self) -> str:
        n = self._notes
        return "; ".join(n[:8]) + (f"; ... {len(n) - 8} more" if len(n) > 8 else "")

    def _break(self, field: str, p: float | None = None) -> bool:
        """True when ``field`` is to be broken in this request (then noted by the caller)."""
        return self._breaking and self.rng.random() < (self.P_BREAK if p is None else p)

    def _pick(self, values):
        return values[int(self.rng.integers(len(values)))]

    def _bad(self, field: str, values):
        v = self._pick(values)
        self._notes.append(f"{field}={_short(v)}")
        return v

    def _floats(self, field: str, good: np.ndarray, long: bool = True) -> list:
        """``good`` (n,), or a copy with a wrong length (10 000 values only if ``long``) or with
        non-finite / huge entries."""
        vals = np.asarray(good, dtype=np.float64).copy()
        if self._break(field + " length", 0.15):
            n = int(self._pick((0, max(vals.size - 1, 0), vals.size + 1) + ((10000,) if long else ())))
            self._notes.append(f"len({field})={n}")
            vals = self.rng.normal(0.0, 1.0, n)
        if vals.size and self._break(field + " values", 0.2):
            k = int(self.rng.integers(vals.size))
            vals[k] = self._bad(f"{field}[{k}]", BAD_FLOATS)
        return vals.tolist()

    def _name(self) -> str:
        if self._break("primitive", 0.2):
            return self._bad("primitive", ("", "unknown", "reach ", "REACH", "réach✓", "x" * 10000, "../reach",
                                           "reach\n", "*"))
        return self._pick(sorted(self.prims))

    def _handle(self, primitive: str | None = None, field: str = "handle") -> str:
        pool = self.handles.get(primitive, []) if primitive else [h for v in self.handles.values() for h in v]
        if not pool or self._break(field, 0.3):
            v = self._pick(("", "reach-1-000000", "reach-999999999-abcdef", "h" * 10000, "wave-3-zzzzzz", " ",
                            "reach-1-000000\x7f"))
            self._notes.append(f"{field}={_short(v)}")
            return v
        return pool[int(self.rng.integers(max(0, len(pool) - 8), len(pool)))]  # one of the latest

    def _count(self, field: str, good, bad, heavy=()) -> int:
        """A uint32 count: one of ``good``, rarely one of ``heavy`` (valid but costly), or (broken)
        one of ``bad`` (uint32 max among them)."""
        if self._break(field, 0.25):
            return int(self._bad(field, bad))
        if heavy and self.rng.random() < 0.02:
            v = int(self._pick(heavy))
            self._notes.append(f"{field}={v} (heavy)")
            return v
        return int(self._pick(good))

    def remember(self, primitive: str, handle: str, duration: float | None = None) -> None:
        """Keep ``handle`` of ``primitive`` for later requests; ``duration``: its shortest (s), if known (0,
        a preview that does not move, tells nothing of the motion between its phases: not kept)."""
        if handle:
            self.handles[primitive].append(handle)
            for gone in self.handles[primitive][:-64]:
                self.durations.pop(gone, None)
            del self.handles[primitive][:-64]
            if duration is not None and duration > 0:
                self.durations[handle] = float(duration)

    def shortest_duration(self, handle: str) -> float:
        """The shortest duration (s) the velocity limits allow for ``handle``: from its preview, else its
        primitive's prior mean (a handle reads '<primitive>-...'), else the longest of the priors."""
        if handle in self.durations:
            return self.durations[handle]
        return self.prior_durations.get(handle.split("-", 1)[0], max(self.prior_durations.values()))

    # -- Condition ---------------------------------------------------------------------------------
    def condition(self):
        from deepprompt_msgs.msg import Context
        from deepprompt_msgs.srv import Condition

        self._start()
        name = self._name()
        info = self.prims.get(name) or self.prims[self._pick(sorted(self.prims))]
        d = len(info.joint_names)
        n = int(self._pick((0, 1, 1, 2, 3, 5, 5, 10, 30)))
        if self._break("via_points count", 0.1):
            n = int(self._bad("len(via_points)", (LIMITS.max_via_points + 1, 10000)))
        elif self.rng.random() < 0.01:
            n = LIMITS.max_via_points
            self._notes.append(f"len(via_points)={n} (heavy)")
        # at most 30 distinct via-points; a longer list repeats them (building 10 000 distinct messages
        # in Python would take longer than the server takes to refuse them)
        distinct = [self._via_point(f"vp{i}", d, long=n <= 30) for i in range(min(n, 30))]
        vps = [distinct[i % len(distinct)] for i in range(n)]
        contexts = []
        for modality, dim in zip(info.context_modalities, info.context_dims):
            if self.rng.random() < 0.6:
                c = Context(modality=modality, values=self._floats(f"{modality}.values",
                                                                   self.rng.uniform(-0.3, 0.3, int(dim))))
                if self.rng.random() < 0.2:
                    c.use_weight, c.weight = True, float(self.rng.uniform(0.0, 2.0))
                    if self._break(f"{modality}.weight", 0.3):
                        c.weight = float(self._bad(f"{modality}.weight", (-1.0, NAN, INF, -INF)))
                contexts.append(c)
        if info.accepts_images and self.rng.random() < 0.7:
            contexts.append(self._image_context(info))
        if self._break("contexts", 0.15):
            kind = self._bad("contexts", ("duplicate", "unknown modality", "empty modality", "65 contexts",
                                          "image on a primitive without images", "images on a vector modality"))
            if kind == "duplicate" and contexts:
                contexts.append(contexts[0])
            elif kind == "unknown modality":
                contexts.append(Context(modality="colour", values=[1.0]))
            elif kind == "empty modality":
                contexts.append(Context(modality="", values=[]))
            elif kind == "65 contexts":
                contexts += [Context(modality=f"m{i}", values=[0.0]) for i in range(65)]
            elif kind == "image on a primitive without images" and not info.accepts_images:
                contexts.append(self._image_context(info, force_shape=WAVE_IMAGE))
            elif kind == "images on a vector modality" and info.context_modalities:
                contexts.append(Context(modality=info.context_modalities[0], values=[0.0] * int(info.context_dims[0]),
                                        images=[self._image(*WAVE_IMAGE, "rgb8")]))
        req = Condition.Request(primitive=name, via_points=vps, contexts=contexts)
        req.refine = bool(self.rng.random() < 0.3)
        req.refine_max_iterations = self._count("refine_max_iterations", (0, 0, 0, 1, 5, 50), (10001, UINT32_MAX),
                                                (10000,))
        if self._break("refine_tolerance", 0.15):
            req.refine_tolerance = float(self._bad("refine_tolerance", (NAN, INF, -INF, -1.0, 1e308, 5e-324)))
        else:
            req.refine_tolerance = float(self._pick((0.0, 0.0, 1e-3, 1e-6)))
        req.preview_points = self._count("preview_points", (0, 2, 50, 100, 1000), (1, 10001, UINT32_MAX), (10000,))
        return req, self._note()

    def _via_point(self, where: str, d: int, long: bool = True):
        """One via-point; ``long``: its arrays may have 10 000 entries (not in a list that repeats it)."""
        from deepprompt_msgs.msg import ViaPoint

        phase = float(self.rng.uniform(0.0, 1.0))
        if self._break(where + " phase", 0.1):
            phase = float(self._bad(f"{where}.phase", (-0.5, 1.5, -1e-9, 1.0 + 1e-9, NAN, INF, -INF, 1e308)))
        m = ViaPoint(phase=phase, positions=self._floats(f"{where}.positions",
                                                         self.home[:d] + self.rng.normal(0.0, 0.1, d), long))
        if self._break(where + " joint_mask", 0.1):
            n = int(self._bad(f"len({where}.joint_mask)", (1, d - 1, d + 1) + ((10000,) if long else ())))
            m.joint_mask = (self.rng.random(n) < 0.5).tolist()
        elif self.rng.random() < 0.2:
            mask = self.rng.random(d) < 0.6
            if self._breaking and self.rng.random() < 0.2:
                mask[:] = False
                self._notes.append(f"{where}.joint_mask all false")
            m.joint_mask = mask.tolist()
        if self.rng.random() < 0.2:
            m.use_weight, m.weight = True, float(self.rng.choice((0.0, 0.5, 1.0, 3.0)))
            if self._break(where + " weight", 0.3):
                m.weight = float(self._bad(f"{where}.weight", (-1.0, -1e-300, NAN, INF, -INF, 1e308)))
        return m

    def _image(self, h: int, w: int, encoding: str):
        from sensor_msgs.msg import Image

        ch = 4 if encoding in ("rgba8", "bgra8") else 3
        img = Image(height=h, width=w, encoding=encoding, step=w * ch)
        img.data = self.rng.integers(0, 256, h * w * ch, dtype=np.uint8).tobytes()
        return img

    def _image_context(self, info, force_shape=None):
        from deepprompt_msgs.msg import Context

        h, w = force_shape or (int(info.image_height), int(info.image_width))
        n = int(self._pick((1, 1, 2, 3)))
        if self._break("images count", 0.1):
            n = int(self._bad("len(images)", (0, 17, 100)))
        images = []
        for i in range(n):
            enc = self._pick(("rgb8", "rgb8", "bgr8", "rgba8", "bgra8"))
            img = self._image(h, w, enc) if n <= 17 else self._image(1, 1, "rgb8")
            if self._break(f"image{i}", 0.3):
                what = self._bad(f"image{i}", ("encoding", "size", "huge header", "step", "data", "big"))
                if what == "encoding":
                    img.encoding = self._bad("encoding", ("mono8", "", "RGB8 ", "rgb16", "16UC3", "jpeg", "x" * 1000))
                elif what == "size":
                    img = self._image(h + int(self._pick((-1, 1))), w, "rgb8")
                elif what == "huge header":
                    img.height, img.width, img.step = UINT32_MAX, UINT32_MAX, UINT32_MAX
                elif what == "step":
                    img.step = int(self._pick((0, img.step - 1, img.step + 1, UINT32_MAX)))
                elif what == "data":
                    img.data = bytes(int(self._pick((0, 1, h * w * 3 - 1, h * w * 3 + 1, 10000))))
                else:
                    img = self._image(480, 640, "rgb8")
            images.append(img)
        c = Context(modality="image", images=images)
        if self._break("image values", 0.1):
            c.values = [0.0] * int(self._bad("len(image values)", (1, 3, 10000)))
        if self.rng.random() < 0.2:
            c.use_weight, c.weight = True, float(self.rng.uniform(0.0, 2.0))
            if self._break("image weight", 0.3):
                c.weight = float(self._bad("image.weight", (-1.0, NAN, INF)))
        return c

    # -- Blend -------------------------------------------------------------------------------------
    def blend(self):
        from deepprompt_msgs.srv import Blend

        self._start()
        prim = self._pick(sorted(self.prims))
        req = Blend.Request(handle_a=self._handle(prim, "handle_a"), handle_b=self._handle(prim, "handle_b"))
        if self._break("handle_b other primitive", 0.1) and len(self.prims) > 1:
            other = [p for p in self.prims if p != prim]
            req.handle_b = self._handle(self._pick(other), "handle_b")
            self._notes.append("handle_b of another primitive")
        if self.rng.random() < 0.5:
            m = int(self._pick((1, 2, 3, 5)))
            x = np.sort(self.rng.uniform(0.0, 1.0, m))
            w = self.rng.uniform(0.0, 1.0, m)
            if self._break("schedule", 0.5):
                kind = self._bad("schedule", ("unsorted", "duplicate phase", "NaN phase", "weight > 1",
                                              "negative weight", "phase > 1", "lengths differ",
                                              f"{LIMITS.max_via_points + 1} knots", "10000 knots", "inf weight"))
                if kind == "unsorted" and m > 1:
                    x = x[::-1]
                elif kind == "duplicate phase" and m > 1:
                    x[1] = x[0]
                elif kind == "NaN phase":
                    x[0] = NAN
                elif kind == "weight > 1":
                    w[0] = 1.5
                elif kind == "negative weight":
                    w[-1] = -0.1
                elif kind == "phase > 1":
                    x[-1] = 2.0
                elif kind == "lengths differ":
                    w = np.append(w, 0.5)
                elif kind.endswith(" knots"):
                    k = int(kind.split()[0])
                    x, w = np.linspace(0.0, 1.0, k), self.rng.uniform(0.0, 1.0, k)
                else:
                    w[0] = INF
            elif self.rng.random() < 0.04:
                m = LIMITS.max_via_points
                x, w = np.linspace(0.0, 1.0, m), self.rng.uniform(0.0, 1.0, m)
                self._notes.append(f"{m} knots (heavy)")
            req.schedule_phases, req.schedule_weights = x.tolist(), w.tolist()
        req.preview_points = self._count("preview_points", (0, 2, 50, 100), (1, 10001, UINT32_MAX), (10000,))
        req.sample = bool(self.rng.random() < 0.5)
        req.seed = int(self._pick((0, 1, 42, INT64_MIN, INT64_MAX, -1)))
        return req, self._note()

    # -- Sample ------------------------------------------------------------------------------------
    def sample(self):
        from deepprompt_msgs.srv import Sample

        self._start()
        req = Sample.Request()
        if self.rng.random() < 0.5:
            req.handle = self._handle()
        else:
            req.primitive = self._name()
            if self._break("both handle and primitive", 0.2):
                req.handle = self._handle()
                self._notes.append("handle and primitive both set")
        req.n_samples = self._count("n_samples", (0, 1, 2, 5, 20), (LIMITS.max_samples + 1, UINT32_MAX),
                                    (LIMITS.max_samples,))
        req.n_points = self._count("n_points", (0, 2, 50, 100), (1, LIMITS.max_preview_points + 1, UINT32_MAX),
                                   (1000, LIMITS.max_preview_points))
        if not self._breaking and self.rng.random() < 0.03:  # the most points the server decodes for one request
            s = int(self._pick((LIMITS.max_samples, LIMITS.max_sample_points // LIMITS.max_preview_points)))
            req.n_samples, req.n_points = s, LIMITS.max_sample_points // s
            self._notes.append(f"n_samples x n_points = {s} x {req.n_points} (heavy)")
        req.seed = int(self._pick((0, 7, INT64_MIN, INT64_MAX, -1)))
        return req, self._note()

    # -- SetPhaseRate ------------------------------------------------------------------------------
    def set_phase_rate(self, running: str | None = None):
        """``running``: the handle of the goal whose rate is to change (None: the slowest prior's)."""
        from deepprompt_msgs.srv import SetPhaseRate

        self._start()
        shortest = self.shortest_duration(running) if running is not None else max(self.prior_durations.values())
        if self.rng.random() < 0.1:
            rate = 0.0  # hold the phase
        else:  # backward a quarter of the time
            rate = float(self.rng.uniform(0.1, 1.0)) / shortest * (-1.0 if self.rng.random() < 0.25 else 1.0)
        if self._break("phase_rate", 0.6):
            if self.rng.random() < 0.2:
                rate = 2.0 / shortest * (-1.0 if self.rng.random() < 0.25 else 1.0)
                self._notes.append(f"phase_rate={rate:.3g} (twice too fast)")
            else:
                rate = float(self._bad("phase_rate", BAD_FLOATS + (101.0, -101.0, 100.0, -100.0)))
        return SetPhaseRate.Request(phase_rate=rate), self._note()

    # -- Execute -----------------------------------------------------------------------------------
    def goal(self):
        from deepprompt_msgs.action import Execute

        self._start()
        g = Execute.Goal(handle=self._handle())
        shortest = self.shortest_duration(g.handle)
        timing = self._pick(("duration", "duration", "phase_rate", "default"))
        if timing == "duration":
            g.duration = shortest * float(self.rng.uniform(1.2, 3.0))
        elif timing == "phase_rate":
            g.phase_rate = 1.0 / (shortest * float(self.rng.uniform(1.2, 3.0)))
        if self._break("timing", 0.4):
            kind = self._bad("timing", ("duration bad", "phase_rate bad", "both set", "too short", "too fast",
                                        "too long"))
            if kind == "duration bad":
                g.duration = float(self._bad("duration", BAD_FLOATS + (-1.0,)))
            elif kind == "phase_rate bad":
                g.phase_rate = float(self._bad("phase_rate", BAD_FLOATS + (-1.0,)))
            elif kind == "both set":
                g.duration, g.phase_rate = 1.0, 1.0
            elif kind == "too short":
                g.duration = float(self._pick((1e-9, 0.009, 0.05)))
            elif kind == "too fast":
                g.duration, g.phase_rate = 0.5 * shortest, 0.0
            else:
                g.duration = float(self._pick((86400.0, 86401.0, 1e9)))
        g.cycles = self._count("cycles", (0, 1, 2, 3), (100001, UINT32_MAX), (100000,))
        g.reverse = bool(self.rng.random() < 0.2)
        return g, self._note()


def _short(v: Any, n: int = 40) -> str:
    s = repr(v)
    return s if len(s) <= n else s[:n] + f"...({len(s)} chars)"


# ------------------------------------------------------------------------------------------------
# a client process
# ------------------------------------------------------------------------------------------------
class Client:
    """One client: its own DDS participant, a service client per service and an action client."""

    KINDS = ("condition", "blend", "sample", "list_primitives", "set_phase_rate", "goal", "cancel")
    WEIGHTS = (0.30, 0.12, 0.11, 0.05, 0.12, 0.20, 0.10)
    SPIN_ROUNDS = 4  # callbacks run between two requests (see collect)
    #: history depth of every service client (the five services; the action's goal, cancel and result
    #: services). rmw_fastrtps sends every response of a service to every client of it; each client's
    #: reader keeps the newest ``depth`` samples until its listener picks out its own. On the loaded
    #: machine the default depth (10) lost a few responses of one client among the other clients'
    #: (Execute results and a Condition response: a handful per 2 000 requests).
    RESPONSE_DEPTH = 100

    def __init__(self, seed, timeout: float):
        from deepprompt_msgs.action import Execute
        from deepprompt_msgs.srv import Blend, Condition, ListPrimitives, Sample, SetPhaseRate
        from rclpy.action import ActionClient
        from rclpy.qos import QoSProfile, qos_profile_services_default

        from deepprompt_ros.ros.testing import RosTestClient

        self.c = RosTestClient(dict(os.environ), f"fuzz_client_{os.getpid()}")
        svc = qos_profile_services_default
        deep = QoSProfile(history=svc.history, depth=self.RESPONSE_DEPTH, reliability=svc.reliability,
                          durability=svc.durability)
        self.ac = ActionClient(self.c.node, Execute, f"{SERVER}/execute", goal_service_qos_profile=deep,
                               result_service_qos_profile=deep, cancel_service_qos_profile=deep)
        self.services = {name: (srv, self.c.node.create_client(srv, f"{SERVER}/{name}", qos_profile=deep))
                         for name, srv in (("condition", Condition), ("blend", Blend), ("sample", Sample),
                                           ("list_primitives", ListPrimitives), ("set_phase_rate", SetPhaseRate))}
        self.rng = np.random.default_rng(seed)
        self.timeout = timeout
        self.records: list[dict] = []
        self.goals: list[dict] = []      # sent and accepted, result pending: {gh, fut, record}
        self.finished: list = []         # goal handles whose result arrived (for cancels of finished goals)
        self.factory: Factory | None = None
        self.primitives: dict = {}       # name -> deepprompt_msgs/PrimitiveInfo (ready)
        self.last_goal_handle: str | None = None  # the handle of this client's latest goal
        self.limits = None               # the Gen3 lite's JointLimits under the default ServerConfig (ready)

    def ready(self, timeout: float) -> bool:
        from deepprompt_msgs.srv import Condition

        from deepprompt_ros.robots.spec import load_robot
        from deepprompt_ros.server.config import robot_limits

        deadline = time.monotonic() + timeout
        if not self.c.wait_for(lambda: self.ac.server_is_ready() and all(
                cli.service_is_ready() for _, cli in self.services.values()), timeout):
            return False
        if not self._warm_up(deadline):
            return False
        res = self._call("list_primitives", None, timeout)
        self.primitives = {p.name: p for p in res.primitives}
        self.limits = robot_limits(load_robot("gen3_lite"), LIMITS)
        prior = {}
        for name in self.primitives:  # each prior mean on the execution grid (not counted as a request)
            r = self._call("condition", Condition.Request(primitive=name, preview_points=LIMITS.execution_grid_points),
                           timeout)
            if not r.success:
                raise RuntimeError(f"bench_fuzz client: Condition of '{name}' with no input failed: {r.message}")
            prior[name] = self.shortest_duration(name, r.preview)
        self.factory = Factory(self.rng, list(res.primitives), load_robot("gen3_lite").home, prior)
        return True

    def shortest_duration(self, primitive: str, preview) -> float | None:
        """The shortest duration (s) the velocity limits allow for the trajectory of ``preview`` (an answer's
        deepprompt_msgs/Preview of ``primitive``); None if it has fewer than 3 phases."""
        if preview.n_points < 3 or primitive not in self.primitives:
            return None
        periodic = self.primitives[primitive].phase_type == "rhythmic"
        return min_duration(preview, self.limits, LIMITS, periodic)

    def _warm_up(self, deadline: float) -> bool:
        """One answer from every service and one Execute result (a goal with no handle), each tried
        again until it comes. A client that has discovered a service can call it before the server
        has discovered the client's response reader, and that response is lost (the first goals of a
        client got no result in a run without this); requests before the run starts are not counted."""
        from deepprompt_msgs.action import Execute

        for kind in self.services:
            while True:
                try:
                    self._call(kind, None, 5.0)
                    break
                except TimeoutError:
                    if time.monotonic() > deadline:
                        return False
        while time.monotonic() < deadline:
            fut = self.ac.send_goal_async(Execute.Goal())
            if self.c.wait_for(fut.done, 5.0) and fut.result().accepted:
                res = fut.result().get_result_async()
                if self.c.wait_for(res.done, 5.0):
                    return True
        return False

    def _record(self, kind: str, note: str, outcome: str, t0: float, code=None, message: str = "",
                answer_s: float | None = None) -> dict:
        """``seconds``: from sending to now (a goal: to its result); ``answer_s``: to its answer (a goal:
        to its acceptance; default ``seconds``)."""
        seconds = time.perf_counter() - t0
        rec = dict(kind=kind, outcome=outcome, code=None if code is None else int(code),
                   message=str(message)[:400], note=note[:400], seconds=seconds,
                   answer_s=seconds if answer_s is None else float(answer_s))
        self.records.append(rec)
        return rec

    def _call(self, kind: str, request, timeout: float):
        """Call service ``kind`` (its default request if None); TimeoutError without an answer."""
        srv, cli = self.services[kind]
        fut = cli.call_async(srv.Request() if request is None else request)
        if not self.c.wait_for(fut.done, timeout):
            raise TimeoutError(f"{kind}: no response within {timeout:g} s")
        return fut.result()

    def call(self, kind: str) -> None:
        f = self.factory
        build = {"condition": f.condition, "blend": f.blend, "sample": f.sample,
                 "list_primitives": lambda: (None, ""),
                 "set_phase_rate": lambda: f.set_phase_rate(self.running_handle())}[kind]
        req, note = build()
        t0 = time.perf_counter()
        try:
            res = self._call(kind, req, self.timeout)
        except TimeoutError:
            self._record(kind, note, "unanswered", t0)
            return
        self._record(kind, note, classify(True, res.success, res.code.value, res.message), t0, res.code.value,
                     res.message)
        if kind in ("condition", "blend") and res.handle:
            primitive = req.primitive if kind == "condition" else req.handle_a.split("-", 1)[0]
            f.remember(primitive, res.handle, self.shortest_duration(primitive, res.preview))

    def running_handle(self) -> str | None:
        """The handle of this client's latest goal whose result has not come (else of its latest goal;
        None before the first)."""
        running = [g for g in self.goals if not g["fut"].done()]
        return running[-1]["handle"] if running else self.last_goal_handle

    def send_goal(self) -> None:
        goal, note = self.factory.goal()
        self.last_goal_handle = goal.handle
        t0 = time.perf_counter()
        fut = self.ac.send_goal_async(goal)
        if not self.c.wait_for(fut.done, self.timeout):
            self._record("goal", note, "unanswered", t0, message="no goal response")
            return
        gh = fut.result()
        accept_s = time.perf_counter() - t0
        if not gh.accepted:
            self._record("goal", note, "no_message", t0, message="goal rejected (a rejection carries no message)")
            return
        self.goals.append(dict(gh=gh, fut=gh.get_result_async(), note=note, t0=t0, accept_s=accept_s, wall=time.time(),
                               cancel_sent=None, handle=goal.handle))
        r = self.rng.random()
        if r < 0.15:  # cancel at once
            self.cancel(self.goals[-1])
        elif r < 0.3:  # let it run a little, then cancel
            self.c.spin_for(float(self.rng.uniform(0.05, 0.5)))
            self.cancel(self.goals[-1])
        elif r < 0.45:  # let it run a little, then change its rate (a request of its own)
            self.c.spin_for(float(self.rng.uniform(0.05, 0.5)))
            self.call("set_phase_rate")

    def cancel(self, entry=None) -> None:
        """Cancel one of this client's goals (running or, sometimes, already finished)."""
        if entry is None:
            running = [g for g in self.goals if not g["fut"].done()]
            if running and self.rng.random() < 0.8:
                entry = running[int(self.rng.integers(len(running)))]
            elif self.finished:
                gh = self.finished[int(self.rng.integers(len(self.finished)))]
                entry = dict(gh=gh, note="finished goal", cancel_sent=None)
            else:
                return self.call("list_primitives")
        t0 = time.perf_counter()
        fut = entry["gh"].cancel_goal_async()
        entry["cancel_sent"] = time.monotonic()
        answered = self.c.wait_for(fut.done, self.timeout)
        # a cancel response carries a return code and no message: answered is what is checked here
        self._record("cancel", "cancel " + ("finished goal" if entry.get("note") == "finished goal" else "goal"),
                     "ok" if answered else "unanswered", t0, message="" if answered else "no cancel response")

    def collect(self, final: bool = False) -> None:
        """Record the goals whose result arrived; ``final``: cancel the others and wait for theirs.

        The executor first runs a few callbacks with no wait: a client that spins only while it waits
        for a service response takes that response first (rclpy runs ready service clients before the
        action client's waitable) and lets its goal results, feedback and status messages queue up."""
        for _ in range(self.SPIN_ROUNDS):
            self.c.executor.spin_once(timeout_sec=0.0)
        if final:
            for g in self.goals:
                if not g["fut"].done() and g["cancel_sent"] is None:
                    g["gh"].cancel_goal_async()
                    g["cancel_sent"] = time.monotonic()
            self.c.wait_for(lambda: all(g["fut"].done() for g in self.goals), self.timeout)
        pending = []
        for g in self.goals:
            if g["fut"].done():
                res = g["fut"].result().result
                self._record("goal", g["note"], classify(True, res.success, res.code.value, res.message), g["t0"],
                             res.code.value, res.message, answer_s=g["accept_s"])
                self.finished.append(g["gh"])
                del self.finished[:-32]
            elif final:
                self._record("goal", g["note"], "unanswered", g["t0"], answer_s=g["accept_s"], message=(
                    f"no result {self.timeout:g} s after the cancel; goal {bytes(g['gh'].goal_id.uuid).hex()} "
                    f"sent at {g['wall']:.3f}, its last status {g['gh'].status}"))
            else:
                pending.append(g)
        self.goals = [] if final else pending

    def run(self, n: int) -> None:
        kinds = self.rng.choice(len(self.KINDS), size=n, p=self.WEIGHTS)
        for k in kinds:
            kind = self.KINDS[int(k)]
            if kind == "goal":
                self.send_goal()
            elif kind == "cancel":
                self.cancel()
            else:
                self.call(kind)
            self.collect()
        self.collect(final=True)

    def close(self) -> None:
        self.ac.destroy()
        self.c.close()


_PARENT = os.getppid()


def _wait_file(path: pathlib.Path, timeout: float = 600.0) -> None:
    end = time.monotonic() + timeout
    while not path.exists():
        if os.getppid() != _PARENT or time.monotonic() > end:
            raise SystemExit(f"bench_fuzz client: no {path.name} (the orchestrator is gone or stuck)")
        time.sleep(0.05)


def role_client(out: str, gate: str, n: int, seed, timeout: float) -> None:
    """Wait for the server, write <gate>.ready.<pid>, wait for <gate>.go, send ``n`` requests, write
    the records to ``out`` (JSON lines, written complete under a temporary name, then renamed)."""
    client = Client(seed, timeout)
    try:
        if not client.ready(120.0):
            raise SystemExit("bench_fuzz client: the server's services and action did not answer within 120 s")
        pathlib.Path(f"{gate}.ready.{os.getpid()}").write_text("ready")
        _wait_file(pathlib.Path(gate + ".go"))
        client.run(n)
        tmp = pathlib.Path(out + ".part")
        tmp.write_text("".join(json.dumps(r) + "\n" for r in client.records))
        tmp.replace(out)
    finally:
        client.close()


# ------------------------------------------------------------------------------------------------
# orchestrator
# ------------------------------------------------------------------------------------------------
def write_primitives(tmp: pathlib.Path) -> pathlib.Path:
    """A primitives file serving the shipped reach model as ``reach`` (with its shipped default_duration,
    config/primitives.yaml) and an untrained rhythmic image primitive ``wave`` (6 Gen3 lite joints, 24x32
    images, a few mrad around home)."""
    import torch
    import yaml

    from deepprompt_ros import paths
    from deepprompt_ros.model.checkpoint import Normalization, save_checkpoint
    from deepprompt_ros.model.network import DeepProMPNet, ModelConfig
    from deepprompt_ros.robots.spec import load_robot

    spec = load_robot("gen3_lite")
    torch.manual_seed(0)
    net = DeepProMPNet(ModelConfig(n_joints=len(spec.joint_names), phase_type="rhythmic", latent_dim=4, hidden=16,
                                   image_shape=WAVE_IMAGE))
    wave = save_checkpoint(tmp / "wave.safetensors", net,
                           Normalization(np.asarray(spec.home, dtype=np.float64), np.full(len(spec.joint_names), 0.02)),
                           spec.joint_names)
    reach = paths.find_data_file("models", "gen3_lite_reach.safetensors")
    shipped = yaml.safe_load(paths.find_data_file("config", "primitives.yaml").read_text())["primitives"]
    default = next(p for p in shipped if p["name"] == "reach").get("default_duration", 0.0)
    f = tmp / "primitives.yaml"
    f.write_text(f"primitives:\n  - name: reach\n    model: {reach}\n    default_duration: {default}\n"
                 f"  - name: wave\n    model: {wave}\n    default_duration: 2.0\n")
    return f


def final_checks(c, ac, home) -> list[str]:
    """A well-formed Condition and an Execute of its handle (1.3 times slower than the shortest duration
    its preview allows); the list of what went wrong ([] = fine)."""
    from deepprompt_msgs.action import Execute
    from deepprompt_msgs.msg import Context
    from deepprompt_msgs.srv import Condition, ListPrimitives

    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.ros import conversions as conv
    from deepprompt_ros.server.config import robot_limits

    problems = []
    try:
        lp = c.call(ListPrimitives, f"{SERVER}/list_primitives", timeout=30.0)
        if not lp.success or sorted(p.name for p in lp.primitives) != ["reach", "wave"]:
            problems.append(f"ListPrimitives: success {lp.success}, {[p.name for p in lp.primitives]}: {lp.message}")
        req = Condition.Request(primitive="reach", via_points=conv.via_points_to_msgs([1.0], [home + 0.05]),
                                contexts=[Context(modality="object", values=[0.4, 0.0, 0.1])],
                                preview_points=LIMITS.execution_grid_points)
        r = c.call(Condition, f"{SERVER}/condition", req, timeout=30.0)
        prev = conv.preview_from_msg(r.preview) if r.success else None
        if not (r.success and r.code.value == Code.SUCCESS and r.handle
                and prev.mean.shape == (LIMITS.execution_grid_points, 6) and np.all(np.isfinite(prev.mean))
                and r.refine_max_error < 0.5):
            problems.append(f"Condition: success {r.success}, code {r.code.value}, handle '{r.handle}': {r.message}")
            return problems
        duration = 1.3 * min_duration(r.preview, robot_limits(load_robot("gen3_lite"), LIMITS), LIMITS)
        fut = ac.send_goal_async(Execute.Goal(handle=r.handle, duration=duration))
        if not c.wait_for(fut.done, 30.0) or not fut.result().accepted:
            return problems + ["Execute: the goal was not accepted within 30 s"]
        res = fut.result().get_result_async()
        if not c.wait_for(res.done, duration + 60.0):
            return problems + [f"Execute: no result within {duration + 60.0:.0f} s"]
        out = res.result().result
        if not (out.success and out.code.value == Code.SUCCESS and abs(out.final_phase - 1.0) < 1e-6):
            problems.append(f"Execute: success {out.success}, code {out.code.value}, final phase "
                            f"{out.final_phase}: {out.message}")
    except TimeoutError as exc:
        problems.append(f"no answer: {exc}")
    return problems


def _alive(pid: int) -> bool:
    try:
        state = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def report(records, fig: dict, problems: list[str], header: str) -> None:
    """The table of outcomes per kind with the answer times (p50 and longest over the answered requests;
    a goal's: to its acceptance), the codes, the slowest answers, the examples of every bad outcome,
    the last line."""
    print(header)
    by_kind: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    answer = collections.defaultdict(list)
    for r in records:
        by_kind[r["kind"]][r["outcome"]] += 1
        if r["outcome"] != "unanswered":
            answer[r["kind"]].append(r["answer_s"])
    print(f"{'kind':16s} {'sent':>6s} " + " ".join(f"{o:>14s}" for o in OUTCOMES)
          + f" {'p50 ms':>8s} {'max ms':>8s}  (answered)")
    for kind in sorted(by_kind):
        cnt, s = by_kind[kind], np.array(answer[kind] or [np.nan]) * 1e3
        print(f"{kind:16s} {sum(cnt.values()):6d} " + " ".join(f"{cnt[o]:14d}" for o in OUTCOMES)
              + f" {np.percentile(s, 50):8.1f} {s.max():8.1f}")
    codes = collections.Counter(r["code"] for r in records if r["code"] is not None)
    names = {int(c): c.name for c in Code}
    print("codes: " + ", ".join(f"{names.get(k, k)} {v}" for k, v in sorted(codes.items())))
    slow = sorted((r for r in records if r["outcome"] != "unanswered"), key=lambda r: -r["answer_s"])[:5]
    print("slowest answers: " + "; ".join(f"{r['kind']} {r['answer_s']:.2f} s [{r['note'] or 'well formed'}]"
                                          for r in slow))
    for outcome in ("unanswered", "no_message", "internal_error"):
        bad = [r for r in records if r["outcome"] == outcome]
        for r in bad[:10]:
            print(f"{outcome}: {r['kind']} [{r['note'] or 'well formed'}] code {r['code']}: {r['message']!r}")
        if len(bad) > 10:
            print(f"{outcome}: ... {len(bad) - 10} more")
    for p in problems:
        print(f"crash: {p}")
    print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in fig.items()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="400 requests from 2 clients (the test's run)")
    ap.add_argument("--requests", type=int, help="total requests (default 10000; --quick 400)")
    ap.add_argument("--clients", type=int, help="client processes (default 4; --quick 2)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the clients' random requests (client i: seed, i)")
    ap.add_argument("--timeout", type=float, default=30.0, help="s a request may wait for its answer (default 30)")
    ap.add_argument("--param", action="append", default=[], help="extra primitive_server parameter name:=value")
    ap.add_argument("--role", choices=("client",), help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--gate", help=argparse.SUPPRESS)
    ap.add_argument("--index", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    n_total = args.requests or (400 if args.quick else 10000)
    n_clients = args.clients or (2 if args.quick else 4)
    if args.role == "client":
        signal.signal(signal.SIGINT, signal.default_int_handler)
        role_client(args.out, args.gate, args.requests, [args.seed, args.index], args.timeout)
        return 0

    from deepprompt_msgs.action import Execute
    from rclpy.action import ActionClient

    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.ros.testing import NodeProcess, RosTestClient, isolated_ros_env

    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="bench_fuzz_"))
    env = isolated_ros_env(tmp / "log")
    home = np.asarray(load_robot("gen3_lite").home, dtype=np.float64)
    procs, clients, problems = [], [], []
    t_start = time.monotonic()
    try:
        prim_file = write_primitives(tmp)
        sim = NodeProcess.start_module("deepprompt_ros.ros.sim_bridge", env, params={
            "camera.enabled": False, "publish_clock": False})
        procs.append(sim)
        # stale_timeout 1 s: on the loaded 2-core machine the Python sim can pause longer than the
        # 0.2 s default, and the final Execute must not end ROBOT_STATE_STALE for that
        ros_args = ["-p", f"primitives_file:={prim_file}", "-p", "stale_timeout:=1.0"]
        for p in args.param:
            ros_args += ["-p", p]
        server = NodeProcess.start_module("deepprompt_ros.ros.primitive_server", env, ros_args=ros_args)
        procs.append(server)
        gate = tmp / "gate"
        shares = [n_total // n_clients + (i < n_total % n_clients) for i in range(n_clients)]
        for i, n in enumerate(shares):
            cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--role", "client", "--out",
                   str(tmp / f"client{i}.jsonl"), "--gate", str(gate), "--requests", str(n), "--seed", str(args.seed),
                   "--index", str(i), "--timeout", str(args.timeout)]
            clients.append(NodeProcess(cmd, env, tmp / f"client{i}.log"))
        procs += clients
        with RosTestClient(env, "fuzz_orchestrator") as c:
            ac = ActionClient(c.node, Execute, f"{SERVER}/execute")
            if not c.wait_for(lambda: "receiving joint_states" in server.output(), 120):
                raise RuntimeError("primitive_server receives no joint_states:\n" + server.output_tail()
                                   + sim.output_tail())
            end = time.monotonic() + 180
            while len(list(tmp.glob("gate.ready.*"))) < n_clients:
                dead = [p for p in clients if not p.running()]
                if dead or time.monotonic() > end:
                    raise RuntimeError("a client did not start:\n" + "\n".join(p.output_tail() for p in clients))
                time.sleep(0.1)
            t0 = time.monotonic()
            pathlib.Path(str(gate) + ".go").write_text("go")
            outs = [tmp / f"client{i}.jsonl" for i in range(n_clients)]
            while not all(o.exists() for o in outs):
                failed = [p for p, o in zip(clients, outs) if not p.running() and not o.exists()]
                if failed:
                    raise RuntimeError("a client failed:\n" + "\n".join(p.output_tail() for p in failed))
                time.sleep(0.2)
            wall = time.monotonic() - t0
            records = [json.loads(line) for o in outs for line in o.read_text().splitlines()]
            # crashes: every process alive, the control process never restarted, a good request answered
            for name, p in (("sim_bridge", sim), ("primitive_server", server)):
                if not p.running():
                    problems.append(f"{name} exited with code {p.returncode}:\n{p.output_tail()}")
            log = server.output()
            child = re.findall(r"control loop running in its own process \(pid (\d+)\)", log)
            if child and not _alive(int(child[-1])):
                problems.append(f"the control process (pid {child[-1]}) is not running")
            for m in re.findall(r"[^\n]*control process \(pid \d+\) exited unexpectedly[^\n]*", log):
                problems.append(m.strip())
            if server.running():
                problems += final_checks(c, ac, home)
            ac.destroy()
    finally:
        NodeProcess.stop_all(procs)
    fig = figures(records, len(problems), wall)
    header = (f"primitive_server fuzzing ({'quick' if args.quick else 'full'}, seed {args.seed}, {n_clients} clients, "
              f"timeout {args.timeout:g} s, load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs, total "
              f"{time.monotonic() - t_start:.0f} s" + "".join(f", server {p}" for p in args.param)
              + f"; logs in {tmp})")
    report(records, fig, problems, header)
    return 0


if __name__ == "__main__":
    sys.exit(main())
