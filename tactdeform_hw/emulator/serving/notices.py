"""What a served board tells its operator on stderr: fall-behinds aggregated, hazards at once.

A busy machine makes the serving thread wake late hundreds of times a minute; one line per late wake-up
buries everything else.  :class:`BehindNotices` prints at most one line per ``interval_s`` with how many
wake-ups came late since the last line and the worst lag; under ``quiet`` it prints only lags above
:data:`QUIET_LAG_LIMIT_US`.  :class:`HazardNotices` prints every new hazard as soon as the serving loop
sees it (one line each), at most one line per hazard kind per ``interval_s``, the rest counted into the
next line of that kind.  Every time is the board's virtual time since serving began, in µs (``t=…us``),
the clock of the live view, ``--spy`` and the hazards themselves (a ``--trace`` file counts it in ns).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Protocol

#: A lag above which the emulated board can no longer show the stop bound of docs/safety.md: the guardian
#: switches a killed owner's board off within 150 ms, its own share about 45 ms, so a board model running
#: 100 ms late would put the delivered "off" beyond the bound.  ``--quiet`` still prints such lags.
QUIET_LAG_LIMIT_US = 100_000.0


class _Late(Protocol):
    due_us: float
    lag_us: float


class _Kinded(Protocol):
    @property
    def kind(self) -> object: ...


class BehindNotices:
    """Fall-behinds aggregated: ``add`` from the serving thread, ``lines(now_s)`` from the loop that
    prints.  The first late wake-up is printed at once, then at most one line per ``interval_s``."""

    def __init__(
        self, interval_s: float = 1.0, quiet: bool = False, quiet_limit_us: float = QUIET_LAG_LIMIT_US
    ) -> None:
        self.interval_s = interval_s
        self.quiet = quiet
        self.quiet_limit_us = quiet_limit_us
        self._lock = threading.Lock()
        self._pending: list[tuple[float, float]] = []  # (due µs, lag µs) not yet printed
        self._last_s = -float("inf")

    def add(self, fb: _Late) -> None:
        """One late wake-up (a :class:`~.realtime.FallBehind`); under ``quiet`` only lags above the
        limit are kept (the summary still counts every one)."""
        if self.quiet and fb.lag_us <= self.quiet_limit_us:
            return
        with self._lock:
            self._pending.append((fb.due_us, fb.lag_us))

    def lines(self, now_s: float, force: bool = False) -> list[str]:
        """The line to print now, if any (``force``: whatever is pending, e.g. when serving stops)."""
        with self._lock:
            if not self._pending or (not force and now_s - self._last_s < self.interval_s):
                return []
            pending, self._pending = self._pending, []
            self._last_s = now_s
        due, worst = max(pending, key=lambda p: p[1])
        first = pending[0][0]
        if len(pending) == 1:
            text = f"fell behind the wall clock by {worst / 1000:.2f} ms at t={due:.1f}us"
        else:
            text = (
                f"fell behind the wall clock {len(pending)} times since t={first:.1f}us "
                f"(worst {worst / 1000:.2f} ms at t={due:.1f}us)"
            )
        if worst > self.quiet_limit_us:
            text += (
                f"; beyond {self.quiet_limit_us / 1000:g} ms the emulated board cannot show the 150 ms "
                "stop bound"
            )
        return [text]


class HazardNotices:
    """New hazards, printed at once: one line each, at most one per kind per ``interval_s``; the ones
    held back are counted into the next line of their kind."""

    def __init__(self, interval_s: float = 1.0) -> None:
        self.interval_s = interval_s
        self._seen = 0
        self._last_s: dict[object, float] = {}
        self._held: dict[object, tuple[int, object]] = {}  # kind: (how many held back, the latest)

    def lines(self, hazards: Sequence[_Kinded], now_s: float, force: bool = False) -> list[str]:
        """Lines for the hazards appended to ``hazards`` since the last call (a list that shrank, e.g.
        after a reset, is read from its start again); ``force``: everything held back, now."""
        if len(hazards) < self._seen:
            self._seen = 0
        new = list(hazards[self._seen :])
        self._seen += len(new)
        out: list[str] = []
        for h in new:
            if force or now_s - self._last_s.get(h.kind, -float("inf")) >= self.interval_s:
                out.append(self._line(h, 0))
                self._last_s[h.kind] = now_s
            else:
                count = self._held.get(h.kind, (0, h))[0]
                self._held[h.kind] = (count + 1, h)
        for kind, (count, latest) in list(self._held.items()):
            if force or now_s - self._last_s[kind] >= self.interval_s:
                del self._held[kind]
                out.append(self._line(latest, count - 1))
                self._last_s[kind] = now_s
        return out

    def _line(self, hazard: object, also: int) -> str:
        """``hazard``'s line, and how many more of its kind were held back before it."""
        kind = getattr(hazard, "kind", None)
        if also == 0 and kind in self._held:
            also, _ = self._held.pop(kind)
        text = f"hazard: {hazard}"
        if also:
            text += f" (+{also} more {_kind_name(kind)} held back since the last line of this kind)"
        return text


def _kind_name(kind: object) -> str:
    return str(getattr(kind, "value", kind))


__all__ = ["QUIET_LAG_LIMIT_US", "BehindNotices", "HazardNotices"]
