"""``tactdeform-hw send``: open a port, configure, send one pattern (bench checks)."""

from __future__ import annotations

import argparse
from typing import Any

from ..errors import ConfigurationError, LimitError
from .common import add_device_arg, add_participant_arg, hold, print_json, session_from_args
from .options import add_current, add_discharge, add_frequency, add_option, add_pulse_width, duration


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
    p.add_argument(
        "--pattern",
        required=True,
        help="comma-separated levels in application order: 0 off, 1 mono, 2 biphasic; or 'all:1'",
    )
    p.add_argument(
        "--electrodes",
        type=int,
        default=None,
        help="electrode count (default 32, the TactDeform array; with --array, the file's)",
    )
    p.add_argument(
        "--array",
        metavar="ARRAY.json",
        help="eTactileKit electrode-array file: its Mapping_func places the pattern's electrodes on hardware "
        "channels and its coordinates give each electrode's calibration region (the participant's limits "
        "follow positions, never list order)",
    )
    add_current(p)
    add_pulse_width(p, default=None, help="pulse width in µs (default: the participant's, else 200)")
    add_discharge(p)
    add_frequency(p)
    p.add_argument(
        "--polarity",
        choices=("anodic", "cathodic"),
        default=None,
        help="default: the participant's, else anodic",
    )
    add_option(
        p,
        "--hold-ms",
        old=("--hold",),
        old_type=duration("s"),
        dest="hold",
        type=duration("ms", to_s=True),
        default=0.0,
        old_note="--hold took seconds, --hold-ms takes milliseconds",
        help="hold the pattern this many ms before all-off (default 0)",
    )
    p.add_argument("--json", action="store_true", help="print what was sent and the device's state as JSON")
    p.add_argument(
        "--quiet", action="store_true", help="print nothing when the pattern was sent (errors still are)"
    )
    p.set_defaults(func=run)


def parse_pattern(text: str, electrodes: int) -> list[int]:
    """The levels of ``--pattern``, checked here so a bad one is refused before the port is opened."""
    levels = _pattern_levels(text, electrodes)
    for i, v in enumerate(levels):
        if v not in (0, 1, 2):
            raise LimitError(f"pattern[{i}]", v, "0 (off), 1 (monophasic) or 2 (biphasic)")
    if len(levels) != electrodes:
        raise ConfigurationError(
            f"--pattern has {len(levels)} level(s) but --electrodes is {electrodes}; give one "
            "level per electrode, or all:LEVEL"
        )
    return levels


def _pattern_levels(text: str, electrodes: int) -> list[int]:
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


def _electrodes(args: argparse.Namespace, array_file: Any) -> int:
    """The pattern's electrode count: the array file's (refusing a different ``--electrodes``), else
    ``--electrodes`` (default 32)."""
    if array_file is None:
        return 32 if args.electrodes is None else int(args.electrodes)
    if args.electrodes is not None and args.electrodes != array_file.electrodes:
        raise ConfigurationError(
            f"--electrodes={args.electrodes} but {array_file.source} has {array_file.electrodes} "
            "electrode(s); leave --electrodes out with --array"
        )
    return int(array_file.electrodes)


def _config(args: argparse.Namespace, profile: Any, channels: int) -> Any:
    """The stimulation the command line asks for; the participant's pulse where it gives none."""
    from ..device import StimConfig

    return StimConfig(
        electrode_count=channels,
        current_ua=args.current_ua,
        pulse_width_us=args.pulse_width
        if args.pulse_width is not None
        else (profile.pulse_width_us if profile else 200),
        discharge_us=args.discharge,
        rate_hz=args.frequency,
        polarity=args.polarity or (profile.polarity if profile else "anodic"),
    )


def _scans_us(config: Any, hw_levels: bytes, version: str) -> float:
    """The longest scan ``version``'s firmware would run for this configuration and frame, by the
    firmware-order estimate the driver refuses frames with: v1.2 scans the pattern as given (an off
    channel gets the sense pulse, and the configuration's all-off scan is checked too); v2 pulses every
    channel in the frame's mode (an off one at height 0)."""
    from ..device.driver.v2 import mode_for
    from ..protocol.commands import V2_COMMANDS
    from ..protocol.constants import PATTERN_BIPHASIC, PATTERN_MONOPHASIC
    from ..protocol.firmware_math import estimate_scan_us

    n = config.electrode_count
    width, discharge, sense = config.pulse_width_us, config.discharge_us, config.sense_width_us
    if version == "v2":
        biphasic = mode_for(hw_levels) == V2_COMMANDS.STIM_MODE_BIPHASIC
        level = PATTERN_BIPHASIC if biphasic else PATTERN_MONOPHASIC
        return max(
            estimate_scan_us([PATTERN_MONOPHASIC] * n, width, discharge, sense),
            estimate_scan_us([level] * n, width, discharge, sense),
        )
    return max(
        estimate_scan_us(bytes(n), width, discharge, sense),
        estimate_scan_us(hw_levels, width, discharge, sense),
    )


