"""``tactdeform-hw calibrate``: the regional calibration procedure, writing a participant profile.

Keys: ``+``/``u`` raise 10 µA, ``-``/``l`` lower 10 µA, ``>``/``<`` ten steps, ``a`` (or Enter, or ``!``)
accept — in the first phase it means "that is uncomfortable" — ``c`` feel the centre again while matching,
``q`` quit without saving.  Interactive on a terminal; with ``--keys FILE`` (``-`` for standard input),
or whenever standard input is not a terminal, the keys come from a script (whitespace and ``#`` comments
ignored), so the procedure can be run from tests and rehearsed without a participant.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path
from typing import Any

from ..errors import ConfigurationError, LimitError
from .common import add_device_arg, print_json, progress, robust_encoding
from .options import add_finisher, add_pulse_width, duration, range_check


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "calibrate",
        help="calibrate a participant's regional amplitudes and write their profile",
        description="The TactDeform calibration: the centre region rises from 0 µA in 10 µA steps until the "
        "participant reports discomfort (accept), is lowered until clear and pain-free (accept); "
        "each other region is matched to the centre's intensity from 0 µA (accept each); all "
        "regions are then adjusted together (accept). The profile is written only when every "
        "phase was accepted. Keys: + raise, - lower, > / < ten steps, a accept, c compare with "
        "the centre, q quit. Every current passes the safety guard (never above --max-ua) and "
        "all channels go off on exit.",
    )
    add_device_arg(p)
    p.add_argument(
        "--participant",
        required=True,
        metavar="ID|FILE",
        help="participant identifier (the profile is written to ID.json, or --out), or the profile file to "
        "write (.json or .toml)",
    )
    p.add_argument("--out", metavar="FILE", help="profile file to write (.json or .toml; default: ID.json)")
    p.add_argument(
        "--calibration-out",
        metavar="FILE.json",
        help="also write the result as an eTactileKit calibration profile: each electrode at its region's "
        "current, its mapping the hardware channel --array's Mapping_func wires it to (the identity "
        "without --array), so the profile limits the channels it was calibrated on",
    )
    p.add_argument(
        "--keys", metavar="FILE", help="read keys from FILE ('-' for standard input) instead of the keyboard"
    )
    p.add_argument(
        "--max-ua", type=int, default=5000, help="calibration ceiling in µA, ≤ 10000 (default 5000)"
    )
    add_pulse_width(p, default=200, help="pulse width in µs (default 200, TactDeform)")
    p.add_argument("--polarity", choices=("anodic", "cathodic"), default="anodic")
    p.add_argument(
        "--contact-mode",
        choices=("orientation", "uniform"),
        default="orientation",
        help="the participant's preferred contact rendering (TactDeform task 2)",
    )
    p.add_argument(
        "--ramp-ua", type=int, default=None, help="ramp limit to store in the profile (µA per frame)"
    )
    add_finisher(p, range_check("ramp_ua", "--ramp-ua", 10, 10000, "µA", step=10))
    p.add_argument(
        "--hold-ms",
        type=duration("ms"),
        default=None,
        help="with a key script: hold each step this long (default 0; interactive: until the next key)",
    )
    p.add_argument("--audit-log", metavar="FILE", help="append every command sent to FILE as JSON lines")
    p.add_argument(
        "--array",
        metavar="ARRAY.json",
        help="eTactileKit electrode-array file of the pad (default: the TactDeform 32-electrode array): each "
        "region's stimulus lights the electrodes whose coordinates lie in it, on the hardware channels "
        "of its Mapping_func",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing profile (and --calibration-out file); the old one is kept beside it as "
        "FILE.bak. Without --force an existing file is refused before anything is sent",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(func=run)


def existing_targets(args: argparse.Namespace, out: Path) -> list[tuple[str, Path]]:
    """The files this calibration would replace, with the option that names each."""
    flag = "--out" if getattr(args, "out", None) else "--participant"
    found = [(flag, out)] if out.exists() else []
    if getattr(args, "calibration_out", None) and Path(args.calibration_out).exists():
        found.append(("--calibration-out", Path(args.calibration_out)))
    return found


def refuse_overwrite(args: argparse.Namespace, out: Path) -> None:
    """A profile holds a participant's calibrated limits, ramp and contact mode: one is never replaced
    without ``--force``, and the refusal comes before the device is opened (nothing is sent)."""
    found = existing_targets(args, out)
    if found and not getattr(args, "force", False):
        names = ", ".join(f"{flag} {path}" for flag, path in found)
        raise ConfigurationError(
            f"{names}: already exists (a participant's calibrated limits); give --force to replace it "
            "(the old file is kept as FILE.bak) or another file name; nothing was sent"
        )


def _back_up(args: argparse.Namespace, out: Path) -> list[str]:
    """With ``--force``, each file about to be replaced copied to ``FILE.bak`` first."""
    import shutil

    kept = []
    for _flag, path in existing_targets(args, out):
        backup = path.with_name(path.name + ".bak")
        shutil.copy2(path, backup)
        kept.append(str(backup))
    return kept


_ID_RE = re.compile(r"^[A-Za-z0-9._-]{1,64}$")


def profile_targets(args: argparse.Namespace) -> tuple[str, Path]:
    part = args.participant
    looks_like_file = (
        "/" in part or "\\" in part or Path(part).suffix.lower() in (".yaml", ".yml", ".txt", ".ini", ".cfg")
    )
    if looks_like_file and Path(part).suffix.lower() not in (".json", ".toml"):
        raise ConfigurationError(f"--participant {part}: a profile is written as .json or .toml")
    if Path(part).suffix.lower() in (".json", ".toml"):
        out = Path(part)
        pid = out.stem
    else:
        pid = part
        out = Path(args.out) if args.out else Path(f"{pid}.json")
    if args.out:
        out = Path(args.out)
    if out.suffix.lower() not in (".json", ".toml"):
        raise ConfigurationError(f"--out {out}: a profile is written as .json or .toml")
    if not _ID_RE.match(pid):
        raise LimitError("participant", pid, "1-64 characters of A-Z a-z 0-9 . _ -")
    return pid, out


def _script_keys(args: argparse.Namespace) -> list[str] | None:
    from tactdeform_hw.device.participant.calibration import parse_key_script

    if args.keys == "-" or (args.keys is None and not sys.stdin.isatty()):
        return parse_key_script(sys.stdin.read())
    if args.keys:
        try:
            return parse_key_script(Path(args.keys).read_text(encoding="utf-8"))
        except OSError as exc:
            raise ConfigurationError(f"--keys {args.keys}: cannot be read ({exc.strerror or exc})") from exc
    return None


def _apply(dev: Any, stim: Any, region_of: tuple[int, ...]) -> None:
    """Lower the current before moving the stimulus, raise it after: no electrode ever gets a level meant
    for another."""
    levels = stim.levels(region_of)
    if stim.current_ua <= dev.target_ua:
        dev.set_current(stim.current_ua)
        dev.send_pattern(levels)
    else:
        dev.send_pattern(levels)
        dev.set_current(stim.current_ua)


def _hold(dev: Any, seconds: float) -> None:
    end = time.monotonic() + seconds
    while True:
        dev.keepalive()
        left = end - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(0.02, left))


def _interactive_keys(dev: Any) -> Any:
    """Single keys from the terminal (raw mode), keeping the device's watchdog fed between keys."""
    import select
    import termios
    import tty

    fd = sys.stdin.fileno()
    old = termios.tcgetattr(fd)
    try:
        tty.setcbreak(fd)
        while True:
            ready, _, _ = select.select([sys.stdin], [], [], 0.02)
            if not ready:
                dev.keepalive()
                continue
            ch = sys.stdin.read(1)
            if ch == "\n":
                ch = "\r"
            if ch.strip() == "" and ch != "\r":
                continue
            yield ch
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, old)


