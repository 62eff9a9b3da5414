"""``tactdeform-hw emulate``: serve the emulated board on a pseudo-terminal or a TCP port, in real time."""

from __future__ import annotations

import argparse
import signal
import sys
import time
from collections.abc import Callable
from typing import Any

from ..errors import ConfigurationError, LimitError
from .common import progress
from .options import add_board, add_firmware_src, add_firmware_version


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "emulate",
        help="serve the emulated board on a pseudo-terminal, a TCP port or as a USB device",
        description="Serve the emulated eTactileKit on a pseudo-terminal (--pty: the device path, e.g. "
        "/dev/pts/7, is the first line of stdout), on a TCP port (--tcp [HOST:]PORT: host:port "
        "is the first line; one client at a time, as the firmware's Wi-Fi build; with --firmware "
        "v2 it also answers UDP discovery, ETK? on port 8888) or as its USB device (--usb: the "
        "device name, usb-emulator:///PATH, is the first line; programs open it with --device "
        "NAME through pyusb, one claim of the interface at a time, released when the claiming "
        "process ends, however it ends). The board is the timed model of "
        "the chosen firmware (--firmware v1.2, the default, or v2) locked to the wall clock: "
        "bytes enter the link and the receive queue as they arrive, the parser reads them on its "
        "own rhythm (v1.2: one command with a payload per 1 ms tick; v2: whole payloads, a cut "
        "command discarded after 2 s), replies leave when the model delivers them, scans run. "
        "--untimed answers every write at once instead. Point the eTactileKit GUI, its Python "
        "library, a Unity app or a terminal at it. Once a second, when something changed, stderr "
        "shows the registers in force, the queue depth, scans per second, overruns and hazards; each "
        "hazard prints at once, late wake-ups at most once a second with their count and worst lag. "
        "SIGUSR1 power-cycles the board. Serves until interrupted (Ctrl-C or SIGTERM).",
    )
    _where_options(p)
    _firmware_options(p)
    _board_options(p)
    _output_options(p)
    p.set_defaults(func=run)


def _where_options(p: argparse.ArgumentParser) -> None:
    """Where the board is served: a pseudo-terminal, a TCP port or its USB device."""
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", action="store_true", help="serve on a pseudo-terminal")
    where.add_argument(
        "--usb",
        action="store_true",
        help="serve the board's USB device (CDC-ACM, 303a:1001) on a Unix socket; needs the 'usb' extra",
    )
    where.add_argument(
        "--tcp",
        metavar="[HOST:]PORT",
        help="serve on TCP PORT (0: any free port) at HOST (default --host, 127.0.0.1: loopback only)",
    )
    p.add_argument(
        "--host", default="127.0.0.1", help="address --tcp listens on (default 127.0.0.1, loopback only)"
    )


def _firmware_options(p: argparse.ArgumentParser) -> None:
    """The firmware the board runs and the discovery its Wi-Fi build answers."""
    add_firmware_version(
        p, help="the firmware the board runs (default v1.2; v2 is upstream's current firmware)"
    )
    add_firmware_src(
        p,
        help="serve the firmware's own C++ tree built on this machine (docs/firmware-host-build.md) in place "
        "of the Python model; the version the driver finds is the one its state map declares",
    )
    p.add_argument(
        "--state-map",
        metavar="FILE",
        help="with --firmware-src: the TOML state map of a tree the package ships none for",
    )
    p.add_argument(
        "--discovery-port",
        type=int,
        default=None,
        metavar="PORT",
        help="with --tcp and --firmware v2: answer UDP discovery (ETK?) on PORT at the --tcp host "
        "(default 8888, as the firmware; 0: do not answer)",
    )
    p.add_argument(
        "--kit-id",
        default=None,
        metavar="ID",
        help="the 6-hex-digit id discovery reports (default: the id the firmware derives from an "
        "Espressif MAC, F93030)",
    )


def _board_options(p: argparse.ArgumentParser) -> None:
    """The board: the build's receive rules, timed or not, its kind and what resets it."""
    p.add_argument(
        "--build",
        choices=("serial", "serial-uart", "wifi"),
        default=None,
        help="the firmware build's receive rules: serial (USB link, a receive queue that drops what does not "
        "fit, 256 bytes on v1.2 and 1024 on v2; the default for --pty), serial-uart (the same behind a "
        "921600-baud UART) or wifi (TCP flow control holds the host back; the default for --tcp)",
    )
    p.add_argument(
        "--untimed", action="store_true", help="answer every write at once (no link, queue, tick or scans)"
    )
    add_board(p)
    p.add_argument(
        "--reset-on-open", action="store_true", help="power-cycle the board whenever a client opens the port"
    )


