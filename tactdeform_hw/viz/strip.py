"""A strip of electrode-array panels side by side: the frames a run sent, in order, each labelled with
its real time and context, so an expansion can be read at a glance (a face approach shows one ring per
2 mm of travel, an edge its diverging lines, a texture its stripes travelling against the finger).

Where an animated GIF has to stretch 14 ms frames to be seen, a strip shows every frame at once and
needs no player.  matplotlib and Pillow (the ``plot`` extra) are imported only when drawing.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigurationError
from ._plot import TITLE_MARGIN_PX, canvas_rgb, fit_width, require
from .array_picture import OFF_COLOUR, level_colour

_PURPOSE = "drawing a strip of electrode-array frames"


@dataclass(frozen=True)
class StripInfo:
    """What was written: the image, how many panels, and how many sent frames were left out."""

    path: Path
    size_px: tuple[int, int]
    panels: int
    left_out: int


def strip_panels(
    records: Iterable[Any], *, sent_only: bool = True, states: Iterable[str] | None = None
) -> list[dict[str, Any]]:
    """The frames a strip shows: frames-file lines (dicts as ``render --frames`` writes them) that were
    sent (or all of them), optionally only in some states, with consecutive repeats of one pattern
    dropped."""
    keep = None if states is None else set(states)
    out: list[dict[str, Any]] = []
    for k, rec in enumerate(records):
        if not isinstance(rec, dict):
            rec = rec.to_json() if hasattr(rec, "to_json") else dict(rec)
        if rec.get("t") is None or (sent_only and not rec.get("sent", True)):
            continue
        if keep is not None and rec.get("state") not in keep:
            continue
        el = rec.get("electrodes")
        if not isinstance(el, (list, tuple)):
            raise ConfigurationError(f"frame {k}: 'electrodes' must be a list of levels, got {el!r}")
        if out and out[-1]["electrodes"] == list(el):
            continue
        out.append({**rec, "electrodes": list(el)})
    return out


def _panel(
    fig: Any,
    ax: Any,
    pos: np.ndarray,
    radius: float,
    rec: dict[str, Any],
    i: int,
    at: tuple[float, float],
    h_px: int,
) -> None:
    """One frame's panel: its electrodes on ``ax``, and under it (centred at ``at``, the panel's centre
    and bottom in figure fractions) its number and time, then its state, feature and texture."""
    from matplotlib.patches import Circle

    centre_x, bottom = at
    levels = rec["electrodes"]
    if len(levels) != len(pos):
        raise ConfigurationError(
            f"a pattern of {len(levels)} level(s) cannot be drawn on an array of {len(pos)} electrode(s)"
        )
    for (x, y), v in zip(pos, levels):
        colour = level_colour(int(v), None, 1.0) if v else OFF_COLOUR
        ax.add_patch(Circle((x, y), radius, facecolor=colour, edgecolor="#333333", lw=0.6))
    words = [str(w) for w in (rec.get("state"), rec.get("feature")) if w]
    if rec.get("texture") not in (None, "smooth"):
        words.append(str(rec["texture"]))
    fig.text(
        centre_x,
        bottom - 6 / h_px,
        f"{i}: t = {rec['t']:.3f} s",
        ha="center",
        va="top",
        fontsize=8,
    )
    fig.text(
        centre_x,
        bottom - 19 / h_px,
        " ".join(words),
        ha="center",
        va="top",
        fontsize=7,
        color="#444444",
    )


def draw_frames_strip(
    array: Any,
    records: Iterable[Any],
    path: str | Path,
    *,
    title: str | None = None,
    max_panels: int = 24,
    columns: int = 12,
    states: Iterable[str] | None = None,
    panel_px: int = 120,
) -> StripInfo:
    """A PNG with the run's sent frames side by side (``columns`` per row, at most ``max_panels``:
    the first ones; the number left out is returned and written under the title)."""
    Figure, FigureCanvasAgg, Image = require(_PURPOSE)
    if not (1 <= int(max_panels) <= 400):
        raise ConfigurationError(f"max_panels={max_panels!r} is out of range: 1 to 400")
    if not (1 <= int(columns) <= 40):
        raise ConfigurationError(f"columns={columns!r} is out of range: 1 to 40")
    if not (60 <= int(panel_px) <= 600):
        raise ConfigurationError(f"panel_px={panel_px!r} is out of range: 60 to 600 pixels")
    panels = strip_panels(records, states=states)
    if not panels:
        raise ConfigurationError("no sent frame to draw in the strip")
    shown = panels[: int(max_panels)]
    left_out = len(panels) - len(shown)
    pos = np.asarray(array.positions_mm, dtype=float).reshape(-1, 2)
    radius = float(array.radius_mm)
    n = len(shown)
    cols = min(int(columns), n)
    rows = -(-n // cols)
    head_px, label_px = 48, 34
    w_px = cols * panel_px
    h_px = head_px + rows * (panel_px + label_px)
    dpi = 100
    fig = Figure(figsize=(w_px / dpi, h_px / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    heading = title or getattr(array, "name", "") or "frames"
    if left_out:
        heading += f"  (first {n} of {len(panels)} frames)"
    heading_text = fig.text(0.5, 1 - 16 / h_px, heading, ha="center", va="center", fontsize=10)
    fit_width(heading_text, w_px - 2 * TITLE_MARGIN_PX, canvas.get_renderer())
    lo, hi = pos.min(axis=0) - radius * 1.6, pos.max(axis=0) + radius * 1.6
    for i, rec in enumerate(shown):
        r, c = divmod(i, cols)
        left = c * panel_px / w_px
        bottom = 1 - (head_px + (r + 1) * (panel_px + label_px) - label_px) / h_px
        ax = fig.add_axes((left + 4 / w_px, bottom, (panel_px - 8) / w_px, (panel_px - 8) / h_px))
        ax.set_aspect("equal")
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.axis("off")
        _panel(fig, ax, pos, radius, rec, i, (left + 0.5 * panel_px / w_px, bottom), h_px)
    rgb = canvas_rgb(canvas)
    p = Path(path)
    Image.fromarray(rgb).save(p, format="PNG")
    return StripInfo(p, (rgb.shape[1], rgb.shape[0]), n, left_out)