def check_scans(guard: Any, config: Any, hw_levels: bytes, firmware: str) -> None:
    """Refuse a frame whose scan leaves the firmware's parser no time, before any byte reaches the device.

    The driver checks the scan of the version the board proved, but only after the identification and
    the configuration have been written; here the check runs on every version the board may be
    (``--firmware auto``: v1.2 and v2, the worst case), so the refusal's "nothing was sent" is true."""
    from ..device.driver.pacing import SCAN_GAP_MIN_US
    from ..errors import SafetyError
    from ..protocol.firmware_math import firmware_period_us

    versions = ("v1.2", "v2") if firmware == "auto" else (firmware,)
    period_us = firmware_period_us(config.rate_hz)
    scans = {version: _scans_us(config, hw_levels, version) for version in versions}
    worst = max(versions, key=lambda version: scans[version])
    try:
        guard.check_scan(scans[worst], period_us, SCAN_GAP_MIN_US)
    except SafetyError as exc:
        fine = [v for v in versions if scans[v] <= period_us - SCAN_GAP_MIN_US]
        if not fine:
            raise
        tail = "; nothing was sent"
        raise SafetyError(
            f"{str(exc).removesuffix(tail)} on firmware {worst}, which --firmware auto may find (a "
            f"{fine[0]} board takes this frame: give --firmware {fine[0]}){tail}"
        ) from None


def run(args: argparse.Namespace) -> int:
    from ..formats import read_array_file
    from ..ports import board_state
    from ..protocol.units import DEFAULT_TRANSFER
    from ..session import Wiring
    from .delivered import delivered_lines

    array_file = read_array_file(args.array) if args.array else None
    mapping = array_file.channel_mapping() if array_file is not None else None
    # a bad profile is refused before anything is opened; a calibration profile's electrodes are read
    # through the array's positions (without --array, the TactDeform array's for 32 electrodes)
    unmapped = 32 if args.electrodes is None else args.electrodes
    session = session_from_args(args, Wiring.for_array_file(array_file, mapping, unmapped), guard_now=False)
    electrodes = _electrodes(args, array_file)
    guard = session.guard
    config = _config(args, session.profile, mapping.hw_channels if mapping is not None else electrodes)
    levels = parse_pattern(args.pattern, electrodes)
    config.validated(DEFAULT_TRANSFER)  # refuse before the port is even opened
    guard.check_config(config)
    hw_levels = mapping.to_hardware(levels) if mapping is not None else bytes(levels)
    check_scans(guard, config, hw_levels, args.firmware)
    if guard.positions_matter:
        guard.require_positions(electrodes, "--pattern")
    log = session.delivery_log(session.header("send"), requested_ua=args.current_ua)
    dev = session.open_device()
    try:
        with dev:  # the command's stop session watches it (see common.run_command); closing switches all off
            dev.configure(config)
            dev.send_pattern(levels)
            state = board_state(dev.port)  # what an emulated board holds; a real one cannot show it
            if args.hold > 0:
                hold(dev, args.hold)
    finally:
        log.close()
    delivered = log.report()
    result: dict[str, Any] = {"device": args.device, "config": config.__dict__, "pattern": levels}
    if array_file is not None:
        result["array"] = array_file.source
        result["mapping"] = list(mapping.app_to_hw) if mapping is not None else None
    result["requested_current_ua"] = args.current_ua
    result["delivered"] = delivered
    sent_code = (
        None
        if state is None
        else state.pulse_height
        if state.pulse_height is not None
        else max(state.stim_pattern[: config.electrode_count])
    )
    result["sent_current_ua"] = DEFAULT_TRANSFER.to_ua(sent_code) if sent_code is not None else None
    result["safety"] = list(guard.log)
    if state is not None:
        result["emulator_state"] = {k: v for k, v in state.as_dict().items() if k != "stim_pattern"}
        result["emulator_pattern"] = list(state.stim_pattern[: config.electrode_count])
    if args.json:
        print_json(result)
    elif not args.quiet:
        print(f"sent {sum(1 for v in levels if v)} active electrode(s) to {args.device}; all off on close")
        for line in delivered_lines(delivered):
            print(line)
    return 0