def _calibration_wiring(args: argparse.Namespace, array_file: Any, electrodes: int) -> list[int] | None:
    """The mapping ``--calibration-out`` will record (None without it): electrode i's channel in the array
    file's ``Mapping_func`` (the identity without ``--array``).  Checked before the device is opened: an
    eTactileKit calibration profile holds only a permutation of channels 0 to count - 1."""
    if not getattr(args, "calibration_out", None):
        return None
    if Path(args.calibration_out).suffix.lower() != ".json":
        raise ConfigurationError(f"--calibration-out {args.calibration_out}: a calibration profile is .json")
    chans = list(array_file.mapping_func) if array_file is not None else list(range(electrodes))
    if sorted(chans) != list(range(len(chans))):
        raise ConfigurationError(
            f"--calibration-out: {array_file.source}'s Mapping_func {chans} is not a permutation of "
            f"channels 0 to {len(chans) - 1}, which an eTactileKit calibration profile needs"
        )
    return chans


def _pad(args: argparse.Namespace) -> tuple[Any, Any, Any]:
    """The pad under calibration: its array file (None: the TactDeform array), its channel mapping and the
    map of its electrode positions; an electrode on a region's border, or a region without an electrode,
    is refused (a region's stimulus must light only electrodes that lie in it)."""
    from tactdeform_hw.device.participant.regions import tactdeform_region_map

    from ..errors import SafetyError
    from ..formats import read_array_file

    array_file = read_array_file(args.array) if args.array else None
    mapping = array_file.channel_mapping() if array_file is not None else None
    rmap = array_file.region_map() if array_file is not None else tactdeform_region_map()
    if rmap.ambiguous:
        i = rmap.ambiguous[0]
        raise SafetyError(
            f"--array: {rmap.describe(i)} sits on the border of regions "
            f"{', '.join(map(str, rmap.candidates[i]))}: a region's stimulus must light only electrodes that "
            "lie in it; nothing was sent"
        )
    missing = sorted(set(range(9)) - set(rmap.resolve(None)))
    if missing:
        raise ConfigurationError(f"--array: no electrode of {rmap.source} lies in region(s) {missing}")
    return array_file, mapping, rmap


