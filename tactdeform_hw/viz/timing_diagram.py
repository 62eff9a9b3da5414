"""Timing diagrams of the stimulation scan: every pulse on every channel against time.

A firmware developer reading a trace wants three things at a glance: the order and width of the pulses
within a scan, whether the scan fits the stimulation period, and where it does not.  The diagram puts
one row per channel (pulse height drawn in proportion to its current, colour by kind), marks the start
of every scan cycle with its period, shades each scan's busy time, and marks overruns — scans longer
than the period, after which the next scan starts at once — in red with their excess.

Input is the emulator's trace: per-pulse records (channel, start, width, current, charge) and per-cycle
records (start, duration, overrun).  Records may be objects with attributes or plain dicts; times are
microseconds.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from ..errors import ConfigurationError
from ._plot import TITLE_MARGIN_PX, box_px, canvas_rgb, fit_width, keep_inside, require

_R = TypeVar("_R")

_PURPOSE = "drawing timing diagrams"
KIND_COLOURS = {
    "mono": "#f16913",
    "bi_anodic": "#54278f",
    "bi_cathodic": "#9e9ac8",
    "sense": "#9e9e9e",
}
KIND_LABELS = {
    "mono": "monophasic pulse",
    "bi_anodic": "biphasic, anodic phase",
    "bi_cathodic": "biphasic, cathodic phase",
    "sense": "sense pulse",
}
#: Other spellings of the kinds, and the emulator's integer pulse kinds (``emulator.scan.PulseKind``).
_KIND_ALIASES = {
    "stim": "mono",
    "monophasic": "mono",
    "biphasic": "bi_anodic",
    "0": "mono",
    "1": "bi_anodic",
    "2": "bi_cathodic",
    "3": "sense",
    "biphasic-anodic": "bi_anodic",
    "biphasic-cathodic": "bi_cathodic",
}
OVERRUN_COLOUR = "#e31a1c"
#: The id of each overrun's label, by which it is kept inside the plot once drawn.
OVERRUN_LABEL_GID = "overrun-label"


@dataclass(frozen=True)
class Pulse:
    channel: int
    start_us: float
    width_us: float
    current_ua: float = 0.0
    kind: str = "mono"


@dataclass(frozen=True)
class Cycle:
    start_us: float
    duration_us: float
    period_us: float | None = None
    overrun_us: float = 0.0


@dataclass(frozen=True)
class TimingInfo:
    path: Path
    size_px: tuple[int, int]
    window_us: tuple[float, float]
    channels: tuple[int, ...]
    pulses_drawn: int
    cycles_drawn: int
    overruns_drawn: int
    #: the plot area and each text drawn on the figure (the title, the overrun labels), as (text, box);
    #: boxes are (left, top, right, bottom) in image pixels, so a test can see that none is cut off
    plot_box_px: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    text_boxes_px: tuple[tuple[str, tuple[float, float, float, float]], ...] = ()


def _field(
    rec: Any, names: Sequence[str], default: Any = None, required: bool = True, where: str = ""
) -> Any:
    for name in names:
        if isinstance(rec, dict):
            if name in rec:
                return rec[name]
        elif hasattr(rec, name):
            return getattr(rec, name)
    if required and default is None:
        raise ConfigurationError(
            f"{where}: missing {names[0]!r} (also accepted: {', '.join(names[1:]) or '-'})"
        )
    return default


def _finite(value: Any, where: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigurationError(f"{where}: expected a number, got {value!r}") from None
    if not np.isfinite(v):
        raise ConfigurationError(f"{where}: expected a finite number, got {value!r}")
    return v


def _time_us(rec: Any, us_names: Sequence[str], ns_names: Sequence[str], where: str, label: str) -> float:
    """A time in µs from a µs-named field, or from an ns-named one (the emulator keeps integer ns)."""
    v = _field(rec, us_names, None, required=False)
    if v is not None:
        return _finite(v, f"{where}.{label}")
    v = _field(rec, ns_names, None, required=False)
    if v is not None:
        return _finite(v, f"{where}.{label}") / 1000.0
    raise ConfigurationError(f"{where}: missing {us_names[0]!r} (or {ns_names[0]!r})")


def _kind(value: Any) -> str:
    name = getattr(value, "name", None)
    text = str(name if isinstance(name, str) else getattr(value, "value", value)).lower()
    return _KIND_ALIASES.get(text, text)


def _rows(records: Any) -> Iterable[Any]:
    """Records one by one, also from a columnar trace (a dict or named tuple of equal-length arrays)."""
    if isinstance(records, dict):  # columns, as ``TimingReports.pulse_table()`` returns them
        cols = {k: np.asarray(v) for k, v in records.items()}
        n = len(next(iter(cols.values()))) if cols else 0
        return [{k: c[i] for k, c in cols.items()} for i in range(n)]
    fields = getattr(records, "_fields", None)
    if fields and not isinstance(records, (Pulse, Cycle)):
        columns = [np.asarray(getattr(records, f)) for f in fields]
        if all(c.ndim >= 1 for c in columns):
            return [{f: c[k] for f, c in zip(fields, columns)} for k in range(len(columns[0]))]
    rows: Iterable[Any] = records  # anything else is taken as records already
    return rows


def _normalised(
    records: Iterable[Any], kind: type[_R], name: str, convert: Callable[[Any, str], _R]
) -> list[_R]:
    """Each record as ``kind``: one already is kept, any other converted by ``convert(record, where)``
    (``where`` names it in errors, ``name[i]``)."""
    return [
        rec if isinstance(rec, kind) else convert(rec, f"{name}[{i}]") for i, rec in enumerate(_rows(records))
    ]


def to_pulses(records: Iterable[Any]) -> list[Pulse]:
    """Normalise per-pulse records (objects or dicts, or a columnar trace; times in µs or ns)."""
    return _normalised(records, Pulse, "pulses", _pulse)


def _pulse(rec: Any, w: str) -> Pulse:
    ch = int(_finite(_field(rec, ("channel", "ch"), where=w), f"{w}.channel"))
    start = _time_us(
        rec, ("start_us", "start", "t_us", "time_us"), ("start_ns", "t_ns", "time_ns"), w, "start_us"
    )
    width = _time_us(rec, ("width_us", "width", "duration_us"), ("width_ns", "duration_ns"), w, "width_us")
    cur = _finite(_field(rec, ("current_ua", "current", "height_ua"), 0.0, required=False), f"{w}.current_ua")
    kind = _kind(_field(rec, ("kind", "type", "shape"), "mono", required=False))
    return Pulse(ch, start, max(width, 0.0), cur, kind)


def to_cycles(records: Iterable[Any], period_us: float | None = None) -> list[Cycle]:
    """Normalise per-cycle records; ``overrun`` may be a bool or the excess in µs."""
    return _normalised(records, Cycle, "cycles", lambda rec, w: _cycle(rec, w, period_us))


def _cycle(rec: Any, w: str, period_us: float | None) -> Cycle:
    start = _time_us(rec, ("start_us", "start", "t_us"), ("start_ns", "t_ns"), w, "start_us")
    dur = _time_us(
        rec,
        ("duration_us", "scan_us", "duration", "length_us"),
        ("duration_ns", "scan_ns"),
        w,
        "duration_us",
    )
    try:
        per: float | None = _time_us(rec, ("period_us", "period"), ("period_ns",), w, "period_us")
    except ConfigurationError:
        per = period_us
    over = _field(rec, ("overrun_us", "overrun"), None, required=False)
    if over is None and _field(rec, ("overrun_ns",), None, required=False) is not None:
        over = _finite(_field(rec, ("overrun_ns",)), f"{w}.overrun_ns") / 1000.0
    if isinstance(over, bool) or over is None:
        flag = bool(over) if over is not None else (per is not None and dur > per)
        excess = (dur - per) if (flag and per is not None) else (1.0 if flag else 0.0)
    else:
        excess = _finite(over, f"{w}.overrun_us")
    return Cycle(start, dur, per, max(excess, 0.0))


def _period_of(cycles: list[Cycle]) -> float | None:
    """The scan period when none is given: the first cycle's own, else the median spacing of the
    cycles (None with fewer than two)."""
    known = [c.period_us for c in cycles if c.period_us]
    if known:
        return known[0]
    if len(cycles) >= 2:
        return float(np.median(np.diff([c.start_us for c in cycles])))
    return None


def _default_window(
    ps: list[Pulse], cs: list[Cycle], period_us: float | None, max_cycles: int
) -> tuple[float, float]:
    """The first ``max_cycles`` cycles (the whole trace without cycle records), with a little room before
    the first; the window ends where the next cycle would begin."""
    if cs:
        shown = cs[: max(1, max_cycles)]
        t0 = shown[0].start_us
        t1 = max(
            shown[-1].start_us + max(shown[-1].duration_us, period_us or 0.0),
            *(c.start_us + c.duration_us for c in shown),
        )
    else:
        t0 = min(p.start_us for p in ps)
        t1 = max(p.start_us + p.width_us for p in ps)
    return (t0 - 0.02 * max(t1 - t0, 1.0), t1)


def _draw_cycles(
    ax: Any, vis_c: list[Cycle], period_us: float | None, scale: float, window: tuple[float, float]
) -> int:
    """Scan busy time and overruns, in the band above the channel rows; how many cycles overran."""
    t0, t1 = window
    overruns = 0
    for c in vis_c:
        ax.axvline(c.start_us * scale, color="#4a4a4a", lw=0.8, ls="--", zorder=1)
        ax.add_patch(_rect(c.start_us * scale, -1.45, c.duration_us * scale, 0.5, "#9ecae1"))
        if c.overrun_us > 0:
            overruns += 1
            per = c.period_us or period_us
            begin = c.start_us + (per if per else c.duration_us - c.overrun_us)
            shown_us = max(c.overrun_us, 0.005 * (t1 - t0))
            ax.axvspan(
                begin * scale,
                (begin + shown_us) * scale,
                color=OVERRUN_COLOUR,
                alpha=0.18,
                zorder=0,
            )
            # However short the excess, the mark stays visible (at least 0.5 % of the window wide).
            ax.add_patch(_rect(begin * scale, -1.45, shown_us * scale, 0.5, OVERRUN_COLOUR, zorder=3))
            end = c.start_us + c.duration_us
            near_right = end > t0 + 0.8 * (t1 - t0)
            ax.annotate(
                f"overrun +{c.overrun_us:.0f} µs",
                ((begin if near_right else end) * scale, -1.2),
                xytext=(-4 if near_right else 4, 0),
                textcoords="offset points",
                fontsize=8,
                color=OVERRUN_COLOUR,
                ha="right" if near_right else "left",
                va="center",
                fontweight="bold",
                clip_on=True,
                annotation_clip=False,  # drawn even when its anchor lies past the window, moved inside
                gid=OVERRUN_LABEL_GID,
            )
    return overruns


def _draw_period(ax: Any, vis_c: list[Cycle], period_us: float | None, scale: float) -> None:
    """The period arrow, on the first overrun cycle (its end is where the overrun begins), else on the
    first cycle; each cycle's own period is used, since a frequency command changes it mid-trace."""
    marked = next((c for c in vis_c if c.overrun_us > 0), vis_c[0] if vis_c else None)
    per_mark = (marked.period_us or period_us) if marked is not None else None
    if marked is not None and per_mark:
        first = marked.start_us
        ax.annotate(
            "",
            xy=((first + per_mark) * scale, -0.75),
            xytext=(first * scale, -0.75),
            arrowprops={"arrowstyle": "<->", "color": "#333333", "lw": 0.9},
        )
        ax.text(
            (first + per_mark / 2) * scale,
            -0.8,
            f"period {per_mark:.0f} µs ({1e6 / per_mark:.1f} Hz)",
            ha="center",
            va="bottom",
            fontsize=8,
            color="#333333",
        )


