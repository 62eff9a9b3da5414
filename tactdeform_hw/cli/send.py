"""``tactdeform-hw send``: open a port, configure, send one pattern (bench checks)."""

from __future__ import annotations

import argparse
import time
from typing import Any

from ..errors import ConfigurationError
from .common import add_device_arg, print_json


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "send",
        help="configure a device and send one pattern (bench check)",
        description="Configure the device (electrode count, pulse width, discharge, rate, polarity, "
        "current) and send one pattern, hold it, then switch every channel off. Every current passes the "
        "safety guard; nothing is written when a value is out of range.",
    )
    add_device_arg(p)
    p.add_argument("--pattern", required=True, help="comma-separated levels in application order: 0 off, 1 mono, 2 biphasic; or 'all:1'")
    p.add_argument("--electrodes", type=int, default=32, help="electrode count (default 32)")
    p.add_argument("--current-ua", type=int, default=0, help="pulse current in µA, 10 µA steps, ≤ 10000 (default 0)")
    p.add_argument("--pulse-width", type=int, default=200, help="pulse width in µs (default 200)")
    p.add_argument("--discharge", type=int, default=45, help="discharge time in µs (default 45)")
    p.add_argument("--frequency", type=int, default=125, help="stimulation rate in Hz (default 125)")
    p.add_argument("--polarity", choices=("anodic", "cathodic"), default="anodic")
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

    config = StimConfig(
        electrode_count=args.electrodes,
        current_ua=args.current_ua,
        pulse_width_us=args.pulse_width,
        discharge_us=args.discharge,
        rate_hz=args.frequency,
        polarity=args.polarity,
    )
    levels = parse_pattern(args.pattern, args.electrodes)
    from ..protocol.units import DEFAULT_TRANSFER

    config.validated(DEFAULT_TRANSFER)  # refuse before the port is even opened
    with open_device(args.device, timeout=args.timeout) as dev:
        dev.configure(config)
        dev.send_pattern(levels)
        emu = getattr(getattr(dev, "port", None), "emulator", None)
        state = emu.state() if emu is not None else None
        if args.hold > 0:
            time.sleep(args.hold)
    result: dict[str, Any] = {"device": args.device, "config": config.__dict__, "pattern": levels}
    if state is not None:
        result["emulator_state"] = {k: v for k, v in state.items() if k != "stim_pattern"}
        result["emulator_pattern"] = state["stim_pattern"][: args.electrodes]
    if args.json:
        print_json(result)
    else:
        print(f"sent {sum(1 for v in levels if v)} active electrode(s) at {config.current_ua} µA to {args.device}; all off on close")
    return 0
