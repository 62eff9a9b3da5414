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


#: The space left between a fitted title and the picture's edges, in pixels.
TITLE_MARGIN_PX = 8

#: The smallest font a fitted title or label is shrunk to; below it, text is elided instead.
MIN_FONTSIZE_PT = 7.0


def fit_width(text: Any, width_px: float, renderer: Any, *, min_fontsize: float = MIN_FONTSIZE_PT) -> None:
    """Make a drawn text at most ``width_px`` wide: a smaller font first (down to ``min_fontsize``), then
    the middle of the text elided with ``…``.  A title that runs past the picture's edge loses its ends —
    the trajectory, the file name — the very words that tell one picture from another."""
    for _ in range(4):  # the extent is not exactly proportional to the size (hinting): a few rounds
        wide = float(text.get_window_extent(renderer).width)
        size = float(text.get_fontsize())
        if wide <= width_px or size <= min_fontsize:
            break
        text.set_fontsize(max(min_fontsize, size * width_px / wide * 0.98))
    full = str(text.get_text())
    keep = len(full)
    while float(text.get_window_extent(renderer).width) > width_px and keep > 1:
        keep -= 1
        head, tail = (keep + 1) // 2, keep // 2
        text.set_text(full[:head] + "…" + (full[len(full) - tail :] if tail else ""))


def keep_inside(label: Any, left_px: float, right_px: float, renderer: Any) -> None:
    """Shift an annotation placed with ``textcoords="offset points"`` sideways so its extent lies between
    ``left_px`` and ``right_px`` (display pixels): a label anchored near a plot's edge is otherwise cut
    off there.  A label wider than the space is first shrunk (:func:`fit_width`)."""
    fit_width(label, right_px - left_px, renderer)
    box = label.get_window_extent(renderer)
    shift_px = 0.0
    if box.x1 > right_px:
        shift_px = right_px - box.x1
    if box.x0 + shift_px < left_px:
        shift_px = left_px - box.x0
    if shift_px:
        dx_pt, dy_pt = label.xyann
        label.xyann = (dx_pt + shift_px * 72.0 / label.figure.dpi, dy_pt)


def box_px(artist: Any, renderer: Any, height_px: int) -> tuple[float, float, float, float]:
    """An artist's drawn extent in image pixels: (left, top, right, bottom), rows counted from the top."""
    box = artist.get_window_extent(renderer)
    return (float(box.x0), float(height_px - box.y1), float(box.x1), float(height_px - box.y0))