def _draw_pulses(
    ax: Any, vis: list[Pulse], row: dict[int, int], full: float, scale: float, window: tuple[float, float]
) -> set[str]:
    """Every pulse in its channel's row, its height proportional to its current; the kinds drawn."""
    t0, t1 = window
    kinds_seen: set[str] = set()
    for p in vis:
        h = 0.15 + 0.6 * min(max(p.current_ua / full, 0.0), 1.0)
        kind = p.kind if p.kind in KIND_COLOURS else "mono"
        colour = KIND_COLOURS[kind]
        kinds_seen.add(kind)
        y = row[p.channel]
        ax.add_patch(
            _rect(
                p.start_us * scale, y + 0.35 - h, max(p.width_us * scale, (t1 - t0) * scale * 4e-4), h, colour
            )
        )
    return kinds_seen


def _legend(fig: Any, kinds_seen: set[str], overruns: int) -> None:
    """What the colours mean: scan busy, each pulse kind drawn, an overrun."""
    from matplotlib.patches import Patch

    handles = [Patch(color="#9ecae1", label="scan busy")]
    handles += [Patch(color=KIND_COLOURS[k], label=KIND_LABELS[k]) for k in KIND_COLOURS if k in kinds_seen]
    if overruns:
        handles.append(Patch(color=OVERRUN_COLOUR, label="overrun"))
    fig.legend(
        handles=handles,
        loc="lower center",
        ncol=len(handles),
        fontsize=8,
        frameon=False,
        bbox_to_anchor=(0.5, 0.0),
    )


