"""What one training update optimizes (paper Sec. III-B): which inputs each trajectory is given,
the loss, and the held-out validation MSE.

Objectives (``TrainConfig.objective``):

``paper``  (the default) the paper's rewritten ELBO: z ~ q(z | subset), reconstruct the whole demonstration,
           plus β Σ_i KL(q(z|a_i) ‖ p0) over the given elements (the "KL of each per-element
           posterior to the prior"). The literal term E_q[log q(z|a_i) − log p0(z)] is unbounded
           below (μ_i far away with small σ_i drives it to −∞: measured −7e14 within 200 updates),
           so the per-element KL, which is ≥ 0, is used.
``np``     Neural-Process form: z ~ q(z | all points + all contexts), reconstruct the demonstration,
           β KL(q(z | all) ‖ q(z | subset)). With a subset that cannot tell modes apart, q(z|subset)
           must cover every mode that is consistent with it — the property that keeps conditioned
           samples multimodal (the paper's objective averages the modes instead: EXPERIMENTS.md,
           section 5 "Bimodal sine"). On a low-dimensional context it trains a less accurate context
           encoder than ``paper`` (EXPERIMENTS.md, section 6, goal 2).

Every update sub-samples which inputs are given (:func:`sample_subset_weights`): via-points (a
random count), each context modality, images, their combinations, and sometimes nothing (the
prior). Tensors are in normalized units (:mod:`deepprompt_ros.training.tensors`); B = batch,
N_total = all elements of a demo (T via-points, then each context's vectors, then the images).
"""
from __future__ import annotations

import numpy as np
import torch

from deepprompt_ros.model.aggregation import bayesian_aggregate, gaussian_kl
from deepprompt_ros.model.checkpoint import Normalization
from deepprompt_ros.model.network import DeepProMPNet
from deepprompt_ros.training.config import TrainConfig
from deepprompt_ros.training.tensors import TensorData

__all__ = ["encode_all", "sample_subset_weights", "consistent_demos", "loss_fn", "validation_weights",
           "validation_mse"]


def encode_all(net: DeepProMPNet, data: TensorData, idx: torch.Tensor):
    """Encode every element of the demos ``idx``: all T points as via-points, all contexts, images.

    Returns
    -------
    mu, var : (B, N_total, k); kinds : list of (kind, slice) naming which columns are which.
    """
    b = idx.shape[0]
    y = data.y[idx]
    x = data.x.unsqueeze(0).expand(b, -1)
    mus, vars_, kinds, start = [], [], [], 0
    mu, var = net.encode_via_points(x, y)
    mus.append(mu), vars_.append(var)
    kinds.append(("via", slice(0, y.shape[1])))
    start = y.shape[1]
    for name in net.cfg.context_names:
        mu, var = net.encode_context(name, data.ctx[name][idx])
        mus.append(mu), vars_.append(var)
        kinds.append((name, slice(start, start + mu.shape[1])))
        start += mu.shape[1]
    if net.image_encoder is not None:
        mu, var = net.encode_images(data.images[idx], data.image_mask[idx])
        mus.append(mu), vars_.append(var)
        kinds.append(("image", slice(start, start + 1)))
        start += 1
    return torch.cat(mus, 1), torch.cat(vars_, 1), kinds


