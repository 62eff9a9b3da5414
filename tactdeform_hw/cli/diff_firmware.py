"""``tactdeform-hw diff-firmware``: a firmware tree built on the host against another tree or the model.

The same byte streams (edge cases, then seeded random ones, and optionally a golden-vector file) go to both
sides; the first divergence in registers, replies or delivered pulses is reported with the bytes that
reached it, the time, both sides' values and a minimal reproduction.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .common import print_json, progress

EXIT_SAME = 0
EXIT_DIVERGED = 1
EXIT_USAGE = 2
EXIT_NOT_BUILT = 3

_EPILOG = """exit status:
  0    no divergence on any stream
  1    a divergence: the first one and its minimal reproduction are printed
  2    usage: unknown option, a value of the wrong kind, --firmware-src or --against naming no
       PlatformIO tree (a folder with src/)
  3    the firmware could not be built or run on the host: no C++ compiler, a compile error (its
       file:line), an undefined symbol, a firmware stuck at boot
  130  interrupted (Ctrl-C)

Against v1.2 or v2 (the package's Python model) the comparison is made modulo named equivalences
(timer origin, setup before the first byte, pulse-width tolerance, the ADC reading the DAC code):
docs/firmware-host-build.md, 'Differential against the model'."""


def _whole(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None


def _count(text: str) -> int:
    n = _whole(text)
    if n < 0:
        raise argparse.ArgumentTypeError(f"{n} is negative (>= 0 streams)")
    return n


def _jobs(text: str) -> int:
    n = _whole(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"{n} is out of range: jobs >= 1 (worker processes)")
    return n


def _in_range(unit: str, low: float, high: float, low_included: bool) -> Callable[[str], float]:
    """An argparse type: a number of ``unit`` in [low, high) (or (low, high)), refused while parsing."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number of {unit}") from None
        if not ((v >= low if low_included else v > low) and v < high):
            sign = "<=" if low_included else "<"
            raise argparse.ArgumentTypeError(f"{v} is out of range: {low:g} {sign} {unit} < {high:g}")
        return v

    return parse


_tolerance = _in_range("µs", 0, 1000, True)
_tolerance_s = _in_range("s", 0, 1e7, False)


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "diff-firmware",
        help="run a firmware tree built on the host against another tree or the Python model, byte for byte",
        description="Build the firmware tree --firmware-src on the host (needs a C++ compiler) and feed it, "
        "and --against (v1.2 or v2: the package's Python model of that firmware; or another tree's folder), "
        "the same timed byte streams: every opcode with its payload edges, electrode counts 0/1/255, cut "
        "commands, overflowing bursts and unknown bytes, then seeded random streams. Reports the first "
        "divergence in registers (by the golden vectors' names), replies or delivered pulses, the bytes "
        "that reached it, the time, both sides' values and a minimal reproduction.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--firmware-src", required=True, type=Path, help="the PlatformIO tree to build (has src/)")
    p.add_argument(
        "--against", required=True, help="v1.2 or v2 (the Python model), or another PlatformIO tree's folder"
    )
    p.add_argument(
        "--streams", type=_count, default=200, help="streams to run, edge cases first (default 200)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the random streams (default 0)")
    p.add_argument(
        "--recorded",
        type=Path,
        help="also run these recorded streams first (a golden-vector .jsonl: 'stream' hex or 'arrivals')",
    )
    p.add_argument("--no-edges", action="store_true", help="skip the edge-case streams: random streams only")
    p.add_argument(
        "--pulse-tolerance-us",
        type=_tolerance,
        default=None,
        help="against the model: pulse widths agree within this, the n-th pulse of a scan starts within "
        "(n + 1) times this (default 0: exact, the model running under the host build's readings)",
    )
    p.add_argument(
        "--state-map",
        type=Path,
        help="TOML naming the firmware variables to compare (default: the tree's hostbuild_state.toml, "
        "else the upstream v1.2/v2 map its unit matches)",
    )
    p.add_argument(
        "--keep-going",
        action="store_true",
        help="run every stream: count the divergences per kind and shrink the first of each",
    )
    p.add_argument(
        "--shrink-runs",
        type=_count,
        default=400,
        help="comparisons a minimal reproduction may cost, at most (default 400)",
    )
    p.add_argument(
        "--time-limit-s",
        type=_tolerance_s,
        help="start no new stream after this many seconds of wall time (the report says how many ran)",
    )
    p.add_argument(
        "--jobs",
        type=_jobs,
        default=1,
        help="worker processes sharing the streams (default 1); the report is the same for any number",
    )
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=run)


