"""The reconstruction metric of the paper's comparison (Sec. IV, Fig. "radar plots"): how well a
model, conditioned on part of a held-out demonstration, reproduces all of it.

Works on any model with the interface of
:class:`deepprompt_ros.baselines.interface.MovementPrimitiveModel` (``kind``, ``context_dims``,
``image_shape``, ``supports_images``, ``condition``, ``mean_trajectory``); it imports no model, so
the models' own validation (:class:`deepprompt_ros.baselines.promp_model.ProMPModel`) can use it.
MSEs are in rad².
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from deepprompt_ros.data.demo_dataset import DemoDataset

if TYPE_CHECKING:
    from deepprompt_ros.baselines.interface import MovementPrimitiveModel

__all__ = ["CONDITIONINGS", "available_conditionings", "reconstruction_mse", "reconstruction_table"]


CONDITIONINGS = ("via_point", "image", "low_dim", "image+low", "aggregate")


def available_conditionings(model: MovementPrimitiveModel, ds: DemoDataset) -> tuple[str, ...]:
    """The conditionings of :data:`CONDITIONINGS` (without "aggregate") that ``model`` and ``ds`` both
    support: "via_point" always; "low_dim" if the data has low-dim contexts; "image" if it has images
    and the model takes them (not ProMP); "image+low" if both."""
    low = bool(ds.context_dims) and bool(model.context_dims)
    img = ds.image_shape is not None and model.supports_images and model.image_shape is not None
    out = ["via_point"]
    if img:
        out.append("image")
    if low:
        out.append("low_dim")
    if img and low:
        out.append("image+low")
    return tuple(out)


def reconstruction_mse(model: MovementPrimitiveModel, test: DemoDataset, conditioning: str,
                       n_via: int | None = None, n_points: int = 100, seed: int = 0) -> float:
    """Mean squared error (rad²) of reconstructing held-out demonstrations (paper Sec. IV).

    Each demo is resampled on ``n_points`` equally spaced phases; the model is conditioned and its
    ``mean_trajectory`` compared with the demo on that grid (mean over demos, phases and joints).

    Conditionings (paper: "for each context variable input, we include the initial robot position"):

    ``via_point``  via-points only, no context. ``n_via=None`` (default, the paper's setting): the
                   full trajectory as via-points (all ``n_points`` points); an int k: k points per demo
                   drawn without replacement by ``np.random.default_rng([seed, demo index])`` (a fixed
                   seeded set, identical for every model).
    ``image``      the first point (x=0, y_0) + the demo's images.
    ``low_dim``    the first point + every low-dimensional context modality.
    ``image+low``  the first point + images + low-dimensional contexts.
    ``aggregate``  the mean of the MSEs of the above that :func:`available_conditionings` lists.

    Raises ValueError for an unknown conditioning or one the model / data do not support.
    """
    if conditioning not in CONDITIONINGS:
        raise ValueError(f"conditioning '{conditioning}' unknown; expected one of {CONDITIONINGS}")
    if int(n_points) != n_points or n_points < 2:
        raise ValueError(f"n_points must be an integer >= 2, got {n_points}")
    if n_via is not None and (int(n_via) != n_via or not 1 <= n_via <= n_points):
        raise ValueError(f"n_via must be None (all points) or an integer in [1, n_points={n_points}], got {n_via}")
    avail = available_conditionings(model, test)
    if conditioning == "aggregate":
        return float(np.mean([reconstruction_mse(model, test, c, n_via, n_points, seed) for c in avail]))
    if conditioning not in avail:
        raise ValueError(f"conditioning '{conditioning}' is not available for model '{model.kind}' on dataset "
                         f"'{test.source}' (contexts {test.context_dims or 'none'}, images "
                         f"{'yes' if test.image_shape else 'none'}); available: {avail}")
    x = np.linspace(0.0, 1.0, n_points)
    errs = []
    for i, demo in enumerate(test.demos):
        y = demo.resampled(n_points)
        kw = {}
        if conditioning == "via_point":
            sel = np.arange(n_points) if n_via is None else np.sort(
                np.random.default_rng([seed, i]).choice(n_points, int(n_via), replace=False))
            kw.update(via_x=x[sel], via_y=y[sel])
        else:
            kw.update(via_x=x[:1], via_y=y[:1])
            if conditioning in ("low_dim", "image+low"):
                kw["contexts"] = dict(demo.contexts)
            if conditioning in ("image", "image+low"):
                kw["images"] = demo.images
        pred = model.mean_trajectory(model.condition(**kw), x)
        errs.append(float(((pred - y) ** 2).mean()))
    return float(np.mean(errs))


def reconstruction_table(model: MovementPrimitiveModel, test: DemoDataset, n_via: int | None = None,
                         n_points: int = 100, seed: int = 0) -> dict[str, float]:
    """All available conditionings and their "aggregate": {conditioning: MSE (rad²)}."""
    out = {c: reconstruction_mse(model, test, c, n_via, n_points, seed) for c in available_conditionings(model, test)}
    out["aggregate"] = float(np.mean(list(out.values())))
    return out
