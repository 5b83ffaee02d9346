"""The primitive server's service logic, without ROS: conditioning, blending, sampling,
describing the loaded primitives and planning an Execute goal.

:class:`PrimitiveServerCore` takes the plain requests of :mod:`deepprompt_ros.server.requests`,
checks them (every invalid request raises
:class:`~deepprompt_ros.common.results.RequestError` with a code and an actionable message),
stores conditioned and blended distributions in the handle store
(:mod:`deepprompt_ros.server.handles`) and turns a handle into the
:class:`~deepprompt_ros.execution.plan.ExecutionPlan` the control loop runs.

One class slightly over 400 lines: its five operations share the request checks and the handle
store, and each is a short method over :mod:`~deepprompt_ros.primitive` operations.
"""
from __future__ import annotations

import math
from typing import Callable, Mapping, Sequence

import numpy as np

from deepprompt_ros.common.results import Code, RequestError
from deepprompt_ros.execution.limits import JointLimits
from deepprompt_ros.execution.plan import ExecutionPlan, ExecutionReference
from deepprompt_ros.server.config import ServerConfig
from deepprompt_ros.server.handles import (BlendedLatent, ConditionedLatent, HandleLimitError, HandleStore, Schedule,
                                           StoredDistribution, UnknownHandleError)
from deepprompt_ros.server.images import decode_image
from deepprompt_ros.server.primitives_file import LoadedPrimitive
from deepprompt_ros.server.requests import (BlendRequest, BlendResult, ConditionRequest, ConditionResult,
                                            ExecuteRequest, Preview, PrimitiveDescription, SampleRequest,
                                            SampleResult)

__all__ = ["PrimitiveServerCore"]


