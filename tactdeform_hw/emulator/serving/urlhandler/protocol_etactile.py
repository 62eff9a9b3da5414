"""``etactile://[NAME][?board=compact|large&switching_boards=N&stack_reading=R&timed=1|0&link=usb|uart&firmware=v1.2|v2&firmware_src=DIR&spy=1]``

The emulated eTactileKit as a pyserial port, so ``serial.serial_for_url("etactile://")`` gives the same
object type, exceptions and calls as a real board on ``/dev/ttyACM0``.

``firmware_src=DIR`` serves a firmware's own C++ tree built on this machine
(:class:`~tactdeform_hw.emulator.hostbuild.timed.HostBuildTimedModel`, docs/firmware-host-build.md) in
place of the Python model; the version it speaks is its state map's, so ``firmware=`` is not read.

By default (``timed=1``) the board is the timed model locked to the wall clock
(:class:`~tactdeform_hw.emulator.serving.realtime.RealtimeEmulator`): a write enters the USB link
(``link=uart``:
a 921600-baud UART) and the receive queue at the moment it is made, the parser reads on the firmware's
rhythm (``firmware=v1.2``, the default: 256-byte queue, one command with a payload per RTOS tick;
``firmware=v2``: 1024-byte queue, whole payloads, a cut command discarded 2 s after its command byte),
replies become readable when the model delivers them, scans run (0xFF answers with the skin model's
readings: ``raw >> 2`` on v1.2, the whole reading on v2).  The port is lazy: each call first brings
the model up to the wall clock.  It declares ``pacing_clock`` (wall time) so a driver paces its writes as for
a board, and the other capabilities of :mod:`tactdeform_hw.ports`: ``instant``, ``pulse_reset()`` (the reset
line pulsed), ``board_state()`` and ``board_hazards``.
``timed=0`` serves the untimed emulator: every write is parsed at once and replies are readable when
``write`` returns (``pacing_clock`` then never waits).

DTR and RTS act as on the ESP32-S3's USB Serial/JTAG controller
(:class:`~tactdeform_hw.emulator.serving.realtime.UsbSerialJtagLines`): RTS asserted without DTR holds the
chip
in reset (a power-on reset, recorded in ``board.resets`` with the state it discarded; bytes written
meanwhile are dropped); esptool's hard reset therefore restarts the firmware, and its download sequence
leaves it in the ROM bootloader, which is not emulated (nothing is answered until the next reset).

With a ``NAME``, every port opened with that name in this process talks to one shared board (like a named
virtual bus), so a test can open a second handle to inspect or disturb the same device; the first opener's
options make the board.  ``spy=1`` hex-dumps every byte both ways, and every reset, with timestamps to
stderr.  Unknown options are rejected.
"""

from __future__ import annotations

import sys
import threading
import time
import urllib.parse as urlparse
from collections.abc import Callable
from typing import Any

from serial.serialutil import PortNotOpenError, SerialBase, SerialException, Timeout

from tactdeform_hw.clock import InstantClock, MonotonicClock
from tactdeform_hw.emulator.core import Emulator
from tactdeform_hw.emulator.firmware.models import model_entry
from tactdeform_hw.emulator.serving.realtime import (
    BUILD_RULES,
    ByteHook,
    RealtimeEmulator,
    UsbSerialJtagLines,
    reset_untimed,
)
from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.ports import PortBase
from tactdeform_hw.protocol.state import BoardState

_OPTIONS = ("board", "switching_boards", "stack_reading", "spy", "timed", "link", "firmware", "firmware_src")
_shared: dict[str, Emulator | RealtimeEmulator] = {}
_shared_lock = threading.Lock()
_watchers: dict[str, list[ByteHook]] = {}
_FALSE = ("0", "", "false", "no", "off")


def shared_emulator(name: str) -> Emulator | RealtimeEmulator | None:
    """The board behind ``etactile://NAME`` if one was opened in this process (an untimed
    :class:`Emulator` or a :class:`RealtimeEmulator`; both have ``state()`` and ``hazards``), else None."""
    return _shared.get(name)