def sample_subset_weights(cfg: TrainConfig, data: TensorData, idx: torch.Tensor, kinds, gen: torch.Generator):
    """Which inputs each trajectory of the batch is given this update (1 = given, 0 = withheld).

    With probability p_empty a trajectory is given nothing at all (the prior). Every other one is
    given at least one input: each kind — the via-points with probability p_via_points, each
    context modality and the images with p_context, a kind counting only where the demonstration
    has it — is drawn independently, and the draw is repeated until something is given (the
    independent draws conditioned on a non-empty subset; a demonstration with no kind it can be
    given stays empty). The share of prior-only trajectories is then p_empty whatever the number of
    modalities. Via-points given: a random count in [1, max_via_points] (skewed towards small
    counts) of randomly placed points.

    Low-information subsets (``p_low_info``): that fraction of the via-point subsets is drawn only
    from the phases where the demonstrations of the batch agree most (the ``low_info_fraction`` of
    phases with the smallest across-demo spread: shared start points, the zero crossings of the
    bimodal sines). Such points cannot tell the demonstrations apart, so the NP objective teaches the
    encoder to give them a large σ²_i — otherwise a few of them aggregate into a narrow posterior
    that sits between the modes, and samples conditioned on the zero crossings of the bimodal sines
    fall between them (EXPERIMENTS.md, section 5 "Bimodal sine").

    Returns
    -------
    w_sub, w_all : (B, N_total)   subset weights and all-elements weights (padding masked).
    """
    b, t = idx.shape[0], data.y.shape[1]
    masks, avail, probs = [], [], []  # per kind: element mask (B, n), kind available (B,), probability
    for kind, sl in kinds:
        if kind == "via":
            mask = torch.ones(b, sl.stop - sl.start)
        else:
            mask = data.image_mask[idx].amax(1, keepdim=True) if kind == "image" else data.ctx_mask[kind][idx]
        masks.append(mask)
        avail.append(mask.amax(1) > 0)
        probs.append(cfg.p_via_points if kind == "via" else cfg.p_context)
    avail_t, probs_t = torch.stack(avail, 1), torch.tensor(probs)  # (B, K), (K,)
    empty = torch.rand(b, generator=gen) < cfg.p_empty
    given = torch.zeros(b, len(kinds), dtype=torch.bool)
    todo = ~empty & (avail_t & (probs_t > 0)).any(1)
    while todo.any():  # rejection sampling: a draw that gives nothing is drawn again
        draw = (torch.rand(b, len(kinds), generator=gen) < probs_t) & avail_t
        given = torch.where(todo.unsqueeze(1), draw, given)
        todo = todo & ~given.any(1)
    parts_sub, parts_all = [], []
    for k, (kind, sl) in enumerate(kinds):
        use = given[:, k]
        if kind == "via":
            # count in [1, max_via_points], skewed towards few points (count = 1 + ⌊u² max⌋): small
            # sets are where a primitive must stay uncertain, and they are the rare case otherwise
            u = torch.rand(b, generator=gen)
            count = 1 + (u * u * cfg.max_via_points).long().clamp_max(max(cfg.max_via_points - 1, 0))
            key = torch.rand(b, t, generator=gen)
            if cfg.p_low_info > 0:
                spread = data.y[idx].std(0).mean(-1)  # (T,) across-demo spread per phase (normalized units)
                n_low = max(1, int(round(cfg.low_info_fraction * t)))
                high = torch.ones(t, dtype=torch.bool)
                high[spread.argsort()[:n_low]] = False
                low_rows = torch.rand(b, generator=gen) < cfg.p_low_info
                key = key + 2.0 * (low_rows.unsqueeze(1) & high.unsqueeze(0)).float()  # informative phases last
                # uniform counts here: several uninformative points must stay as uninformative as one
                low_count = 1 + (torch.rand(b, generator=gen) * min(cfg.max_via_points, n_low)).long()
                count = torch.where(low_rows, low_count.clamp_max(n_low), count)
            rank = key.argsort(1).argsort(1)  # random rank of each point
            parts_sub.append(((rank < count.unsqueeze(1)) & use.unsqueeze(1)).float())
        else:
            parts_sub.append(masks[k] * use.float().unsqueeze(1))
        parts_all.append(masks[k])
    return torch.cat(parts_sub, 1), torch.cat(parts_all, 1)


def consistent_demos(cfg: TrainConfig, data: TensorData, idx, kinds, w_sub) -> torch.Tensor:
    """C[i, j] = True when demo j of the batch agrees with everything demo i's subset gives:
    its joint positions at i's via-points (within ``consistency_tol``, normalized units), its
    contexts of the given modalities (same tolerance), and — images being high-dimensional —
    j == i when i's images are given. C[i, i] is always True; an empty subset admits every demo.
    """
    b = idx.shape[0]
    ok = torch.ones(b, b, dtype=torch.bool)
    for kind, sl in kinds:
        w = w_sub[:, sl] > 0  # (B, n)
        if kind == "via":
            y = data.y[idx]  # (B, T, d)
            dev = (y.unsqueeze(0) - y.unsqueeze(1)).abs().amax(-1)  # (B_i, B_j, T)
            dev = torch.where(w.unsqueeze(1), dev, torch.zeros(()))
            ok &= dev.amax(-1) <= cfg.consistency_tol
        elif kind == "image":
            ok &= ~w[:, 0:1] | torch.eye(b, dtype=torch.bool)
        else:
            c = data.ctx[kind][idx]  # (B, M, c)
            dev = (c.unsqueeze(0) - c.unsqueeze(1)).abs().amax(-1)  # (B_i, B_j, M)
            dev = torch.where(w.unsqueeze(1), dev, torch.zeros(()))
            ok &= dev.amax(-1) <= cfg.consistency_tol
    return ok | torch.eye(b, dtype=torch.bool)