def _procedure(
    args: argparse.Namespace, dev: Any, cal: Any, region_of: tuple[int, ...], keys: Any
) -> tuple[int, int]:
    """Step the procedure through the keys on the open device; how many keys were taken and the highest
    current asked for."""
    hold_s = (args.hold_ms or 0.0) / 1000.0
    steps = 0
    peak = 0
    stim = cal.stimulus()
    progress(f"{stim.prompt}  [{stim.current_ua} µA]")
    source = keys if keys is not None else _interactive_keys(dev)
    for key in source:
        stim = cal.press(key)
        steps += 1
        peak = max(peak, stim.current_ua)
        _apply(dev, stim, region_of)
        progress(f"{stim.prompt}  [{stim.current_ua} µA]")
        if cal.finished:
            break
        if keys is not None and hold_s > 0:
            _hold(dev, hold_s)
    return steps, peak


def _write_profiles(
    args: argparse.Namespace,
    cal: Any,
    out: Path,
    region_of: tuple[int, ...],
    wiring: list[int] | None,
    result: dict[str, Any],
) -> Any:
    """Write the participant profile (and with ``--calibration-out`` the eTactileKit calibration profile)."""
    from tactdeform_hw.device.participant.profiles import save_profile

    backups = _back_up(args, out)
    if backups:
        result["backups"] = backups
    profile = cal.profile(
        pulse_width_us=args.pulse_width,
        polarity=args.polarity,
        contact_mode=args.contact_mode,
        ramp_ua_per_frame=args.ramp_ua,
        source=str(out),
    )
    save_profile(profile, out)
    result["profile"] = str(out)
    if wiring is not None:
        from ..formats.calibration_profile import from_participant, save_calibration_profile

        name = Path(args.array).stem if args.array else "TactDeform finger pad"
        etk = from_participant(
            profile, region_of, mapping=wiring, layout_name=name, layout_slug=name.lower().replace(" ", "-")
        )
        result["calibration_profile"] = str(save_calibration_profile(etk, args.calibration_out))
    result.update(profile.to_dict())
    return profile


def _unfinished(args: argparse.Namespace, cal: Any, result: dict[str, Any]) -> int:
    from tactdeform_hw.device.participant.calibration import Phase

    from .delivered import delivered_lines

    result["profile"] = None
    if args.json:
        print_json(result)
    else:
        for line in delivered_lines(result["delivered"]):
            progress(line)
    why = "quit" if cal.phase is Phase.ABORTED else f"the keys ended in phase {cal.phase.value}"
    progress(f"calibration not finished ({why}); no profile written")
    return 1


def run(args: argparse.Namespace) -> int:
    from tactdeform_hw.device.participant.calibration import Calibration, Phase
    from tactdeform_hw.device.safety.guard import SafetyGuard

    from ..device import StimConfig
    from ..protocol.units import DEFAULT_TRANSFER
    from ..session import Session, Wiring
    from .delivered import delivered_lines

    pid, out = profile_targets(args)
    refuse_overwrite(args, out)
    cal = Calibration(pid, max_ua=args.max_ua)
    array_file, mapping, rmap = _pad(args)
    region_of = rmap.resolve(None)
    wiring = _calibration_wiring(args, array_file, len(region_of))
    config = StimConfig(
        electrode_count=mapping.hw_channels if mapping is not None else 32,
        current_ua=0,
        pulse_width_us=args.pulse_width,
        polarity=args.polarity,
    )
    # its refusals and clips name the participant; the profile being made is not read
    session = Session(
        device=args.device,
        timeout_s=args.timeout,
        firmware=getattr(args, "firmware", "auto"),
        robust_encoding=robust_encoding(args),
        audit_path=args.audit_log,
        wiring=Wiring(mapping=mapping, positions=rmap),
        guard=SafetyGuard(cap_ua=args.max_ua, participant=pid),
    )
    config.validated(DEFAULT_TRANSFER)
    session.guard.check_config(config)
    keys = _script_keys(args)
    header = {"command": "calibrate", "participant": pid, "device": args.device, "array": args.array}
    audit = session.delivery_log(header, guard_regions=False)
    dev = session.open_device()
    with dev:  # the command's stop session watches it (see common.run_command); closing switches all off
        dev.configure(config)
        steps, peak = _procedure(args, dev, cal, region_of, keys)
        dev.all_off()
    audit.close()
    delivered = audit.report()
    delivered["requested_ua"] = peak  # the highest step asked for
    result: dict[str, Any] = {
        "participant": pid,
        "phase": cal.phase.value,
        "keys": steps,
        "peak_ua": peak,
        "array": args.array,
        "delivered": delivered,
    }
    if cal.phase is not Phase.DONE:
        return _unfinished(args, cal, result)
    profile = _write_profiles(args, cal, out, region_of, wiring, result)
    if args.json:
        print_json(result)
    else:
        for backup in result.get("backups", []):
            print(f"kept the previous file as {backup}")
        print(f"wrote {out}: cap {profile.cap_ua} µA, regions {list(profile.regions_ua)} µA")
        if wiring is not None:
            print(f"wrote {args.calibration_out}: eTactileKit calibration profile, mapping {wiring}")
        for line in delivered_lines(delivered):
            print(line)
    return 0
