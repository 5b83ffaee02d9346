"""The measures of the model family's goals (EXPERIMENTS.md, "Goals"), one function per goal, on any
trained model behind :class:`deepprompt_ros.baselines.interface.MovementPrimitiveModel`:

======  ==========================================================================================
goal    measure
======  ==========================================================================================
1       :func:`subset_mse` — held-out MSE from the start point alone and from start + end (the 5
        random via-points and the whole trajectory are ``reconstruction_mse``'s ``via_5`` / ``via_point``)
3       :func:`mode_shares` — bimodal sine: share of samples on a mode with ambiguous via-points (the
        zero crossings), on the right mode with distinguishing ones
4       :func:`sample_stats` — after conditioning on N held-out via-points: the executed mean's error,
        the K-sample mean's error (paper Eq. 5) and the per-sample spread at the via-points
5       :func:`planner_via_sets`, :func:`via_met` — random planner via-points inside the joint limits
        and the demonstrations' range ±20 % of the span: share met by the executed mean to 1e-6 rad;
        :func:`server_via_met` the same through the server's Condition path
6       :func:`uncertainty_checks` — a partial via-point's free joints wider than a full one's;
        MAP refinement with the posterior prior not counting the via-points twice
7       :class:`AblatedDeepProMP` — a trained DeepProMP with its trained parts replaced by what they
        start from
======  ==========================================================================================

Units: phases in [0, 1], joint positions in rad, MSEs in rad², errors in rad.

Length: over 400 lines because it is the one definition of each goal's measure that the experiments
(:mod:`experiments.reconstruction`, :mod:`experiments.goals`) and ``bench/bench_method.py`` share; it
reads as one section per goal, and split by goal the sections would import each other's pieces.
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
import torch

from bench.plot_bimodal import fractions
from deepprompt_ros.baselines.deep_promp_model import DeepProMPModel
from deepprompt_ros.baselines.interface import MovementPrimitiveModel
from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.synthetic import bimodal_sine
from deepprompt_ros.model.network import DeepProMPNet
from deepprompt_ros.primitive.deep_promp import DeepProMP
from deepprompt_ros.primitive.latent import PLANNER_VIA_NOISE

#: the tolerance of goal 5 (rad): a via-point is met when the executed mean passes it this closely
MET_TOL = 1e-6
#: goal 5: a planner's via-point lies within the demonstrations' range at its phase widened by this
#: fraction of the range on either side (and inside the joint limits)
RANGE_MARGIN = 0.2
#: goal 3: "both modes present" when each mode holds at least this share of the samples
BOTH_MODES_MIN = 0.1
#: goal 3: phases of the bimodal protocol (bench/plot_bimodal.py): a 101-point grid, the zero
#: crossings, 3 and 12 distinguishing via-points
BIMODAL_GRID = 101
ZERO_CROSSINGS = (0, 50, 100)
DISTINGUISHING = {"3 via-points": (10, 25, 60), "12 via-points": tuple(range(0, 101, 9))}


# ------------------------------------------------------------------------------------------------
# Goal 7: the ablation
# ------------------------------------------------------------------------------------------------

class AblatedDeepProMP(DeepProMPModel):
    """A trained DeepProMP with its trained parts replaced by what they start from (goal 7).

    * decoder with a linear part (``decoder_basis`` > 0): the linear part Φ(x)(b + A z_lin) alone (MLP
      residual off; the linear part is the PPCA the training initializes it with) and the encoders
      unused: via-points condition z_lin exactly from the prior N(0, I) (split latent,
      :meth:`DeepProMP.condition` without contexts or images), or by the closed-form MAP of the
      linear decoder with the standard prior and the model's ``via_noise`` (no split); contexts and
      images are validated and then ignored;
    * plain MLP decoder: the network at its initial weights (``torch.manual_seed`` of the training's
      seed, as :func:`deepprompt_ros.training.loop.train` starts), with every input.

    ``what`` says which of the two it is.
    """

    kind = "deepprompt_ablation"

    def __init__(self, trained: DeepProMPModel):
        super().__init__()
        prim = trained.primitive
        if prim is None:
            raise ValueError("AblatedDeepProMP needs a trained DeepProMPModel (fit or load it first)")
        cfg = prim.cfg
        self.linear = bool(cfg.decoder_basis)
        if self.linear:
            base = prim.with_residual_scale(0.0)
            modes = f", {cfg.decoder_modes} modes" if cfg.decoder_modes else ""
            self.what = (f"linear part alone ({cfg.decoder_basis} RBFs/joint, latent_linear {cfg.latent_linear}"
                         f"{modes}), encoders unused")
        else:
            torch.manual_seed(int(prim.metadata.get("train_config", {}).get("seed", 0)))
            base = DeepProMP(DeepProMPNet(cfg), prim.norm, prim.joint_names, name=self.kind, metadata=prim.metadata)
            self.what = "untrained network (initial weights of the training's seed)"
        self._set(base)

    def condition(self, via_x=None, via_y=None, contexts=None, images=None):
        inp = self.check_inputs(via_x, via_y, contexts, images)
        prim = self.primitive
        has_via = inp.via_x.size > 0
        if not self.linear:
            return prim.condition(inp.via_x if has_via else None, inp.via_y if has_via else None,
                                  contexts=inp.contexts or None, images=inp.images)
        if not has_via:
            return prim.prior()
        if prim.cfg.latent_linear > 0:
            return prim.condition_planner(inp.via_x, inp.via_y).latent
        noise = prim.cfg.via_noise * np.asarray(prim.norm.y_std, dtype=np.float64)
        return prim.refine_map(prim.prior(), inp.via_x, inp.via_y, prior="standard", noise_std=noise).latent


def model_label(model: MovementPrimitiveModel) -> str:
    """What produced a model's numbers: DeepProMP's decoder as its training chose it, the ablation's
    :attr:`AblatedDeepProMP.what`, ProMP's regularizer and noise."""
    if isinstance(model, AblatedDeepProMP):
        return model.what
    if isinstance(model, DeepProMPModel):
        c = model.primitive.cfg
        dec = (f"linear part {c.decoder_basis} RBFs/joint, latent_linear {c.latent_linear} of {c.latent_dim}, "
               f"{f'{c.decoder_modes} modes, ' if c.decoder_modes else ''}"
               f"residual {'kept' if c.residual_scale else 'dropped'}" if c.decoder_basis
               else f"plain MLP decoder, latent {c.latent_dim}")
        return f"{dec}, objective {model.primitive.metadata.get('train_config', {}).get('objective', '?')}"
    if hasattr(model, "cov_reg_scale"):
        return f"cov_reg_scale {model.cov_reg_scale:g}, via_noise {model.via_noise:g}"
    return model.kind


