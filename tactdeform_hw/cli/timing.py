"""``tactdeform-hw timing``: the scan budget of a configuration, pattern-update latency, waveform traces.

Computed from the firmware's own arithmetic and the named timing model
(:class:`~tactdeform_hw.emulator.timed.timing.TimingModel`), so a firmware developer can check a configuration
before flashing a board: per-channel cost, scan time, period, margin, verdict and the rate really reached.
"""

from __future__ import annotations

import argparse
import io
import math
from pathlib import Path
from typing import Any

from ..errors import ConfigurationError, LimitError
from .common import print_json
from .options import (
    DeprecatedAlias,
    PolarityCode,
    add_board,
    add_discharge,
    add_finisher,
    add_firmware_src,
    add_firmware_version,
    add_frequency,
    add_option,
    add_pulse_width,
    typed_flag,
)
from .outputs import writing

#: Exit statuses of ``timing`` beyond 0/1/2: the verdict a script can branch on.
EXIT_OVERRUN = 3
EXIT_WATCHDOG = 4


def register(sub: Any) -> None:
    p = sub.add_parser(
        "timing",
        help="scan budget, overruns, update latency and waveform traces of a configuration",
        description="Emulate the stimulation scan of a configuration with the timing model and print its "
        "budget: per-channel cost, scan time, timer period, margin and verdict (fits / overrun "
        "/ watchdog reset). Example (the TactDeform setting): --electrodes 32 --pulse-width-us "
        "200 --discharge-us 45 --frequency-hz 125. Exit status: 0 when the scan fits its "
        f"period, {EXIT_OVERRUN} when it OVERRUNs it, {EXIT_WATCHDOG} when it trips the "
        "interrupt WATCHDOG (the board resets); 1 for a refused value, 2 for a usage error.",
    )
    _firmware_options(p)
    _firmware_src_option(p)
    _scan_options(p)
    _board_options(p)
    _output_options(p)
    p.set_defaults(func=run)


def _firmware_options(p: argparse.ArgumentParser) -> None:
    """The firmware version and the timing model's reading of its exchanges."""
    add_firmware_version(
        p, help="firmware version (default v1.2). v2: --pattern holds DAC codes and --mode picks the waveform"
    )
    p.add_argument(
        "--mode",
        type=int,
        default=None,
        help="v2 stimulation mode: 0 monophasic (default), 1 biphasic, 2 impedance only (sense pulse on "
        "every channel)",
    )
    p.add_argument(
        "--cs-writes",
        choices=("inside", "costed"),
        default="inside",
        help="whether the 6.6 µs DAC/ADC exchange includes its chip-select writes (inside, the default) "
        "or they cost one GPIO write each on top (costed, the firmware's host build)",
    )
    p.add_argument(
        "--dac-load",
        choices=("mid_exchange", "cs_rise"),
        default="mid_exchange",
        help="when the DAC output changes: 3.3 µs into the exchange (default, the firmware comment) or "
        "when DA_CS rises (the converter's load moment)",
    )


def _firmware_src_option(p: argparse.ArgumentParser) -> None:
    """The firmware tree whose own scans are measured in place of the timing model's."""
    add_firmware_src(
        p,
        help="measure the firmware's own C++ tree built on this machine (docs/firmware-host-build.md): "
        "configured through its parser, the budget measured on its scans; its state map says the version "
        "(--firmware is not read)",
    )