def _output_options(p: argparse.ArgumentParser) -> None:
    """What the command shows and records while it serves."""
    p.add_argument(
        "--spy",
        action="store_true",
        help="hex-dump every byte both ways to stderr, stamped with the board's virtual µs since serving "
        "began (t=…us, the clock of the live view, the hazards and --trace)",
    )
    p.add_argument(
        "--quiet",
        action="store_true",
        help="no live view and no fall-behind lines unless a lag exceeds 100 ms, beyond which the emulated "
        "board cannot show the 150 ms stop bound (resets, hazards and the summary still print)",
    )
    p.add_argument(
        "--trace",
        metavar="FILE",
        help="record a waveform trace of the timed model that answers the client: .vcd (GTKWave; needs the "
        "'trace' extra), .csv or .json event list",
    )


#: the MAC the emulated Wi-Fi board reports its id from (Espressif's OUI 30:30:F9)
EMULATED_MAC = bytes.fromhex("3030f9a1b2c3")


def _tcp_address(args: argparse.Namespace) -> tuple[str, int]:
    host, sep, port = str(args.tcp).rpartition(":")
    try:
        number = int(port)
    except ValueError:
        raise LimitError("--tcp", args.tcp, "[HOST:]PORT with PORT a number 0..65535") from None
    if not 0 <= number <= 65535:
        raise LimitError("--tcp", number, "a TCP port 0..65535")
    return (host.strip("[]") if sep and host else args.host), number


def _check_firmware_src(args: argparse.Namespace) -> None:
    """``--firmware-src`` serves the built tree in real time (pty, TCP or USB); its ``--trace`` is the
    firmware's own pin and DAC events (:meth:`~..emulator.hostbuild.timed.HostBuildTimedModel.attach`)."""
    if args.firmware_src is None:
        if args.state_map is not None:
            raise ConfigurationError("--state-map names the state map of a --firmware-src tree; add one")
        return
    if args.untimed:
        raise ConfigurationError("--firmware-src serves the built firmware in real time; drop --untimed")


def _check(args: argparse.Namespace) -> None:
    _check_firmware_src(args)
    if args.tcp is not None:
        args.tcp_address = _tcp_address(args)
    if args.discovery_port is not None:
        if args.tcp is None or args.firmware != "v2":
            raise ConfigurationError(
                "--discovery-port: only the v2 Wi-Fi build answers discovery; use it with "
                "--tcp and --firmware v2"
            )
        if not 0 <= args.discovery_port <= 65535:
            raise LimitError("--discovery-port", args.discovery_port, "a UDP port 1..65535, or 0 for none")
    if args.kit_id is not None:
        if args.tcp is None or args.firmware != "v2":
            raise ConfigurationError(
                "--kit-id: only the v2 Wi-Fi build answers discovery; use it with --tcp and --firmware v2"
            )
        if len(args.kit_id) != 6 or any(ch not in "0123456789ABCDEFabcdef" for ch in args.kit_id):
            raise LimitError("--kit-id", args.kit_id, "6 hexadecimal digits, as the firmware reports")
    if args.usb and args.untimed:
        raise ConfigurationError(
            "--usb serves the timed firmware model behind its USB device; drop --untimed"
        )
    if args.usb and args.build not in (None, "serial"):
        raise ConfigurationError(f"--build {args.build}: a board on USB runs the serial build; drop --build")
    if not 1 <= args.switching_boards <= 16:
        raise LimitError("--switching-boards", args.switching_boards, "1..16")
    if args.untimed and args.trace:
        raise ConfigurationError(
            "--trace records the timed model that answers the client; drop --untimed to use it"
        )
    if args.untimed and args.build:
        raise ConfigurationError(
            f"--build {args.build} sets the timed model's receive rules; drop --untimed to use it"
        )


def _board(args: argparse.Namespace, rules: Any) -> Any:
    """The emulated board: the firmware's timed model locked to the wall clock, or with ``--untimed`` one
    that answers every write at once."""
    from tactdeform_hw.emulator.serving.realtime import RealtimeEmulator

    from ..emulator import Emulator

    if args.untimed:
        return Emulator(args.board, args.switching_boards, firmware=args.firmware)
    if args.firmware_src is not None:
        return _host_build_board(args, rules)
    return RealtimeEmulator(args.board, args.switching_boards, rules=rules, firmware=args.firmware)