# ------------------------------------------------------------------------------------------------
# Goal 1: start only, start + end
# ------------------------------------------------------------------------------------------------

SUBSETS = {"start": lambda n: np.array([0]), "start_end": lambda n: np.array([0, n - 1])}


def subset_mse(model: MovementPrimitiveModel, test: DemoDataset, subset: str, n_points: int = 100) -> float:
    """MSE (rad²) of the held-out demos reconstructed from the via-points ``subset`` of each
    (:data:`SUBSETS`: ``start`` x = 0, ``start_end`` x = 0 and 1), no context: the rule of
    :func:`deepprompt_ros.evaluation.reconstruction.reconstruction_mse` with other points."""
    if subset not in SUBSETS:
        raise ValueError(f"subset '{subset}' unknown; expected one of {sorted(SUBSETS)}")
    x = np.linspace(0.0, 1.0, n_points)
    sel = SUBSETS[subset](n_points)
    errs = []
    for demo in test.demos:
        y = demo.resampled(n_points)
        errs.append(float(((model.mean_trajectory(model.condition(x[sel], y[sel]), x) - y) ** 2).mean()))
    return float(np.mean(errs))


# ------------------------------------------------------------------------------------------------
# Goal 3: modes of the bimodal sine
# ------------------------------------------------------------------------------------------------

