"""Lazy access to matplotlib and Pillow, the ``plot`` extra.

Pictures are drawn on a bare ``Figure`` with the Agg canvas, never through ``pyplot``: no global figure
state, no GUI backend, and the pixel grid of the saved image is exactly the canvas, so the position of
every electrode in the image is known from the axes transform.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import MissingDependencyError


def require(purpose: str) -> tuple[Any, Any, Any]:
    """``(Figure, FigureCanvasAgg, PIL.Image)`` or :class:`MissingDependencyError` naming the extra."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise MissingDependencyError("matplotlib", "plot", purpose) from exc
    try:
        from PIL import Image
    except ImportError as exc:
        raise MissingDependencyError("pillow", "plot", purpose) from exc
    return Figure, FigureCanvasAgg, Image


def canvas_rgb(canvas: Any) -> np.ndarray:
    """The drawn canvas as an ``(H, W, 3)`` uint8 array."""
    canvas.draw()
    rgb: np.ndarray = np.asarray(canvas.buffer_rgba())[..., :3].copy()
    return rgb
