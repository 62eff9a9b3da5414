"""Pictures of the electrode array: which electrodes are on, with what pulse, at what current.

Electrodes are drawn as discs at their real positions and radius (millimetres, x right, y up, equal
scale on both axes) over the board outline, so a picture compares directly with the array on the finger
and with the eTactileKit GUI's view.  Off electrodes are grey; monophasic ones warm (yellow to dark red
with the current), biphasic ones cool (light to deep purple).  A pattern or a frames file becomes an
animated GIF with one frame per change of pattern, held for its real duration.

GIF players do not honour frames shorter than about 20 ms, and a renderer running at 72 Hz changes the
pattern every 14 ms; :func:`draw_array_gif` therefore holds each GIF frame at least ``min_frame_ms``
(stretching time where patterns change faster than that, never dropping one) unless ``frame_ms`` asks
for sampling at a fixed interval instead.  A stretched frame says so on the picture: its label carries
the real time it was held beside the time it is shown.  A renderer's frames (:func:`draw_frames_gif`)
are held at least :data:`MIN_DISPLAY_MS` — long enough for an eye to take in a pattern — and each one
is labelled with its real time ``t``, so an expansion is seen frame by frame and still read in real
time.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigurationError
from ._plot import TITLE_MARGIN_PX, box_px, canvas_rgb, fit_width, require

OFF_COLOUR = "#c8c8c8"
OUTLINE_FILL = "#f4f1ea"
#: Full-scale current for the colour ramp when none is given (the hardware ceiling, 10 mA).
FULL_SCALE_UA = 10_000.0
_PURPOSE = "drawing electrode-array pictures"
#: The shortest time a renderer's frame is shown in a GIF: about what an eye needs to take in a pattern.
MIN_DISPLAY_MS = 250.0


@dataclass(frozen=True)
class PictureFrame:
    """What one picture shows: levels in application order (0 off, 1 mono, 2 biphasic)."""

    levels: tuple[int, ...]
    duration_ms: float = 100.0
    label: str = ""
    current_ua: float | None = None


@dataclass(frozen=True)
class PictureInfo:
    """What was written.  ``centres_px[i]`` is electrode i's centre as (column, row) in the image."""

    path: Path
    size_px: tuple[int, int]
    frames: int
    centres_px: np.ndarray
    radius_px: float
    durations_ms: tuple[int, ...] = ()
    notes: tuple[str, ...] = field(default_factory=tuple)
    #: the title as drawn (shrunk or elided to fit) and its extent, (left, top, right, bottom) in pixels
    title: str = ""
    title_box_px: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)


# --- inputs -------------------------------------------------------------------------------------------------


def frames_from_sequence(
    seq: Any, array_file: Any | None = None, current_ua: float | None = None
) -> list[PictureFrame]:
    """Picture frames of an eTactileKit pattern (an OFF phase becomes an all-off frame)."""
    out: list[PictureFrame] = []
    total = len(seq.steps)
    for i, step in enumerate(seq.steps):
        levels = (
            array_file.levels_for(step.levels, f"Pattern_Data[{i}][0].pattern") if array_file else step.levels
        )
        head = f"step {i + 1}/{total}"
        out.append(PictureFrame(tuple(levels), step.on_ms, f"{head} · ON {step.on_ms:g} ms", current_ua))
        if step.off_ms > 0:
            out.append(
                PictureFrame((0,) * len(levels), step.off_ms, f"{head} · OFF {step.off_ms:g} ms", current_ua)
            )
    return out


def frames_from_frames(
    frames: Iterable[Any],
    *,
    sent_only: bool = True,
    last_ms: float | None = None,
    current_ua: float | None = None,
) -> list[PictureFrame]:
    """Picture frames of a TactDeform frames record: what the board held, span by span (see
    :func:`~tactdeform_hw.formats.frames.delivered_spans`; unsent frames are skipped by default, since
    the board kept the previous pattern through them)."""
    from ..formats.frames import delivered_spans

    out = []
    for f, _, dur in delivered_spans(list(frames), sent_only=sent_only, last_ms=last_ms):
        parts = [f"t = {f.t_s:.3f} s"] + [p for p in (f.state, f.feature, f.texture) if p]
        cur = f.current_ua if f.current_ua is not None else current_ua
        out.append(PictureFrame(tuple(f.electrodes), dur, " · ".join(parts), cur))
    return out


def merge_runs(frames: Sequence[PictureFrame]) -> list[PictureFrame]:
    """Join consecutive frames that look the same (levels and current), adding their durations."""
    out: list[PictureFrame] = []
    for f in frames:
        if out and out[-1].levels == f.levels and out[-1].current_ua == f.current_ua:
            prev = out[-1]
            out[-1] = PictureFrame(prev.levels, prev.duration_ms + f.duration_ms, prev.label, prev.current_ua)
        else:
            out.append(f)
    return out