def mode_shares(model: MovementPrimitiveModel, n_samples: int = 200, n_held: int = 10, seed: int = 0) -> dict:
    """Goal 3 on a model of the bimodal sine task (1 joint, modes ±A sin 2πx), the protocol of
    bench/plot_bimodal.py (fractions at x = 0.25 on a 101-point grid: on the + mode y > 0.6, on the
    − mode y < −0.6):

    ``ambiguous``       y = 0 at the zero crossings x = 0, 0.5, 1: ``on_mode`` the share of samples on
                        either mode, ``on_pos`` / ``on_neg`` each, ``both`` each mode >= :data:`BOTH_MODES_MIN`
    ``3 via-points``,   points of ``n_held`` held-out demos (``bimodal_sine(n_held, seed=99)``) at the
    ``12 via-points``   phases of :data:`DISTINGUISHING`: the share of samples on that demo's mode (mean)
    """
    x = np.linspace(0.0, 1.0, BIMODAL_GRID)
    idx = list(ZERO_CROSSINGS)
    s = model.sample(model.condition(x[idx], np.zeros((len(idx), 1))), x, n_samples, seed)
    pos, neg, _ = fractions(s)
    out = {"ambiguous": {"on_pos": float(pos), "on_neg": float(neg), "on_mode": float(pos + neg),
                         "both": bool(min(pos, neg) >= BOTH_MODES_MIN)}, "n_samples": n_samples, "n_held": n_held}
    held = [d.resampled(BIMODAL_GRID) for d in bimodal_sine(n_held, seed=99).demos]
    for name, pts in DISTINGUISHING.items():
        pts = list(pts)
        right = []
        for i, y in enumerate(held):
            p, n, _ = fractions(model.sample(model.condition(x[pts], y[pts]), x, n_samples, seed + 1 + i))
            right.append(p if y[25, 0] > 0 else n)
        out[name] = float(np.mean(right))
    return out


# ------------------------------------------------------------------------------------------------
# Goal 4: samples at the via-points
# ------------------------------------------------------------------------------------------------

def stated_noise(model: MovementPrimitiveModel) -> float:
    """The via-point standard deviation the model's conditioning states (rad, RMS over joints): a
    DeepProMP's (split latent: the planner's :data:`PLANNER_VIA_NOISE`, else the model's ``via_noise``;
    normalized units) times each joint's normalization std; ProMP's the
    same with its own ``via_noise``; NaN for models without one."""
    if isinstance(model, DeepProMPModel):
        prim = model.primitive
        v, std = PLANNER_VIA_NOISE if prim.exact_conditioning else prim.cfg.via_noise, prim.norm.y_std
    elif hasattr(model, "via_noise") and getattr(model, "norm", None) is not None:
        v, std = model.via_noise, model.norm.y_std
    else:
        return float("nan")
    return float(v * np.sqrt(np.mean(np.asarray(std, dtype=np.float64) ** 2)))


