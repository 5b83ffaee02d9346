"""A dataset as the padded, normalized tensors the training updates index into, and the
normalization fitted to the training demonstrations (:class:`deepprompt_ros.model.checkpoint.Normalization`,
stored in every checkpoint)."""
from __future__ import annotations

import dataclasses
from typing import Mapping, Sequence

import numpy as np
import torch

from deepprompt_ros.data.demo_dataset import DemoDataset
from deepprompt_ros.data.demonstration import Demonstration
from deepprompt_ros.model.checkpoint import Normalization

__all__ = ["TensorData", "fit_normalization", "to_tensors", "demos_to_tensors"]


@dataclasses.dataclass(frozen=True)
class TensorData:
    """A dataset as padded tensors (normalized units).

    y : (D, T, d); x : (T,); ctx[name] : (D, M, c) with ctx_mask[name] (D, M);
    images : (D, n, 3, H, W) float in [0, 1] with image_mask (D, n), or None.
    """

    y: torch.Tensor
    x: torch.Tensor
    ctx: Mapping[str, torch.Tensor]
    ctx_mask: Mapping[str, torch.Tensor]
    images: torch.Tensor | None
    image_mask: torch.Tensor | None


def fit_normalization(ds: DemoDataset, n_points: int) -> Normalization:
    """Per-joint mean and std (>= 1e-3) of the demos resampled at ``n_points`` phases, and of every
    context modality's vectors."""
    y = np.stack([d.resampled(n_points) for d in ds.demos])  # (D, T, d)
    y_std = np.maximum(y.reshape(-1, y.shape[-1]).std(0), 1e-3)
    ctx_mean, ctx_std = {}, {}
    for name in ds.context_dims:
        c = np.concatenate([d.contexts[name] for d in ds.demos], 0)
        ctx_mean[name] = c.mean(0)
        ctx_std[name] = np.maximum(c.std(0), 1e-3)
    return Normalization(y.reshape(-1, y.shape[-1]).mean(0), y_std, ctx_mean, ctx_std)


def to_tensors(ds: DemoDataset, norm: Normalization, n_points: int) -> TensorData:
    """``ds`` resampled at ``n_points`` equally spaced phases and normalized with ``norm``; contexts
    and images padded to the largest count with their masks."""
    return demos_to_tensors(ds.demos, norm, n_points, ds.context_dims, ds.image_shape)


def demos_to_tensors(demos: Sequence[Demonstration], norm: Normalization, n_points: int,
                     context_dims: Mapping[str, int], image_shape: tuple[int, int] | None,
                     max_contexts: Mapping[str, int] | None = None, max_images: int | None = None) -> TensorData:
    """:func:`to_tensors` of a list of demonstrations with the modalities ``context_dims`` and images of
    ``image_shape`` (or none): contexts padded to ``max_contexts[name]`` and images to ``max_images``
    (a sharded dataset's largest counts), by default to the largest count among ``demos``."""
    b = len(demos)
    y = np.stack([d.resampled(n_points) for d in demos])
    y = (y - norm.y_mean) / norm.y_std
    ctx, ctx_mask = {}, {}
    for name, dim in context_dims.items():
        m = max(d.contexts[name].shape[0] for d in demos) if max_contexts is None else max_contexts[name]
        arr, mask = np.zeros((b, m, dim)), np.zeros((b, m))
        for i, d in enumerate(demos):
            c = d.contexts[name]
            arr[i, : len(c)] = (c - norm.ctx_mean[name]) / norm.ctx_std[name]
            mask[i, : len(c)] = 1.0
        ctx[name] = torch.tensor(arr, dtype=torch.float32)
        ctx_mask[name] = torch.tensor(mask, dtype=torch.float32)
    images = image_mask = None
    if image_shape is not None:
        n = max(d.images.shape[0] for d in demos) if max_images is None else max_images
        h, w = image_shape
        images, image_mask = torch.zeros(b, n, 3, h, w), torch.zeros(b, n)
        for i, d in enumerate(demos):
            images[i, : len(d.images)] = torch.from_numpy(d.images).permute(0, 3, 1, 2).float() / 255.0
            image_mask[i, : len(d.images)] = 1.0
    return TensorData(torch.tensor(y, dtype=torch.float32), torch.linspace(0, 1, n_points), ctx, ctx_mask,
                      images, image_mask)
