"""``tactdeform-hw emulate``: serve the emulated board on a pseudo-terminal."""

from __future__ import annotations

import argparse
import signal
import sys
import time
from typing import Any

from .common import progress


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "emulate",
        help="serve the emulated board on a pseudo-terminal any program can open",
        description="Create a pseudo-terminal with the emulated eTactileKit behind it. The device path "
        "(e.g. /dev/pts/7) is the first line of stdout; point the eTactileKit GUI, its Python library, a "
        "Unity app or a terminal at it. Serves until interrupted (Ctrl-C or SIGTERM); hazards the "
        "firmware would hit are reported on stderr as they happen.",
    )
    p.add_argument("--pty", action="store_true", required=True, help="serve on a pseudo-terminal (required)")
    p.add_argument("--board", choices=("compact", "large"), default="compact", help="board kind (default compact)")
    p.add_argument("--switching-boards", type=int, default=1, help="stacked switching boards (default 1)")
    p.add_argument("--spy", action="store_true", help="hex-dump every byte both ways with timestamps to stderr")
    p.add_argument(
        "--trace",
        metavar="FILE",
        help="record a waveform trace while serving, following the wall clock on the timed model: "
        ".vcd (GTKWave; needs the 'trace' extra), .csv or .json event list",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..emulator import Emulator
    from ..emulator.pty_server import PtyServer

    emu = Emulator(args.board, args.switching_boards)

    hooks = []
    if args.spy:

        def spy(direction: str, data: bytes, t: float) -> None:
            progress(f"{t:.6f} {direction} {data.hex(' ')}")

        hooks.append(spy)
    live = None
    if args.trace:
        from ..emulator.trace import LiveTrace

        live = LiveTrace(args.trace, board=args.board, switching_boards=args.switching_boards)
        hooks.append(live.hook)

    def hook(direction: str, data: bytes, t: float) -> None:
        for h in hooks:
            h(direction, data, t)

    def _term(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    server = PtyServer(emu, hook=hook if hooks else None)
    seen = 0
    try:  # from here on any stop (Ctrl-C or SIGTERM as soon as the path is out) ends in the finally below
        signal.signal(signal.SIGTERM, _term)
        server.start()
        print(server.path, flush=True)
        progress(f"emulating a {args.board} board with {args.switching_boards} switching board(s) on {server.path}")
        while True:
            time.sleep(0.1)
            if live is not None:
                live.poll()
            while seen < len(emu.hazards):
                progress(f"hazard: {emu.hazards[seen]}")
                seen += 1
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
        if live is not None:
            live.close()
            progress(f"trace written to {args.trace}")
        progress(f"stopped: {server.bytes_in} bytes in, {server.bytes_out} bytes out, {len(emu.hazards)} hazard(s)")
    sys.stdout.flush()
    return 0