def sample_stats(model: MovementPrimitiveModel, test: DemoDataset, n_vias: Sequence[int] = (1, 5, 50),
                 n_samples: int = 50, n_points: int = 100) -> dict:
    """Goal 4: for N in ``n_vias`` (at most ``n_points``), each held-out demo conditioned on N of its
    points (``default_rng([N, i])``, no context; :func:`server_path`: refined where the server refines
    by default), mean over demos of

    ``mean_error``         max |executed mean − via-point| (rad), the trajectory a robot runs
    ``sample_mean_error``  max |mean of ``n_samples`` samples − via-point| (paper Eq. 5's quantity)
    ``spread``             RMS over samples, via-points and joints of (sample − via-point) (rad)

    and ``noise``, :func:`stated_noise`. Returns {str(N): {...}}."""
    x = np.linspace(0.0, 1.0, n_points)
    out = {}
    for n in n_vias:
        n = min(int(n), n_points)
        rows = []
        for i, demo in enumerate(test.demos):
            y = demo.resampled(n_points)
            sel = np.sort(np.random.default_rng([n, i]).choice(n_points, n, replace=False))
            xv, yv = x[sel], y[sel]
            cond = server_path(model, model.condition(xv, yv), xv, yv)
            s = model.sample(cond, xv, n_samples, np.random.default_rng([n, i, 1]))  # (K, n, d)
            rows.append((np.abs(model.mean_trajectory(cond, xv) - yv).max(), np.abs(s.mean(0) - yv).max(),
                         np.sqrt(((s - yv[None]) ** 2).mean())))
        r = np.mean(rows, axis=0)
        out[str(n)] = {"mean_error": float(r[0]), "sample_mean_error": float(r[1]), "spread": float(r[2]),
                       "noise": stated_noise(model)}
    return out


# ------------------------------------------------------------------------------------------------
# Goal 5: any reasonable via-point is met
# ------------------------------------------------------------------------------------------------

def planner_via_sets(train: DemoDataset, n_sets: int, seed: int, lower=None, upper=None, max_via: int = 5,
                     n_points: int = 101, contexts_from: DemoDataset | None = None) -> list[dict]:
    """``n_sets`` random via-point sets as a planner asks for them (goal 5): 1 to ``max_via``
    via-points (uniform count) at distinct phases of an ``n_points`` grid, each joint's position
    uniform in the range of the demonstrations ``train`` at that phase widened by
    :data:`RANGE_MARGIN` of its span on either side, cut to the joint limits ``lower`` / ``upper``
    (rad, (d,); None: no limit). Each set carries the contexts of a random demo of
    ``contexts_from`` (default ``train``; none when the data have none).

    Returns
    -------
    list of {"x": (n,), "y": (n, d), "contexts": {modality: (m, c)}}
    """
    if not 1 <= max_via <= n_points:
        raise ValueError(f"max_via must be in [1, n_points={n_points}], got {max_via}")
    Y = np.stack([d.resampled(n_points) for d in train.demos])  # (N, T, d)
    lo, hi = Y.min(0), Y.max(0)
    span = hi - lo
    a, b = lo - RANGE_MARGIN * span, hi + RANGE_MARGIN * span
    if lower is not None:
        a = np.maximum(a, np.asarray(lower, dtype=np.float64))
    if upper is not None:
        b = np.minimum(b, np.asarray(upper, dtype=np.float64))
    if np.any(a > b):
        t, j = np.argwhere(a > b)[0]
        raise ValueError(f"joint {train.joint_names[j]} at phase {t / (n_points - 1):.2f}: the demonstrations' range "
                         f"[{lo[t, j]:.3g}, {hi[t, j]:.3g}] rad lies outside the joint limits")
    x = np.linspace(0.0, 1.0, n_points)
    ctx_demos = (contexts_from or train).demos
    rng = np.random.default_rng(seed)
    sets = []
    for _ in range(n_sets):
        n = int(rng.integers(1, max_via + 1))
        idx = np.sort(rng.choice(n_points, n, replace=False))
        y = rng.uniform(a[idx], b[idx])
        ctx = dict(ctx_demos[int(rng.integers(len(ctx_demos)))].contexts)
        sets.append({"x": x[idx], "y": y, "contexts": ctx})
    return sets


def server_default_refine() -> bool:
    """Whether the server refines a Condition request that does not say (the request's default)."""
    from deepprompt_ros.server.requests import ConditionRequest

    return bool(ConditionRequest("primitive").refine)


