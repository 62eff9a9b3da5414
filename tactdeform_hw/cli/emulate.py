"""``tactdeform-hw emulate``: serve the emulated board on a pseudo-terminal or a TCP port, in real time."""

from __future__ import annotations

import argparse
import signal
import sys
import time
from typing import Any

from ..errors import ConfigurationError, LimitError
from .common import progress


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "emulate",
        help="serve the emulated board on a pseudo-terminal or a TCP port any program can open",
        description="Serve the emulated eTactileKit on a pseudo-terminal (--pty: the device path, e.g. "
        "/dev/pts/7, is the first line of stdout) or on a TCP port (--tcp PORT: host:port is the first line; "
        "one client at a time, as the firmware's Wi-Fi build). The board is the timed model locked to the "
        "wall clock: bytes enter the link and the 256-byte receive queue as they arrive, the parser reads one "
        "command with a payload per 1 ms tick, replies leave when the model delivers them, scans run. "
        "--untimed answers every write at once instead. Point the eTactileKit GUI, its Python library, a "
        "Unity app or a terminal at it. Once a second, when something changed, stderr shows the registers in "
        "force, the queue depth, scans per second, overruns and hazards. SIGUSR1 power-cycles the board. "
        "Serves until interrupted (Ctrl-C or SIGTERM).",
    )
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", action="store_true", help="serve on a pseudo-terminal")
    where.add_argument("--tcp", type=int, metavar="PORT", help="serve on TCP PORT (0: any free port)")
    p.add_argument("--host", default="127.0.0.1", help="address --tcp listens on (default 127.0.0.1, loopback only)")
    p.add_argument(
        "--build",
        choices=("serial", "serial-uart", "wifi"),
        default=None,
        help="the firmware build's receive rules: serial (USB link, 256-byte queue that drops what does not "
        "fit; the default for --pty), serial-uart (the same behind a 921600-baud UART) or wifi (TCP flow "
        "control holds the host back; the default for --tcp)",
    )
    p.add_argument("--untimed", action="store_true", help="answer every write at once (no link, queue, tick or scans)")
    p.add_argument("--board", choices=("compact", "large"), default="compact", help="board kind (default compact)")
    p.add_argument("--switching-boards", type=int, default=1, help="stacked switching boards (default 1)")
    p.add_argument("--reset-on-open", action="store_true", help="power-cycle the board whenever a client opens the port")
    p.add_argument("--spy", action="store_true", help="hex-dump every byte both ways with timestamps to stderr")
    p.add_argument("--quiet", action="store_true", help="no live view (resets, fall-behinds and the summary still print)")
    p.add_argument(
        "--trace",
        metavar="FILE",
        help="record a waveform trace of the timed model that answers the client: .vcd (GTKWave; needs the "
        "'trace' extra), .csv or .json event list",
    )
    p.set_defaults(func=run)


def _check(args: argparse.Namespace) -> None:
    if args.tcp is not None and not 0 <= args.tcp <= 65535:
        raise LimitError("--tcp", args.tcp, "a TCP port 0..65535")
    if not 1 <= args.switching_boards <= 16:
        raise LimitError("--switching-boards", args.switching_boards, "1..16")
    if args.untimed and args.trace:
        raise ConfigurationError("--trace records the timed model that answers the client; drop --untimed to use it")
    if args.untimed and args.build:
        raise ConfigurationError(f"--build {args.build} sets the timed model's receive rules; drop --untimed to use it")


def run(args: argparse.Namespace) -> int:
    from ..emulator import Emulator
    from ..emulator.realtime import BUILD_RULES, FallBehind, LiveView, RealtimeEmulator, ResetRecord

    _check(args)
    rules = BUILD_RULES[args.build or ("wifi" if args.tcp is not None else "serial")]
    board: Any
    if args.untimed:
        board = Emulator(args.board, args.switching_boards)
    else:
        board = RealtimeEmulator(args.board, args.switching_boards, rules=rules)

    behind: list[FallBehind] = []
    resets: list[ResetRecord] = []

    def spy(direction: str, data: bytes, t: float) -> None:
        progress(f"{t:.6f} {direction} {data.hex(' ')}")

    sink = None
    if args.trace:
        from ..emulator.realtime import BackgroundSink
        from ..emulator.trace import open_trace

        sink = BackgroundSink(open_trace(args.trace))
        with board.lock:
            board.timed.attach(sink)
    if not args.untimed:
        board.on_behind = behind.append
    opts: dict[str, Any] = {"hook": spy if args.spy else None, "reset_on_open": args.reset_on_open,
                            "on_reset": resets.append}
    server: Any
    if args.tcp is not None:
        from ..emulator.tcp_server import TcpServer

        server = TcpServer(board, host=args.host, port=args.tcp, rules=rules, **opts)
        where = f"{server.address[0]}:{server.address[1]}"
    else:
        from ..emulator.pty_server import PtyServer

        server = PtyServer(board, **opts)
        where = server.path
    mode = "untimed (instant)" if args.untimed else f"in real time, {rules.name} build rules"

    reset_requested: list[str] = []

    def _term(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    def _usr1(signum: int, frame: object) -> None:
        reset_requested.append("SIGUSR1")  # applied by the loop below: a handler must not take the board's lock

    seen_hazards = 0
    view = LiveView()
    try:  # from here on any stop (Ctrl-C or SIGTERM as soon as the path is out) ends in the finally below
        signal.signal(signal.SIGTERM, _term)
        if hasattr(signal, "SIGUSR1"):
            signal.signal(signal.SIGUSR1, _usr1)
        server.start()
        print(where, flush=True)
        progress(f"emulating a {args.board} board with {args.switching_boards} switching board(s) on {where}, "
                 f"{mode}; SIGUSR1 resets it")
        while True:
            time.sleep(0.05)
            while reset_requested:
                server.reset(reset_requested.pop())
            while resets:
                progress(str(resets.pop(0)))
            if behind:
                n = len(behind)
                for fb in behind[:3]:
                    progress(str(fb))
                if n > 3:
                    progress(f"fell behind the wall clock {n - 3} more time(s) (worst {max(b.lag_us for b in behind) / 1000:.2f} ms)")
                del behind[:n]
            if args.untimed:
                while seen_hazards < len(board.hazards):
                    progress(f"hazard: {board.hazards[seen_hazards]}")
                    seen_hazards += 1
            elif not args.quiet:
                for line in view.poll(board, time.monotonic()):
                    progress(line)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
        summary = f"stopped: {server.bytes_in} bytes in, {server.bytes_out} bytes out, {len(server.emulator.hazards)} hazard(s)"
        if not args.untimed:
            st = board.lag.stats()
            summary += (f", {len(server.resets)} reset(s); lag median {st['median_us'] / 1000:.3f} ms, p99 "
                        f"{st['p99_us'] / 1000:.3f} ms, max {st['max_us'] / 1000:.3f} ms over {st['wakeups']} wake-up(s), "
                        f"{st['behind']} fall-behind(s) > {board.lag.limit_us / 1000:g} ms; serving thread CPU "
                        f"{server.cpu_s:.2f} s")
        if sink is not None:
            with board.lock:
                board.catch_up(record_lag=False)
                board.timed.detach(sink)
                sink.close()
            progress(f"trace written to {args.trace}")
        progress(summary)
    sys.stdout.flush()
    return 0