def resample(frames: Sequence[PictureFrame], frame_ms: float) -> list[PictureFrame]:
    """The frame showing at every ``frame_ms`` of real time (changes shorter than that may be skipped)."""
    if not frame_ms > 0:
        raise ConfigurationError(f"frame_ms={frame_ms!r} is out of range: a positive number of milliseconds")
    ends = np.cumsum([f.duration_ms for f in frames])
    total = float(ends[-1]) if len(ends) else 0.0
    count = max(1, int(np.ceil(total / frame_ms - 1e-9)))
    out = []
    for k in range(count):
        idx = min(int(np.searchsorted(ends, k * frame_ms, side="right")), len(frames) - 1)
        src = frames[idx]
        out.append(PictureFrame(src.levels, frame_ms, src.label, src.current_ua))
    return merge_runs(out)


# --- drawing ------------------------------------------------------------------------------------------------


def level_colour(
    level: int, current_ua: float | None, full_scale_ua: float
) -> tuple[float, float, float, float]:
    from matplotlib import colormaps

    if level not in (1, 2):
        from matplotlib.colors import to_rgba

        return to_rgba(OFF_COLOUR)
    frac = 1.0 if current_ua is None else float(np.clip(current_ua / full_scale_ua, 0.0, 1.0))
    cmap = colormaps["YlOrRd" if level == 1 else "Purples"]
    r, g, b, a = cmap(0.45 + 0.55 * frac)
    return (r, g, b, a)


