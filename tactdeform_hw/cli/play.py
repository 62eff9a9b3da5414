"""``tactdeform-hw play``: play an eTactileKit pattern file through a device.

The steps run as the eTactileKit GUI runs them: each step's pattern is sent and held for its ON time,
then, when its OFF time is not 0, every electrode is switched off for that long.  ``frequency`` sets the
stimulation rate and ``stim_mode`` the polarity (1 anodic, 0 cathodic; see
:mod:`tactdeform_hw.formats.etactilekit`).  Unlike the GUI, which loops until stopped, the file plays
``--repeat`` times (default once) and ends with every channel off.

Electrode counts: a pattern file holds one level per electrode of the array it was made for.  Without
``--array`` the device is configured for exactly that many electrodes (identity mapping).  With
``--array`` the array file's ``Mapping_func`` places the electrodes on hardware channels, and an on-board
array takes the last 8 values of the GUI's 32-value patterns.  A pattern whose length matches neither is
refused before the port is opened.

The schedule keeps to absolute deadlines from the start, so time spent sending does not add up over a
long file; how late each step started is reported.  ``clock`` and ``sleep`` are injectable for tests.
"""

from __future__ import annotations

import argparse
import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ..errors import ConfigurationError, TactDeformError
from .common import add_device_arg, add_participant_arg, hold, print_json, progress, session_from_args
from .options import add_current, add_discharge, add_pulse_width

if TYPE_CHECKING:
    from tactdeform_hw.device.driver.config import Polarity


@dataclass(frozen=True)
class PlannedStep:
    """One step as it will be sent: device-order levels (application order when a mapping is used)."""

    index: int
    levels: tuple[int, ...]
    on_ms: float
    off_ms: float
    frequency_hz: int
    polarity: Polarity


@dataclass
class PlayResult:
    steps_played: int = 0
    patterns_sent: int = 0
    configures: int = 0
    scheduled_ms: float = 0.0
    elapsed_ms: float = 0.0
    max_late_ms: float = 0.0


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "play",
        help="play an eTactileKit pattern file (Pattern_Data) through a device",
        description="Play an eTactileKit pattern file through a device: configure once (rate from "
        "params.frequency, polarity from params.stim_mode: 1 anodic, 0 cathodic), then for every step send "
        "its pattern, hold it for delay.ON ms, and switch all electrodes off for delay.OFF ms. Pattern "
        "values: 0 off, 1 monophasic, 2 biphasic. Every current passes the safety guard; the device is left "
        "with every channel off. Progress goes to stderr.",
    )
    p.add_argument("file", help="eTactileKit pattern file (JSON with Pattern_Data)")
    add_device_arg(p)
    add_participant_arg(p)
    p.add_argument(
        "--array",
        metavar="ARRAY.json",
        help="eTactileKit electrode-array file whose Mapping_func maps the pattern's electrodes to hardware "
        "channels (default: identity, one channel per pattern value)",
    )
    p.add_argument(
        "--electrodes",
        type=int,
        help="electrode count the device scans (default: the pattern's length, or what --array needs); "
        "a pattern that does not fit is refused",
    )
    add_current(p)
    add_pulse_width(p, default=200, help="pulse width in µs (default 200)")
    add_discharge(p)
    p.add_argument("--repeat", type=int, default=1, help="play the file this many times (default 1)")
    p.add_argument("--dry-run", action="store_true", help="check the file and print the plan; open no device")
    p.add_argument(
        "--gif",
        metavar="OUT.gif",
        help="also draw the steps on the array as an animated GIF (needs the plot extra; positions from "
        "--array, or the TactDeform pad for 32-electrode patterns)",
    )
    p.add_argument(
        "--ignore-execution-flag",
        action="store_true",
        help="send a file whose Execution is false (the eTactileKit GUI only draws such a file)",
    )
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--quiet", action="store_true", help="no per-step progress on stderr")
    p.set_defaults(func=run)


def plan_steps(
    seq: Any, array_file: Any | None, repeat: int = 1
) -> tuple[list[PlannedStep], int, Any | None]:
    """The steps to send, the electrode count to configure, and the channel mapping (or None)."""
    if repeat < 1:
        raise ConfigurationError(f"--repeat={repeat} is out of range: at least 1")
    steps: list[PlannedStep] = []
    mapping = array_file.channel_mapping() if array_file is not None else None
    for i, step in enumerate(seq.steps):
        where = f"{seq.source or 'pattern'}: Pattern_Data[{i}][0].pattern"
        levels = array_file.levels_for(step.levels, where) if array_file is not None else step.levels
        steps.append(PlannedStep(i, tuple(levels), step.on_ms, step.off_ms, step.frequency_hz, step.polarity))
    n = mapping.hw_channels if mapping is not None else seq.electrodes
    return steps * repeat, n, mapping


