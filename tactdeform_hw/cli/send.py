"""``tactdeform-hw send``: open a port, configure, send one pattern (bench checks)."""

from __future__ import annotations

import argparse
from typing import Any

from ..errors import ConfigurationError
from .common import (
    add_device_arg,
    add_participant_arg,
    audit_from_args,
    guard_from_args,
    hold,
    print_json,
    profile_from_args,
)


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "send",
        help="configure a device and send one pattern (bench check)",
        description="Configure the device (electrode count, pulse width, discharge, rate, polarity, "
        "current) and send one pattern, hold it, then switch every channel off. Every current passes the "
        "safety guard; nothing is written when a value is out of range.",
    )
    add_device_arg(p)
    add_participant_arg(p)
    p.add_argument("--pattern", required=True, help="comma-separated levels in application order: 0 off, 1 mono, 2 biphasic; or 'all:1'")
    p.add_argument("--electrodes", type=int, default=32, help="electrode count (default 32)")
    p.add_argument("--current-ua", type=int, default=0, help="pulse current in µA, 10 µA steps, ≤ 10000 (default 0)")
    p.add_argument("--pulse-width", type=int, default=None, help="pulse width in µs (default: the participant's, else 200)")
    p.add_argument("--discharge", type=int, default=45, help="discharge time in µs (default 45)")
    p.add_argument("--frequency", type=int, default=125, help="stimulation rate in Hz (default 125)")
    p.add_argument("--polarity", choices=("anodic", "cathodic"), default=None, help="default: the participant's, else anodic")
    p.add_argument("--hold", type=float, default=0.0, help="seconds to hold the pattern before all-off (default 0)")
    p.add_argument("--json", action="store_true", help="print what was sent and the device's state as JSON")
    p.set_defaults(func=run)


def parse_pattern(text: str, electrodes: int) -> list[int]:
    text = text.strip()
    if text.startswith("all:"):
        try:
            return [int(text[4:])] * electrodes
        except ValueError as exc:
            raise ConfigurationError(f"--pattern {text!r}: expected all:LEVEL") from exc
    try:
        return [int(v) for v in text.split(",") if v.strip() != ""]
    except ValueError as exc:
        raise ConfigurationError(f"--pattern {text!r}: expected comma-separated integers") from exc


def run(args: argparse.Namespace) -> int:
    from ..device import StimConfig, open_device
    from ..device.failsafe import FailSafe

    profile = profile_from_args(args)  # a bad profile is refused before anything is opened
    guard = guard_from_args(args)
    config = StimConfig(
        electrode_count=args.electrodes,
        current_ua=args.current_ua,
        pulse_width_us=args.pulse_width if args.pulse_width is not None else (profile.pulse_width_us if profile else 200),
        discharge_us=args.discharge,
        rate_hz=args.frequency,
        polarity=args.polarity or (profile.polarity if profile else "anodic"),
    )
    levels = parse_pattern(args.pattern, args.electrodes)
    from ..protocol.units import DEFAULT_TRANSFER

    config.validated(DEFAULT_TRANSFER)  # refuse before the port is even opened
    guard.check_config(config)
    audit = audit_from_args(args, participant=profile.participant if profile else None)
    dev = open_device(args.device, timeout=args.timeout, firmware=getattr(args, "firmware", "v1.2"), guard=guard, audit=audit)
    with FailSafe(dev):
        dev.configure(config)
        dev.send_pattern(levels)
        emu = getattr(getattr(dev, "port", None), "emulator", None)
        state = emu.state() if emu is not None else None
        if args.hold > 0:
            hold(dev, args.hold)
    if audit is not None:
        audit.close()
    result: dict[str, Any] = {"device": args.device, "config": config.__dict__, "pattern": levels}
    result["sent_current_ua"] = DEFAULT_TRANSFER.to_ua(state["pulse_height"]) if state is not None else None
    result["safety"] = list(guard.log)
    if state is not None:
        result["emulator_state"] = {k: v for k, v in state.items() if k != "stim_pattern"}
        result["emulator_pattern"] = state["stim_pattern"][: args.electrodes]
    if args.json:
        print_json(result)
    else:
        print(f"sent {sum(1 for v in levels if v)} active electrode(s) at {config.current_ua} µA to {args.device}; all off on close")
    return 0
