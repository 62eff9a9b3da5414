"""The console's account of what a stimulating command delivered (the ``delivered`` block of its
``--json`` comes from :class:`~tactdeform_hw.session.delivery.DeliveryLog`, which the session writes)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ..session.delivery import HEIGHTS_SHOWN, DeliveryLog, session_region_map

__all__ = [
    "HEIGHTS_SHOWN",
    "DeliveryLog",
    "delivered_lines",
    "describe_lowering",
    "session_region_map",
    "span",
]


def span(values: Sequence[int]) -> str:
    """``0-3, 7, 9-10`` for a sorted list of ints."""
    runs: list[list[int]] = []
    for v in values:
        if runs and v == runs[-1][1] + 1:
            runs[-1][1] = v
        else:
            runs.append([v, v])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def describe_lowering(e: dict[str, Any]) -> str:
    rule = e.get("rule", "?")
    a, b = e.get("requested_ua"), e.get("sent_ua")
    head = f"{a} → {b} µA" if a is not None and b is not None else e.get("message", "")
    if rule == "region":
        named = sorted(e.get("electrodes") or ([e["electrode"]] if "electrode" in e else []))
        where = f"region {e['region']}" if "region" in e else "an electrode's region"
        limit = f" limit {e['limit_ua']} µA" if "limit_ua" in e else ""
        on = f" on electrode{'s' if len(named) > 1 else ''} {span(named)}" if named else ""
        why = f"by {where}{limit}{on}"
    elif rule == "electrode_limit" and "electrode" in e:
        limit = f" {e['limit_ua']} µA" if "limit_ua" in e else ""
        why = f"by electrode {e['electrode']}'s calibrated limit{limit}"
    elif rule == "ramp":
        why = "by ramp"
    elif rule in ("cap", "charge"):
        why = f"by {rule}"
    else:
        why = f"by {rule}"
    times = f" ×{e['count']}" if e.get("count", 1) > 1 else ""
    return f"lowered {why}: {head}{times}"


def delivered_lines(rep: dict[str, Any]) -> list[str]:
    """The console's account of what went to the board (one line each)."""
    lines: list[str] = []
    req = rep.get("requested_ua")
    if not req and not rep["max_delivered_ua"] and not rep["lowered"] and not rep["refused"]:
        return lines  # no current asked for, none sent: patterns only, nothing to account for
    head = f"requested {req} µA; " if req is not None else ""
    lines.append(f"{head}delivered at most {rep['max_delivered_ua']} µA")
    ramps = [e for e in rep["lowered"] if e.get("rule") == "ramp" and "sent_ua" in e]
    for e in rep["lowered"]:
        if e not in ramps:
            lines.append("  " + describe_lowering(e))
    if ramps:
        steps = sorted({int(e["sent_ua"]) for e in ramps})
        frames = sum(int(e.get("count", 1)) for e in ramps)
        shown = ", ".join(str(v) for v in steps[:16]) + (", …" if len(steps) > 16 else "")
        lines.append(f"  lowered by ramp: {frames} frame(s) held below their height, at {shown} µA")
    for e in rep["refused"]:
        times = f" ×{e['count']}" if e.get("count", 1) > 1 else ""
        lines.append(f"  refused ({e.get('rule')}): {e.get('message', '')}{times}")
    heights = rep["pulse_heights_ua"]
    if heights:
        # the log keeps the successive nonzero heights (up to HEIGHTS_SHOWN); a switch to 0 and back to
        # the same height is a change but no new height, so only a longer list has more to show
        shown = heights[:16]
        more = ", …" if len(heights) > len(shown) or len(heights) >= HEIGHTS_SHOWN else ""
        lines.append(f"  pulse heights sent: {', '.join(str(h) for h in shown)}{more} µA")
    by_value: dict[int, list[dict[str, Any]]] = {}
    for row in rep["electrodes"]:
        by_value.setdefault(row["max_ua"], []).append(row)
    for ua in sorted(by_value, reverse=True):
        rows = by_value[ua]
        named = sorted(r["electrode"] for r in rows if r["electrode"] is not None)
        unmapped = sorted(r["channel"] for r in rows if r["electrode"] is None)
        regions = sorted({r["region"] for r in rows if "region" in r})
        text = f"  {ua} µA at most on electrode(s) {span(named)}" if named else f"  {ua} µA at most"
        if regions:
            text += f" (region{'s' if len(regions) > 1 else ''} {span(regions)})"
        if unmapped:
            text += f"; on hardware channel(s) {span(unmapped)} no electrode maps to"
        lines.append(text)
    return lines