def loss_fn(net: DeepProMPNet, cfg: TrainConfig, data: TensorData, idx, gen, beta: float):
    """Negative ELBO per trajectory (mean over the batch) plus the sample-consistency term.

    Returns
    -------
    loss (tensor), nll, kl, consistency (floats, batch means)
    """
    mu, var, kinds = encode_all(net, data, idx)
    w_sub, w_all = sample_subset_weights(cfg, data, idx, kinds, gen)
    mu_s, var_s = bayesian_aggregate(mu, var, w_sub)
    y = data.y[idx]
    if cfg.objective == "np":
        mu_a, var_a = bayesian_aggregate(mu, var, w_all)
        z = mu_a + torch.randn(mu_a.shape, generator=gen) * var_a.sqrt()  # ONE z per trajectory
        kl = gaussian_kl(mu_a, var_a, mu_s, var_s)
        if cfg.prior_kl_weight > 0:  # VAE term: the posteriors of whole demos fill the prior
            zeros = torch.zeros(())
            kl = kl + cfg.prior_kl_weight * gaussian_kl(mu_a, var_a, zeros, zeros + 1.0)
    else:
        z = mu_s + torch.randn(mu_s.shape, generator=gen) * var_s.sqrt()
        zeros = torch.zeros(())
        kl = (w_sub * gaussian_kl(mu, var, zeros, zeros + 1.0)).sum(1)  # Σ_i ω_i KL(q(z|a_i) ‖ p0)
    y_hat = net.decode(z, data.x)
    nll = 0.5 * ((y - y_hat) ** 2).sum((1, 2)) / cfg.sigma_y ** 2
    loss = nll + beta * kl
    cons = torch.zeros(())
    if cfg.consistency_weight > 0:
        # Sample consistency (Chamfer distance between sets): the M trajectories decoded from
        # z ~ q(z | subset) and the demonstrations of the batch that agree with the subset must
        # match as sets — every sample near SOME consistent demo (no sample between modes) and
        # every consistent demo near some sample (no mode dropped). ``consistency_encoder`` says
        # which part reaches the encoder through z: "none" (only the KL shapes q(z | subset); this
        # term shapes the decoder), "coverage" (the coverage part widens q(z | subset) until its
        # samples reach every consistent mode; the precision part, which any single mode
        # satisfies, stays a decoder term), "all".
        m = cfg.consistency_samples
        eps = torch.randn((mu_s.shape[0], m, mu_s.shape[1]), generator=gen)
        z_s = mu_s.unsqueeze(1) + eps * var_s.sqrt().unsqueeze(1)  # (B, M, k)
        ok = consistent_demos(cfg, data, idx, kinds, w_sub).unsqueeze(1)  # (B_i, 1, B_j)

        def decoded(z):  # (B_i, M, T, d): the samples' trajectories
            return net.decode(z.reshape(-1, z.shape[-1]), data.x).reshape(z.shape[0], m, *y.shape[1:])

        def distances(y_s, to, scale=1.0):  # (B_i, M, B_j): scaled squared distance of every sample to every demo's
            return ((y_s.unsqueeze(2) - to.unsqueeze(0).unsqueeze(0)) ** 2 / scale).sum((3, 4))

        z_p = z_s if cfg.consistency_encoder == "all" else z_s.detach()
        y_p = decoded(z_p)
        err = distances(y_p, y)
        inf = torch.full((), float("inf"))
        precision = torch.where(ok, err, inf).amin(2).mean(1)  # nearest consistent demo per sample
        cover = (distances(decoded(z_s), y) if cfg.consistency_encoder == "coverage" else err).amin(1)  # nearest sample per demo
        okf = ok.squeeze(1).float()
        coverage = (cover * okf).sum(1) / okf.sum(1)
        cons = 0.5 * (precision + coverage) / cfg.sigma_y ** 2
        loss = loss + cfg.consistency_weight * cons
    return loss.mean(), nll.mean().item(), kl.mean().item(), cons.mean().item()


def validation_weights(cfg: TrainConfig, data: TensorData, kinds) -> dict:
    """The fixed (seeded) conditionings of the validation MSE, as element weights (B, N_total):
    ``via`` (val_via_points random points per demo), and — when there are contexts or images —
    ``context`` (all of them, no via-point) and ``both``."""
    b, t = data.y.shape[:2]
    gen = torch.Generator(data.y.device).manual_seed(12345)
    rank = torch.rand(b, t, generator=gen).argsort(1).argsort(1)
    via = (rank < cfg.val_via_points).float()
    weights = {"via": [], "context": [], "both": []}
    for kind, sl in kinds:
        n = sl.stop - sl.start
        if kind == "via":
            weights["via"].append(via), weights["both"].append(via), weights["context"].append(torch.zeros(b, n))
        else:
            mask = data.image_mask.amax(1, keepdim=True) if kind == "image" else data.ctx_mask[kind]
            weights["via"].append(torch.zeros(b, n)), weights["context"].append(mask), weights["both"].append(mask)
    return {name: torch.cat(parts, 1) for name, parts in weights.items() if name == "via" or len(kinds) > 1}


@torch.no_grad()
def validation_mse(net: DeepProMPNet, cfg: TrainConfig, data: TensorData, norm: Normalization) -> dict:
    """Held-out reconstruction MSE (rad²), decoding at the posterior mean, for the conditionings of
    :func:`validation_weights`; ``mean`` averages the available ones."""
    net.eval()
    mu, var, kinds = encode_all(net, data, torch.arange(data.y.shape[0]))
    scale = torch.tensor(norm.y_std, dtype=torch.float32)
    out = {}
    for name, w in validation_weights(cfg, data, kinds).items():
        mu_z, _ = bayesian_aggregate(mu, var, w)
        err = (net.decode(mu_z, data.x) - data.y) * scale
        out[name] = float((err ** 2).mean())
    out["mean"] = float(np.mean(list(out.values())))
    net.train()
    return out
