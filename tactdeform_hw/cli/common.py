"""Options shared by subcommands."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

DEVICE_HELP = (
    "serial port path (e.g. /dev/ttyACM0), pyserial URL (e.g. etactile://?board=compact), "
    "usb:VID:PID[:SERIAL] for the board's USB interface through pyusb (e.g. usb:303a:1001), "
    "usb-emulator, or 'emulator' (default: the in-process emulator)"
)


def add_device_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default="emulator", help=DEVICE_HELP)
    from .options import add_option, positive

    add_option(
        parser,
        "--timeout-s",
        old=("--timeout",),
        dest="timeout",
        type=positive("s"),
        default=0.5,
        help="read/write timeout in seconds (default 0.5)",
    )
    parser.add_argument(
        "--firmware",
        choices=("v1.2", "v2", "auto"),
        default="auto",
        help="the board's firmware. The board is always identified first (v2's 2 s command timeout "
        "waited out, every current off, then a reply only one version gives); auto (the default) drives "
        "the version it proved, v1.2 or v2 refuses a board that proved the other; a board that proves "
        "neither is refused",
    )


def print_json(obj: Any) -> None:
    json.dump(obj, sys.stdout, indent=2, sort_keys=False, default=str)
    sys.stdout.write("\n")


def progress(msg: str) -> None:
    _line_to_stderr(msg)


def _line_to_stderr(msg: str) -> None:
    """One write for the text and its newline: a stop signal's handler raises between a ``print``'s two
    writes, which would leave the line unfinished and glue the stop's own line onto it."""
    sys.stderr.write(msg + "\n")
    sys.stderr.flush()


# --- participant safety (every command that can stimulate) ------------------------------------------------

PARTICIPANT_HELP = (
    "participant profile (.json or .toml, see 'tactdeform-hw calibrate'), or an eTactileKit calibration "
    "profile (.json, format etactilekit_calibration_profile: each electrode's intensity limits the hardware "
    "channel its mapping names, and a mapping that disagrees with --array's Mapping_func, or with the "
    "identity without --array, is refused): its cap, regional amplitudes, charge and ramp limits, pulse "
    "width and polarity bound every current this command sends; a malformed file is refused before the "
    "device is opened"
)


def add_participant_arg(parser: argparse.ArgumentParser) -> None:
    """``--participant FILE`` and ``--audit-log FILE`` (JSON lines of every command sent)."""
    parser.add_argument("--participant", metavar="FILE", default=None, help=PARTICIPANT_HELP)
    parser.add_argument(
        "--audit-log",
        metavar="FILE",
        default=None,
        help="append every command sent (with its time) and every safety refusal or clip to FILE as JSON "
        "lines",
    )


def _participant_file(args: argparse.Namespace, region_of: Any = None) -> tuple[Any, Any]:
    """``--participant``'s participant profile and, for an eTactileKit calibration profile, the calibration
    profile itself ((None, None) without the option).  ``region_of`` (one region per electrode, or a
    :class:`~tactdeform_hw.device.participant.regions.RegionMap` of the electrode positions) converts a
    calibration
    profile's intensities to regions; default: the TactDeform array's regions."""
    path = getattr(args, "participant", None)
    if not path:
        return None, None
    from tactdeform_hw.device.participant.regions import RegionMap

    from ..formats.calibration_profile import read_participant_file

    if isinstance(region_of, RegionMap):
        region_of = region_of.resolve(None)
    if region_of is None:
        from ..render.array import ElectrodeArray

        region_of = ElectrodeArray.tactdeform().regions
    return read_participant_file(path, region_of)


def profile_from_args(args: argparse.Namespace, region_of: Any = None) -> Any:
    """The participant profile named by ``--participant`` (None without one); raises
    :class:`~tactdeform_hw.errors.ProfileError` naming the field for a bad file.  An upstream calibration
    profile is converted through ``region_of`` (default: the TactDeform array's regions)."""
    return _participant_file(args, region_of)[0]


def guard_with_array(args: argparse.Namespace, array_file: Any, mapping: Any) -> Any:
    """:func:`guard_from_args` for a command that may take ``--array``: regional limits by the array
    file's positions, and a calibration profile checked against its ``Mapping_func`` (an on-board
    array's counts from hardware channel 24)."""
    if array_file is None:
        return guard_from_args(args, mapping=mapping)
    return guard_from_args(
        args,
        region_of=array_file.region_map(),
        mapping=mapping,
        against=f"--array {array_file.source}'s Mapping_func",
        channel_offset=array_file.pattern_offset,
    )


