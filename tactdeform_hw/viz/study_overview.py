"""One picture of a whole study: every trial in a grid sized to a screen, its key frames on small arrays.

The per-trial strips hold the detail (axes, titles, legends); the overview is for seeing all trials at
once, so it is laid out to fit :data:`SCREEN_PX` (1920 × 1200, a common laboratory monitor at 100 %)
with every label at least :data:`MIN_FONT_PT` points (at the figure's 100 dpi, 10 pt is 14 px).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ._plot import require

SCREEN_PX = (1920, 1200)
DPI = 100
MIN_FONT_PT = 10.0
MAX_FRAMES = 4
_PAD = 10
_TITLE_PX = 24
_CAPTION_PX = 20
_HEADER_PX = 34
_MAX_THUMB = 150
_GAP = 16


@dataclass(frozen=True)
class OverviewFrame:
    levels: tuple[int, ...]
    caption: str


@dataclass(frozen=True)
class OverviewTrial:
    title: str
    passed: bool
    frames: tuple[OverviewFrame, ...]
    note: str = ""


@dataclass(frozen=True)
class OverviewInfo:
    path: Path
    size_px: tuple[int, int]
    columns: int
    rows: int
    thumb_px: int
    min_font_pt: float


def grid_for(n: int, frames: int, screen: tuple[int, int] = SCREEN_PX) -> tuple[int, int, int]:
    """``(columns, rows, thumbnail px)`` giving the largest thumbnails that fit ``screen``."""
    best = (1, max(n, 1), 0)
    frames = max(1, frames)
    for cols in range(1, max(1, n) + 1):
        rows = math.ceil(max(n, 1) / cols)
        by_w = (screen[0] / cols - 2 * _PAD + _GAP) / frames - _GAP
        by_h = (screen[1] - _HEADER_PX) / rows - _TITLE_PX - _CAPTION_PX - _PAD
        size = int(min(by_w, by_h, _MAX_THUMB))
        if size > best[2]:
            best = (cols, rows, size)
    return best


@dataclass
class _Sheet:
    """The figure's one axes in pixel coordinates (y down), and every font size written on it."""

    ax: Any
    fonts: list[float] = field(default_factory=list)

    def text(self, x: float, y: float, s: str, size: float = MIN_FONT_PT, **kw: Any) -> None:
        self.fonts.append(size)
        self.ax.text(x, y, s, fontsize=size, va="center", **kw)


@dataclass(frozen=True)
class _Thumbs:
    """How an array is drawn in a thumbnail of ``thumb`` pixels: positions, bounds, scale, disc size and
    the colour of each level."""

    pos: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    span: float
    thumb: int
    scale: float
    disc_pt: float
    colours: dict[int, Any]


def _draw_header(sheet: _Sheet, title: str, colours: dict[int, Any]) -> None:
    """The title and what each colour means."""
    x = float(_PAD)
    if title:
        sheet.text(x, _HEADER_PX / 2, title, 12, weight="bold")
        x += 12 * 0.62 * len(title) * DPI / 72 + 24
    for level, name in ((0, "off"), (1, "monophasic"), (2, "biphasic")):
        sheet.ax.scatter(
            [x + 7], [_HEADER_PX / 2], s=110, color=colours[level], edgecolors="#333333", linewidths=0.6
        )
        sheet.text(x + 20, _HEADER_PX / 2, name)
        x += 20 + 10 * 0.62 * len(name) * DPI / 72 + 24