def _scan_options(p: argparse.ArgumentParser) -> None:
    """The configuration whose scan is timed: electrodes, pattern, pulse, rate, polarity, sense pulse."""
    p.add_argument(
        "--electrodes",
        type=int,
        default=None,
        help="electrode_num, 0-255 (default 32, or the pattern's length)",
    )
    p.add_argument(
        "--pattern",
        default=None,
        help="v1.2: one value for every channel (1 monophasic, 2 biphasic, other: sense pulse) or a comma "
        "list, one per channel (default 1); v2: DAC codes 0-4095, one for all or h1,h2,... (default 100)",
    )
    add_pulse_width(p, default=200, help="stimulation pulse width in µs, 1-65535 (v2: 0-65535) (default 200)")
    add_option(
        p,
        "--current-ua",
        type=int,
        default=None,
        help="pulse current in µA, 10 µA steps, ≤ 10000 (default 1000 = DAC code 100)",
    )
    _code_alias(p, "--pulse-height", 100, "--current-ua", "a DAC code; --current-ua takes µA, 10 µA per code")
    add_discharge(p, help="channel discharge time in µs, 0-255 (default 45)")
    add_frequency(p, help="stimulation rate in Hz, 1-65535 (default 125)")
    p.add_argument(
        "--polarity",
        action=PolarityCode,
        default=1,
        metavar="{anodic,cathodic}",
        help="pulse polarity (default anodic)",
    )
    _sense_options(p)


def _sense_options(p: argparse.ArgumentParser) -> None:
    """The sense pulse, and the currents given in µA turned into the codes the firmware stores."""
    add_option(
        p,
        "--sense-current-ua",
        type=int,
        default=None,
        help="sense pulse current in µA (default 0): v1.2 stores the byte sent << 2, so 40 µA steps up to "
        "10200; v2 stores the byte itself, so 10 µA steps up to 2550",
    )
    _code_alias(p, "--sense-height", 0, "--sense-current-ua", "the byte sent; --sense-current-ua takes µA")
    add_option(
        p,
        "--sense-width-us",
        old=("--sense-width",),
        dest="sense_width",
        type=int,
        default=0,
        help="sense pulse width in µs, 0-255",
    )
    add_finisher(p, currents_from_ua)


def _code_alias(p: argparse.ArgumentParser, flag: str, default: int, canonical: str, took: str) -> None:
    """A hidden, warning spelling that takes the code the firmware stores where ``canonical`` takes µA: it
    keeps its own dest (the code), which :func:`currents_from_ua` reads when the µA option is not given."""
    p.add_argument(
        flag,
        type=int,
        default=default,
        help=argparse.SUPPRESS,
        action=DeprecatedAlias,
        canonical=canonical,
        note=f"{flag} took {took}",
    )