def _fit_texts(ax: Any, heading: Any, renderer: Any, width_px: int) -> list[Any]:
    """The title fitted to the figure's width, each overrun label moved inside the plot; the labels."""
    fit_width(heading, width_px - 2 * TITLE_MARGIN_PX, renderer)
    plot_box = ax.get_window_extent(renderer)
    labels = [t for t in ax.texts if t.get_gid() == OVERRUN_LABEL_GID]
    for label in labels:
        keep_inside(label, plot_box.x0 + 2, plot_box.x1 - 2, renderer)
    return labels


def draw_timing_png(
    pulses: Iterable[Any],
    cycles: Iterable[Any] = (),
    path: str | Path = "timing.png",
    *,
    period_us: float | None = None,
    window_us: tuple[float, float] | None = None,
    max_cycles: int = 3,
    title: str = "stimulation scan",
    width_px: int = 1100,
    full_scale_ua: float | None = None,
) -> TimingInfo:
    """Write the timing diagram PNG.  The window defaults to the first ``max_cycles`` cycles (all of the
    trace when there are no cycle records)."""
    Figure, FigureCanvasAgg, Image = require(_PURPOSE)
    ps = to_pulses(pulses)
    cs = to_cycles(cycles, period_us)
    if not ps and not cs:
        raise ConfigurationError("the trace holds no pulse and no cycle: nothing to draw")
    if period_us is None:
        period_us = _period_of(cs)
    if window_us is None:
        window_us = _default_window(ps, cs, period_us, max_cycles)
    t0, t1 = (float(v) for v in window_us)
    if not t1 > t0:
        raise ConfigurationError(f"window_us={window_us!r}: the end must come after the start")
    vis = [p for p in ps if p.start_us + p.width_us > t0 and p.start_us < t1]
    vis_c = [c for c in cs if c.start_us < t1 and c.start_us + max(c.duration_us, period_us or 0) > t0]
    channels = tuple(sorted({p.channel for p in ps})) or (0,)
    row = {ch: k for k, ch in enumerate(channels)}
    peak = max([p.current_ua for p in ps] + [0.0])
    full = float(full_scale_ua or peak or 1.0)

    unit, scale = ("ms", 1e-3) if (t1 - t0) >= 2000 else ("µs", 1.0)
    height_px = int(min(2400, 210 + 17 * len(channels)))
    dpi = 100
    fig = Figure(figsize=(width_px / dpi, height_px / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.07, 85 / height_px, 0.90, 1 - 125 / height_px))
    ax.set_xlim(t0 * scale, t1 * scale)
    ax.set_ylim(len(channels) - 0.4, -1.6)
    ax.set_yticks(range(len(channels)))
    ax.set_yticklabels([str(c) for c in channels], fontsize=7 if len(channels) > 16 else 9)
    ax.set_ylabel("channel")
    ax.set_xlabel(f"time ({unit})")
    heading = ax.set_title(title, fontsize=11)
    ax.grid(axis="x", color="#eeeeee", lw=0.6)
    for k in range(len(channels)):
        ax.axhline(k + 0.4, color="#f0f0f0", lw=0.5, zorder=0)

    overruns = _draw_cycles(ax, vis_c, period_us, scale, (t0, t1))
    labels = _fit_texts(ax, heading, canvas.get_renderer(), width_px)
    _draw_period(ax, vis_c, period_us, scale)

    kinds_seen = _draw_pulses(ax, vis, row, full, scale, (t0, t1))

    _legend(fig, kinds_seen, overruns)
    fig.text(
        0.97,
        1 - 12 / height_px,
        f"pulse height ∝ current (full scale {full / 1000:.2f} mA)"
        if peak > 0
        else "no current delivered in this trace",
        ha="right",
        va="top",
        fontsize=7,
        color="#666666",
    )
    rgb = canvas_rgb(canvas)
    p_out = Path(path)
    Image.fromarray(rgb).save(p_out, format="PNG")
    boxes = _boxes(ax, [heading, *labels], canvas.get_renderer(), rgb.shape[0])
    return TimingInfo(
        p_out, (rgb.shape[1], rgb.shape[0]), (t0, t1), channels, len(vis), len(vis_c), overruns, *boxes
    )