def _error(msg: str) -> None:
    sys.stderr.write(f"tactdeform-hw diff-firmware: error: {msg}\n")
    sys.stderr.flush()


def run(args: argparse.Namespace) -> int:
    from ..emulator.hostbuild.diff import MODELS, PULSE_TOLERANCE_US, STATE_MAP_FILE, diff_firmware
    from ..emulator.hostbuild.statemap import StateMap
    from ..emulator.hostbuild.streams import recorded_streams
    from ..errors import ConfigurationError, FirmwareBuildError

    src: Path = args.firmware_src
    if not (src / "src").is_dir():
        what = "does not exist" if not src.exists() else "is not a PlatformIO tree: it has no src/ folder"
        _error(f"--firmware-src {src} {what}")
        return EXIT_USAGE
    if args.against not in MODELS:
        other = Path(args.against)
        if not (other / "src").is_dir():
            what = "does not exist" if not other.exists() else "has no src/ folder"
            _error(f"--against {args.against!r} is neither v1.2, v2 nor a PlatformIO tree ({what})")
            return EXIT_USAGE
    try:
        extra = recorded_streams(args.recorded) if args.recorded is not None else []
    except ConfigurationError as exc:
        _error(f"--recorded: {exc}")
        return EXIT_USAGE
    map_file = args.state_map
    if map_file is None and (src / STATE_MAP_FILE).is_file():
        map_file = src / STATE_MAP_FILE
    try:
        state_map = StateMap.from_toml(map_file) if map_file is not None else None
    except ConfigurationError as exc:
        _error(f"--state-map: {exc}")
        return EXIT_USAGE

    def tell(message: str) -> None:
        progress(f"tactdeform-hw diff-firmware: {message}")

    try:
        report = diff_firmware(
            src,
            args.against,
            streams=args.streams,
            seed=args.seed,
            extra_streams=extra,
            edges=not args.no_edges,
            pulse_tolerance_us=PULSE_TOLERANCE_US
            if args.pulse_tolerance_us is None
            else args.pulse_tolerance_us,
            state_map=state_map,
            progress=tell,
            keep_going=args.keep_going,
            time_limit_s=args.time_limit_s,
            shrink_runs=args.shrink_runs,
            jobs=args.jobs,
        )
    except FirmwareBuildError as exc:
        _error(str(exc).splitlines()[0] if not args.debug else str(exc))
        return EXIT_NOT_BUILT
    if args.json:
        print_json(report.to_dict())
    else:
        _print_text(report)
    return EXIT_SAME if report.divergence is None else EXIT_DIVERGED


def _print_text(report: Any) -> None:
    rate = report.streams_run / report.seconds if report.seconds else 0.0
    print(
        f"{report.tree} against {report.against}: {report.streams_run} streams in {report.seconds:.1f} s "
        f"({rate:.1f}/s)"
    )
    if report.stopped_by_time:
        print("stopped by --time-limit-s: the streams after these were not run")
    if report.watchdog_cut:
        print(
            f"{report.watchdog_cut} streams compared up to the model's watchdog reset (equivalence watchdog)"
        )
    if report.call_resolved:
        print(
            f"{report.call_resolved} streams had a difference gone once the parser call was over "
            "(equivalence call-resolution)"
        )
    if report.equivalences:
        print("modulo: " + ", ".join(report.equivalences))
    d = report.divergence
    if d is None:
        print("no divergence")
        return
    print(
        f"DIVERGENCE on {report.stream.label}: {d.kind} {d.field} at {d.at_us:.3f} us "
        f"(arose after {d.since_us:.3f} us)"
    )
    print(f"  {report.tree}: {d.left!r}")
    print(f"  {report.against}: {d.right!r}")
    print(f"  bytes written before it: {d.delivered.hex(' ') or '(none)'}")
    if len(report.kinds) > 1 or report.diverged > 1:
        print(f"{report.diverged} streams diverged:")
        for key, row in report.kinds.items():
            md = row["minimal_divergence"]
            where = f"minimal: {md['field']} at {md['at_us']} us"
            print(f"  {key}: {row['streams']} (first {row['first']}; {where})")
    m, md = report.minimal, report.minimal_divergence
    print(
        f"minimal reproduction ({sum(len(b) for _, b in m.writes)} bytes, run to {m.end_us:.0f} us): "
        f"{md.kind} {md.field} at {md.at_us:.3f} us: {md.left!r} vs {md.right!r}"
    )
    for t, data in m.writes:
        print(f"  at {t:.3f} us: {data.hex(' ')}")