def _finite(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and math.isfinite(v)


class PrimitiveServerCore:
    """Conditioning, blending, sampling and execution planning on loaded primitives.

    Parameters
    ----------
    primitives : mapping name -> LoadedPrimitive
    config : ServerConfig
    limits : JointLimits
        The robot's limits, robot joint order (used by :meth:`plan_execution`).
    clock : callable () -> float
        Monotonic seconds, for handle expiry.
    """

    MAX_DURATION = 86400.0
    MIN_DURATION = 0.01

    def __init__(self, primitives: Mapping[str, LoadedPrimitive], config: ServerConfig, limits: JointLimits,
                 clock: Callable[[], float] | None = None):
        self.primitives = dict(primitives)
        self.config = config
        self.limits = limits
        kw = {} if clock is None else {"clock": clock}
        self.handles = HandleStore(config.max_handles, config.handle_ttl, config.evict_when_full, **kw)

    # ------------------------------------------------------------------ helpers
    def _primitive(self, name: str) -> LoadedPrimitive:
        prim = self.primitives.get(name)
        if prim is None:
            shown = name if len(name) <= 64 else name[:64] + "..."
            raise RequestError(Code.UNKNOWN_PRIMITIVE, f"unknown primitive '{shown}'; loaded primitives: "
                               f"{', '.join(sorted(self.primitives)) or '(none)'}")
        return prim

    def _handle(self, handle: str, field: str = "handle") -> StoredDistribution:
        try:
            return self.handles.get(handle)
        except UnknownHandleError as exc:
            raise RequestError(Code.UNKNOWN_HANDLE, f"{field}: {exc}") from None

    def _store(self, value: StoredDistribution) -> tuple[str, float]:
        try:
            return self.handles.put(value, prefix=value.primitive)
        except HandleLimitError as exc:
            raise RequestError(Code.HANDLE_LIMIT, str(exc)) from None

    def _n_points(self, n: int, field: str) -> int:
        if n == 0:
            return self.config.preview_points
        if n < 2 or n > self.config.max_preview_points:
            raise RequestError(Code.INVALID_REQUEST, f"{field} = {n}; expected 0 (server default "
                               f"{self.config.preview_points}) or 2..{self.config.max_preview_points} "
                               "(parameter max_preview_points)")
        return int(n)

    @staticmethod
    def _weight(use: bool, w: float, where: str, code: Code) -> float:
        if not use:
            return 1.0
        if not _finite(w) or w < 0:
            raise RequestError(code, f"{where}: weight {w!r} is invalid; expected a finite number >= 0 "
                               "(0 removes it, 1 is the default)")
        return float(w)

    def _decode(self, prim: LoadedPrimitive, dist: StoredDistribution, x: np.ndarray,
                eps: np.ndarray | None) -> np.ndarray:
        """Trajectory of ``dist`` at phases x (T,): z(x) = μ(x) + ε σ(x) (ε None -> 0), (T, d)."""
        if isinstance(dist, ConditionedLatent):
            return prim.model.decode_mean(dist.latent, x, eps)
        mean, var = dist.latent_at(x)
        z = mean if eps is None else mean + eps[None, :] * np.sqrt(var)
        return prim.model.decode_per_phase(z, x, self._mode_weights(prim, dist, x))

    @staticmethod
    def _mode_weights(prim: LoadedPrimitive, dist: StoredDistribution, x: np.ndarray) -> np.ndarray | None:
        """The weights (T, K) of a decoder's modes along a blend (None for one mode)."""
        if not prim.model.cfg.decoder_modes:
            return None
        return dist.mode_weights_at(x, prim.model.mode_weights)

    def _samples(self, prim: LoadedPrimitive, dist: StoredDistribution, x: np.ndarray, n: int,
                 seed: int) -> np.ndarray:
        """n trajectories, ONE ε per trajectory: shape (n, T, d)."""
        if isinstance(dist, ConditionedLatent) and (dist.latent.linear is not None or prim.model.cfg.decoder_modes):
            # the model's draws: a split latent's exact posterior; with several modes each z in the mode it chooses
            return prim.model.sample(dist.latent, x, n, seed)
        k, t = prim.model.latent_dim, x.shape[0]
        eps = np.random.default_rng(seed).standard_normal((n, k))
        mean, var = dist.latent_at(x)  # (T, k) each
        z = mean[None] + eps[:, None, :] * np.sqrt(var)[None]  # (n, T, k)
        # one (n T) x k matrix through the decoder: a single matrix product per layer (faster than
        # numpy's stacked 3-D matmul for these sizes)
        modes = self._mode_weights(prim, dist, x)
        y = prim.model.decode_per_phase(z.reshape(n * t, k), np.tile(x, n),
                                        None if modes is None else np.tile(modes, (n, 1)))
        return y.reshape(n, t, -1)

    def _preview(self, prim: LoadedPrimitive, dist: StoredDistribution, n_points: int) -> Preview:
        """Mean at n_points phases; std at preview_std_points phases (linearized, or from
        preview_std_samples trajectories with ONE z each), interpolated linearly onto the n_points."""
        x = np.linspace(0.0, 1.0, n_points)
        mean = self._decode(prim, dist, x, dist.eps)
        xs = np.linspace(0.0, 1.0, min(n_points, self.config.preview_std_points))
        if isinstance(dist, ConditionedLatent) and self.config.preview_std_method == "linearized":
            std_s = prim.model.linearized_std(dist.latent, xs)
        else:
            std_s = self._samples(prim, dist, xs, self.config.preview_std_samples, seed=0).std(axis=0)
        std = std_s if xs.size == n_points else np.stack(
            [np.interp(x, xs, std_s[:, j]) for j in range(std_s.shape[1])], axis=1)
        return Preview(prim.joint_names, x, mean, std)

    # ------------------------------------------------------------------ ListPrimitives
    def describe(self) -> list[PrimitiveDescription]:
        out = []
        for name in sorted(self.primitives):
            p = self.primitives[name]
            m = p.model
            img = m.image_shape
            out.append(PrimitiveDescription(
                name=name, joint_names=m.joint_names,
                position_lower=np.asarray(self.limits.lower)[p.robot_index],
                position_upper=np.asarray(self.limits.upper)[p.robot_index],
                phase_type=m.phase_type, context_modalities=tuple(m.context_dims),
                context_dims=tuple(int(v) for v in m.context_dims.values()),
                accepts_images=img is not None, image_height=int(img[0]) if img else 0,
                image_width=int(img[1]) if img else 0, image_encoding="rgb8" if img else "",
                latent_dim=m.latent_dim,
                description=p.entry.description or f"model {p.path.name}"))
        return out

    # ------------------------------------------------------------------ Condition
    def check_condition_sizes(self, n_via_points: int, n_contexts: int, n_images: Sequence[int],
                              preview_points: int) -> None:
        """Cheap bounds check BEFORE the message is converted (absurd sizes are refused here)."""
        cfg = self.config
        if n_via_points > cfg.max_via_points:
            raise RequestError(Code.INVALID_REQUEST, f"{n_via_points} via-points; the server accepts at most "
                               f"{cfg.max_via_points} (parameter max_via_points)")
        if n_contexts > 64:
            raise RequestError(Code.INVALID_CONTEXT, f"{n_contexts} contexts; expected at most one per "
                               "modality of the primitive (see ListPrimitives)")
        for i, n in enumerate(n_images):
            if n > cfg.max_images:
                raise RequestError(Code.INVALID_IMAGE, f"context {i} has {n} images; the server accepts at "
                                   f"most {cfg.max_images} per context (parameter max_images)")
        self._n_points(preview_points, "preview_points")

    def condition(self, req: ConditionRequest) -> ConditionResult:
        """Bayesian aggregation (paper Eq. 1/3) of via-points and contexts, optional refinement
        (paper Eq. 5), stored under a new handle, with a preview of mean and std."""
        cfg = self.config
        prim = self._primitive(req.primitive)
        model = prim.model
        d = model.n_joints
        self.check_condition_sizes(len(req.via_points), len(req.contexts),
                                   [len(c.images) for c in req.contexts], req.preview_points)
        n_points = self._n_points(req.preview_points, "preview_points")
        if not _finite(req.refine_tolerance) or req.refine_tolerance < 0:
            raise RequestError(Code.INVALID_REQUEST, f"refine_tolerance {req.refine_tolerance!r} is invalid; "
                               f"expected a finite number >= 0 (0 = server default {cfg.refine_tolerance:g} rad)")
        tol = float(req.refine_tolerance) or cfg.refine_tolerance
        iters = int(req.refine_max_iterations) or cfg.refine_max_iterations
        if iters > 10000:
            raise RequestError(Code.INVALID_REQUEST, f"refine_max_iterations {iters} is too large; expected "
                               "0 (server default) or 1..10000")

        # ---- via-points
        n = len(req.via_points)
        vx, vy = np.zeros(n), np.zeros((n, d))
        vmask, vw = np.ones((n, d), dtype=bool), np.ones(n)
        for i, vp in enumerate(req.via_points):
            where = f"via-point {i}"
            if not _finite(vp.phase) or not 0.0 <= vp.phase <= 1.0:
                raise RequestError(Code.INVALID_VIA_POINT, f"{where}: phase {vp.phase!r} is outside [0, 1]; "
                                   "phases are normalized time (0 = start, 1 = end"
                                   f"{', fraction of a cycle' if model.phase_type == 'rhythmic' else ''})")
            pos = np.asarray(vp.positions, dtype=np.float64).reshape(-1)
            if pos.size != d:
                raise RequestError(Code.INVALID_VIA_POINT, f"{where} has {pos.size} joint values; primitive "
                                   f"'{prim.name}' has {d} joints: {', '.join(model.joint_names)}")
            if not np.all(np.isfinite(pos)):
                j = int(np.argmax(~np.isfinite(pos)))
                raise RequestError(Code.INVALID_VIA_POINT, f"{where}: joint '{model.joint_names[j]}' is "
                                   f"{pos[j]}; expected finite positions (rad) for every joint, masked or not")
            mask = np.asarray(vp.joint_mask, dtype=bool).reshape(-1)
            if mask.size not in (0, d):
                raise RequestError(Code.INVALID_VIA_POINT, f"{where}: joint_mask has {mask.size} entries; "
                                   f"expected 0 (all joints) or {d} (one per joint)")
            if mask.size and not mask.any():
                raise RequestError(Code.INVALID_VIA_POINT, f"{where}: joint_mask selects no joint; set at least "
                                   "one entry true or leave the mask empty (all joints)")
            vx[i], vy[i] = float(vp.phase), pos
            if mask.size:
                vmask[i] = mask
            vw[i] = self._weight(vp.use_weight, vp.weight, where, Code.INVALID_VIA_POINT)

        # ---- contexts
        contexts, cweights, images, image_weight = {}, {}, None, 1.0
        seen = set()
        dims = model.context_dims
        for i, c in enumerate(req.contexts):
            where = f"context {i} ('{c.modality}')"
            if c.modality in seen:
                raise RequestError(Code.INVALID_CONTEXT, f"{where}: modality given twice; expected at most one "
                                   "Context per modality (put several images of one scene into one Context)")
            seen.add(c.modality)
            w = self._weight(c.use_weight, c.weight, where,
                             Code.INVALID_IMAGE if c.modality == "image" else Code.INVALID_CONTEXT)
            if c.modality == "image":
                if model.image_shape is None:
                    raise RequestError(Code.INVALID_IMAGE, f"{where}: primitive '{prim.name}' accepts no images; "
                                       f"its contexts: {', '.join(dims) or 'none'}")
                if len(c.values):
                    raise RequestError(Code.INVALID_IMAGE, f"{where}: values must be empty for modality 'image'")
                if not c.images:
                    raise RequestError(Code.INVALID_IMAGE, f"{where}: no images; expected at least one "
                                       f"{model.image_shape[0]}x{model.image_shape[1]} rgb8 image")
                images = np.stack([decode_image(im, model.image_shape, f"{where} image {k}")
                                   for k, im in enumerate(c.images)])
                image_weight = w
                continue
            if c.modality not in dims:
                raise RequestError(Code.INVALID_CONTEXT, f"{where}: unknown modality; primitive '{prim.name}' "
                                   f"accepts {', '.join(repr(m) for m in dims) or 'no low-dimensional contexts'}"
                                   f"{' and images' if model.image_shape else ''}")
            if c.images:
                raise RequestError(Code.INVALID_CONTEXT, f"{where}: images are only allowed with modality 'image'")
            vals = np.asarray(c.values, dtype=np.float64).reshape(-1)
            if vals.size != dims[c.modality]:
                raise RequestError(Code.INVALID_CONTEXT, f"{where} has {vals.size} values; expected exactly "
                                   f"{dims[c.modality]}")
            if not np.all(np.isfinite(vals)):
                raise RequestError(Code.INVALID_CONTEXT, f"{where} contains NaN or inf; expected finite values")
            contexts[c.modality] = vals[None, :]
            cweights[c.modality] = [w]

        # ---- aggregate (paper Eq. 1 / Eq. 3 with importance weights); a split latent's linear block is
        # conditioned exactly with the planner's via-point noise (parameter via_noise) and, unless Eq. 5
        # refinement is asked for, conditioned again while a via-point is missed (no gradient stage); an
        # overflow of finite but huge inputs is refused by the model with the values that caused it
        exact = model.exact_conditioning
        inputs = (vx if n else None, vy if n else None, vw if n else None, vmask if n else None, contexts or None,
                  cweights or None, images, image_weight)
        via_noise = (cfg.via_noise or None) if exact else None
        try:
            if req.refine:
                latent = model.condition(*inputs, via_noise=via_noise)
            else:
                planned = model.condition_planner(*inputs, via_noise=via_noise, tol=tol, max_iterations=iters,
                                                  time_budget=cfg.refine_time_budget)
        except ValueError as exc:
            raise RequestError(Code.INVALID_REQUEST, str(exc)) from None

        # ---- error of the executed mean at the via-points (of weight > 0), optional refinement (paper Eq. 5)
        active = vw > 0
        iterations, reason, out_of_time = 0, "", False
        if not req.refine:
            latent, max_err, iterations = planned.latent, planned.via_error, planned.iterations
        elif active.any():
            res = model.refine(latent, vx[active], vy[active], vmask[active], max_iterations=iters, tol=tol,
                               time_budget=cfg.refine_time_budget)
            latent, iterations, reason, out_of_time = res.latent, res.iterations, res.reason, res.out_of_time
            max_err = res.max_error
        else:
            max_err = 0.0
        reachable = max_err <= tol
        dist = ConditionedLatent(prim.name, latent)
        try:  # (before the handle is stored: a distribution whose spread cannot be computed is refused)
            preview = self._preview(prim, dist, n_points)
        except ValueError as exc:
            raise RequestError(Code.INVALID_REQUEST, str(exc)) from None
        handle, expires = self._store(dist)
        if req.refine and not reachable and out_of_time:
            code = Code.REFINEMENT_UNREACHABLE
            msg = (f"refinement stopped by its time budget of {cfg.refine_time_budget:g} s (parameter "
                   f"refine_time_budget) after {iterations} iterations with max via-point error {max_err:.3g} rad > "
                   f"tolerance {tol:g} rad: the via-points were not met in that time (fewer via-points, a looser "
                   f"tolerance or a larger refine_time_budget may meet them); handle '{handle}' holds the best fit "
                   f"({reason})")
        elif req.refine and not reachable:
            code = Code.REFINEMENT_UNREACHABLE
            msg = (f"refinement stopped ({reason}) after {iterations} iterations with max via-point error "
                   f"{max_err:.3g} rad > tolerance {tol:g} rad: the via-points cannot all be met by this "
                   f"primitive; handle '{handle}' holds the best fit")
        else:
            code = Code.SUCCESS
            msg = (f"conditioned '{prim.name}' on {int(active.sum())} via-points and {len(req.contexts)} contexts"
                   + (f"; refined in {iterations} iterations" if req.refine and active.any() else "")
                   + (f"; linear block conditioned again {iterations} times with a smaller via-point noise"
                      if exact and iterations and not req.refine else "")
                   + f"; max via-point error {max_err:.3g} rad"
                   + (f" > tolerance {tol:g} rad, not met: {planned.reason}" if not req.refine and not reachable
                      else ""))
        return ConditionResult(code, msg, handle, expires, preview, max_err, iterations, reachable)

    # ------------------------------------------------------------------ Blend
    def blend(self, req: BlendRequest) -> BlendResult:
        """q_b(z | x) ∝ q_a^ω(x) q_b^(1-ω(x)) (paper Eq. 4) of two stored distributions."""
        a = self._handle(req.handle_a, "handle_a")
        b = self._handle(req.handle_b, "handle_b")
        if a.primitive != b.primitive:
            raise RequestError(Code.INVALID_REQUEST, f"handle_a is of primitive '{a.primitive}' and handle_b of "
                               f"'{b.primitive}'; blending combines latent distributions of ONE primitive "
                               "(one decoder), so both handles must come from the same primitive")
        prim = self._primitive(a.primitive)
        parts = a.parts + b.parts
        if parts > self.config.max_blend_parts:
            raise RequestError(Code.INVALID_REQUEST, f"handle_a is made of {a.parts} and handle_b of {b.parts} "
                               f"conditioned distributions: their blend would be made of {parts}; the server accepts "
                               f"at most {self.config.max_blend_parts} (parameter max_blend_parts): blend handles "
                               "from Condition, or blends of fewer parts")
        nx, nw = len(req.schedule_phases), len(req.schedule_weights)
        if max(nx, nw) > self.config.max_via_points:
            raise RequestError(Code.INVALID_REQUEST, f"schedule has {max(nx, nw)} knots; the server accepts at most "
                               f"{self.config.max_via_points} (parameter max_via_points)")
        n_points = self._n_points(req.preview_points, "preview_points")
        if nx == 0 and nw == 0:
            schedule = Schedule.linear_handover()
        else:
            try:
                schedule = Schedule(np.asarray(req.schedule_phases, dtype=np.float64),
                                    np.asarray(req.schedule_weights, dtype=np.float64))
            except ValueError as exc:
                raise RequestError(Code.INVALID_REQUEST, f"{exc} (schedule_phases strictly increasing in "
                                   "[0, 1], schedule_weights in [0, 1], same length; both empty = linear "
                                   "hand-over from a to b)") from None
        eps = None
        if req.sample:
            eps = np.random.default_rng(int(req.seed) & 0xFFFFFFFFFFFFFFFF).standard_normal(prim.model.latent_dim)
        dist = BlendedLatent(prim.name, a, b, schedule, eps)
        handle, expires = self._store(dist)
        return BlendResult(handle, expires, self._preview(prim, dist, n_points))

    # ------------------------------------------------------------------ Sample
    def sample(self, req: SampleRequest) -> SampleResult:
        """S whole trajectories, z ~ q(z) once per trajectory (prior of ``primitive`` if no handle)."""
        if req.handle:
            dist = self._handle(req.handle)
            prim = self._primitive(dist.primitive)
        else:
            if not req.primitive:
                raise RequestError(Code.INVALID_REQUEST, "set handle (from Condition or Blend) or, to sample "
                                   "the prior, primitive")
            prim = self._primitive(req.primitive)
            dist = ConditionedLatent(prim.name, prim.model.prior())
        s = int(req.n_samples) or 1
        if s > self.config.max_samples:
            raise RequestError(Code.INVALID_REQUEST, f"n_samples = {s}; expected 0 (= 1) or 1..{self.config.max_samples}"
                               " (parameter max_samples)")
        t = self._n_points(req.n_points, "n_points")
        if s * t > self.config.max_sample_points:
            raise RequestError(Code.INVALID_REQUEST, f"n_samples x n_points = {s} x {t} = {s * t} trajectory points; "
                               f"the server decodes at most {self.config.max_sample_points} per request (parameter "
                               "max_sample_points): ask for fewer samples or points, or in several requests")
        x = np.linspace(0.0, 1.0, t)
        return SampleResult(prim.joint_names, x, self._samples(prim, dist, x, s, int(req.seed) & 0xFFFFFFFFFFFFFFFF))

    # ------------------------------------------------------------------ Execute
    def plan_execution(self, req: ExecuteRequest) -> ExecutionPlan:
        """Validate an Execute goal and decode the executed mean on the dense grid (robot order)."""
        cfg = self.config
        dist = self._handle(req.handle)
        prim = self._primitive(dist.primitive)
        for field in ("duration", "phase_rate"):
            v = getattr(req, field)
            if not _finite(v) or v < 0:
                raise RequestError(Code.INVALID_REQUEST, f"{field} {v!r} is invalid; expected a finite number "
                                   ">= 0 (0 = not set)")
        if req.duration > 0 and req.phase_rate > 0:
            raise RequestError(Code.INVALID_REQUEST, f"both duration ({req.duration:g} s) and phase_rate "
                               f"({req.phase_rate:g} /s) are set; set at most one (phase_rate = 1 / duration)")
        if req.duration > 0:
            duration = float(req.duration)
        elif req.phase_rate > 0:
            duration = 1.0 / float(req.phase_rate)
        else:
            duration = prim.entry.default_duration or cfg.default_duration
        if not self.MIN_DURATION <= duration <= self.MAX_DURATION:
            raise RequestError(Code.INVALID_REQUEST, f"duration {duration:.6g} s (phase rate {1 / duration:.6g} /s)"
                               f" is out of range; expected {self.MIN_DURATION:g}..{self.MAX_DURATION:g} s")
        rhythmic = prim.model.phase_type == "rhythmic"
        cycles = 1
        if rhythmic:
            cycles = int(req.cycles) or 1
            if cycles > cfg.max_cycles:
                raise RequestError(Code.INVALID_REQUEST, f"cycles = {cycles}; expected 0 (= 1) or 1..{cfg.max_cycles}"
                                   " (parameter max_cycles)")
        x = np.linspace(0.0, 1.0, cfg.execution_grid_points)
        y = prim.to_robot_order(self._decode(prim, dist, x, dist.eps))
        if not np.all(np.isfinite(y)):
            raise RequestError(Code.INVALID_REQUEST, f"handle '{req.handle}' decodes to a trajectory with NaN or "
                               "inf; condition again with via-points and contexts of moderate size")
        ref = ExecutionReference(y, rhythmic, cfg.derivative_step)
        if cfg.check_feasibility:
            self._check_positions(ref, x)
            self.check_rate(ref, 1.0 / duration)
        return ExecutionPlan(req.handle, prim.name, ref, duration, rhythmic, cycles, bool(req.reverse))

    def _check_positions(self, ref: ExecutionReference, x: np.ndarray) -> None:
        lim = self.limits
        tol = 1e-6
        below = ref.y < lim.lower - tol
        above = ref.y > lim.upper + tol
        if below.any() or above.any():
            i, j = np.argwhere(below | above)[0]
            side, bound = ("lower", lim.lower[j]) if below[i, j] else ("upper", lim.upper[j])
            raise RequestError(Code.LIMIT_VIOLATION, f"the trajectory of this handle leaves the position limits: "
                               f"{lim.names[j]} reaches {ref.y[i, j]:.4g} rad at phase {x[i]:.3f}, beyond its "
                               f"{side} limit {bound:.4g} rad; condition on via-points inside the limits")

    def check_rate(self, ref: ExecutionReference, rate: float) -> None:
        """Refuse (LIMIT_VIOLATION) a phase rate at which the reference needs more than v_max."""
        speed = ref.max_speed_per_phase()
        need = speed * abs(rate)
        vmax = self.limits.max_velocity
        over = need > vmax * (1 + 1e-9)
        if over.any():
            j = int(np.argmax(need / vmax))
            t_min = ref.shortest_duration(vmax)
            raise RequestError(Code.LIMIT_VIOLATION, f"at phase rate {abs(rate):.4g} /s (duration "
                               f"{1 / abs(rate):.4g} s) {self.limits.names[j]} would need {need[j]:.3g} rad/s; its "
                               f"velocity limit is {vmax[j]:.3g} rad/s: use a duration >= {t_min:.3g} s "
                               f"(phase rate <= {1 / t_min:.4g} /s)")