def _boxes(
    ax: Any, texts: list[Any], renderer: Any, height_px: int
) -> tuple[tuple[float, float, float, float], tuple[tuple[str, tuple[float, float, float, float]], ...]]:
    """The plot's box and each text's, as :class:`TimingInfo` reports them."""
    return box_px(ax, renderer, height_px), tuple(
        (str(t.get_text()), box_px(t, renderer, height_px)) for t in texts
    )


def _rect(x: float, y: float, w: float, h: float, colour: str, zorder: float = 2) -> Any:
    from matplotlib.patches import Rectangle

    return Rectangle((x, y), w, h, facecolor=colour, edgecolor="none", zorder=zorder)


def draw_reports_png(
    reports: Any,
    path: str | Path = "timing.png",
    *,
    first_cycle: int | None = None,
    max_cycles: int = 3,
    title: str | None = None,
    **options: Any,
) -> TimingInfo:
    """The timing diagram of a timed emulator's reports (``TimedEmulator.reports``).

    Only the cycles shown are expanded, so a trace of hours costs no more than one of milliseconds.  By
    default the window starts one cycle before the first overrun (where there is one), else at the
    first cycle."""
    if first_cycle is None:
        first_cycle = 0
        for run in getattr(reports, "runs", []):
            if run.overrun:
                first_cycle = max(0, int(run.first_index) - 1)
                break
    n = max(1, int(max_cycles))
    cycles = reports.cycles(first_cycle, first_cycle + n)
    if not cycles:
        raise ConfigurationError(
            f"the trace has no scan cycle at index {first_cycle} (it holds {reports.scan_count()} cycle(s))"
        )
    cs = to_cycles(cycles)
    t0 = cs[0].start_us
    t1 = max(c.start_us + max(c.duration_us, c.period_us or 0.0) for c in cs)
    table = reports.pulse_table(t0, t1)
    if title is None:
        last = first_cycle + len(cs) - 1
        title = (
            f"stimulation scan, cycles {first_cycle}–{last}"
            if len(cs) > 1
            else f"stimulation scan, cycle {first_cycle}"
        )
    return draw_timing_png(table, cs, path, window_us=(t0 - 0.02 * (t1 - t0), t1), title=title, **options)