class _Scene:
    """One figure with the outline and a disc per electrode; frames only recolour the discs."""

    def __init__(
        self,
        array: Any,
        outline_mm: np.ndarray | None,
        title: str,
        size_px: tuple[int, int],
        full_scale_ua: float,
        show_current_scale: bool,
        numbers: bool,
    ) -> None:
        Figure, FigureCanvasAgg, _ = require(_PURPOSE)
        from matplotlib.patches import Polygon

        self.pos = np.asarray(array.positions_mm, dtype=float).reshape(-1, 2)
        self.radius = float(array.radius_mm)
        if not (np.all(np.isfinite(self.pos)) and np.isfinite(self.radius) and self.radius > 0):
            raise ConfigurationError("the array has a non-finite position or radius; nothing can be drawn")
        self.full_scale_ua = full_scale_ua
        dpi = 100
        self.fig = Figure(figsize=(size_px[0] / dpi, size_px[1] / dpi), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.fig)
        w_px, h_px = size_px
        left = 62 / w_px
        right = 1 - (95 if show_current_scale else 20) / w_px
        bottom, top = 70 / h_px, 1 - 62 / h_px
        ax = self.fig.add_axes((left, bottom, right - left, top - bottom))
        self.ax = ax
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_facecolor("white")
        pts = [self.pos - self.radius, self.pos + self.radius]
        if outline_mm is not None and len(outline_mm):
            outline = np.asarray(outline_mm, dtype=float)
            ax.add_patch(
                Polygon(outline, closed=True, facecolor=OUTLINE_FILL, edgecolor="#555555", lw=1.2, zorder=1)
            )
            pts.append(outline)
        allpts = np.vstack(pts)
        lo, hi = allpts.min(axis=0), allpts.max(axis=0)
        pad = 0.06 * float(np.max(hi - lo)) + self.radius
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        self.discs = self._discs(numbers)
        self.heading = self.fig.suptitle(title, fontsize=11, y=1 - 8 / h_px, va="top")
        fit_width(self.heading, w_px - 2 * TITLE_MARGIN_PX, self.canvas.get_renderer())
        self.label = self.fig.text(
            0.5, 1 - 40 / h_px, "", ha="center", va="center", fontsize=9, color="#222222"
        )
        self._legend()
        if show_current_scale:
            self._current_scale(w_px, bottom, top)
        self.canvas.draw()
        disp = ax.transData.transform(self.pos)
        height = self.canvas.get_width_height()[1]
        self.centres_px = np.column_stack([disp[:, 0], height - disp[:, 1]])
        edge = ax.transData.transform(self.pos[:1] + [self.radius, 0.0])
        self.radius_px = float(edge[0, 0] - disp[0, 0]) if len(self.pos) else 0.0

    @classmethod
    def of(
        cls,
        array: Any,
        outline_mm: np.ndarray | None,
        title: str | None,
        size_px: tuple[int, int],
        full_scale_ua: float | None,
        show_current_scale: bool,
        numbers: bool,
    ) -> _Scene:
        """The scene with the picture defaults: the array's name as title, the 10 mA full scale."""
        return cls(
            array,
            outline_mm,
            title or getattr(array, "name", "") or "electrode array",
            size_px,
            float(full_scale_ua or FULL_SCALE_UA),
            show_current_scale,
            numbers,
        )

    def _discs(self, numbers: bool) -> list[Any]:
        """A disc per electrode at its position and radius, off; numbered when ``numbers``."""
        from matplotlib.patches import Circle

        ax = self.ax
        discs = []
        for i, (x, y) in enumerate(self.pos):
            disc = Circle((x, y), self.radius, facecolor=OFF_COLOUR, edgecolor="#333333", lw=0.8, zorder=3)
            ax.add_patch(disc)
            discs.append(disc)
            if numbers:
                ax.annotate(
                    str(i),
                    (x, y - self.radius),
                    xytext=(0, -2),
                    textcoords="offset points",
                    ha="center",
                    va="top",
                    fontsize=6,
                    color="#444444",
                    zorder=4,
                )
        return discs

    def _legend(self) -> None:
        """What the colours mean: off, monophasic, biphasic."""
        from matplotlib.lines import Line2D

        handles = [
            Line2D([], [], ls="", marker="o", ms=8, mfc=colour, mec="#333333", label=label)
            for colour, label in (
                (OFF_COLOUR, "off"),
                (level_colour(1, None, 1.0), "monophasic"),
                (level_colour(2, None, 1.0), "biphasic"),
            )
        ]
        self.fig.legend(
            handles=handles, loc="lower center", bbox_to_anchor=(0.5, 0.0), ncol=3, fontsize=8, frameon=False
        )

    def _current_scale(self, w_px: int, bottom: float, top: float) -> None:
        """The colour ramp of the current, from 0 to the full scale in mA."""
        from matplotlib import colormaps
        from matplotlib.cm import ScalarMappable
        from matplotlib.colors import LinearSegmentedColormap, Normalize

        ramp = LinearSegmentedColormap.from_list(
            "on", [colormaps["YlOrRd"](v) for v in np.linspace(0.45, 1.0, 32)]
        )
        cax = self.fig.add_axes(
            (1 - 75 / w_px, bottom + 0.1 * (top - bottom), 12 / w_px, 0.8 * (top - bottom))
        )
        bar = self.fig.colorbar(ScalarMappable(Normalize(0, self.full_scale_ua / 1000.0), ramp), cax=cax)
        bar.set_label("current (mA)", fontsize=8)
        bar.ax.tick_params(labelsize=7)

    def title_box_px(self) -> tuple[float, float, float, float]:
        return box_px(self.heading, self.canvas.get_renderer(), self.canvas.get_width_height()[1])

    def render(self, frame: PictureFrame) -> np.ndarray:
        if len(frame.levels) != len(self.discs):
            raise ConfigurationError(
                f"a pattern of {len(frame.levels)} level(s) cannot be drawn on an array of "
                f"{len(self.discs)} electrode(s)"
            )
        if frame.current_ua is not None and not (np.isfinite(frame.current_ua) and frame.current_ua >= 0):
            raise ConfigurationError(
                f"current_ua={frame.current_ua!r} is out of range: a finite current ≥ 0 µA"
            )
        for disc, level in zip(self.discs, frame.levels):
            disc.set_facecolor(level_colour(int(level), frame.current_ua, self.full_scale_ua))
        active = sum(1 for v in frame.levels if v)
        parts = [frame.label] if frame.label else []
        parts.append(f"{active}/{len(frame.levels)} on")
        if frame.current_ua is not None:
            parts.append(f"{frame.current_ua / 1000.0:.2f} mA")
        self.label.set_text(" · ".join(parts))
        return canvas_rgb(self.canvas)


def _check_size(size_px: tuple[int, int]) -> tuple[int, int]:
    w, h = (int(v) for v in size_px)
    if not (120 <= w <= 4000 and 120 <= h <= 4000):
        raise ConfigurationError(f"size_px={size_px!r} is out of range: 120 to 4000 pixels each way")
    return w, h


