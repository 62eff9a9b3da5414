"""Safety sessions at the seams between programs, firmware versions, links and calibration files, on the timed
emulator (simulated clock), judged on the pulses the emulated board delivered.

    python tools/safety_campaign.py --seams --sessions 3000 [--jobs J] [--seed S] [--only I] [--json]

The plain campaign drives one program on one board over USB or a UART.  The places where a board passes
from one program to another, or is driven in a version or a wiring it does not have, are where the package
had its safety bugs; each session here picks one of them at random (``seed * 1_000_003 + index``, as the
campaign: a run is deterministic for a seed and ``--only I`` replays one session):

``wifi``
    The campaign's own random session of public ``Device`` calls (and its verdict) on the Wi-Fi board: the
    timed model behind a TCP link (:class:`SimWifiBoard`, the TCP receive window, replies over TCP).
``busy``
    Two programs on one Wi-Fi board.  The second opens while the first holds the board: it must be refused
    (the board answers one client at a time; its bytes wait in the backlog and are read after the first
    leaves).  No pulse above the first program's limit, none after the first program's close.
``cut``
    A program leaves the Wi-Fi board (its connection closes) in the middle of a frame, at a random byte;
    the next program opens it after a random delay (shorter and longer than v2's 2 s command timeout).
    Until the new program's identification returns, nothing above the first program's limit; from then
    on, nothing above the new program's own; nothing after its close.  On v2 a command cut in the middle
    is discarded by the firmware's timeout (the identification waits it out), and the new program's bytes
    never complete it (``inherited_command`` is a defect).
``mismatch``
    A program of the board's firmware runs a session and leaves (closes, or is killed); then a program
    forced to the other version (``firmware=`` explicit) opens the board over USB, a UART or TCP: it must
    be refused (``FirmwareMismatchError``), and no pulse starts after the refusal.
``kill``
    The owner is killed at a random byte of its stream (its write stops there, nothing more is written;
    on TCP the kernel closes the connection, on a serial port the board notices nothing).  A new program
    opens the board after a random delay and drives it; the windows of ``cut`` apply.
``calibration``
    A calibration profile with a random cap per electrode and a random wiring (``mapping``, a permutation of
    the 32 channels), driven through its own guard and wiring: every pulse on a hardware channel stays
    within the calibrated current of the electrode wired to it (read from the profile's document, not from
    the guard).

Every session also counts the bytes the board lost (none may be) and the firmware hazards it recorded:
every kind not in the campaign's ``designed()`` list is a defect, except, in ``cut`` and ``kill`` sessions,
the hazards of commands that began in the killed or cut program's own bytes (see :data:`NEVER_LEFTOVER`);
``inherited_command`` is always a defect.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import random
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import campaign_engine as engine  # noqa: E402
import safety_campaign as sc  # noqa: E402

from tactdeform_hw.clock import SimulatedClock  # noqa: E402
from tactdeform_hw.device import EtactileKitDevice, StimConfig  # noqa: E402
from tactdeform_hw.device.driver.firmware_probe import FirmwareMismatchError  # noqa: E402
from tactdeform_hw.device.participant.mapping import ChannelMapping  # noqa: E402
from tactdeform_hw.emulator.faults import TimedPort  # noqa: E402
from tactdeform_hw.emulator.serving.realtime import WIFI_TCP, TcpLink  # noqa: E402
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator  # noqa: E402
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2  # noqa: E402
from tactdeform_hw.errors import BoardBusyError, TactDeformError  # noqa: E402
from tactdeform_hw.formats.calibration_profile import calibration_from_dict, calibration_guard  # noqa: E402
from tactdeform_hw.ports import PortBase  # noqa: E402
from tactdeform_hw.protocol.state import BoardState  # noqa: E402
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER  # noqa: E402
from tactdeform_hw.render.array import ElectrodeArray  # noqa: E402

SCENARIOS = ("wifi", "busy", "cut", "mismatch", "kill", "calibration")
LINKS = ("usb", "uart", "tcp")
#: What the killed or cut program's own bytes leave behind is not the new program's doing: a hazard whose
#: command began in those bytes (a command the v2 timeout discards, a cut v1.2 pattern completed by the
#: identification's bytes, a pattern torn by the cut) is counted apart, as are the bytes v2's timeout
#: discards with the cut command.  Never counted apart: a command the new program's bytes complete.
NEVER_LEFTOVER = frozenset({"inherited_command"})
#: Simulated time after a program's close within which the board must be off (its ``close`` proves it
#: off before it returns; the campaign's settle time covers a scan in progress).
OFF_AFTER_CLOSE_S = sc.SETTLE_S


# --- the Wi-Fi board in simulated time ------------------------------------------------------------------


class SimWifiBoard:
    """The Wi-Fi board (:data:`~tactdeform_hw.emulator.serving.realtime.WIFI_TCP`) in simulated time: one
    timed
    model with a TCP link both ways and the TCP window as its receive path, serving one connection at a
    time as :class:`~tactdeform_hw.emulator.serving.tcp_server.TcpServer` does.  A later connection waits in
    the
    backlog: its bytes are read, in order, once every earlier connection has gone (even if it closed
    meanwhile), and it is answered only from then on; the model hears of each new client
    (``TimedEmulatorV2.new_client``), so a command an earlier client cut can take its bytes."""

    def __init__(self, firmware: str, switching_boards: int = 1) -> None:
        self.firmware = firmware
        timing = WIFI_TCP.timing(None)
        self.emulator: TimedEmulator | TimedEmulatorV2
        if firmware == "v2":
            self.emulator = TimedEmulatorV2(
                "compact", switching_boards, link=TcpLink(), tx_link=TcpLink(), model=timing
            )
        else:
            self.emulator = TimedEmulator(
                "compact", switching_boards, link=TcpLink(), tx_link=TcpLink(), model=timing
            )
        self.clock = SimulatedClock(0.0, on_advance=self._advanced)
        self.serving: WifiClient | None = None
        self.backlog: list[WifiClient] = []
        self.accepted: list[tuple[float, str]] = []  # (time, client) each connection was served from

    @property
    def now_s(self) -> float:
        return self.clock.now()

    def _advanced(self, t_s: float) -> None:
        self.emulator.advance_to(max(self.emulator.now_us, t_s * 1e6))

    def room(self) -> int:
        """Bytes the receive path takes now (TCP's flow control holds the sender back otherwise)."""
        return max(0, self.emulator.queue.free - self.emulator.in_flight)

    def connect(self, name: str) -> WifiClient:
        client = WifiClient(self, name)
        client.open()
        return client

    def join(self, client: WifiClient) -> None:
        if self.serving is None and not self.backlog:
            self._accept(client)
        else:
            self.backlog.append(client)

    def leave(self, client: WifiClient) -> None:
        if client is self.serving:
            self.serving = None
            while self.serving is None and self.backlog:
                nxt = self.backlog.pop(0)
                self._accept(nxt)
                if not nxt.connected:  # it closed while waiting: its bytes were read, and it is gone
                    self.serving = None

    def _accept(self, client: WifiClient) -> None:
        emu = self.emulator
        emu.read_tx()  # replies written before this client came are no one's now
        if isinstance(emu, TimedEmulatorV2):
            emu.new_client(client.name)
        self.serving = client
        self.accepted.append((self.now_s, client.name))
        pending, client.pending = client.pending, bytearray()
        if pending:
            client.deliver(bytes(pending))


class WifiClient(PortBase):
    """One program's TCP connection to a :class:`SimWifiBoard`: a pyserial-like port in the board's
    simulated time.  It declares what a TCP port declares: one client at a time, no reset line."""

    serves_one_client = True
    reset_line = False

    def __init__(self, board: SimWifiBoard, name: str, *, timeout: float = 0.02) -> None:
        self.board = board
        self.name = name
        self.port = f"socket://wifi-board ({name})"
        self.timeout = timeout
        self.write_timeout: float | None = None
        self.pacing_clock = board.clock
        self.robust_encoding = False
        self.read_step_s = 0.0002
        self.is_open = False
        self.connected = False
        self.pending = bytearray()  # written while waiting in the backlog (the kernel's buffers)
        self.dtr = False
        self.rts = False

    # --- what the session reads --------------------------------------------------------------------------

    @property
    def emulator(self) -> TimedEmulator | TimedEmulatorV2:
        return self.board.emulator

    @property
    def now_s(self) -> float:
        return self.board.now_s

    def advance(self, seconds: float) -> None:
        self.board.clock.advance(seconds)

    @property
    def board_untouched(self) -> bool:
        return self.board.emulator.received_bytes == 0 and self.board.serving is self

    def board_state(self) -> BoardState:
        return self.board.emulator.state()

    @property
    def board_hazards(self) -> list[Any]:
        return self.board.emulator.hazards

    # --- pyserial face -----------------------------------------------------------------------------------

    def open(self) -> None:
        if self.is_open:
            raise TactDeformError(f"{self.port}: already open")
        self.is_open = self.connected = True
        self.board.join(self)

    def close(self) -> None:
        if not self.is_open:
            return
        self.is_open = self.connected = False
        self.board.leave(self)

    def _check(self) -> None:
        self._check_open()

    def deliver(self, data: bytes) -> None:
        """Bytes into the board's receive path, as fast as TCP's window lets them in."""
        board = self.board
        i = 0
        while i < len(data):
            take = min(len(data) - i, board.room())
            if take == 0:
                board.clock.advance(0.0005)  # the sender blocks until the window opens
                continue
            board.emulator.write(data[i : i + take])
            i += take

    def write(self, data: bytes) -> int:
        self._check()
        data = bytes(data)
        if self.board.serving is self:
            self.deliver(data)
        else:
            self.pending += data
        return len(data)

    def read(self, size: int = 1) -> bytes:
        self._check()
        emu = self.board.emulator
        serving = self.board.serving is self
        out = bytearray(emu.read_tx(size) if serving else b"")
        deadline = self.now_s + (self.timeout or 0.0)
        while len(out) < size and self.now_s < deadline:
            self.board.clock.advance(min(self.read_step_s, deadline - self.now_s))
            if self.board.serving is self:
                out += emu.read_tx(size - len(out))
        return bytes(out)

    @property
    def in_waiting(self) -> int:
        self._check()
        return int(self.board.emulator.in_waiting) if self.board.serving is self else 0

    def reset_input_buffer(self) -> None:
        self._check()
        if self.board.serving is self:
            self.board.emulator.read_tx()


# --- a program that is killed ---------------------------------------------------------------------------


class ProgramKilled(BaseException):
    """The program's process died (SIGKILL): no handler of the driver's runs, nothing more is written."""


class KillablePort:
    """A port in front of another whose program dies once it has written ``kill_at`` bytes: the write in
    progress stops there, and the dead program writes and reads nothing more.  Its process' descriptors
    are closed by the kernel (:meth:`bury`) — on TCP the board sees the connection close."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.kill_at: int | None = None
        self.written = 0
        self.dead = False
        self.killed_at_s: float | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def arm(self, after_bytes: int) -> None:
        self.kill_at = self.written + max(0, after_bytes)

    def write(self, data: bytes) -> int:
        if self.dead:
            raise ProgramKilled()
        data = bytes(data)
        if self.kill_at is not None and self.written + len(data) >= self.kill_at:
            keep = self.kill_at - self.written
            if keep:
                self.inner.write(data[:keep])
            self.written += keep
            self.dead = True
            self.killed_at_s = float(self.inner.now_s)
            raise ProgramKilled()
        self.written += len(data)
        return int(self.inner.write(data))

    def die(self) -> None:
        self.dead = True
        self.killed_at_s = float(self.inner.now_s)
        raise ProgramKilled()

    def read(self, size: int = 1) -> bytes:
        if self.dead:
            raise ProgramKilled()
        return bytes(self.inner.read(size))

    def close(self) -> None:
        if not self.dead:
            self.inner.close()

    def bury(self) -> None:
        """The kernel closes the dead process' descriptors."""
        self.inner.close()


# --- results --------------------------------------------------------------------------------------------


@dataclass
class SeamResult:
    index: int
    seed: int
    scenario: str
    firmware: str
    link: str
    campaign_seed: int = 0
    pulses: int = 0
    over_limit: int = 0
    late: int = 0  # pulses after a close or a refusal (beyond the bound)
    lost_bytes: int = 0
    cut_discarded_bytes: int = 0  # the cut command's bytes v2's timeout discarded (cut, kill)
    hazard_counts: dict[str, int] = field(default_factory=dict)
    leftovers: dict[str, int] = field(default_factory=dict)  # hazards of the cut program's bytes
    broken: list[str] = field(default_factory=list)  # promises broken other than by a pulse
    notes: list[str] = field(default_factory=list)
    first_violation: dict[str, Any] | None = None
    sim_s: float = 0.0
    wall_s: float = 0.0

    @property
    def defect_counts(self) -> dict[str, int]:
        ok = sc.designed(self.firmware)
        return {k: n for k, n in self.hazard_counts.items() if k not in ok}

    @property
    def ok(self) -> bool:
        return not (self.over_limit or self.late or self.lost_bytes or self.defect_counts or self.broken)

    def failure(self) -> str:
        if self.ok:
            return ""
        why: list[str] = []
        if self.over_limit:
            why.append(f"{self.over_limit} pulses above the limit")
        if self.late:
            why.append(f"{self.late} pulses after a close or a refusal")
        if self.lost_bytes:
            why.append(f"{self.lost_bytes} bytes lost")
        if self.defect_counts:
            why.append("defects " + ", ".join(f"{k} x{n}" for k, n in self.defect_counts.items()))
        why += self.broken
        return f"{self.scenario} {self.firmware} {self.link}: " + "; ".join(why)

    def reproduce(self) -> str:
        return f"python tools/safety_campaign.py --seams --seed {self.campaign_seed} --only {self.index}"


# --- programs -------------------------------------------------------------------------------------------


@dataclass
class Program:
    """One program's session: what it may deliver (the largest current it asked for, on the channels it
    configured) and when it started, was ready and left."""

    name: str
    electrodes: int
    allowed_ua: float = 0.0
    opened_s: float = 0.0
    ready_s: float | None = None  # its identification returned (the board proved off)
    closed_s: float | None = None  # its close returned
    limits: np.ndarray | None = None  # per hardware channel (None: ``allowed_ua`` on its channels)

    def channel_limits(self) -> np.ndarray:
        if self.limits is not None:
            return np.asarray(np.minimum(self.limits, self.allowed_ua), dtype=float)
        out = np.zeros(256)
        out[: self.electrodes] = self.allowed_ua
        return out


def _config(rng: random.Random, n: int | None = None) -> StimConfig:
    n = n if n is not None else rng.choice((1, 4, 8, 16, 32))
    return StimConfig(
        electrode_count=n,
        current_ua=rng.choice((200, 500, 800, 1000, 1500, 2000)),
        pulse_width_us=rng.choice((50, 100, 200)),
        discharge_us=rng.choice((0, 45)),
        rate_hz=rng.choice((60, 100, 125)),
    )


def _open(
    port: Any, firmware: str, prog: Program, **kw: Any
) -> EtactileKitDevice:  # the board is asked which firmware it runs first
    prog.opened_s = float(port.now_s)
    dev = EtactileKitDevice(port, firmware=firmware, **kw)
    prog.ready_s = float(port.now_s)
    return dev


def _drive(
    dev: EtactileKitDevice,
    port: Any,
    rng: random.Random,
    cfg: StimConfig,
    prog: Program,
    calls: int,
    biphasic: bool,
    errors: list[str],
) -> None:
    """``configure`` then ``calls`` random public calls, as an application makes them."""

    def call(name: str, fn: Callable[[], Any]) -> None:
        try:
            fn()
        except TactDeformError as exc:
            errors.append(f"{prog.name} {name}: {type(exc).__name__}: {exc}"[:160])

    prog.allowed_ua = max(prog.allowed_ua, cfg.current_ua)
    call("configure", lambda: dev.configure(cfg))
    n = cfg.electrode_count
    for _ in range(calls):
        r = rng.random()
        if r < 0.45:
            pat = sc.random_pattern(rng, n, biphasic, mixed=False)
            call("send_pattern", lambda frame=pat: dev.send_pattern(frame))  # type: ignore[misc]
        elif r < 0.55:
            ua = rng.choice((0, 300, 700, 1200, 1800))
            prog.allowed_ua = max(prog.allowed_ua, ua)
            call("set_current", lambda amps=ua: dev.set_current(amps))  # type: ignore[misc]
        elif r < 0.62:
            call("keepalive", dev.keepalive)
        elif r < 0.67:
            call("all_off", dev.all_off)
        elif r < 0.72:
            call("probe", dev.probe)
        else:
            port.advance(rng.choice((0.001, 0.005, 0.02, 0.05)))


def _close(dev: EtactileKitDevice, port: Any, prog: Program, errors: list[str]) -> None:
    try:
        dev.close()
    except TactDeformError as exc:
        errors.append(f"{prog.name} close: {type(exc).__name__}: {exc}"[:160])
    prog.closed_s = float(port.now_s)


# --- one session ----------------------------------------------------------------------------------------


class SeamSession:
    def __init__(self, index: int, seed: int, campaign_seed: int) -> None:
        self.rng = random.Random(seed)
        rng = self.rng
        self.scenario = rng.choice(SCENARIOS)
        self.firmware = rng.choice(sc.FIRMWARES)
        if self.scenario in ("busy", "cut", "wifi"):
            self.link = "tcp"
        else:
            self.link = rng.choice(LINKS)
        self.res = SeamResult(index, seed, self.scenario, self.firmware, self.link, campaign_seed)
        self.errors: list[str] = []
        self.windows: list[tuple[float, float, np.ndarray]] = []  # [t0, t1): per-channel limit
        self.off_from_s: float | None = None  # no pulse may start after this
        self.next_first_byte = -1  # host offset of the new program's first byte (cut, kill)
        self.next_ident_end = -1  # ... and just past its identification
        self.emulator: Any = None
        self._board_obj: Any = None
        self.clock_now: Callable[[], float] = lambda: 0.0

    # --- boards -------------------------------------------------------------------------------------

    def _board(self) -> tuple[Any, Callable[[str], Any]]:
        """The board for the session's firmware and link, and how a program opens a port to it."""
        fw = self.firmware
        if self.link == "tcp":
            wifi = SimWifiBoard(fw)
            self.emulator = wifi.emulator
            self.clock_now = wifi.clock.now
            self._board_obj = wifi
            return wifi, wifi.connect
        emu: TimedEmulator | TimedEmulatorV2
        if fw == "v2":
            emu = TimedEmulatorV2("compact", 1, link=self.link)
        else:
            emu = TimedEmulator("compact", 1, link=self.link)
        port = TimedPort(emu, link=self.link, seed=self.res.seed, robust_encoding=self.link == "uart")
        self.emulator = emu
        self.clock_now = port.pacing_clock.now
        self._board_obj = port

        def reopen(_: str) -> TimedPort:
            if port.is_open:
                port.close()
            port.open()
            return port

        return port, reopen

    # --- scenarios ----------------------------------------------------------------------------------

    def run(self) -> None:
        getattr(self, f"_run_{self.scenario}")()

    def _run_busy(self) -> None:
        rng, fw = self.rng, self.firmware
        board, connect = self._board()
        a = Program("first", 0)
        cfg = _config(rng)
        a.electrodes = cfg.electrode_count
        pa = connect("first")
        dev_a = _open(pa, fw, a)
        _drive(dev_a, pa, rng, cfg, a, rng.randint(2, 8), rng.random() < 0.5, self.errors)
        b = Program("second", 0)
        pb = connect("second")
        refused = False
        try:
            dev_b = _open(pb, fw, b)
        except BoardBusyError:
            refused = True
        except TactDeformError as exc:
            refused = True
            self.res.notes.append(f"second refused as {type(exc).__name__}")
        if not refused:
            self.res.broken.append("the second program was not refused on a busy board")
            # a program that believes it holds the board drives it, higher than the first
            bcfg = StimConfig(**{**asdict(_config(rng, a.electrodes)), "current_ua": 2500})
            _drive(dev_b, pb, rng, bcfg, b, 4, False, self.errors)
        _drive(dev_a, pa, rng, cfg, a, rng.randint(1, 5), False, self.errors)
        _close(dev_a, pa, a, self.errors)
        board.clock.advance(0.5)
        self.windows.append((0.0, float("inf"), a.channel_limits()))
        assert a.closed_s is not None
        self.off_from_s = a.closed_s + OFF_AFTER_CLOSE_S

    def _killed_owner(self, connect: Callable[[str], Any], in_frame: bool) -> Program:
        """The first program: a session killed at a random byte (of a frame, with ``in_frame``)."""
        rng, fw = self.rng, self.firmware
        a = Program("owner", 0)
        cfg = _config(rng)
        a.electrodes = cfg.electrode_count
        pa = KillablePort(connect("owner"))
        biphasic = rng.random() < 0.5
        try:
            if not in_frame and rng.random() < 0.2:
                pa.arm(rng.randint(0, 600))  # during the identification
            dev = _open(pa, fw, a)
            a.allowed_ua = cfg.current_ua
            if not in_frame:
                pa.arm(rng.randint(0, 400))  # configuration and the calls that follow
            calls = rng.randint(1, 6)
            _drive(dev, pa, rng, cfg, a, calls, biphasic, self.errors)
            frame_bytes = (2 if fw == "v2" else 1) * cfg.electrode_count + 2
            cut_frame = rng.randint(0, 5)
            for i in range(40):  # frames until the cut
                if in_frame and i == cut_frame:
                    pa.arm(rng.randint(1, frame_bytes))
                pat = sc.random_pattern(rng, cfg.electrode_count, biphasic, mixed=False)
                try:
                    dev.send_pattern(pat)
                except TactDeformError:
                    pass
                pa.inner.advance(rng.choice((0.0, 0.002, 0.02)))
            pa.die()  # not cut by then: killed between two writes
        except ProgramKilled:
            pass
        a.closed_s = pa.killed_at_s
        self.res.notes.append(f"owner killed after {pa.written} bytes at {pa.killed_at_s}")
        pa.bury()
        return a

    def _next_program(self, connect: Callable[[str], Any], a: Program, **kw: Any) -> None:
        """A new program opens the board after a random delay, drives it and closes it."""
        rng, fw = self.rng, self.firmware
        port_a_gone = self.clock_now()
        delay = rng.choice((0.0, 0.05, 0.5, 1.5, 2.5))
        self._advance(delay)
        b = Program("next", 0)
        cfg = _config(rng)
        b.electrodes = cfg.electrode_count
        emu = self.emulator
        self.next_first_byte = int(emu.received_bytes)
        pb = connect("next")
        mid_command = isinstance(emu, TimedEmulatorV2) and bool(emu.parser.processing)
        try:
            dev = _open(pb, fw, b, **kw)
        except TactDeformError as exc:
            self.res.broken.append(f"the next program could not open the board: {type(exc).__name__}")
            self.windows.append((0.0, float("inf"), a.channel_limits()))
            return
        assert b.ready_s is not None
        self.next_ident_end = self.next_first_byte + dev.identification.bytes_sent
        _drive(dev, pb, rng, cfg, b, rng.randint(2, 10), rng.random() < 0.5, self.errors)
        _close(dev, pb, b, self.errors)
        self._advance(0.2)
        self.windows.append((0.0, b.ready_s, np.maximum(a.channel_limits(), 0.0)))
        self.windows.append((b.ready_s, float("inf"), b.channel_limits()))
        assert b.closed_s is not None
        self.off_from_s = b.closed_s + OFF_AFTER_CLOSE_S
        if mid_command and delay < 2.0 and "command_timeout" not in self._hazards():
            self.res.broken.append("v2 never discarded the command cut in the middle by its timeout")
        self.res.notes.append(f"owner gone at {port_a_gone:.3f} s, next after {delay} s")

    def _advance(self, seconds: float) -> None:
        """Time passes with no program writing."""
        board = self._board_obj
        if isinstance(board, SimWifiBoard):
            board.clock.advance(seconds)
        else:
            board.advance(seconds)

    def _run_cut(self) -> None:
        board, connect = self._board()
        a = self._killed_owner(connect, in_frame=True)
        self._next_program(connect, a)

    def _run_kill(self) -> None:
        board, connect = self._board()
        a = self._killed_owner(connect, in_frame=False)
        self._next_program(connect, a)

    def _run_mismatch(self) -> None:
        rng, fw = self.rng, self.firmware
        board, connect = self._board()
        a = Program("owner", 0)
        cfg = _config(rng)
        a.electrodes = cfg.electrode_count
        pa = KillablePort(connect("owner"))
        dev = _open(pa, fw, a)
        _drive(dev, pa, rng, cfg, a, rng.randint(2, 8), rng.random() < 0.5, self.errors)
        if rng.random() < 0.5:
            _close(dev, pa, a, self.errors)
        else:  # killed between two calls: its last frame runs on
            pa.bury()
            self.res.notes.append("owner killed")
        self._advance(rng.choice((0.0, 0.1, 2.5)))
        other = "v1.2" if fw == "v2" else "v2"
        b = Program("mismatched", 0)
        pb = connect("mismatched")
        refused_at: float | None = None
        try:
            dev_b = _open(pb, other, b)
        except FirmwareMismatchError:
            refused_at = self.clock_now()
        if refused_at is None:
            self.res.broken.append(f"a {other} driver was not refused by a {fw} board")
            bcfg = _config(rng)
            _drive(dev_b, pb, rng, bcfg, b, 4, False, self.errors)
            refused_at = b.ready_s
        self._advance(0.2)
        self.windows.append((0.0, float("inf"), a.channel_limits()))
        assert refused_at is not None
        self.off_from_s = refused_at

    def _run_calibration(self) -> None:
        rng, fw = self.rng, self.firmware
        board, connect = self._board()
        n = 32
        perm = tuple(rng.sample(range(n), n))
        caps_ua = [rng.choice(range(200, 3001, 50)) for _ in range(n)]
        doc = {
            "format": "etactilekit_calibration_profile",
            "version": "1.0",
            "created_at": "2026-11-27T10:00:00",
            "layout": {"name": "Finger pad", "slug": "finger-pad", "electrode_count": n},
            "electrodes": [
                {
                    "id": i,
                    "label": f"E{i}",
                    "mapping": perm[i],
                    "intensity": DEFAULT_TRANSFER.to_code(ua, "cap"),
                }
                for i, ua in enumerate(caps_ua)
            ],
        }
        prof = calibration_from_dict(doc, "random.json")
        wired = ChannelMapping(prof.mapping(), prof.electrode_count)
        guard = calibration_guard(prof, [int(r) for r in ElectrodeArray.tactdeform().regions], mapping=wired)
        # the truth, from the document: the electrode wired to each channel, and its calibrated current
        truth = np.zeros(256)
        for i, ua in enumerate(prof.currents_ua()):
            truth[perm[i]] = ua
        a = Program("calibrated", n, limits=truth)
        port = connect("calibrated")
        dev = _open(port, fw, a, guard=guard, mapping=wired)
        cfg = StimConfig(
            electrode_count=n,
            current_ua=rng.choice((500, 1000, 2000, 3000)),
            pulse_width_us=rng.choice((50, 100, 200)),
            rate_hz=rng.choice((60, 100)),
        )
        _drive(dev, port, rng, cfg, a, rng.randint(4, 14), rng.random() < 0.5, self.errors)
        a.allowed_ua = float("inf")  # the calibrated caps are the promise judged here
        _close(dev, port, a, self.errors)
        self._advance(0.1)
        self.windows.append((0.0, float("inf"), truth))
        assert a.closed_s is not None
        self.off_from_s = a.closed_s + OFF_AFTER_CLOSE_S

    # --- the verdict --------------------------------------------------------------------------------

    def _hazards(self) -> dict[str, int]:
        counts: dict[str, int] = {}
        for h in self.emulator.hazards:
            name = sc.hazard_name(h)
            counts[name] = counts.get(name, 0) + 1
        return counts

    def judge(self) -> SeamResult:
        res, emu = self.res, self.emulator
        res.sim_s = self.clock_now()
        table = emu.reports.pulse_table()
        code = table["code"]
        cur = np.maximum(table["current_ua"], code * DEFAULT_TRANSFER.step_ua) if code.size else np.zeros(0)
        live = np.nonzero(cur > 0)[0]
        res.pulses = int(live.size)
        t_s = table["start_us"] / 1e6 if code.size else np.zeros(0)
        ch = table["channel"].astype(int) if code.size else np.zeros(0, dtype=int)
        for k in live:
            t, c, ua = float(t_s[k]), int(ch[k]), float(cur[k])
            limit = 0.0
            for t0, t1, lim in self.windows:
                if t0 <= t < t1:
                    limit = float(lim[c])
            why = ""
            if self.off_from_s is not None and t > self.off_from_s:
                res.late += 1
                why = "after close or refusal"
            elif ua > limit + 1e-6:
                res.over_limit += 1
                why = f"above {limit:g} uA"
            if why and res.first_violation is None:
                res.first_violation = {"t_s": t, "channel": c, "current_ua": ua, "why": why}
        first = self.next_first_byte
        for lo in emu.losses:
            if 0 <= lo.host_offset < first and lo.reason == "command_timeout":
                res.cut_discarded_bytes += lo.count
            else:
                res.lost_bytes += lo.count
        counts: dict[str, int] = {}
        leftovers: dict[str, int] = {}
        for h in emu.hazards:
            name = sc.hazard_name(h)
            origin = int(h.detail.get("command_offset", h.detail.get("command_host_offset", h.offset)))
            if 0 <= origin < first and name not in NEVER_LEFTOVER:
                leftovers[name] = leftovers.get(name, 0) + 1
            else:
                counts[name] = counts.get(name, 0) + 1
        # the emulator follows the host's stream as one: across a cut it expects the cut command's payload
        # where the new program's identification begins (bytes meant to read safely either way)
        out_of_step = sum(
            1
            for c in getattr(emu, "commands", [])
            if not c.in_sync and not 0 <= c.host_offset < self.next_ident_end
        )
        if out_of_step:
            counts["commands_out_of_step"] = out_of_step
        res.hazard_counts = dict(sorted(counts.items()))
        res.leftovers = dict(sorted(leftovers.items()))
        return res


def _wifi_session(index: int, seed: int, campaign_seed: int, firmware: str) -> SeamResult:
    """The campaign's own session (its calls, its verdict) on the Wi-Fi board."""
    s = WifiCampaignSession(index, seed, firmware)
    try:
        s.run()
    except Exception as exc:  # noqa: BLE001 - a crash of the driver is a finding
        s.res.errors.append(f"CRASH {type(exc).__name__}: {exc}"[:200])
    r = s.judge()
    out = SeamResult(index, seed, "wifi", firmware, "tcp", campaign_seed)
    out.pulses, out.over_limit, out.late, out.lost_bytes = r.pulses, r.over_limit, r.meant_off, r.lost_bytes
    out.hazard_counts = dict(r.hazard_counts)
    if any(e.startswith("CRASH") for e in r.errors):
        out.hazard_counts["driver_crash"] = 1
    out.first_violation = r.first_violation
    out.sim_s = r.sim_s
    return out


class WifiCampaignSession(sc.Session):
    """The campaign's session with its port on a :class:`SimWifiBoard`."""

    def __init__(self, index: int, seed: int, firmware: str) -> None:
        super().__init__(index, seed, False, firmware)
        self.link = self.res.link = "tcp"
        boards = (self.cfg.electrode_count + 31) // 32
        self.board = SimWifiBoard(firmware, boards)
        client = self.board.connect("program")
        client.robust_encoding = self.robust
        self.port = client  # type: ignore[assignment]
        self.dev = self._new_device()
        self.devices = [self.dev]

    def _call(self, name: str, fn: Callable[[], Any], intent: tuple[int, ...] | None = None) -> bool:
        """As the campaign's, but TCP has no reset line: ``hardware_reset`` returns False and the board runs
        the frame it had, which is still what the host means."""
        if name == "hardware_reset" and not getattr(self.port, "reset_line", True):
            intent = None
        return bool(super()._call(name, fn, intent))


def run_session(index: int, seed: int = 0) -> SeamResult:
    """Run one seam session and judge it."""
    wall = time.perf_counter()
    sub = seed * 1_000_003 + index
    s = SeamSession(index, sub, seed)
    if s.scenario == "wifi":
        res = _wifi_session(index, sub, seed, s.firmware)
    else:
        try:
            s.run()
        except Exception as exc:  # noqa: BLE001 - a crash of the driver is a finding, reported with the session
            s.res.broken.append(f"CRASH {type(exc).__name__}: {exc}"[:200])
        res = s.judge()
    res.wall_s = time.perf_counter() - wall
    return res


def _worker(args: tuple[int, int]) -> SeamResult:
    return run_session(*args)


def run_seams(sessions: int, *, seed: int = 0, jobs: int = 1, first: int = 0) -> list[SeamResult]:
    """Sessions ``first .. first + sessions - 1``; the same list for the same arguments, whatever ``jobs``."""
    tasks = [(first + i, seed) for i in range(sessions)]
    if jobs <= 1:
        return [_worker(t) for t in tasks]
    with mp.get_context("fork" if sys.platform != "win32" else "spawn").Pool(jobs) as pool:
        return list(pool.imap(_worker, tasks, chunksize=max(1, min(32, sessions // (jobs * 8) or 1))))


def results_chunk(seed: int, first: int, count: int) -> engine.Results:
    """Sessions ``first .. first + count - 1`` (a chunk of a distributed run)."""
    logging.disable(logging.WARNING)
    return engine.Results([run_session(i, seed) for i in range(first, first + count)])


def summarize(results: Sequence[SeamResult]) -> dict[str, Any]:
    """Per scenario × firmware × link: sessions, pulses, over-limit, late, bytes lost, defects by kind."""
    rows: dict[str, dict[str, Any]] = {}
    for r in results:
        key = f"{r.scenario} {r.firmware} {r.link}"
        row = rows.setdefault(
            key,
            {
                "sessions": 0,
                "pulses": 0,
                "over_limit": 0,
                "late": 0,
                "bytes_lost": 0,
                "defects": {},
                "cut_leftovers": {},
                "cut_discarded_bytes": 0,
                "failed": 0,
            },
        )
        row["sessions"] += 1
        row["pulses"] += r.pulses
        row["over_limit"] += r.over_limit
        row["late"] += r.late
        row["bytes_lost"] += r.lost_bytes
        row["cut_discarded_bytes"] += r.cut_discarded_bytes
        row["failed"] += 0 if r.ok else 1
        for k, n in r.defect_counts.items():
            row["defects"][k] = row["defects"].get(k, 0) + n
        for k, n in r.leftovers.items():
            row["cut_leftovers"][k] = row["cut_leftovers"].get(k, 0) + n
    failed = [r for r in results if not r.ok]
    return {
        "sessions": len(results),
        "failed_sessions": len(failed),
        "rows": dict(sorted(rows.items())),
        "failures": [
            {"index": r.index, "seed": r.campaign_seed, "why": r.failure(), "reproduce": r.reproduce()}
            for r in failed[:20]
        ],
        "session_s": round(sum(r.wall_s for r in results), 3),
        "simulated_s": round(sum(r.sim_s for r in results), 3),
    }


def table(summary: dict[str, Any]) -> str:
    head = (
        f"{'scenario firmware link':<24} {'sessions':>8} {'pulses':>9} {'over':>5} {'late':>5} {'lost':>5}"
        "  defects"
    )
    lines = [head]
    for key, row in summary["rows"].items():
        defects = ", ".join(f"{k} {v}" for k, v in row["defects"].items()) or "none"
        lines.append(
            f"{key:<24} {row['sessions']:>8} {row['pulses']:>9} {row['over_limit']:>5} {row['late']:>5} "
            f"{row['bytes_lost']:>5}  {defects}"
        )
    lines.append(
        f"sessions {summary['sessions']}, failed {summary['failed_sessions']}, "
        f"wall {summary.get('wall_s', 0)} s, simulated {summary['simulated_s']} s"
    )
    return "\n".join(lines)


def main(a: Any) -> int:
    """``safety_campaign.py --seams``: the parsed arguments of the campaign's command line."""
    if a.only is not None:
        r = run_session(a.only, a.seed)
        print(json.dumps({**asdict(r), "ok": r.ok, "defect_counts": r.defect_counts}, indent=1, default=str))
        if not r.ok:
            print(f"FAILED session {r.index}: {r.failure()} -- reproduce: {r.reproduce()}", file=sys.stderr)
        return 0 if r.ok else 1
    t0 = time.perf_counter()
    job = engine.Job(
        "seam_sessions",
        "results_chunk",
        (a.seed,),
        a.sessions,
        first=a.first,
        chunk=a.chunk,
        fingerprint=engine.fingerprint(),
    )
    results = engine.run(job, jobs=a.jobs, cluster=a.cluster, progress=True).ordered()
    summary = summarize(results)
    where = {"jobs": a.jobs} if a.cluster is None else {"cluster": a.cluster}
    summary.update({"seed": a.seed, **where, "wall_s": round(time.perf_counter() - t0, 3)})
    print(json.dumps(summary, indent=1) if a.json else table(summary))
    for f in summary["failures"]:
        print(f"FAILED session {f['index']}: {f['why']} -- reproduce: {f['reproduce']}", file=sys.stderr)
    if summary["failed_sessions"] > len(summary["failures"]):
        print(f"... and {summary['failed_sessions'] - len(summary['failures'])} more", file=sys.stderr)
    return 0 if summary["failed_sessions"] == 0 else 1
