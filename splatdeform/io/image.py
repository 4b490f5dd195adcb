"""Writing rendered images: PNG and animated GIF, atomically (Pillow).

Every writer goes through the tool's one atomic writer, :func:`splatdeform.io.atomic.atomic_write`
(temp file in the target folder, then rename), so a failed write leaves no partial file and the
image gets the file mode models get.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from splatdeform.errors import InputError
from splatdeform.io.atomic import atomic_write


def save_png(image: np.ndarray, path: str | os.PathLike[str]) -> Path:
    """Write an (H, W, 3|4) uint8 image as PNG atomically. Returns the path."""
    from PIL import Image

    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise InputError(f"image: expected (H, W, 3|4) uint8, got {arr.shape} {arr.dtype}")
    return save_pil(Image.fromarray(arr), path, format="PNG")


def save_gif(frames: Sequence[np.ndarray], path: str | os.PathLike[str], *,
             duration_ms: int) -> Path:
    """Write (H, W, 3) uint8 frames as one looping animated GIF (256 colours per frame, median
    cut), ``duration_ms`` per frame, atomically. Returns the path."""
    from PIL import Image

    pil = [
        Image.fromarray(f).quantize(colors=256, method=Image.Quantize.MEDIANCUT) for f in frames
    ]
    return save_pil(pil[0], path, format="GIF", save_all=True, append_images=pil[1:],
                    duration=int(duration_ms), loop=0)


def save_pil(image: Any, path: str | os.PathLike[str], **save_kwargs: Any) -> Path:
    """Save a Pillow image atomically (``save_kwargs`` go to ``Image.save``). Returns the path."""
    out = Path(path)
    with atomic_write(out) as handle:
        image.save(handle, **save_kwargs)
    return out
