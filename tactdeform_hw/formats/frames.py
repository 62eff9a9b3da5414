"""Frames files: the JSON-lines record ``tactdeform-hw render --frames`` writes, one line per frame.

Each line is an object with ``t`` (seconds from the start), ``electrodes`` (one level per electrode in
application order: 0 off, 1 monophasic, 2 biphasic) and, when the renderer knows them, ``state``,
``feature``, ``texture`` and ``sent`` (false when the frame was computed but not sent to the device,
e.g. because it equals the previous one).  Readers here use them for pictures and for export to the
eTactileKit pattern format; any other key is kept in :attr:`Frame.extra`.  A line whose ``t`` is null
(the renderer's record of a non-finite time) cannot be placed in time and is skipped.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigurationError


@dataclass(frozen=True)
class Frame:
    """One rendered frame (``t_s`` in seconds; ``electrodes`` the levels as sent)."""

    t_s: float
    electrodes: tuple[int, ...]
    state: str | None = None
    feature: str | None = None
    texture: str | None = None
    sent: bool = True
    current_ua: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)


_KNOWN = {"t", "electrodes", "state", "feature", "texture", "sent", "current_ua"}


def _show(value: Any) -> str:
    text = json.dumps(value) if not isinstance(value, float) or math.isfinite(value) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def parse_frame(obj: Any, where: str) -> Frame:
    """Check one decoded line (``where`` names it in errors, e.g. ``frames.jsonl:12``)."""
    if not isinstance(obj, dict):
        raise ConfigurationError(f"{where}: expected an object, got {_show(obj)}")
    t = obj.get("t")
    if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t):
        raise ConfigurationError(f"{where}: t: expected a time in seconds, got {_show(t)}")
    levels = obj.get("electrodes")
    if not isinstance(levels, list) or not levels:
        raise ConfigurationError(
            f"{where}: electrodes: expected a non-empty list of levels, got {_show(levels)}"
        )
    for j, v in enumerate(levels):
        if isinstance(v, bool) or not isinstance(v, int) or v not in (0, 1, 2):
            raise ConfigurationError(f"{where}: electrodes[{j}]: expected 0, 1 or 2, got {_show(v)}")
    sent = obj.get("sent", True)
    if not isinstance(sent, bool):
        raise ConfigurationError(f"{where}: sent: expected true or false, got {_show(sent)}")
    current = obj.get("current_ua")
    if current is not None and (
        isinstance(current, bool) or not isinstance(current, (int, float)) or not math.isfinite(current)
    ):
        raise ConfigurationError(f"{where}: current_ua: expected a finite number, got {_show(current)}")

    def text(key: str) -> str | None:
        v = obj.get(key)
        return None if v is None else str(v)

    return Frame(
        t_s=float(t),
        electrodes=tuple(levels),
        state=text("state"),
        feature=text("feature"),
        texture=text("texture"),
        sent=sent,
        current_ua=None if current is None else float(current),
        extra={k: v for k, v in obj.items() if k not in _KNOWN},
    )


def iter_frames(path: str | Path) -> Iterator[Frame]:
    """Frames of a JSON-lines file, checked line by line (blank lines are skipped)."""
    p = Path(path)
    try:
        fh = p.open(encoding="utf-8")
    except OSError as exc:
        raise ConfigurationError(f"{p}: cannot read: {exc.strerror or exc}") from exc
    width: int | None = None
    last_t = -math.inf
    with fh:
        for lineno, line in enumerate(fh, 1):
            if not line.strip():
                continue
            where = f"{p.name}:{lineno}"
            try:
                obj = json.loads(line)
            except json.JSONDecodeError as exc:
                raise ConfigurationError(f"{where}: not JSON ({exc.msg} at column {exc.colno})") from exc
            if isinstance(obj, dict) and "t" in obj and obj["t"] is None:
                continue  # the renderer writes null for a non-finite time: it has no place on the time line
            frame = parse_frame(obj, where)
            if width is None:
                width = len(frame.electrodes)
            elif len(frame.electrodes) != width:
                raise ConfigurationError(
                    f"{where}: electrodes: has {len(frame.electrodes)} level(s) but the first frame has "
                    f"{width}"
                )
            if frame.t_s < last_t:
                raise ConfigurationError(
                    f"{where}: t: {frame.t_s} goes back in time (previous frame at {last_t})"
                )
            last_t = frame.t_s
            yield frame


def read_frames_file(path: str | Path) -> list[Frame]:
    """All frames of a JSON-lines file (see :func:`iter_frames`); an empty file is an error."""
    frames = list(iter_frames(path))
    if not frames:
        raise ConfigurationError(f"{Path(path).name}: holds no frame")
    return frames


def delivered_spans(
    frames: Sequence[Frame], *, sent_only: bool = True, last_ms: float | None = None
) -> list[tuple[Frame, float, float]]:
    """What the board held, as ``(frame, start_s, duration_ms)`` spans covering the whole record.

    The board keeps the last pattern it was sent, so with ``sent_only`` each sent frame lasts until the
    next sent one; before the first, the board was all off (a leading all-off span, flagged
    ``extra["lead_in"]``, when the record starts earlier).  The last span lasts to the end of the record
    plus one frame interval (the median), or ``last_ms`` when given.
    """
    if not frames:
        raise ConfigurationError("the record holds no frame")
    times = [f.t_s for f in frames]
    gaps = np.diff(times)
    frame_ms = float(np.median(gaps)) * 1000.0 if len(gaps) else 100.0
    chosen = [f for f in frames if f.sent or not sent_only]
    if sent_only and (not chosen or chosen[0].t_s > frames[0].t_s):
        first = frames[0]
        off = Frame(
            first.t_s,
            (0,) * len(first.electrodes),
            first.state,
            first.feature,
            first.texture,
            True,
            first.current_ua,
            {"lead_in": True},
        )
        chosen.insert(0, off)
    spans = []
    for k, f in enumerate(chosen):
        if k + 1 < len(chosen):
            dur = (chosen[k + 1].t_s - f.t_s) * 1000.0
        elif last_ms is not None:
            dur = float(last_ms)
        else:
            dur = (times[-1] - f.t_s) * 1000.0 + frame_ms
        spans.append((f, f.t_s, dur))
    return spans
