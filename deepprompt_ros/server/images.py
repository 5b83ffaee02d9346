"""Images of an image context: checked against the primitive's size and decoded to RGB."""
from __future__ import annotations

import numpy as np

from deepprompt_ros.common.results import Code, RequestError
from deepprompt_ros.server.requests import ImageIn

__all__ = ["IMAGE_ENCODINGS", "decode_image"]

IMAGE_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8")
_CHANNELS = {"rgb8": (3, (0, 1, 2)), "bgr8": (3, (2, 1, 0)), "rgba8": (4, (0, 1, 2)), "bgra8": (4, (2, 1, 0))}


def decode_image(img: ImageIn, shape: tuple[int, int], where: str = "image") -> np.ndarray:
    """Check one image against the primitive's (H, W) and return it as RGB uint8 (H, W, 3).

    Accepted encodings: rgb8, bgr8, rgba8, bgra8 (alpha dropped). Raises RequestError(INVALID_IMAGE).
    """
    h, w = shape
    enc = img.encoding.lower()
    if enc not in _CHANNELS:
        raise RequestError(Code.INVALID_IMAGE, f"{where} has encoding '{img.encoding}'; expected one of "
                           f"{', '.join(IMAGE_ENCODINGS)} (rgb8 preferred)")
    if (img.height, img.width) != (h, w):
        raise RequestError(Code.INVALID_IMAGE, f"{where} is {img.height}x{img.width} (height x width); the "
                           f"primitive expects {h}x{w} images")
    ch, order = _CHANNELS[enc]
    if img.step < w * ch:
        raise RequestError(Code.INVALID_IMAGE, f"{where} has step {img.step} bytes per row; {enc} at width {w} "
                           f"needs at least {w * ch}")
    if img.data.size != img.step * h:
        raise RequestError(Code.INVALID_IMAGE, f"{where} has {img.data.size} bytes of data; expected "
                           f"step x height = {img.step} x {h} = {img.step * h}")
    rows = np.asarray(img.data, dtype=np.uint8).reshape(h, img.step)[:, :w * ch].reshape(h, w, ch)
    return np.ascontiguousarray(rows[:, :, list(order)])