def forget_shared(name: str | None = None) -> None:
    """Drop one (or every) named board, e.g. between tests, with its watchers."""
    with _shared_lock:
        if name is None:
            _shared.clear()
            _watchers.clear()
        else:
            _shared.pop(name, None)
            _watchers.pop(name, None)


def watch_shared(name: str, hook: ByteHook) -> Callable[[], None]:
    """Call ``hook(direction, data, t)`` — the ``hook`` of the pty, TCP and USB servers — with every byte
    that reaches the board behind ``etactile://NAME`` from any of its ports (``host->dev``: bytes held
    back by a reset line never reach it) and every byte read from it (``dev->host``), from now on;
    ``t`` is ``time.monotonic()``.  A test sees on the in-process URL the bytes a server shows it (which
    of them the package's own driver wrote, say).  Returns the function that stops the calls."""
    if not name:
        raise ConfigurationError("watch_shared: a board is shared by its NAME (etactile://NAME)")
    with _shared_lock:
        _watchers.setdefault(name, []).append(hook)

    def stop() -> None:
        with _shared_lock:
            hooks = _watchers.get(name, [])
            if hook in hooks:
                hooks.remove(hook)

    return stop


def _parse(url: str) -> tuple[str, dict[str, str]]:
    parts = urlparse.urlsplit(url)
    if parts.scheme != "etactile":
        raise SerialException(f"expected etactile://[NAME][?options], not {url!r}")
    opts: dict[str, str] = {}
    for option, values in urlparse.parse_qs(parts.query, keep_blank_values=True).items():
        if option not in _OPTIONS:
            raise SerialException(f"unknown option {option!r} in {url!r} (known: {', '.join(_OPTIONS)})")
        opts[option] = values[-1]
    timed = opts.get("timed", "1").lower()
    if timed not in ("0", "1", "true", "false", "yes", "no", "on", "off"):
        raise SerialException(
            f"option timed={opts['timed']!r} in {url!r}: use 1 (real time, the default) or 0 (instant)"
        )
    link = opts.get("link", "usb")
    if link not in ("usb", "uart"):
        raise SerialException(f"option link={link!r} in {url!r}: use usb (the default) or uart")
    return (parts.netloc + parts.path).strip("/"), opts