def guard_from_args(
    args: argparse.Namespace,
    *,
    region_of: Any = None,
    mapping: Any = None,
    against: str | None = None,
    channel_offset: int = 0,
) -> Any:
    """The safety guard for this command: the participant's limits with ``--participant``, the 10 mA
    hardware ceiling without.  Call it before opening the device, so a bad profile sends nothing.

    ``mapping`` is the channel mapping the command will open the device with (None: the identity) and
    ``against`` names it for errors; ``channel_offset`` is an on-board array's (its ``Mapping_func`` counts
    from hardware channel 24).  An eTactileKit calibration profile's intensities bind the hardware
    channels its ``mapping`` names, and a profile whose mapping disagrees with ``mapping`` is refused
    here, before the device is opened."""
    from tactdeform_hw.device.participant.regions import RegionMap
    from tactdeform_hw.device.safety.guard import SafetyGuard

    from ..formats.calibration_profile import calibration_guard

    profile, calibration = _participant_file(args, region_of)
    if profile is None:
        return SafetyGuard()
    if calibration is None:
        return SafetyGuard.from_profile(profile, region_of=region_of)
    if against is None:
        against = (
            "the identity mapping (electrode i on channel i; no --array)"
            if mapping is None
            else "the device's channel mapping"
        )
    by_id = region_of.resolve(None) if isinstance(region_of, RegionMap) else region_of
    if by_id is None:
        from ..render.array import ElectrodeArray

        by_id = tuple(int(r) for r in ElectrodeArray.tactdeform().regions)
    return calibration_guard(
        calibration,
        by_id,
        region_map=region_of,
        mapping=mapping,
        against=against,
        channel_offset=channel_offset,
    )


def audit_from_args(args: argparse.Namespace, **session: Any) -> Any:
    """An :class:`~tactdeform_hw.device.driver.audit.AuditLog` for ``--audit-log`` (None without one)."""
    path = getattr(args, "audit_log", None)
    if not path:
        return None
    from tactdeform_hw.device.driver.audit import AuditLog

    session.setdefault("command", getattr(args, "command", None))
    session.setdefault("device", getattr(args, "device", None))
    session.setdefault("participant_file", getattr(args, "participant", None))
    return AuditLog(path, **session)


def hold(device: Any, seconds: float, *, interval_s: float = 0.02) -> None:
    """Hold the current frame for ``seconds`` while telling the device's fail-safe watchdog that the
    owner is still there (a deliberate hold must not look like a stalled renderer)."""
    import time

    end = time.monotonic() + max(0.0, seconds)
    while True:
        left = end - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(interval_s, left))
        device.keepalive()  # after the wait: each ramp step (one per frame) is held for a whole interval


# --- the stop (every command) -------------------------------------------------------------------------------


def run_command(func: Any, args: argparse.Namespace) -> int:
    """Run one subcommand under a :class:`~tactdeform_hw.device.safety.failsafe.StopSession`: every device it
    opens — directly or through the study runner, the renderer or anything added later — is watched by the
    fail-safe (the no-frame watchdog in its own thread), an exception anywhere closes it (every channel
    off), and SIGINT, SIGTERM, SIGHUP or SIGQUIT switch it off before the command ends with 128 + the
    signal (130 for Ctrl-C) and one line on stderr, never a traceback.  The command-line entry point runs
    every command through here, so no command can forget it."""
    from tactdeform_hw.device.safety import failsafe

    name = getattr(args, "command", None) or "command"
    try:
        with failsafe.StopSession():
            return int(func(args) or 0)
    except failsafe.SignalStop as stop:
        _report_stop(name, stop.signum, stop.devices, stop.all_off)
        return int(stop.code) if isinstance(stop.code, int) else 128 + stop.signum
    except KeyboardInterrupt:
        rec = failsafe.last_stop
        if rec is not None:
            _report_stop(name, rec.signum, rec.devices, rec.all_off)
        else:
            print(f"tactdeform-hw {name}: interrupted", file=sys.stderr, flush=True)
        return 130


def _report_stop(name: str, signum: int, devices: int, all_off: bool) -> None:
    import signal

    what = signal.Signals(signum).name
    if devices == 0:
        tail = "no device was open"
    elif all_off:
        tail = "every channel off"
    else:
        tail = "all-off FAILED: the board may still be stimulating, unplug it"
    _line_to_stderr(f"tactdeform-hw {name}: stopped by {what}; {tail}")