def _host_build_board(args: argparse.Namespace, rules: Any) -> Any:
    """``--firmware-src``: the tree built on this machine, served in real time over the build's link."""
    from pathlib import Path

    from tactdeform_hw.emulator.hostbuild.statemap import StateMap
    from tactdeform_hw.emulator.hostbuild.timed import HostBuildTimedModel
    from tactdeform_hw.emulator.serving.realtime import RealtimeEmulator

    if not Path(args.firmware_src).is_dir():
        raise ConfigurationError(f"--firmware-src {args.firmware_src}: not a folder")
    smap = StateMap.from_toml(Path(args.state_map)) if args.state_map else None
    model = HostBuildTimedModel(
        args.firmware_src,
        args.board,
        args.switching_boards,
        state_map=smap,
        link=rules.make_link(),
        model=rules.timing(None),
    )
    args.firmware = model.firmware.name if model.firmware is not None else "none declared"
    if model.firmware is None:
        args.quiet = True  # the live view reads a board state; this tree's map declares none
    return RealtimeEmulator(rules=rules, timed=model)  # type: ignore[arg-type]


def _trace_sink(args: argparse.Namespace, board: Any) -> Any:
    """``--trace``: the waveform recorder attached to the board's timed model (None without it)."""
    if not args.trace:
        return None
    from tactdeform_hw.emulator.records.trace import open_trace
    from tactdeform_hw.emulator.serving.realtime import BackgroundSink

    sink = BackgroundSink(open_trace(args.trace))
    with board.lock:
        board.timed.attach(sink)
    return sink


def _server(args: argparse.Namespace, board: Any, rules: Any, opts: dict[str, Any]) -> tuple[Any, str]:
    """The server for ``--tcp``, ``--usb`` or ``--pty`` and the address a client opens."""
    if args.tcp is not None:
        from tactdeform_hw.emulator.serving.tcp_server import TcpServer

        host, port = args.tcp_address
        server = TcpServer(board, host=host, port=port, rules=rules, **opts)
        return server, f"{server.address[0]}:{server.address[1]}"
    if args.usb:
        from tactdeform_hw.emulator.serving.usb_server import UsbServer

        usb = UsbServer(board, **opts)
        return usb, usb.name
    from tactdeform_hw.emulator.serving.pty_server import PtyServer

    pty = PtyServer(board, **opts)
    return pty, pty.path


def _discovery(args: argparse.Namespace, server: Any) -> Any:
    """The v2 Wi-Fi build's UDP discovery responder (None where the board answers none); the server is
    stopped if it cannot be made."""
    if args.tcp is None or args.firmware != "v2" or args.discovery_port == 0:
        return None
    from tactdeform_hw.emulator.serving.udp_discovery import (
        DISCOVERY_PORT,
        DiscoveryResponder,
        device_id_from_mac,
    )

    kit_id = (args.kit_id or device_id_from_mac(EMULATED_MAC)).upper()
    try:
        return DiscoveryResponder(
            kit_id,
            host=server.address[0],
            port=DISCOVERY_PORT if args.discovery_port is None else args.discovery_port,
            tcp_port=server.address[1],
        )
    except BaseException:
        server.stop()
        raise


def _announce(args: argparse.Namespace, where: str, mode: str, responder: Any) -> None:
    print(where, flush=True)
    progress(
        f"emulating a {args.board} board with {args.switching_boards} switching board(s) on {where}, "
        f"{mode}; SIGUSR1 resets it; times (t=…us) are the board's virtual µs since serving began"
        + (" (the trace counts the same clock in ns)" if args.trace else "")
    )
    if responder is not None:
        progress(
            f"answering discovery on UDP {responder.address[0]}:{responder.address[1]} as "
            f"etactilekit-{responder.device_id} (etactilekit://{responder.device_id}?discovery="
            f"{responder.address[0]}:{responder.address[1]})"
        )