# pyserial ships no type information: SerialBase is Any
class Serial(SerialBase, PortBase):  # type: ignore[misc]
    """pyserial port backed by an in-process emulated board (see the module documentation)."""

    is_open: bool  # set by SerialBase.__init__; declared so the checker knows its type

    def _not_open_error(self) -> Exception:
        return PortNotOpenError()  # type: ignore[no-any-return]

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.emulator: Any = None  # Emulator | RealtimeEmulator once open (None while closed)
        self.lines = UsbSerialJtagLines()
        self.bytes_dropped = 0
        self._rx = bytearray()  # untimed replies not read yet
        self._lock = threading.Lock()
        self._spy = False
        self._shared_name = ""  # the NAME of etactile://NAME, whose watchers see this port's bytes
        self._instant_clock = InstantClock()
        super().__init__(*args, **kwargs)

    # --- what the port declares ------------------------------------------------------------------------

    @property
    def instant(self) -> bool:
        """Whether the board behind this port consumes every byte the moment it is written (``timed=0``)."""
        if self._port is None:
            return False
        try:
            return _parse(self._port)[1].get("timed", "1").lower() in _FALSE
        except SerialException:
            return False

    @property
    def loses_bytes(self) -> bool:
        """Whether the emulated link can lose a byte without telling: ``link=uart`` (a UART has no
        checksum), so a driver warns of the plain encoding as on a real UART."""
        if self._port is None:
            return False
        try:
            return _parse(self._port)[1].get("link", "usb") == "uart"
        except SerialException:
            return False

    @property
    def pacing_clock(self) -> Any:
        """The clock a driver must pace this port in: wall time for the real-time board, a clock that
        never waits for the instant one."""
        return self._instant_clock if self.instant else MonotonicClock()

    @property
    def board_untouched(self) -> bool:
        """No byte has reached the board since its power-on (a board named in the URL may be shared with
        another port, which the count sees too)."""
        return self.emulator is not None and self.emulator.received_bytes == 0

    @property
    def timed(self) -> bool:
        return isinstance(self.emulator, RealtimeEmulator)

    def pulse_reset(self) -> None:
        """Pulse the reset line as a driver does on a board (RTS asserted with DTR released, then
        released): the board is power-cycled and the firmware boots again."""
        self.dtr = False
        self.rts = True
        self.rts = False

    def board_state(self) -> BoardState:
        """The firmware's registers as the board holds them now."""
        self._check_open()
        state: BoardState = self.emulator.state()
        return state

    @property
    def board_hazards(self) -> list[Any]:
        """Every firmware defect the board behind this port has hit."""
        self._check_open()
        return self.emulator.hazards  # type: ignore[no-any-return]

    # --- open / close ---------------------------------------------------------------------------------

    def open(self) -> None:
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        self.emulator = self.from_url(self.port)
        self._rx.clear()
        self.is_open = True
        self._apply_lines()

    def close(self) -> None:
        self.is_open = False
        super().close()

    def from_url(self, url: str) -> Any:
        name, opts = _parse(url)
        self._shared_name = name
        try:
            board = opts.get("board", "compact")
            switching = int(opts.get("switching_boards", "1"))
            reading = float(opts["stack_reading"]) if "stack_reading" in opts else None
            firmware = model_entry(opts.get("firmware", "v1.2")).spec
        except ValueError as exc:  # a ConfigurationError too: an unknown firmware names the choices
            raise SerialException(f"bad option value in {url!r}: {exc}") from exc
        self._spy = opts.get("spy", "0").lower() not in _FALSE
        timed = opts.get("timed", "1").lower() not in _FALSE
        rules = BUILD_RULES["serial" if opts.get("link", "usb") == "usb" else "serial-uart"]

        source = opts.get("firmware_src")
        if source is not None and not timed:
            raise SerialException(
                f"{url!r}: firmware_src= runs the built firmware in real time; drop timed=0"
            )

        def make() -> Emulator | RealtimeEmulator:
            if source is not None:
                return _host_build(source, board, switching, reading, rules)
            if timed:
                return RealtimeEmulator(
                    board, switching, rules=rules, stack_reading=reading, firmware=firmware
                )
            return Emulator(board, switching, stack_reading=reading, firmware=firmware)

        try:
            if not name:
                return make()
            with _shared_lock:
                emu = _shared.get(name)
                if emu is None:
                    emu = _shared[name] = make()
                elif source is None and (
                    isinstance(emu, RealtimeEmulator) != timed or emu.firmware is not firmware
                ):
                    have = "timed" if isinstance(emu, RealtimeEmulator) else "untimed"
                    served = emu.firmware.name if emu.firmware is not None else "(a host build)"
                    raise SerialException(
                        f"{url!r}: the board {name!r} is already open {have} with firmware {served}"
                    )
                return emu
        except (ValueError, ConfigurationError) as exc:
            raise SerialException(str(exc)) from exc

    def _reconfigure_port(self) -> None:
        """Line settings mean nothing to an in-process device (on native USB the baud rate is nominal)."""

    def _dump(self, direction: str, data: bytes) -> None:
        if self._spy and data:
            sys.stderr.write(f"{time.monotonic():.6f} {direction} {data.hex(' ')}\n")

    def _tell(self, direction: str, data: bytes) -> None:
        """The board's watchers (:func:`watch_shared`) see bytes that reached it or came from it."""
        hooks = _watchers.get(self._shared_name) if self._shared_name and data else None
        if hooks:
            now = time.monotonic()
            for hook in list(hooks):
                hook(direction, data, now)

    def _note(self, text: str) -> None:
        if self._spy:
            sys.stderr.write(f"{time.monotonic():.6f} {text}\n")

    # --- data -----------------------------------------------------------------------------------------

    @property
    def in_waiting(self) -> int:
        self._check_open()
        if self.timed and self.lines.running:
            return int(self.emulator.in_waiting)
        return len(self._rx)

    def read(self, size: int = 1) -> bytes:
        """Untimed: replies exist as soon as the write that caused them returned, so a short read returns
        at once.  Timed: waits (up to ``timeout``) for replies the model has yet to deliver."""
        self._check_open()
        if not self.timed:
            with self._lock:
                got = bytes(self._rx[:size])
                del self._rx[:size]
            return got
        board: RealtimeEmulator = self.emulator
        timeout = Timeout(self._timeout)
        out = bytearray()
        while len(out) < size:
            if self.lines.running:
                got = board.read(size - len(out))
                if got:
                    self._dump("dev->host", got)
                    self._tell("dev->host", got)
                    out += got
                    continue
            if timeout.expired():
                break
            wait = board.wait_s(0.005) if self.lines.running else 0.005
            left = timeout.time_left()
            time.sleep(max(0.0002, min(wait, left if left is not None else wait)))
        return bytes(out)

    def write(self, data: bytes) -> int:
        self._check_open()
        data = bytes(data)
        self._dump("host->dev", data)
        if not self.lines.running:
            self.bytes_dropped += len(data)  # held in reset, or the ROM bootloader: the firmware gets nothing
            return len(data)
        self._tell("host->dev", data)
        if self.timed:
            return int(self.emulator.write(data))
        with self._lock:
            reply = self.emulator.feed(data)
            self._dump("dev->host", reply)
            self._tell("dev->host", reply)
            self._rx += reply
        return len(data)

    def reset_input_buffer(self) -> None:
        self._check_open()
        with self._lock:
            self._rx.clear()
        if self.timed:
            self.emulator.read()

    def _update_break_state(self) -> None:
        self._check_open()

    # --- DTR / RTS: the USB Serial/JTAG reset ------------------------------------------------------------

    def _apply_lines(self) -> None:
        event = self.lines.set(bool(self._dtr_state), bool(self._rts_state))
        if event == "held":
            self._rx.clear()
            if self.timed:
                rec = self.emulator.reset("USB Serial/JTAG reset (RTS without DTR)")
            else:
                rec = reset_untimed(self.emulator, "USB Serial/JTAG reset (RTS without DTR)")
                self.resets.append(rec)
            self._note(str(rec))
        elif event == "released":
            if self.timed:
                with self.emulator.lock:
                    self.emulator.advance_now()
                    self.emulator.timed.reset("USB Serial/JTAG reset released")  # boots from this moment
                    self.emulator.timed.read_tx()
            self._note(
                "reset released: "
                + (
                    "ROM download mode (the application does not run)"
                    if self.lines.download_mode
                    else "the firmware boots"
                )
            )

    @property
    def resets(self) -> list[Any]:
        """Every reset of the board behind this port, with the state it discarded."""
        board = self.emulator
        if isinstance(board, RealtimeEmulator):
            return board.resets
        if board is None:
            return []
        if not hasattr(board, "resets"):
            board.resets = []
        return board.resets  # type: ignore[no-any-return]

    def _update_rts_state(self) -> None:
        if self.is_open:
            self._apply_lines()

    def _update_dtr_state(self) -> None:
        if self.is_open:
            self._apply_lines()

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True


def _host_build(
    source: str, board: str, switching: int, reading: float | None, rules: Any
) -> RealtimeEmulator:
    """``firmware_src=DIR``: the firmware's own tree built on this machine, locked to the wall clock."""
    from tactdeform_hw.emulator.hostbuild.timed import realtime_host_build

    served: RealtimeEmulator = realtime_host_build(
        source, board, switching, rules=rules, stack_reading=reading
    )
    return served