def server_path(model: MovementPrimitiveModel, cond, via_x, via_y):
    """``cond`` as the server's default Condition path leaves it: a DeepProMP's latent refined
    (:meth:`DeepProMP.refine`, the server's default budget and tolerance) when the server refines by
    default (:func:`server_default_refine`), else as it is (every other model: as it is)."""
    if not (isinstance(model, DeepProMPModel) and server_default_refine()):
        return cond
    from deepprompt_ros.server.config import ServerConfig

    cfg = ServerConfig()
    return model.primitive.refine(cond, via_x, via_y, max_iterations=cfg.refine_max_iterations,
                                  tol=cfg.refine_tolerance).latent


def via_met(model: MovementPrimitiveModel, sets: Sequence[Mapping], tol: float = MET_TOL) -> dict:
    """Goal 5 for a model's own conditioning (DeepProMP: :meth:`DeepProMP.condition_planner` and
    :func:`server_path`, the computation of the server's default Condition): each set of
    :func:`planner_via_sets` with its contexts (when the model takes them); ``share`` of the sets
    whose executed mean passes every via-point within ``tol``, ``errors`` the max error of each."""
    errs = []
    for s in sets:
        ctx = {k: v for k, v in s["contexts"].items() if k in model.context_dims} or None
        cond = server_path(model, model.condition(s["x"], s["y"], contexts=ctx), s["x"], s["y"])
        errs.append(float(np.abs(model.mean_trajectory(cond, s["x"]) - s["y"]).max()))
    errs = np.asarray(errs)
    return {"share": float(np.mean(errs <= tol)), "n": len(errs), "errors": errs.tolist(),
            "median_error": float(np.median(errs))}


def server_via_met(model_path, robot: str, sets: Sequence[Mapping], tol: float = MET_TOL,
                   primitive: str = "primitive", refine: bool | None = None) -> dict:
    """Goal 5 through the primitive server's Condition path
    (:meth:`deepprompt_ros.server.service.PrimitiveServerCore.condition` with the request's default
    ``refine`` unless ``refine`` is given, the server's default configuration and ``robot``'s limits)
    on the model file ``model_path``: each set as one request (its via-points and contexts). A set is
    met when the mean of the stored handle, decoded here at the via-points, passes each within ``tol``
    (a request refused, or answered REFINEMENT_UNREACHABLE, is not met). Returns ``share``, ``n``,
    ``errors`` (inf for a refused request), ``refused`` (their messages), ``reported_agree`` (the
    server's reported error equals the one measured here), ``refine`` (the value used)."""
    import pathlib

    from deepprompt_ros.common.results import Code, RequestError
    from deepprompt_ros.robots.spec import load_robot
    from deepprompt_ros.server.config import ServerConfig, robot_limits
    from deepprompt_ros.server.primitives_file import PrimitiveEntry, load_primitive
    from deepprompt_ros.server.requests import ConditionRequest, ContextIn, ViaPointIn
    from deepprompt_ros.server.service import PrimitiveServerCore

    spec = load_robot(robot)
    cfg = ServerConfig()
    loaded = load_primitive(PrimitiveEntry(primitive, str(model_path)), spec.joint_names, pathlib.Path)
    core = PrimitiveServerCore({primitive: loaded}, cfg, robot_limits(spec, cfg))
    refine = ConditionRequest(primitive).refine if refine is None else bool(refine)
    errs, success, refused, agree = [], [], [], []
    for s in sets:
        vps = [ViaPointIn(float(a), np.asarray(b, dtype=np.float64), np.zeros(0, dtype=bool))
               for a, b in zip(s["x"], s["y"])]
        ctx = [ContextIn(k, np.asarray(v, dtype=np.float64).reshape(-1)) for k, v in s["contexts"].items()
               if k in loaded.model.context_dims]
        try:
            res = core.condition(ConditionRequest(primitive, vps, ctx, refine=refine))
        except RequestError as exc:
            errs.append(float("inf"))
            success.append(False)
            refused.append(str(exc))
            continue
        lat = core.handles.get(res.handle).latent
        e = float(np.abs(loaded.model.mean_trajectory(lat, s["x"]) - s["y"]).max())
        errs.append(e)
        success.append(res.code == Code.SUCCESS)
        agree.append(abs(e - res.refine_max_error) <= 1e-9 + 1e-6 * e)
    errs = np.asarray(errs)
    return {"share": float(np.mean((errs <= tol) & np.asarray(success))), "n": len(errs), "errors": errs.tolist(),
            "median_error": float(np.median(errs)), "refused": refused, "reported_agree": bool(all(agree)),
            "refine": refine}


