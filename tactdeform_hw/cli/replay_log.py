"""``tactdeform-hw replay-log FILE``: re-run an audit log on the timed emulator and report what was delivered.

The audit log holds every byte a session wrote and when (see :mod:`tactdeform_hw.device.driver.audit`).
Writing
them again, at the same relative times, into the timed emulator reproduces what the firmware's scans did
with them — which channels received which current, and how much charge — so a session can be checked
after the fact, e.g. against the participant's profile (``--participant``).

A log is replayed on the model of the firmware it was written for: the device records a ``firmware`` event
with the version it speaks, so a v2 log (each pattern element a u16 height, the stimulation mode, the sync
check) goes to the v2 timed model and its bytes are read with the v2 command table; a log without that
record (written before the device recorded it) was written for v1.2.  A log naming a firmware this
package does not know, or naming two, is refused, as is a log whose firmware is not the one ``--firmware``
asks for.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

from ..errors import ConfigurationError
from ..protocol.firmware import FIRMWARES, V1_2, V2
from .common import print_json
from .options import duration


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "replay-log",
        help="re-run an audit log on the emulator and report the currents and charges delivered",
        description="Replay the commands of an audit log (--audit-log of send, render, play, study, "
        "calibrate) into the timed emulator at their recorded times and report, per channel, the pulses, "
        "the largest current and the charge actually delivered by the emulated scans. With --participant, "
        "pulses above the participant's limits are listed and the exit code is 3. A log is replayed on the "
        "model of the firmware it records (v1.2 or v2).",
    )
    p.add_argument("file", help="audit log (JSON lines)")
    p.add_argument(
        "--firmware",
        choices=tuple(FIRMWARES),
        default=None,
        help="the firmware the log must have been written for (default: the one the log records); a log "
        "written for another is refused",
    )
    p.add_argument(
        "--link", choices=("usb", "uart"), default="usb", help="link model for the replay (default usb)"
    )
    p.add_argument("--participant", metavar="FILE", help="profile to check the delivered currents against")
    p.add_argument(
        "--array",
        metavar="ARRAY.json|tactdeform",
        help="electrode-array file of the session (or 'tactdeform' for the 32-electrode TactDeform array on "
        "channels 0-31): each channel's limit follows the position of the electrode on it. Default: the map "
        "the log's session line records",
    )
    p.add_argument(
        "--tail-ms",
        type=duration("ms"),
        default=50.0,
        help="emulated time after the last command (default 50)",
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=run)


def log_firmware(path: str, asked: str | None = None) -> tuple[str, str]:
    """The firmware ``path`` was written for and where that comes from: its ``firmware`` record (an event,
    or a field of the session line), else v1.2.  Refused (one line each): a firmware this package does not
    know, two different ones in one log, and a log not written for ``asked`` (``--firmware``)."""
    from tactdeform_hw.device.driver.audit import read_log

    named: list[tuple[int, str]] = []
    for n, rec in enumerate(read_log(path), start=1):
        if rec.get("type") == "session" and "firmware" in rec:
            named.append((n, str(rec["firmware"])))
        elif rec.get("type") == "event" and rec.get("event") == "firmware":
            named.append((n, str(rec.get("firmware"))))
    names = sorted({name for _, name in named})
    for name in names:
        if name not in FIRMWARES:
            line = next(n for n, v in named if v == name)
            raise ConfigurationError(
                f"audit log {path} line {line}: firmware {name!r} is not a known firmware version "
                f"(choices: {', '.join(FIRMWARES)}); its bytes cannot be replayed on a model of another"
            )
    if len(names) > 1:
        raise ConfigurationError(
            f"audit log {path}: records firmware {' and '.join(names)}; one log is one session on one board, "
            "replay each session's log on its own"
        )
    if names:
        firmware, source = names[0], "the log's firmware record"
    else:
        firmware, source = V1_2.name, "no firmware record in the log: written for v1.2"
    if asked is not None and asked != firmware:
        raise ConfigurationError(
            f"--firmware {asked}: audit log {path} was written for firmware {firmware} ({source}); replay it "
            f"with --firmware {firmware}, or without --firmware"
        )
    return firmware, source


def written(records: list[dict[str, Any]]) -> list[tuple[float, bytes]]:
    """The writes the ``tx`` records stand for, in order: ``(t, bytes)``, the lines of one write of several
    commands (``part`` ``[k, n]``) joined again into that write."""
    out: list[tuple[float, bytes]] = []
    joining = False
    for r in records:
        data = bytes.fromhex(r["hex"])
        part = r.get("part")
        if joining and part is not None and part[0] > 1:
            out[-1] = (out[-1][0], out[-1][1] + data)
        else:
            out.append((float(r["t"]), data))
        joining = part is not None and part[0] < part[1]
    return out


def replay(
    path: str, *, link: str = "usb", tail_s: float = 0.05, firmware: str | None = None
) -> dict[str, Any]:
    """Replay a log on the timed model of the firmware it was written for (``firmware``: the one it must
    have been written for, refused otherwise); return the delivery report (also used by tests and tools)."""
    import numpy as np

    from tactdeform_hw.device.driver.audit import read_log
    from tactdeform_hw.emulator.firmware.models import model_entry

    ran, source = log_firmware(path, firmware)
    records = [r for r in read_log(path) if r["type"] == "tx" and r.get("ok", True)]
    if not records:
        raise ConfigurationError(f"audit log {path}: no commands to replay")
    v2 = ran == V2.name
    emu: Any = model_entry(ran).timed(link=link)
    t_last = 0.0
    for t_rec, data in written(records):
        t = max(t_rec, t_last)  # writes must come in time order
        t_last = t
        emu.advance_to(t * 1e6)
        emu.write(data)
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
        if v2:
            # every v2 channel has its own height: the heights it was pulsed at
            channels[ch]["heights_ua"] = sorted({round(float(v), 1) for v in cur[sel].tolist()})
    losses = list(emu.losses)  # bytes that never took effect
    return {
        "file": str(path),
        "firmware": ran,
        "firmware_source": source,
        "commands": len(records),
        "duration_s": round(t_last, 6),
        "pulses": int(live.sum()),
        "max_current_ua": round(float(cur[live].max()), 1) if live.any() else 0.0,
        "max_charge_nc": round(float(table["charge_nc"][live].max()), 2) if live.any() else 0.0,
        "total_charge_nc": round(float(np.sum(table["charge_nc"][live])), 1),
        "channels": channels,
        "losses": [lo.to_dict() for lo in losses],
        "hazards": sorted({h.kind.value for h in emu.hazards}),
        "final_state": {k: v for k, v in emu.state().as_dict().items() if k != "stim_pattern"},
        "_table": table,
    }


def channel_regions(
    path: str, array: str | None, regions_ua: Sequence[int] | None = None
) -> tuple[dict[int, tuple[int, int]], str]:
    """Hardware channel → (electrode, region) for judging a log, and where the map came from: ``array``
    (an array file, or ``tactdeform``), else the map the log's session line records.  A channel's region
    comes from the position of the electrode on it, never from the channel number; a log without a map
    (and no ``--array``) is refused, naming what is missing."""
    from tactdeform_hw.device.driver.audit import read_log
    from tactdeform_hw.device.participant.regions import tactdeform_region_map

    if array is not None:
        if array.lower() == "tactdeform":
            tactdeform = tactdeform_region_map().resolve(None)
            return {
                i: (i, r) for i, r in enumerate(tactdeform)
            }, "the TactDeform 32-electrode array (--array)"
        from ..formats import read_array_file

        af = read_array_file(array)
        return af.hardware_regions(af.region_map().resolve(regions_ua)), f"{af.source} (--array)"
    header = next((r for r in read_log(path) if r.get("type") == "session"), {})
    positions, mapping = header.get("positions_mm"), header.get("mapping")
    if not isinstance(positions, list) or not isinstance(mapping, list) or len(positions) != len(mapping):
        raise ConfigurationError(
            f"audit log {path}: its session line records no electrode positions (positions_mm and mapping), "
            "so the region of the electrode on each channel cannot be determined; give --array with the "
            "session's electrode-array file (or --array tactdeform for the TactDeform array on channels "
            "0-31)"
        )
    from tactdeform_hw.device.participant.regions import region_map_from_positions

    region_of = region_map_from_positions(positions, f"the session line of {path}").resolve(regions_ua)
    return {
        int(ch): (i, region_of[i]) for i, ch in enumerate(mapping)
    }, "the positions the log's session line records"


def _calibration_layout(array: str | None) -> tuple[Sequence[int], int]:
    """The region of each electrode by id (to read a calibration profile's intensities as regions) and the
    first hardware channel of its ``Mapping_func``: the array file's with ``--array``, else the TactDeform
    array's."""
    if array is not None and array.lower() != "tactdeform":
        from ..formats import read_array_file

        af = read_array_file(array)
        return af.region_map().resolve(None), af.pattern_offset
    from ..render.array import ElectrodeArray

    return tuple(int(r) for r in ElectrodeArray.tactdeform().regions), 0


def judge(table: dict[str, Any], hw: dict[int, tuple[int, int]] | None, guard: Any) -> list[dict[str, Any]]:
    """Every pulse above the limit of the channel it reached: the regional limit of the electrode on it
    (lowered to the cap), 0 on a channel no electrode maps to, and the charge limit per pulse.  ``hw`` None
    (no map) is only for limits that are the same in every region: every channel then has that limit."""
    import numpy as np

    regions: Sequence[int] = guard.regions_ua or (guard.cap_ua,) * 9
    cur = table["current_ua"]
    chans = table["channel"].astype(int)
    size = int(chans.max()) + 1 if chans.size else 1
    if hw is None:
        limit_of = np.full(size, float(min(min(regions), guard.cap_ua)))
        hw = {}
    else:
        limit_of = np.zeros(size)
    for ch, (_e, region) in hw.items():
        if ch < limit_of.size:
            limit_of[ch] = min(regions[region], guard.cap_ua)
    calibrated = guard.channels  # a calibration profile's limits belong to the channel each electrode is on
    if calibrated is not None:
        for ch in range(limit_of.size):
            limit_of[ch] = min(limit_of[ch], calibrated.channel_limit_ua(ch))
    limit = limit_of[chans] if chans.size else np.zeros(0)
    over_current = (cur > 0) & (cur > limit + 1e-6)
    over_charge = (cur > 0) & (table["charge_nc"] > guard.max_charge_nc + 1e-6)
    out = []
    for i in np.flatnonzero(over_current | over_charge).tolist():
        ch = int(chans[i])
        e: int | None = None
        r: int | None = None
        if ch in hw:
            e, r = hw[ch]
        out.append(
            {
                "t_s": round(float(table["start_us"][i]) / 1e6, 6),
                "channel": ch,
                "electrode": e,
                "region": r,
                "current_ua": round(float(cur[i]), 1),
                "limit_ua": float(limit[i]),
                "charge_nc": round(float(table["charge_nc"][i]), 3),
                "rule": ("region" if r is not None else "cap" if not limit_of[ch] == 0 else "unmapped")
                if over_current[i]
                else "charge",
            }
        )
    return out


def _participant_guard(args: argparse.Namespace) -> tuple[Any, Any]:
    """``--participant``'s profile and the guard whose limits judge the replay: a participant profile's,
    or an eTactileKit calibration profile's, each channel held to the electrode calibrated on it."""
    from tactdeform_hw.device.safety.guard import SafetyGuard

    from ..formats.calibration_profile import calibration_guard
    from ..session import read_participant

    region_of, offset = _calibration_layout(args.array)
    prof, calibration = read_participant(args.participant, region_of)
    if calibration is None:
        return prof, SafetyGuard.from_profile(prof)
    wiring = [offset + ch for ch in calibration.mapping()]
    return prof, calibration_guard(
        calibration, region_of, mapping=wiring, against="its own", channel_offset=offset
    )


def _judged(args: argparse.Namespace, table: Any, rep: dict[str, Any]) -> int:
    """Judge every pulse against ``--participant``'s limits into ``rep``; 3 when one was above them."""
    prof, guard = _participant_guard(args)
    hw: dict[int, tuple[int, int]] | None = None
    try:
        hw, source = channel_regions(args.file, args.array, prof.regions_ua)
    except ConfigurationError:
        if guard.positions_matter:
            raise
        source = "no positions (the participant's limit is the same in every region)"
    over = judge(table, hw, guard)
    rep["judged_by"] = source
    if hw is not None:
        rep["channel_regions"] = {str(ch): {"electrode": e, "region": r} for ch, (e, r) in sorted(hw.items())}
    rep["above_limit"] = over
    rep["above_limit_count"] = len(over)
    by: dict[int, dict[str, Any]] = {}
    for o in over:
        b = by.setdefault(
            o["channel"],
            {
                "channel": o["channel"],
                "electrode": o["electrode"],
                "region": o["region"],
                "limit_ua": o["limit_ua"],
                "pulses": 0,
                "max_current_ua": 0.0,
                "first_s": o["t_s"],
                "last_s": o["t_s"],
            },
        )
        b["pulses"] += 1
        b["max_current_ua"] = max(b["max_current_ua"], o["current_ua"])
        b["last_s"] = o["t_s"]
    rep["above_limit_by_channel"] = [by[k] for k in sorted(by)]
    return 3 if over else 0


def _print_replay(rep: dict[str, Any]) -> None:
    print(f"replayed on the firmware {rep['firmware']} model ({rep['firmware_source']})")
    print(
        f"{rep['commands']} command(s) over {rep['duration_s']:.3f} s: {rep['pulses']} pulse(s), "
        f"max {rep['max_current_ua']} µA, max {rep['max_charge_nc']} nC per pulse, "
        f"{rep['total_charge_nc']} nC in all"
    )
    for ch, c in rep["channels"].items():
        heights = c.get("heights_ua")
        print(
            f"  channel {ch:3d}: {c['pulses']:6d} pulses, max {c['max_current_ua']:8.1f} µA, "
            f"{c['total_charge_nc']:10.1f} nC"
            + (f", heights {', '.join(f'{h:g}' for h in heights)} µA" if heights else "")
        )
    if rep["losses"]:
        print(f"  {len(rep['losses'])} loss(es) in the replay")
    if "above_limit_count" in rep:
        print(
            f"  {rep['above_limit_count']} pulse(s) above the participant's limits (regions from "
            f"{rep['judged_by']})"
        )
        for b in rep["above_limit_by_channel"]:
            where = (
                f"electrode {b['electrode']} in region {b['region']}"
                if b["electrode"] is not None
                else "no electrode mapped"
                if b["limit_ua"] == 0
                else "electrode unknown"
            )
            print(
                f"  EXCESS channel {b['channel']} ({where}, limit {b['limit_ua']:g} µA): {b['pulses']} "
                f"pulse(s) up to {b['max_current_ua']:g} µA, {b['first_s']:.6f}-{b['last_s']:.6f} s"
            )


def run(args: argparse.Namespace) -> int:
    if args.array is not None and args.array.lower() != "tactdeform":
        from ..formats import read_array_file

        try:  # a missing or malformed file is refused whether it is used or not
            read_array_file(args.array)
        except ConfigurationError as exc:
            raise ConfigurationError(f"--array {exc}") from exc
        if not args.participant:
            from .common import progress

            progress(
                f"tactdeform-hw replay-log: warning: --array {args.array} places the channels for judging "
                "against --participant's limits; without --participant it changes nothing"
            )
    rep = replay(args.file, link=args.link, tail_s=args.tail_ms / 1000.0, firmware=args.firmware)
    table = rep.pop("_table")
    code = _judged(args, table, rep) if args.participant else 0
    if args.json:
        print_json(rep)
    else:
        _print_replay(rep)
    return code