def draw_array_png(
    array: Any,
    levels: Sequence[int],
    path: str | Path,
    *,
    current_ua: float | None = None,
    outline_mm: np.ndarray | None = None,
    title: str | None = None,
    label: str = "",
    full_scale_ua: float | None = None,
    size_px: tuple[int, int] = (640, 600),
    numbers: bool = False,
) -> PictureInfo:
    """A PNG of ``array`` showing ``levels`` (application order) at ``current_ua``."""
    _, _, Image = require(_PURPOSE)
    size_px = _check_size(size_px)
    scene = _Scene.of(array, outline_mm, title, size_px, full_scale_ua, current_ua is not None, numbers)
    rgb = scene.render(PictureFrame(tuple(int(v) for v in levels), 0.0, label, current_ua))
    p = Path(path)
    Image.fromarray(rgb).save(p, format="PNG")
    return PictureInfo(
        p,
        (rgb.shape[1], rgb.shape[0]),
        1,
        scene.centres_px,
        scene.radius_px,
        title=str(scene.heading.get_text()),
        title_box_px=scene.title_box_px(),
    )


def draw_array_gif(
    array: Any,
    frames: Sequence[PictureFrame],
    path: str | Path,
    *,
    outline_mm: np.ndarray | None = None,
    title: str | None = None,
    speed: float = 1.0,
    min_frame_ms: float = 20.0,
    frame_ms: float | None = None,
    max_frames: int = 1500,
    full_scale_ua: float | None = None,
    size_px: tuple[int, int] = (480, 450),
    numbers: bool = False,
    loop: bool = True,
) -> PictureInfo:
    """An animated GIF of ``frames`` on ``array``.

    Consecutive identical frames become one; ``speed`` > 1 plays faster than real time.  ``frame_ms``
    samples at a fixed real-time interval instead.  More than ``max_frames`` frames are resampled evenly
    (a note says so).
    """
    _, _, Image = require(_PURPOSE)
    size_px = _check_size(size_px)
    if not frames:
        raise ConfigurationError("no frame to draw")
    if not (speed > 0 and np.isfinite(speed)):
        raise ConfigurationError(f"speed={speed!r} is out of range: a positive number")
    notes: list[str] = []
    seq = resample(frames, frame_ms) if frame_ms is not None else merge_runs(frames)
    if len(seq) > max_frames:
        total = sum(f.duration_ms for f in seq)
        step = total / max_frames
        notes.append(
            f"{len(seq)} frames resampled every {step:.1f} ms to stay within {max_frames} GIF frames"
        )
        seq = resample(seq, step)
    durations = []
    stretched = 0
    for i, f in enumerate(seq):
        d = f.duration_ms / speed
        if d < min_frame_ms:
            stretched += 1
            real = f"real {f.duration_ms:.0f} ms, shown {min_frame_ms:.0f} ms"
            seq[i] = PictureFrame(
                f.levels, f.duration_ms, f"{f.label} · {real}" if f.label else real, f.current_ua
            )
            d = min_frame_ms
        durations.append(int(round(d)))
    if stretched:
        notes.append(f"{stretched} frame(s) shorter than {min_frame_ms:g} ms were held {min_frame_ms:g} ms")
    currents = [f.current_ua for f in seq if f.current_ua is not None]
    scene = _Scene.of(array, outline_mm, title, size_px, full_scale_ua, bool(currents), numbers)
    images = [
        Image.fromarray(scene.render(f)).convert("P", palette=Image.Palette.ADAPTIVE, colors=255) for f in seq
    ]
    p = Path(path)
    options: dict[str, Any] = {
        "save_all": True,
        "append_images": images[1:],
        "duration": durations,
        "disposal": 1,
    }
    if loop:
        options["loop"] = 0  # 0 = forever; without the key the GIF plays once
    images[0].save(p, format="GIF", **options)
    return PictureInfo(
        p,
        images[0].size,
        len(images),
        scene.centres_px,
        scene.radius_px,
        tuple(durations),
        tuple(notes),
        str(scene.heading.get_text()),
        scene.title_box_px(),
    )


def draw_frames_gif(
    array: Any,
    records: Iterable[Any],
    path: str | Path,
    *,
    current_ua: float | None = None,
    title: str | None = None,
    **options: Any,
) -> PictureInfo:
    """An animated GIF of frames-file lines (dicts as ``tactdeform-hw render --frames`` writes them, or
    :class:`~tactdeform_hw.formats.frames.Frame` objects); lines without a time are skipped.  Each frame
    is shown at least ``min_frame_ms`` (default :data:`MIN_DISPLAY_MS`) with its real time on it."""
    options.setdefault("min_frame_ms", MIN_DISPLAY_MS)
    from ..formats.frames import Frame, parse_frame

    frames = []
    for k, rec in enumerate(records):
        if isinstance(rec, Frame):
            frames.append(rec)
        elif not (isinstance(rec, dict) and rec.get("t", 0) is None):
            frames.append(parse_frame(rec, f"frame {k}"))
    return draw_array_gif(
        array, frames_from_frames(frames, current_ua=current_ua), path, title=title, **options
    )
