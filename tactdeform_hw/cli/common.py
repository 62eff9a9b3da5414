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
    parser.add_argument(
        "--encoding",
        choices=ENCODINGS,
        default=None,
        help="how values are written: robust (loss-tolerant: a lost byte can only lower a value or leave "
        "it) for any link that can lose bytes — a USB-to-UART bridge, a raw UART; plain for native USB "
        "CDC (CRC-checked) or Wi-Fi/TCP (reliable). On a lossy link the plain encoding lets one lost byte "
        "set a full-scale pulse until the fail-safe's recovery (docs/safety.md). Default: the port's own "
        "(plain on every real port)",
    )


#: ``--encoding``'s choices, and the ``robust_encoding`` each gives the device.
ENCODINGS = ("plain", "robust")


def robust_encoding(args: argparse.Namespace) -> bool | None:
    """``--encoding`` as ``open_device``'s ``robust_encoding``: None when not given (the port's own)."""
    encoding = getattr(args, "encoding", None)
    return None if encoding is None else encoding == "robust"


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


def session_from_args(
    args: argparse.Namespace, wiring: Any = None, *, guard: Any = None, guard_now: bool = True
) -> Any:
    """The :class:`~tactdeform_hw.session.Session` of a stimulating command: ``--device``, ``--timeout-s``,
    ``--firmware``, ``--encoding``, ``--participant`` and ``--audit-log`` on ``wiring``.  The profile is
    read here (and the guard built, unless ``guard_now`` is False), so call it before anything is opened: a
    bad profile sends nothing."""
    from ..session import Session

    return Session(
        device=args.device,
        timeout_s=args.timeout,
        firmware=getattr(args, "firmware", "auto"),
        robust_encoding=robust_encoding(args),
        participant_file=getattr(args, "participant", None),
        audit_path=getattr(args, "audit_log", None),
        wiring=wiring,
        guard=guard,
        guard_now=guard_now,
    )


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