def _board_options(p: argparse.ArgumentParser) -> None:
    """The board and the timing model's constants."""
    add_board(p)
    p.add_argument(
        "--hv513",
        type=int,
        default=None,
        help="HV513 count the firmware believes in (default: what the board's detection returns)",
    )
    p.add_argument(
        "--overrun-policy",
        choices=("immediate", "skip"),
        default=None,
        help="what follows a scan longer than the period (default immediate: the chip's behaviour)",
    )
    p.add_argument(
        "--set",
        dest="model_set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="change a timing-model constant, e.g. --set gpio_write_us=0.1 (repeatable; "
        "--list-model shows them all)",
    )
    p.add_argument(
        "--list-model", action="store_true", help="print every timing constant with its source and exit"
    )


def _output_options(p: argparse.ArgumentParser) -> None:
    """What is measured and written beyond the budget: latency, traces, a diagram, JSON."""
    p.add_argument(
        "--latency",
        action="store_true",
        help="also measure the latency of a pattern update over USB and UART (wire + loop tick + scan)",
    )
    p.add_argument(
        "--phases", type=int, default=16, help="update moments spread over one period for --latency"
    )
    p.add_argument(
        "--vcd",
        metavar="FILE",
        default=None,
        help="write BL, LE, POL, CLK, DIN, DAC, SEL (and ADC) of --cycles scans as a VCD (needs pyvcd)",
    )
    p.add_argument(
        "--events",
        metavar="FILE",
        default=None,
        help="write the same scans as an event list (.csv or .json; on either version one row per signal "
        "change: t_ns, t_us, kind, name, value)",
    )
    p.add_argument("--cycles", type=int, default=2, help="scans to trace for --vcd/--events (default 2)")
    p.add_argument(
        "--png",
        metavar="FILE",
        default=None,
        help="draw a timing diagram of --cycles scans as a PNG: pulses per channel against time, the "
        "period and any overrun marked (needs the plot extra)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="write --vcd/--events traces estimated above 100 MB (refused without it, before any is "
        "written; a long run prints its progress on stderr)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")


def currents_from_ua(args: argparse.Namespace) -> None:
    """``--current-ua`` and ``--sense-current-ua`` (µA) as the codes the scan model takes."""

    from ..protocol.units import DEFAULT_TRANSFER

    typed = getattr(args, "_typed_flags", None) or {}
    for flag, old in (("--current-ua", "--pulse-height"), ("--sense-current-ua", "--sense-height")):
        if getattr(args, flag[2:].replace("-", "_"), None) is not None and typed_flag(args, flag) != flag:
            raise ConfigurationError(f"give {flag} or {typed.get(flag, old)}, not both")
    if args.current_ua is not None:
        args.pulse_height = DEFAULT_TRANSFER.to_code(args.current_ua, "current_ua")
    if args.sense_current_ua is not None:
        args.sense_height = sense_byte(args.sense_current_ua, getattr(args, "firmware", "v1.2"))


def sense_byte(sense_current_ua: int, firmware: str) -> int:
    """The 0xF9 byte of a sense current on ``firmware``: v1.2 stores ``byte << 2`` as the DAC code (40 µA
    steps up to byte 255, 10200 µA), v2 stores the byte itself (10 µA steps up to 2550 µA).  The timing
    model holds any byte the firmware holds, so the limit is the byte's, not the 10 mA stimulation
    ceiling (nothing is sent to a participant here)."""
    from ..protocol.constants import U8_MAX, Opcode
    from ..protocol.firmware import V1_2, V2
    from ..protocol.units import DEFAULT_TRANSFER, check_int

    spec = V2 if firmware == "v2" else V1_2
    step = 1 << spec.command(Opcode.SENSE_HEIGHT).shift
    ua_per_byte = DEFAULT_TRANSFER.ua_per_code * step
    top_ua = int(U8_MAX * ua_per_byte)
    stored = "the byte sent << 2" if step > 1 else "the byte sent, unshifted"
    limit = f"a multiple of {ua_per_byte:g} µA from 0 to {top_ua} µA (firmware {spec.name} stores {stored})"
    value = check_int("--sense-current-ua", sense_current_ua, 0, 1 << 31, "µA")
    byte = value / ua_per_byte
    if not byte.is_integer() or value > top_ua:
        raise LimitError("--sense-current-ua", sense_current_ua, limit)
    return int(byte)


def verdict_status(budget: Any) -> int:
    """0 when the scan fits, :data:`EXIT_OVERRUN` or :data:`EXIT_WATCHDOG` when it does not."""
    if budget.watchdog_reset:
        return EXIT_WATCHDOG
    return EXIT_OVERRUN if budget.overrun else 0


def _parse_value(text: str) -> Any:
    if text.lower() in ("none", "off"):
        return None
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def model_from_args(args: argparse.Namespace) -> Any:
    from tactdeform_hw.emulator.timed.timing import TimingModel

    changes: dict[str, Any] = {}
    for item in args.model_set:
        if "=" not in item:
            raise LimitError("--set", item, "NAME=VALUE")
        name, value = item.split("=", 1)
        changes[name.strip()] = _parse_value(value.strip())
    if args.overrun_policy is not None:
        changes["overrun_policy"] = args.overrun_policy
    return TimingModel().with_(**changes) if changes else TimingModel()


def config_from_args(args: argparse.Namespace) -> Any:
    from tactdeform_hw.emulator.firmware.board import Board
    from tactdeform_hw.emulator.firmware.scan import ScanConfig

    text = "1" if args.pattern is None else str(args.pattern).strip()
    pattern: int | list[int]
    if "," in text:
        try:
            pattern = [int(v) for v in text.split(",") if v.strip() != ""]
        except ValueError as exc:
            raise LimitError("--pattern", text, "integers 0-255 separated by commas") from exc
    else:
        try:
            pattern = int(text)
        except ValueError as exc:
            raise LimitError("--pattern", text, "an integer 0-255 or a comma list") from exc
    electrodes = args.electrodes
    if electrodes is None:
        electrodes = len(pattern) if isinstance(pattern, list) else 32
    hv = args.hv513
    if hv is None:
        hv = Board(args.board, args.switching_boards).detect_hv513()
    return ScanConfig.make(
        electrodes,
        pattern,
        pulse_width_us=args.pulse_width,
        pulse_height=args.pulse_height,
        discharge_us=args.discharge,
        rate_hz=args.frequency,
        polarity=args.polarity,
        sense_height_raw=args.sense_height,
        sense_width_us=args.sense_width,
        hv513_num=hv,
    )


def trace_scans(
    cfg: Any,
    model: Any,
    cycles: int,
    sinks: list[Any],
    board: str = "compact",
    switching_boards: int = 1,
    on_progress: Any = None,
) -> Any:
    """Run ``cycles`` scans of ``cfg`` from power-on (registers set directly) into ``sinks``;
    ``on_progress(done, cycles)`` is called at every tenth of a long run (1000 scans or more)."""
    from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator

    if not isinstance(cycles, int) or cycles < 1:
        raise LimitError("--cycles", cycles, "an integer >= 1")
    emu = TimedEmulator(board, switching_boards, model=model)
    for s in sinks:
        emu.attach(s)
    emu.configure(cfg)
    step = max(1, cycles // 10) if cycles >= 1000 and on_progress is not None else 0
    said = 0
    while emu.reports.scan_count() < cycles:
        emu.advance_to(emu.next_alarm / 1000.0 if math.isfinite(emu.next_alarm) else emu.now_us + 1e6)
        if step and emu.reports.scan_count() >= said + step:
            said = emu.reports.scan_count()
            on_progress(said, cycles)
    # let the last scan finish
    emu.advance_to(max(emu.now_us, emu.runs[-1].end_ns / 1000.0))
    for s in sinks:
        emu.detach(s)
        s.close()
    return emu


def conventions_from_args(args: argparse.Namespace) -> Any:
    from tactdeform_hw.emulator.firmware.firmware_scan import ScanConventions

    return ScanConventions(cs_writes_costed=args.cs_writes == "costed", dac_load=args.dac_load)


def _convention_rows(conv: Any) -> list[dict[str, Any]]:
    return [
        {
            "name": "chip_select_writes",
            "value": "costed" if conv.cs_writes_costed else "inside",
            "unit": "",
            "source": "option",
            "doc": "whether the 6.6 µs exchange includes the chip-select writes (v1.2: 4, v2: 2 per "
            "exchange); default inside (the firmware comment's reading); --cs-writes costed adds one "
            "GPIO write each",
        },
        {
            "name": "dac_load",
            "value": conv.dac_load,
            "unit": "",
            "source": "option",
            "doc": "when the DAC output changes: mid_exchange (3.3 µs in, default) or cs_rise (when DA_CS "
            "rises, about 6.6 µs in); pulse widths do not change, every DAC edge moves",
        },
    ]


def v2_config_from_args(args: argparse.Namespace) -> Any:
    """A v2 configuration: per-electrode DAC codes, a mode, every value the firmware can hold."""
    from tactdeform_hw.emulator.firmware.board import Board
    from tactdeform_hw.emulator.firmware.firmware_scan import FirmwareScanConfig

    from ..protocol.constants import U8_MAX, U16_MAX
    from ..protocol.firmware import V2, OpcodeV2
    from ..protocol.units import check_int

    text = "100" if args.pattern is None else str(args.pattern).strip()
    limit = V2.dac_max_code
    try:
        values = [int(v) for v in text.split(",") if v.strip() != ""]
    except ValueError as exc:
        raise LimitError("--pattern", text, f"DAC codes 0-{limit}, one or a comma list") from exc
    if not values:
        raise LimitError("--pattern", text, f"DAC codes 0-{limit}, one or a comma list")
    for i, v in enumerate(values):
        check_int("--pattern" if len(values) == 1 else f"--pattern[{i}]", v, 0, limit)
    electrodes = args.electrodes
    if electrodes is None:
        electrodes = len(values) if len(values) > 1 else 32
    electrodes = check_int("--electrodes", electrodes, 0, V2.max_electrodes)
    if len(values) == 1:
        values = values * electrodes
    elif len(values) != electrodes:
        raise LimitError("--pattern length", len(values), f"exactly --electrodes = {electrodes}")
    mode = check_int(
        "--mode", 0 if args.mode is None else args.mode, 0, V2.command(OpcodeV2.STIM_MODE).max_value or 0
    )
    hv = args.hv513
    if hv is None:
        hv = Board(args.board, args.switching_boards).detect_hv513()
    return FirmwareScanConfig(
        electrode_num=electrodes,
        stim_pattern=values,
        pulse_width=check_int("--pulse-width-us", args.pulse_width, 0, U16_MAX, "µs"),
        discharge_time=check_int("--discharge-us", args.discharge, 0, U8_MAX, "µs"),
        polarity=args.polarity,
        hv513_num=check_int("--hv513", hv, 0, U8_MAX),
        sense_pulse_height=check_int("--sense-height", args.sense_height, 0, U8_MAX),
        sense_pulse_width=check_int("--sense-width-us", args.sense_width, 0, U8_MAX, "µs"),
        stim_mode=mode,
        frequency_hz=check_int("--frequency", args.frequency, 1, U16_MAX, "Hz"),
    )


def _refuse_default_only(args: argparse.Namespace) -> None:
    """``--latency``, ``--vcd`` and ``--png`` are drawn from v1.2's timed model under the default readings."""
    for flag in ("latency", "vcd", "png"):
        if getattr(args, flag):
            raise ConfigurationError(
                f"--{flag} models v1.2 with the timing model's defaults; it does not take "
                f"--firmware v2, --cs-writes costed or --dac-load cs_rise"
            )


def _print_firmware_budget(args: argparse.Namespace, b: Any, events: list[list[Any]] | None) -> int:
    """A budget in the firmware's scan-log terms, and ``--events`` from the scan's logged events."""
    result = b.to_dict()
    if events is not None:
        _write_logged_events(Path(args.events), _events_format(args.events), events)
        result["traces"] = [args.events]
    if args.json:
        print_json(result)
        return verdict_status(b)
    print(b.table())
    if args.events:
        print(f"wrote {args.events}")
    return verdict_status(b)


def _run_v2(args: argparse.Namespace) -> int:
    """v2: the budget and events of firmware v2's scan engine, the statement walker."""
    from tactdeform_hw.emulator.firmware.firmware_scan import budget, trace_scan

    conv = conventions_from_args(args)
    cfg = v2_config_from_args(args)
    _refuse_default_only(args)
    b = budget(cfg, args.firmware, conv)
    events = trace_scan(cfg, args.firmware, conv).events if args.events else None
    return _print_firmware_budget(args, b, events)


def _run_v1_2_readings(args: argparse.Namespace, model: Any) -> int:
    """v1.2 under ``--cs-writes costed`` or ``--dac-load cs_rise``: v1.2's scan engine timed under those
    readings, its budget and events in the firmware's scan-log terms (chip selects included)."""
    from tactdeform_hw.emulator.firmware.scan import ScanEngine, firmware_trace
    from tactdeform_hw.emulator.records.reports import firmware_budget

    cfg = config_from_args(args)
    _refuse_default_only(args)
    b = firmware_budget(cfg, model)
    events = None
    if args.events:
        _events_format(args.events)  # a bad file name is refused before any work
        scan = ScanEngine(model).template(cfg)
        events = [[round(e[0] / 1000, 3), *e[1:]] for e in firmware_trace(scan, model)]
    return _print_firmware_budget(args, b, events)


def logged_event_rows(events: list[list[Any]]) -> list[dict[str, Any]]:
    """A scan log's ``[time_us, kind, pin, value]`` events (either version's scan engine, as the firmware's
    own code logs them) in the format ``--events`` writes on both versions: ``{"t_ns", "t_us", "kind",
    "name", "value"}``, as the v1.2 trace's rows are (kind ``gpio`` with name ``GPIO<n>``, or ``dac`` with
    name ``DAC``), so one reader takes either."""
    rows = []
    for t_us, kind, pin, value in events:
        t_ns = round(float(t_us) * 1000)
        name = f"GPIO{pin}" if str(kind).upper() == "GPIO" else str(pin)
        rows.append(
            {"t_ns": t_ns, "t_us": t_ns / 1000, "kind": str(kind).lower(), "name": name, "value": value}
        )
    return rows


def _write_logged_events(path: Path, fmt: str, events: list[list[Any]]) -> None:
    import json

    rows = logged_event_rows(events)
    with writing("--events", path):
        if fmt == "json":
            path.write_text("[\n" + ",\n".join(json.dumps(r) for r in rows) + ("\n]\n" if rows else "]\n"))
        else:
            path.write_text(
                "time_ns,time_us,kind,name,value\n"
                + "".join(f"{r['t_ns']},{r['t_us']:.3f},{r['kind']},{r['name']},{r['value']}\n" for r in rows)
            )


def run(args: argparse.Namespace) -> int:
    from tactdeform_hw.emulator.records.reports import Budget

    model = model_from_args(args)
    if args.list_model:
        rows = model.describe() + _convention_rows(conventions_from_args(args))
        if args.json:
            print_json(rows)
        else:
            for r in rows:
                print(f"{r['name']:<26}{r['value']!s:>12} {r['unit']:<8} {r['source']:<17} {r['doc']}")
        return 0
    if args.firmware_src is not None:
        return _run_host_build(args, model)
    if args.firmware == "v2":
        return _run_v2(args)
    if args.mode is not None:
        raise ConfigurationError(
            f"--mode {args.mode}: v1.2 has no stimulation mode (the pattern byte picks the "
            "waveform); use --firmware v2"
        )
    if args.cs_writes == "costed" or args.dac_load != "mid_exchange":
        return _run_v1_2_readings(
            args, model.with_(cs_writes_costed=args.cs_writes == "costed", dac_load=args.dac_load)
        )
    cfg = config_from_args(args)
    if args.events:
        _events_format(args.events)  # a bad file name is refused before any work
    budget = Budget.of(cfg, model, requested_rate_hz=args.frequency)
    result: dict[str, Any] = budget.to_dict()
    result["model"] = model.to_dict()
    result["assumptions"] = model.assumptions()

    if args.latency:
        if cfg.electrode_num == 0:
            raise ConfigurationError("--latency needs at least one electrode")
        from tactdeform_hw.emulator.timed.model_v1_2 import pattern_latency

        result["latency"] = {}
        for link in ("usb", "uart"):
            lat = pattern_latency(
                cfg,
                link,
                model=model,
                phases=args.phases,
                board=args.board,
                switching_boards=args.switching_boards,
            )
            lat.pop("runs")
            result["latency"][link] = lat

    written = _write_traces(args, cfg, model)
    if written:
        result["traces"] = written
    if args.png:
        result["png"] = _draw_png(args, cfg, model)

    if args.json:
        print_json(result)
        return verdict_status(budget)
    print(budget.table())
    if args.latency:
        print()
        print(_latency_table(result["latency"]))
    for path in written:
        print(f"wrote {path}")
    if args.png:
        print(f"wrote {args.png}")
    return verdict_status(budget)


def _run_host_build(args: argparse.Namespace, model: Any) -> int:
    """``--firmware-src``: the budget, events, VCD and picture measured on the built firmware's scans."""
    from tactdeform_hw.emulator.hostbuild import timing_run as hb
    from tactdeform_hw.emulator.hostbuild.statemap import detect

    if args.latency:
        raise ConfigurationError("--latency is the Python model's; drop it with --firmware-src")
    if args.events:
        _events_format(args.events)
    smap = detect(Path(args.firmware_src))
    if smap is None or not smap.firmware:
        raise ConfigurationError(
            f"--firmware-src {args.firmware_src}: no shipped state map fits the tree (v1.2 or v2 upstream)"
        )
    if smap.firmware == "v2":
        c = v2_config_from_args(args)
        wire = hb.wire_v2(
            c.electrode_num, list(c.stim_pattern), frequency_hz=c.frequency_hz, stim_mode=c.stim_mode,
            pulse_width_us=c.pulse_width, sense_height=c.sense_pulse_height,
            sense_width_us=c.sense_pulse_width, discharge_us=c.discharge_time, polarity=c.polarity,
        )  # fmt: skip
        hv = c.hv513_num
    else:
        cfg = config_from_args(args)
        wire = hb.wire_v1_2(
            cfg.electrode_num, cfg.pattern, frequency_hz=args.frequency, pulse_height=cfg.pulse_height,
            pulse_width_us=cfg.pulse_width, sense_height_code=cfg.sense_pulse_height,
            sense_width_us=cfg.sense_pulse_width, discharge_us=cfg.discharge_time, polarity=cfg.polarity,
        )  # fmt: skip
        hv = cfg.hv513_num
    budget, events, _ = hb.measure(args.firmware_src, wire, args.cycles, hv513_count=hv, timing=model)
    result: dict[str, Any] = budget.to_dict()
    written = [p for p in (args.events, args.vcd) if p]
    if args.events:
        hb.write_events(args.events, events)
    if args.vcd:
        hb.write_vcd(args.vcd, events)
    if args.png:
        result["png"] = hb.draw_png(args.png, events, f"{args.firmware_src}: {len(budget.scans)} scans")
    if written:
        result["traces"] = written
    if args.json:
        print_json(result)
    else:
        print(budget.table())
        for path in written + ([args.png] if args.png else []):
            print(f"wrote {path}")
    return EXIT_OVERRUN if budget.overrun else 0


def _draw_png(args: argparse.Namespace, cfg: Any, model: Any) -> dict[str, Any]:
    from ..viz.timing_diagram import draw_reports_png

    emu = trace_scans(cfg, model, args.cycles, [], args.board, args.switching_boards)
    title = (
        f"{cfg.electrode_num} electrodes, {args.pulse_width} µs pulses, {args.discharge} µs discharge, "
        f"{args.frequency} Hz"
    )
    info = draw_reports_png(emu.reports, args.png, first_cycle=0, max_cycles=args.cycles, title=title)
    return {
        "path": str(info.path),
        "cycles": info.cycles_drawn,
        "overruns": info.overruns_drawn,
        "size_px": list(info.size_px),
    }


EVENT_SUFFIXES = (".csv", ".json")


def _events_format(path: str) -> str:
    """``csv`` or ``json``, from the ``--events`` file's suffix (the only thing that says which)."""
    suffix = Path(path).suffix
    if suffix.lower() not in EVENT_SUFFIXES:
        raise ConfigurationError(
            f"--events {path!r}: unknown file suffix {suffix!r}; use {' or '.join(EVENT_SUFFIXES)}"
        )
    return suffix.lower()[1:]


def _write_traces(args: argparse.Namespace, cfg: Any, model: Any) -> list[str]:
    if not args.vcd and not args.events:
        return []
    from tactdeform_hw.emulator.records.trace import CsvSink, JsonSink, VcdSink

    from .common import progress

    estimate = trace_bytes(args, cfg, model)
    if estimate > TRACE_LIMIT_BYTES and not args.force:
        raise ConfigurationError(
            f"--cycles {args.cycles}: the traces would take about {estimate / 1e6:.0f} MB (more than "
            f"{TRACE_LIMIT_BYTES / 1e6:.0f} MB); give fewer --cycles, or --force to write them"
        )
    if args.cycles >= 1000:
        progress(f"timing: tracing {args.cycles} scans, about {estimate / 1e6:.1f} MB")
    sinks: list[Any] = []
    paths: list[str] = []
    if args.vcd:
        sinks.append(VcdSink(args.vcd))
        paths.append(args.vcd)
    if args.events:
        sinks.append(CsvSink(args.events) if _events_format(args.events) == "csv" else JsonSink(args.events))
        paths.append(args.events)
    with writing("/".join(f"--{k}" for k in ("vcd", "events") if getattr(args, k)), " ".join(paths)):
        trace_scans(
            cfg,
            model,
            args.cycles,
            sinks,
            args.board,
            args.switching_boards,
            on_progress=lambda done, total: progress(f"timing: {done}/{total} scans traced"),
        )
    return paths


#: Above this many bytes of traces (``--vcd`` and ``--events`` together) ``timing`` refuses unless
#: ``--force``: a long ``--cycles`` fills a disk in minutes.
TRACE_LIMIT_BYTES = 100_000_000


class _Kept(io.StringIO):
    """A text buffer the trace sinks may close without losing what they wrote."""

    def close(self) -> None:
        pass


def trace_bytes(args: argparse.Namespace, cfg: Any, model: Any) -> int:
    """About the size the ``--vcd`` and ``--events`` files will have (erring large): one and two scans
    traced into memory, the second scan's bytes counted once per further scan (every scan of one
    configuration writes the same events)."""
    from tactdeform_hw.emulator.records.trace import CsvSink, JsonSink, VcdSink

    sizes = []
    for cycles in (1, 2):
        bufs = [_Kept() for _ in range(2)]
        sinks: list[Any] = []
        if args.vcd:
            sinks.append(VcdSink(bufs[0]))
        if args.events:
            kind = CsvSink if _events_format(args.events) == "csv" else JsonSink
            sinks.append(kind(bufs[1]))
        trace_scans(cfg, model, cycles, sinks, args.board, args.switching_boards)
        sizes.append(sum(len(b.getvalue().encode()) for b in bufs))
    # later scans' times have more digits: a quarter more errs on the large side
    return int((sizes[0] + max(0, sizes[1] - sizes[0]) * (int(args.cycles) - 1)) * 1.25)


def _latency_table(lat: dict[str, Any]) -> str:
    lines = [
        "Pattern update latency (same pattern, written at moments spread over one period), µs:",
        f"{'link':<6}{'':<14}{'min':>10}{'mean':>10}{'max':>10}",
    ]
    labels = (
        ("wire_us", "wire"),
        ("loop_wait_us", "loop tick"),
        ("scan_wait_us", "scan wait"),
        ("first_channel_us", "first channel"),
        ("last_channel_us", "last channel"),
    )
    for link, d in lat.items():
        for key, label in labels:
            s = d[key]
            if s["min"] is None:
                lines.append(f"{link:<6}{label:<14}{'never':>10}")
                continue
            lines.append(f"{link:<6}{label:<14}{s['min']:>10.1f}{s['mean']:>10.1f}{s['max']:>10.1f}")
        if d.get("mid_copy"):
            lines.append(
                f"{'':<6}{d['mid_copy']} of {d['phases']} runs felt channel 0 from a scan inside the "
                "pattern's copy (no scan wait)"
            )
        link = ""
    return "\n".join(lines)