def play_sequence(
    device: Any,
    steps: Sequence[PlannedStep],
    make_config: Callable[[int, Polarity], Any],
    current_ua: int,
    *,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
    report: Callable[[str], None] | None = None,
) -> PlayResult:
    """Send ``steps`` through ``device`` on an absolute schedule; leaves every channel off.

    ``make_config(frequency_hz, polarity)`` builds the :class:`~tactdeform_hw.device.StimConfig` for a
    step; the device is configured again only where the rate or polarity changes.
    """
    result = PlayResult()
    current_key: tuple[int, str] | None = None
    start = clock()
    deadline_ms = 0.0

    def wait_until(ms: float) -> None:
        remaining = start + ms / 1000.0 - clock()
        if remaining > 0:
            sleep(remaining)

    try:
        for k, step in enumerate(steps):
            key = (step.frequency_hz, step.polarity)
            late = (clock() - start) * 1000.0 - deadline_ms
            result.max_late_ms = max(result.max_late_ms, late)
            if key != current_key:
                device.configure(make_config(*key))
                result.configures += 1
                current_key = key
            device.send_pattern(list(step.levels))
            if device.current_ua != current_ua:
                device.set_current(current_ua)
            result.patterns_sent += 1
            if report is not None:
                active = sum(1 for v in step.levels if v)
                report(
                    f"step {k + 1}/{len(steps)} (Pattern_Data[{step.index}]): {active} active, "
                    f"ON {step.on_ms:g} ms, OFF {step.off_ms:g} ms, {step.frequency_hz} Hz {step.polarity}"
                )
            deadline_ms += step.on_ms
            wait_until(deadline_ms)
            if step.off_ms > 0:
                device.all_off()
                deadline_ms += step.off_ms
                wait_until(deadline_ms)
            result.steps_played += 1
    finally:
        if current_key is not None and not device.closed:
            device.all_off()
    result.scheduled_ms = deadline_ms
    result.elapsed_ms = (clock() - start) * 1000.0
    return result


def _draw_gif(seq: Any, array_file: Any | None, path: str, current_ua: int) -> dict[str, Any]:
    from ..render.array import ElectrodeArray
    from ..viz.array_picture import draw_array_gif, frames_from_sequence

    if array_file is not None:
        array, outline = array_file.array, array_file.outline_mm
    elif seq.electrodes == 32:
        array, outline = ElectrodeArray.tactdeform(), None
    else:
        raise ConfigurationError(
            f"--gif: {seq.source} has {seq.electrodes} electrodes; give --array with its electrode-array "
            "file so the picture has their positions"
        )
    info = draw_array_gif(
        array,
        frames_from_sequence(seq, array_file, current_ua or None),
        path,
        outline_mm=outline,
        title=seq.source or "pattern",
    )
    for note in info.notes:
        progress(f"note: {note}")
    return {"path": str(info.path), "frames": info.frames, "size_px": list(info.size_px)}


def _device_channels(
    args: argparse.Namespace, seq: Any, array_file: Any, n: int, mapping: Any
) -> tuple[int, Any]:
    """The channels the device is configured for and the mapping onto them, with ``--electrodes`` widening
    an array file's (never narrowing it, never without an array file)."""
    from ..device import ChannelMapping

    if args.electrodes is None or args.electrodes == n:
        return n, mapping
    if array_file is None:
        raise ConfigurationError(
            f"{seq.source}: every step has {seq.electrodes} value(s) but --electrodes is "
            f"{args.electrodes}; use --electrodes {seq.electrodes}, or --array with the electrode-array "
            "file the pattern was made for so its Mapping_func places the electrodes on hardware "
            "channels"
        )
    if args.electrodes < n:
        raise ConfigurationError(
            f"--electrodes={args.electrodes} is too few: {array_file.source}'s Mapping_func uses "
            f"hardware channels up to {n - 1}"
        )
    return args.electrodes, ChannelMapping(array_file.channel_mapping().app_to_hw, args.electrodes)


def _plan_summary(
    args: argparse.Namespace,
    seq: Any,
    steps: list[PlannedStep],
    n: int,
    mapping: Any,
    array_file: Any,
    guard: Any,
) -> dict[str, Any]:
    """The summary of what will be played, before anything is sent (the ``--json`` of a dry run)."""
    app_electrodes = len(steps[0].levels) if steps else seq.electrodes
    return {
        "file": seq.source,
        "device": None if args.dry_run else args.device,
        "dry_run": bool(args.dry_run),
        "steps": len(seq.steps),
        "repeat": args.repeat,
        "pattern_electrodes": seq.electrodes,
        "device_electrodes": n,
        "mapping": list(mapping.app_to_hw) if mapping is not None else "identity",
        "array": array_file.source if array_file is not None else None,
        "regions": list(guard.regions_for(app_electrodes) or []) or None,
        "current_ua": args.current_ua,
        "frequencies_hz": list(seq.frequencies_hz),
        "polarities": sorted({s.polarity for s in steps}),
        "scheduled_ms": sum(s.on_ms + s.off_ms for s in steps),
        "notes": list(seq.notes),
    }