class _Notices:
    """What the serving loop prints besides the live view: resets, fall-behinds (aggregated, at most one
    line a second; under ``--quiet`` only lags beyond :data:`~.notices.QUIET_LAG_LIMIT_US`) and hazards
    (at once, one line each, at most one a second per kind).  Every time is the board's virtual µs since
    serving began (``t=…us``)."""

    def __init__(self, args: argparse.Namespace) -> None:
        from tactdeform_hw.emulator.serving.notices import BehindNotices, HazardNotices
        from tactdeform_hw.emulator.serving.realtime import LiveView

        self.behind = BehindNotices(quiet=args.quiet)
        self.hazards = HazardNotices()
        self.view = None if args.quiet or args.untimed else LiveView(hazards=False)
        self.resets: list[Any] = []

    def lines(self, board: Any, now_s: float, force: bool = False) -> list[str]:
        """The lines to print at wall time ``now_s`` (``force``: everything held back, when stopping)."""
        out = [str(self.resets.pop(0)) for _ in range(len(self.resets))]
        out += self.behind.lines(now_s, force)
        if hasattr(board, "advance_now"):  # a timed board: up to now, as the serving thread keeps it
            with board.lock:
                board.advance_now()
                hazards = list(board.hazards)
        else:
            hazards = list(board.hazards)
        out += self.hazards.lines(hazards, now_s, force)
        if self.view is not None and not force:
            out += self.view.poll(board, now_s)
        return out


def _spy(args: argparse.Namespace, board: Any, origin: list[float]) -> Callable[[str, bytes, float], None]:
    """``--spy``'s byte hook: every byte both ways, stamped with the board's virtual µs since serving
    began (a timed board's own clock origin; for ``--untimed``, ``origin[0]``)."""

    def spy(direction: str, data: bytes, t: float) -> None:
        t0 = origin[0] if args.untimed else board.t0
        progress(f"t={(t - t0) * 1e6:.1f}us {direction} {data.hex(' ')}")

    return spy


def _serve(
    board: Any,
    server: Any,
    notices: _Notices,
    reset_requested: list[str],
) -> None:
    """Watch the served board until interrupted: apply resets, print what :class:`_Notices` has."""
    while True:
        time.sleep(0.05)
        while reset_requested:
            server.reset(reset_requested.pop())
        for line in notices.lines(board, time.monotonic()):
            progress(line)


def _stopped(args: argparse.Namespace, board: Any, server: Any) -> str:
    """The summary line of a stopped server."""
    summary = (
        f"stopped: {server.bytes_in} bytes in, {server.bytes_out} bytes out, "
        f"{len(server.emulator.hazards)} hazard(s)"
    )
    if not args.untimed:
        st = board.lag.stats()
        summary += (
            f", {len(server.resets)} reset(s); lag median {st['median_us'] / 1000:.3f} ms, p99 "
            f"{st['p99_us'] / 1000:.3f} ms, max {st['max_us'] / 1000:.3f} ms over {st['wakeups']} "
            f"wake-up(s), {st['behind']} fall-behind(s) > {board.lag.limit_us / 1000:g} ms; serving "
            f"thread CPU {server.cpu_s:.2f} s"
        )
    return summary


def run(args: argparse.Namespace) -> int:
    from tactdeform_hw.emulator.serving.realtime import BUILD_RULES

    _check(args)
    rules = BUILD_RULES[args.build or ("wifi" if args.tcp is not None else "serial")]
    board = _board(args, rules)
    notices = _Notices(args)
    origin = [time.monotonic()]  # an untimed board's time 0: set again when serving begins
    sink = _trace_sink(args, board)
    if not args.untimed:
        board.on_behind = notices.behind.add
    opts: dict[str, Any] = {
        "hook": _spy(args, board, origin) if args.spy else None,
        "reset_on_open": args.reset_on_open,
        "on_reset": notices.resets.append,
    }
    server, where = _server(args, board, rules, opts)
    mode = "untimed (instant)" if args.untimed else f"in real time, {rules.name} build rules"
    mode += f", firmware {args.firmware}"
    responder = _discovery(args, server)
    reset_requested: list[str] = []

    def _term(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    def _usr1(signum: int, frame: object) -> None:
        # applied by the loop: a handler must not take the board's lock
        reset_requested.append("SIGUSR1")

    try:  # from here on any stop (Ctrl-C or SIGTERM as soon as the path is out) ends in the finally below
        signal.signal(signal.SIGTERM, _term)
        if hasattr(signal, "SIGUSR1"):
            signal.signal(signal.SIGUSR1, _usr1)
        origin[0] = time.monotonic()
        server.start()
        _announce(args, where, mode, responder)
        _serve(board, server, notices, reset_requested)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
        for line in notices.lines(board, time.monotonic(), force=True):
            progress(line)
        if responder is not None:
            responder.close()
        summary = _stopped(args, board, server)
        if sink is not None:
            with board.lock:
                board.catch_up(record_lag=False)
                board.timed.detach(sink)
                sink.close()
            progress(f"trace written to {args.trace}")
        progress(summary)
    sys.stdout.flush()
    return 0
