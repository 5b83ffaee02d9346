"""Camera images of a recording: area-averaging resize (:func:`resize_image`) and a bounded,
evenly spread selection of the images that arrive (:class:`ImageKeeper`)."""
from __future__ import annotations

import numpy as np

from deepprompt_ros.recording.checks import RecordingError

__all__ = ["resize_image", "ImageKeeper"]


def _area_weights(n_in: int, n_out: int) -> np.ndarray:
    """Matrix (n_out, n_in): output pixel i averages input interval [i, i+1) * n_in / n_out."""
    edges = np.arange(n_out + 1) * (n_in / n_out)
    lo, hi = edges[:-1, None], edges[1:, None]
    px = np.arange(n_in)[None, :]
    overlap = np.clip(np.minimum(hi, px + 1) - np.maximum(lo, px), 0.0, None)
    return overlap / overlap.sum(axis=1, keepdims=True)


def resize_image(image, height: int, width: int) -> np.ndarray:
    """Resize an RGB image by area averaging (each output pixel is the mean of the input area it
    covers; for enlargement this is a nearest / linear mix).

    Parameters
    ----------
    image : array of uint8, shape (H, W, 3)
    height, width : int
        Output size (>= 1).

    Returns
    -------
    array of uint8, shape (height, width, 3)
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise RecordingError(f"image must be uint8 with shape (H, W, 3); got {img.dtype} {img.shape}")
    height, width = int(height), int(width)
    if height < 1 or width < 1:
        raise RecordingError(f"image size must be >= 1 pixel per side; got {width}x{height}")
    if img.shape[:2] == (height, width):
        return img.copy()
    wy = _area_weights(img.shape[0], height).astype(np.float32)
    wx = _area_weights(img.shape[1], width).astype(np.float32)
    out = np.einsum("ih,hwc,jw->ijc", wy, img.astype(np.float32), wx, optimize=True)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


class ImageKeeper:
    """Keep a bounded, roughly evenly spaced set of downsampled images of a recording.

    Images arrive at the camera rate for an unknown duration. Each is resized on arrival; when
    ``capacity`` images are held, every other one is dropped (the rest stay evenly spaced).
    :meth:`selected` returns ``max_images`` of them evenly spread over the recording.

    Parameters
    ----------
    max_images : int
        Images per demonstration (>= 1).
    height, width : int
        Stored image size.
    """

    def __init__(self, max_images: int, height: int, width: int):
        if int(max_images) < 1:
            raise RecordingError(f"max_images must be >= 1; got {max_images}")
        self.max_images = int(max_images)
        self.height, self.width = int(height), int(width)
        if self.height < 1 or self.width < 1:
            raise RecordingError(f"image size must be >= 1 pixel per side; got {width}x{height}")
        self.capacity = max(4 * self.max_images, 16)
        self._images: list[np.ndarray] = []
        self._stride = 1  # keep one of every `_stride` arriving images
        self._seen = 0

    def __len__(self) -> int:
        return len(self._images)

    def add(self, image) -> None:
        """Offer one RGB uint8 image, shape (H, W, 3), of any size."""
        self._seen += 1
        if (self._seen - 1) % self._stride:
            return
        self._images.append(resize_image(image, self.height, self.width))
        if len(self._images) >= self.capacity:
            self._images = self._images[::2]
            self._stride *= 2

    def selected(self) -> np.ndarray | None:
        """Up to ``max_images`` images evenly spread over the recording, shape (n, H, W, 3) uint8,
        or None when no image arrived."""
        if not self._images:
            return None
        n = len(self._images)
        idx = np.unique(np.rint(np.linspace(0, n - 1, min(self.max_images, n))).astype(int))
        return np.stack([self._images[i] for i in idx])