def _dry_run(
    args: argparse.Namespace, seq: Any, steps: list[PlannedStep], n: int, summary: dict[str, Any]
) -> int:
    summary["plan"] = [
        {"step": s.index, "active": sum(1 for v in s.levels if v), "on_ms": s.on_ms, "off_ms": s.off_ms}
        for s in steps
    ]
    if args.json:
        print_json(summary)
    else:
        print(
            f"{seq.source}: {len(seq.steps)} step(s) × {args.repeat}, {summary['scheduled_ms']:g} ms, "
            f"{seq.electrodes} electrode(s) on {n} channel(s) — dry run, nothing sent"
        )
    return 0


def _report_switch_chips(dev: Any, n: int, summary: dict[str, Any]) -> None:
    """Warn when the board's HV513 switch chips give fewer outputs than the channels scanned."""
    try:
        chips = dev.hv513_count()
        summary["hv513_count"] = chips
        if chips * 8 < n:
            progress(
                f"warning: the board reports {chips} HV513 switch chip(s) = {chips * 8} outputs, fewer "
                f"than the {n} channels scanned; electrodes beyond them will not be stimulated"
            )
    except TactDeformError as exc:
        progress(f"note: could not ask the board for its HV513 count ({exc})")


def run(
    args: argparse.Namespace,
    *,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> int:
    from ..device import StimConfig
    from ..formats import read_array_file, read_pattern_file
    from ..protocol.units import DEFAULT_TRANSFER
    from ..session import Wiring

    seq = read_pattern_file(args.file)
    array_file = read_array_file(args.array) if args.array else None
    for note in seq.notes + (array_file.notes if array_file is not None else ()):
        progress(f"note: {note}")
    steps, n, mapping = plan_steps(seq, array_file, args.repeat)
    n, mapping = _device_channels(args, seq, array_file, n, mapping)

    def make_config(frequency_hz: int, polarity: Polarity) -> StimConfig:
        return StimConfig(
            electrode_count=n,
            current_ua=args.current_ua,
            pulse_width_us=args.pulse_width,
            discharge_us=args.discharge,
            rate_hz=frequency_hz,
            polarity=polarity,
        )

    # Refuse every configuration before the port is opened (a bad participant profile too).  The regional
    # limits follow each electrode's position in the array file, whatever order it lists them in.
    app_electrodes = len(steps[0].levels) if steps else seq.electrodes
    session = session_from_args(args, Wiring.for_array_file(array_file, mapping, app_electrodes))
    guard = session.guard
    for key in {(s.frequency_hz, s.polarity) for s in steps}:
        guard.check_config(make_config(*key).validated(DEFAULT_TRANSFER))
    if guard.positions_matter:
        guard.require_positions(app_electrodes, f"{seq.source}: a pattern")
    summary = _plan_summary(args, seq, steps, n, mapping, array_file, guard)
    if args.gif:
        summary["gif"] = _draw_gif(seq, array_file, args.gif, args.current_ua)
    if args.dry_run:
        return _dry_run(args, seq, steps, n, summary)
    if not seq.execution and not args.ignore_execution_flag:
        raise ConfigurationError(
            f"{seq.source}: Execution is false, so the eTactileKit GUI would only draw this file and send "
            "nothing; use --dry-run to check it, or --ignore-execution-flag to send it anyway"
        )
    report = None if args.quiet else progress
    header = {
        "command": "play",
        "device": args.device,
        "participant_file": args.participant,
        "array": args.array,
    }
    log = session.delivery_log(header, requested_ua=args.current_ua)
    with log, session.open_device() as dev:
        _report_switch_chips(dev, n, summary)
        if sleep is time.sleep:  # a step held in real time feeds the fail-safe watchdog while it waits
            sleep = functools.partial(hold, dev)
        result = play_sequence(
            dev, steps, make_config, args.current_ua, clock=clock, sleep=sleep, report=report
        )
    summary.update(
        steps_played=result.steps_played,
        patterns_sent=result.patterns_sent,
        configures=result.configures,
        elapsed_ms=round(result.elapsed_ms, 3),
        max_late_ms=round(result.max_late_ms, 3),
        delivered=log.report(),
    )
    if args.json:
        print_json(summary)
    else:
        _print_played(args, seq, result, summary)
    return 0


def _print_played(args: argparse.Namespace, seq: Any, result: PlayResult, summary: dict[str, Any]) -> None:
    from .delivered import delivered_lines

    print(
        f"played {result.steps_played} step(s) of {seq.source} on {args.device} in "
        f"{result.elapsed_ms / 1000:.3f} s (at most {result.max_late_ms:.1f} ms late); all channels off"
    )
    for line in delivered_lines(summary["delivered"]):
        print(line)