# ------------------------------------------------------------------------------------------------
# Goal 6: honest uncertainty
# ------------------------------------------------------------------------------------------------

def uncertainty_checks(model: DeepProMPModel, test: DemoDataset, n_points: int = 100, n_via: int = 5) -> dict:
    """Goal 6 on a DeepProMP (means over the held-out demos ``test``):

    ``partial_over_full``  the free joints' std at x = 0.5 (:meth:`DeepProMP.linearized_std`) under a
                           via-point of the demo at x = 0.5 that constrains only the first half of the
                           joints, divided by their std under the full via-point (> 1: the free joints
                           stay wider); NaN for a single joint
    ``map_double_count``   mean latent variance of :meth:`DeepProMP.refine_map` (posterior prior) started
                           from q(z | ``n_via`` via-points, the demo's contexts) over that started from
                           q(z | the contexts alone) (the prior without contexts): both must use q_c as
                           prior and the via-points once, in the likelihood (1); counting the via-points
                           twice narrows the first
    """
    prim = model.primitive
    d = prim.n_joints
    x = np.linspace(0.0, 1.0, n_points)
    mid = n_points // 2
    ratios, dbl = [], []
    mask = np.arange(d) < max(1, d // 2)
    for i, demo in enumerate(test.demos):
        y = demo.resampled(n_points)
        if d > 1:
            xv, yv = x[[mid]], y[[mid]]
            full = prim.linearized_std(prim.condition(xv, yv), xv)[0]
            part = prim.linearized_std(prim.condition(xv, yv, via_mask=mask[None]), xv)[0]
            ratios.append(float(np.mean(part[~mask] / full[~mask])))
        sel = np.sort(np.random.default_rng([n_via, i]).choice(n_points, min(n_via, n_points), replace=False))
        ctx = {k: v for k, v in demo.contexts.items() if k in prim.context_dims} or None
        lat = prim.condition(x[sel], y[sel], contexts=ctx)
        ref = prim.condition(contexts=ctx) if ctx else prim.prior()
        twice = prim.refine_map(lat, x[sel], y[sel], prior="posterior").latent.var
        once = prim.refine_map(ref, x[sel], y[sel], prior="posterior").latent.var
        dbl.append(float(np.mean(twice / once)))
    return {"partial_over_full": float(np.mean(ratios)) if ratios else float("nan"),
            "map_double_count": float(np.mean(dbl))}


# ------------------------------------------------------------------------------------------------
# All of them on one trained model
# ------------------------------------------------------------------------------------------------

def joint_limits(joint_names: Sequence[str]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(lower, upper) position limits (rad) of the packaged robot whose joints are ``joint_names``
    (the Gen3 lite or the WAM), in that order; (None, None) for other joints (the synthetic tasks)."""
    from deepprompt_ros.robots.spec import load_robot

    for robot in ("gen3_lite", "wam"):
        spec = load_robot(robot)
        if tuple(spec.joint_names) == tuple(joint_names):
            return np.asarray(spec.lower, dtype=np.float64), np.asarray(spec.upper, dtype=np.float64)
    return None, None


def measure(model: MovementPrimitiveModel, data, n_points: int = 100, n_sets: int = 50, n_samples: int = 50,
            seed: int = 0) -> dict:
    """Every goal measure on ``model`` trained on ``data`` (a :class:`experiments.common.TaskData`):
    ``label`` (:func:`model_label`), ``subsets`` (goal 1: :func:`subset_mse` start, start_end),
    ``samples`` (goal 4, :func:`sample_stats` with ``n_samples``), ``via_met`` (goal 5: :func:`via_met`
    on ``n_sets`` :func:`planner_via_sets` from the training demos, the robot's limits, contexts of the
    test demos), ``modes`` (goal 3, bimodal sine only: :func:`mode_shares`) and ``uncertainty`` (goal
    6, trained DeepProMPs only: :func:`uncertainty_checks`)."""
    lower, upper = joint_limits(data.train.joint_names)
    sets = planner_via_sets(data.train, n_sets, seed, lower, upper, contexts_from=data.test)
    out = {"label": model_label(model),
           "subsets": {k: subset_mse(model, data.test, k, n_points) for k in SUBSETS},
           "samples": sample_stats(model, data.test, n_samples=n_samples, n_points=n_points),
           "via_met": via_met(model, sets)}
    if data.name == "bimodal_sine":
        out["modes"] = mode_shares(model)
    if isinstance(model, DeepProMPModel) and not isinstance(model, AblatedDeepProMP):
        out["uncertainty"] = uncertainty_checks(model, data.test, n_points)
    return out


SHIPPED_REACH = "models/gen3_lite_reach.safetensors"


def shipped_reach_via_met(root, n_sets: int, seed: int = 0, n_contexts: int = 20, context_seed: int = 1001) -> dict:
    """Goal 5 on the shipped reach primitive (``<root>/models/gen3_lite_reach.safetensors``, the Gen3
    lite): ``n_sets`` :func:`planner_via_sets` from its training demonstrations (the built-in
    ``gen3_lite_reach`` of the seed its metadata records), within the Gen3 lite's limits, each with
    the object of one of ``n_contexts`` other demonstrations (seed ``context_seed``);

    ``server``               :func:`server_via_met`, the server's default Condition path on the model file
    ``server_other_refine``  the same requests with the other value of ``refine``
    ``promp``                :func:`via_met` of ProMP (:class:`ProMPModel` defaults, its automatic
                             selection) fitted on the same training demonstrations

    and ``model`` (the file's training facts) and ``promp_label``."""
    import pathlib

    from deepprompt_ros.baselines.promp_model import ProMPModel
    from deepprompt_ros.data.builtin import gen3_lite_reach
    from deepprompt_ros.training.config import TrainConfig

    path = pathlib.Path(root) / SHIPPED_REACH
    meta = DeepProMPModel.load(path).primitive.metadata
    tc = meta.get("train_config", {})
    train = gen3_lite_reach(seed=int(tc.get("seed", 0)))
    others = gen3_lite_reach(seed=context_seed, n_demos=n_contexts)
    lower, upper = joint_limits(train.joint_names)
    sets = planner_via_sets(train, n_sets, seed, lower, upper, contexts_from=others)
    promp = ProMPModel(log=lambda s: None).fit(train, TrainConfig(seed=int(tc.get("seed", 0))))
    sel = meta.get("selection", {}).get("linear_part", {})
    default = server_default_refine()
    return {"server": server_via_met(path, "gen3_lite", sets, primitive="reach"),
            "server_other_refine": server_via_met(path, "gen3_lite", sets, primitive="reach", refine=not default),
            "promp": via_met(promp, sets),
            "promp_label": model_label(promp),
            "model": {"file": SHIPPED_REACH, "dataset": meta.get("provenance", {}).get("dataset"),
                      "steps": tc.get("steps"), "objective": tc.get("objective"),
                      "latent_linear": tc.get("latent_linear", 0), "decoder_basis": tc.get("decoder_basis", 0),
                      "residual_scale": tc.get("residual_scale"), "auto_select": tc.get("auto_select", False),
                      "selected": bool(sel)},
            "n_train_demos": len(train)}