def _draw_trial(
    sheet: _Sheet, trial: OverviewTrial, at: tuple[int, int], cell: tuple[int, int], th: _Thumbs
) -> None:
    """One trial's cell of size ``cell`` at ``at``: its title and verdict, then its frames with their
    captions."""
    (cx, cy), (cell_w, cell_h) = at, cell
    ax, thumb = sheet.ax, th.thumb
    ax.add_patch(_rect(cx + 3, cy + 2, cell_w - 6, cell_h - 4, "#f6f6f6" if trial.passed else "#fbeaea"))
    sheet.text(
        cx + _PAD,
        cy + _TITLE_PX / 2 + 2,
        trial.title,
        MIN_FONT_PT,
        weight="bold",
        color="#222222" if trial.passed else "#aa0000",
    )
    sheet.text(
        cx + cell_w - _PAD,
        cy + _TITLE_PX / 2 + 2,
        "pass" if trial.passed else "FAIL",
        MIN_FONT_PT,
        ha="right",
        weight="bold",
        color="#226622" if trial.passed else "#aa0000",
    )
    if not trial.frames:
        sheet.text(
            cx + _PAD,
            cy + _TITLE_PX + thumb / 2,
            trial.note or "no electrode was switched on",
            MIN_FONT_PT,
            color="#aa0000",
        )
        return
    pos, lo, hi, span, scale = th.pos, th.lo, th.hi, th.span, th.scale
    for j, frame in enumerate(trial.frames):
        ox = cx + _PAD + j * (thumb + _GAP) + 4
        oy = cy + _TITLE_PX + 4
        px = ox + (pos[:, 0] - lo[0]) * scale + (span - (hi[0] - lo[0])) * scale / 2
        py = oy + (hi[1] - pos[:, 1]) * scale + (span - (hi[1] - lo[1])) * scale / 2
        cs = [th.colours[int(v) if int(v) in (1, 2) else 0] for v in frame.levels[: len(pos)]]
        ax.scatter(px, py, s=th.disc_pt**2, c=cs, edgecolors="#333333", linewidths=0.4)
        sheet.text(
            ox + (thumb - 8) / 2,
            oy + thumb + _CAPTION_PX / 2 - 4,
            frame.caption,
            MIN_FONT_PT,
            ha="center",
            color="#222222",
        )


def draw_study_overview(
    positions_mm: np.ndarray,
    radius_mm: float,
    trials: Sequence[OverviewTrial],
    path: str | Path,
    *,
    title: str = "",
    screen: tuple[int, int] = SCREEN_PX,
) -> OverviewInfo:
    """Draw ``trials`` as a grid that fits ``screen``; each cell: the trial's title and verdict, its
    frames on the array (off grey, monophasic red, biphasic purple) with a caption under each."""
    figure_cls, canvas_cls, _image = require("drawing the study overview")
    from .array_picture import level_colour

    frames = max((len(t.frames) for t in trials), default=1)
    cols, rows, thumb = grid_for(len(trials), frames, screen)
    cell_w = frames * thumb + (frames - 1) * _GAP + 2 * _PAD
    cell_h = _TITLE_PX + thumb + _CAPTION_PX + _PAD
    width = cols * cell_w
    height = _HEADER_PX + rows * cell_h
    fig = figure_cls(figsize=(width / DPI, height / DPI), dpi=DPI)
    canvas_cls(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_xlim(0, width)
    ax.set_ylim(height, 0)
    ax.axis("off")
    sheet = _Sheet(ax)
    pos = np.asarray(positions_mm, dtype=float)
    lo, hi = pos.min(axis=0) - radius_mm, pos.max(axis=0) + radius_mm
    span = float(max(hi - lo)) or 1.0
    colours = {level: level_colour(level, None, 1.0) for level in (0, 1, 2)}
    _draw_header(sheet, title, colours)
    scale = (thumb - 8) / span
    th = _Thumbs(pos, lo, hi, span, thumb, scale, 2 * radius_mm * scale * 72 / DPI, colours)
    for k, trial in enumerate(trials):
        _draw_trial(
            sheet, trial, ((k % cols) * cell_w, _HEADER_PX + (k // cols) * cell_h), (cell_w, cell_h), th
        )
    out = Path(path)
    fig.savefig(out, format="png", dpi=DPI)
    fonts = sheet.fonts
    return OverviewInfo(out, (width, height), cols, rows, thumb, min(fonts) if fonts else MIN_FONT_PT)


def _rect(x: float, y: float, w: float, h: float, colour: str) -> Any:
    from matplotlib.patches import Rectangle

    return Rectangle((x, y), w, h, facecolor=colour, edgecolor="#dddddd", lw=0.8, zorder=0)
