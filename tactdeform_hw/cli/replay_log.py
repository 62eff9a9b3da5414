"""``tactdeform-hw replay-log FILE``: re-run an audit log on the timed emulator and report what was delivered.

The audit log holds every byte a session wrote and when (see :mod:`tactdeform_hw.device.audit`).  Writing
them again, at the same relative times, into the timed emulator reproduces what the firmware's scans did
with them — which channels received which current, and how much charge — so a session can be checked
after the fact, e.g. against the participant's profile (``--participant``).
"""

from __future__ import annotations

import argparse
from typing import Any

from ..errors import ConfigurationError
from .common import print_json
from .options import duration


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "replay-log",
        help="re-run an audit log on the emulator and report the currents and charges delivered",
        description="Replay the commands of an audit log (--audit-log of send, render, play, study, "
        "calibrate) into the timed emulator at their recorded times and report, per channel, the pulses, "
        "the largest current and the charge actually delivered by the emulated scans. With --participant, "
        "pulses above the participant's limits are listed and the exit code is 3.",
    )
    p.add_argument("file", help="audit log (JSON lines)")
    p.add_argument("--link", choices=("usb", "uart"), default="usb", help="link model for the replay (default usb)")
    p.add_argument("--participant", metavar="FILE", help="profile to check the delivered currents against")
    p.add_argument("--tail-ms", type=duration("ms"), default=50.0, help="emulated time after the last command (default 50)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=run)


def replay(path: str, *, link: str = "usb", tail_s: float = 0.05) -> dict[str, Any]:
    """Replay a log; return the delivery report (also used by tests and tools)."""
    import numpy as np

    from ..device.audit import read_log
    from ..emulator.timed import TimedEmulator

    records = [r for r in read_log(path) if r["type"] == "tx" and r.get("ok", True)]
    if not records:
        raise ConfigurationError(f"audit log {path}: no commands to replay")
    emu = TimedEmulator(link=link)
    t_last = 0.0
    for r in records:
        t = max(float(r["t"]), t_last)  # writes must come in time order
        t_last = t
        emu.advance_to(t * 1e6)
        emu.write(bytes.fromhex(r["hex"]))
    emu.advance_to((t_last + tail_s) * 1e6)
    table = emu.reports.pulse_table()
    cur = table["current_ua"]
    live = cur > 0
    channels: dict[int, dict[str, Any]] = {}
    for ch in sorted({int(c) for c in table["channel"][live]}):
        sel = live & (table["channel"] == ch)
        channels[ch] = {
            "pulses": int(sel.sum()),
            "max_current_ua": round(float(cur[sel].max()), 1),
            "total_charge_nc": round(float(table["charge_nc"][sel].sum()), 1),
            "max_charge_nc": round(float(table["charge_nc"][sel].max()), 2),
            "first_s": round(float(table["start_us"][sel].min()) / 1e6, 6),
            "last_s": round(float(table["start_us"][sel].max()) / 1e6, 6),
        }
    return {
        "file": str(path),
        "commands": len(records),
        "duration_s": round(t_last, 6),
        "pulses": int(live.sum()),
        "max_current_ua": round(float(cur[live].max()), 1) if live.any() else 0.0,
        "max_charge_nc": round(float(table["charge_nc"][live].max()), 2) if live.any() else 0.0,
        "total_charge_nc": round(float(np.sum(table["charge_nc"][live])), 1),
        "channels": channels,
        "losses": [lo.to_dict() for lo in emu.losses],
        "hazards": sorted({h.kind.value for h in emu.hazards}),
        "final_state": {k: v for k, v in emu.state().items() if k != "stim_pattern"},
        "_table": table,
    }


def run(args: argparse.Namespace) -> int:
    rep = replay(args.file, link=args.link, tail_s=args.tail_ms / 1000.0)
    table = rep.pop("_table")
    code = 0
    if args.participant:
        from ..device.profiles import load_profile
        from ..device.safety import SafetyGuard

        prof = load_profile(args.participant)
        guard = SafetyGuard.from_profile(prof)
        n = int(rep["final_state"]["electrode_num"]) or 32
        limits = guard.electrode_limits(max(n, 32))
        over = []
        for i in range(table["channel"].size):
            ua = float(table["current_ua"][i])
            ch = int(table["channel"][i])
            if ua > 0 and ch < len(limits) and ua > limits[ch] + 1e-6:
                over.append({"t_s": round(float(table["start_us"][i]) / 1e6, 6), "channel": ch,
                             "current_ua": round(ua, 1), "limit_ua": limits[ch]})
        rep["above_limit"] = over[:100]
        rep["above_limit_count"] = len(over)
        code = 3 if over else 0
    if args.json:
        print_json(rep)
    else:
        print(f"{rep['commands']} command(s) over {rep['duration_s']:.3f} s: {rep['pulses']} pulse(s), "
              f"max {rep['max_current_ua']} µA, max {rep['max_charge_nc']} nC per pulse, "
              f"{rep['total_charge_nc']} nC in all")
        for ch, c in rep["channels"].items():
            print(f"  channel {ch:3d}: {c['pulses']:6d} pulses, max {c['max_current_ua']:8.1f} µA, "
                  f"{c['total_charge_nc']:10.1f} nC")
        if rep["losses"]:
            print(f"  {len(rep['losses'])} loss(es) in the replay")
        if "above_limit_count" in rep:
            print(f"  {rep['above_limit_count']} pulse(s) above the participant's limits")
    return code
