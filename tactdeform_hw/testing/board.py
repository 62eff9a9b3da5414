"""An emulated eTactileKit board for a program's own tests: where it is opened, what it delivered, what
hazards it met (with severity and origin), and assertions whose failures name the pulse.

Safety is judged on what the emulated board delivered (the timed model's pulse records), never on the
bytes a program meant to send: :func:`delivered_pulses` is the one reading of those records, the same
for :meth:`EmulatedBoard.delivered` and the assertions.  See ``docs/testing-downstream.md``.
"""

from __future__ import annotations

import os
import time
import urllib.parse as urlparse
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from tactdeform_hw.emulator.firmware.hazards import (
    Assessment,
    Origin,
    Severity,
    assess,
)
from tactdeform_hw.emulator.firmware.scan import PulseKind
from tactdeform_hw.emulator.hostbuild.statemap import declared_firmware
from tactdeform_hw.emulator.records.reports import PULSE_KIND_NAMES
from tactdeform_hw.emulator.serving.realtime import RealtimeEmulator, settle
from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.protocol.state import BoardState

#: The transports a board can be served on: the in-process pyserial URL handler, a pseudo-terminal, TCP,
#: the board's own USB device (``usb-emulator://PATH``, opened through pyusb).
TRANSPORTS = ("url", "pty", "tcp", "usb")
#: The options a board takes (the marker's keywords and an indirect parameter's keys).
BOARD_OPTIONS = ("firmware", "transport", "board", "switching_boards", "firmware_src")


@dataclass(frozen=True)
class DeliveredPulse:
    """One pulse the emulated board delivered: when it started (µs of device time since power-up), on
    which electrode (the channel index the firmware scanned), with what current (µA, 0 for a pulse that
    carried none) and width (µs), and its kind (``monophasic``, ``biphasic-anodic``,
    ``biphasic-cathodic``, ``sense``)."""

    time_us: float
    electrode: int
    current_ua: float
    width_us: float
    kind: str

    def __str__(self) -> str:
        return (
            f"{self.kind} pulse at t={self.time_us / 1000:.3f} ms on electrode {self.electrode}: "
            f"{self.current_ua:.1f} µA for {self.width_us:.1f} µs"
        )


def delivered_pulses(
    board: RealtimeEmulator, since_us: float = 0.0, until_us: float | None = None
) -> list[DeliveredPulse]:
    """Every pulse a real-time emulated board delivered in ``[since_us, until_us)`` of device time, the
    model first brought up to the wall clock.  Read from the timed model's pulse records
    (``reports.pulse_table``), which keep the last minutes of a long session."""
    with board.lock:
        board.advance_now()
        timed: Any = board.timed  # both firmwares' models keep ``reports.pulse_table`` (not in TimedModel)
        table = timed.reports.pulse_table(since_us, until_us)
    return [
        DeliveredPulse(float(t), int(ch), float(ua), float(w), PULSE_KIND_NAMES[PulseKind(int(k))])
        for t, ch, ua, w, k in zip(
            table["start_us"],
            table["channel"],
            table["current_ua"],
            table["width_us"],
            table["kind"],
            strict=True,
        )
    ]


def _find_all(haystack: bytes, needle: bytes) -> Iterator[int]:
    at = haystack.find(needle)
    while at >= 0:
        yield at
        at = haystack.find(needle, at + len(needle))


def identification_spans(received: bytes) -> list[tuple[int, int]]:
    """The ``[start, end)`` offsets in ``received`` (the bytes a board received since power-on) of the
    package driver's identification — the bytes its audit log marks ``op="identify"``: the clearing
    sequence and the signature, either alone (the clearing sequence stops current before a refusal, the
    signature alone is a later proof that the same firmware answers)."""
    from tactdeform_hw.device.driver.firmware_probe import IDENT_OFF, SIGNATURE

    spans: list[tuple[int, int]] = []
    for needle in (IDENT_OFF + SIGNATURE, IDENT_OFF, SIGNATURE):
        for at in _find_all(received, needle):
            if not any(lo <= at < hi for lo, hi in spans):
                spans.append((at, at + len(needle)))
    return sorted(spans)


def driver_spans(received: bytes, firmware: str = "v1.2") -> list[tuple[int, int]]:
    """The byte spans of ``received`` the package's driver sends by design and the firmware records as
    harmless: its identification (:func:`identification_spans`); a proof of a command boundary (a run of
    zeros, then the 0xF5 or 0xFF request they let be read as a command); a flush (a run of zeros, then
    the stop sequence ``firmware_probe.SAFE_TAIL``); and the loss-tolerant padding
    right after a whole command (``tactdeform_hw.device.driver.pacing.padding_for``).  Recognised by their
    bytes: a program writing the same bytes by itself is taken as the driver."""
    from tactdeform_hw.device.driver.firmware_probe import SAFE_TAIL
    from tactdeform_hw.device.driver.pacing import padding_for
    from tactdeform_hw.protocol.decoder import OK, UNKNOWN, decode
    from tactdeform_hw.protocol.firmware import get_firmware

    spec = get_firmware(firmware)
    spans = identification_spans(received)
    commands = decode(received, firmware=spec)
    for before, run, after in zip([None, *commands[:-1]], commands, [*commands[1:], None], strict=True):
        if run.status != UNKNOWN:
            continue
        if after is not None and run.raw == bytes(len(run.raw)):
            if after.status == OK and after.raw[:1] in (b"\xf5", b"\xff"):
                spans.append((run.offset, after.offset + 1))
                continue
            if received.startswith(SAFE_TAIL, after.offset):
                spans.append((run.offset, after.offset + len(SAFE_TAIL)))
                continue
        if before is not None and before.status == OK:
            pad = padding_for(before.raw, spec)
            if pad and run.raw.startswith(pad):
                spans.append((run.offset, run.offset + len(pad)))
    return sorted(spans)


class RecordingBoard(RealtimeEmulator):
    """A real-time emulated board that also keeps every byte it received, so the records of the driver's
    own identification can be told from the program's (:func:`identification_spans`).  The bytes are
    counted as :attr:`Hazard.offset` counts them while no byte is lost in the receive queue."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.received = bytearray()

    def write(self, data: bytes, t: float | None = None) -> int:
        with self.lock:
            self.received += data
            return super().write(data, t)


class HazardReport(Sequence[Assessment]):
    """The hazards an emulated board recorded, each with its severity and origin (see
    :func:`~tactdeform_hw.emulator.firmware.hazards.assess`)."""

    def __init__(self, items: Sequence[Assessment]) -> None:
        self._items = list(items)

    def __getitem__(self, i: Any) -> Any:
        return self._items[i]

    def __len__(self) -> int:
        return len(self._items)

    def __iter__(self) -> Iterator[Assessment]:
        return iter(self._items)

    def defects(self) -> list[Assessment]:
        """The firmware defects hit (severity ``defect``): empty after a clean session of the package's
        driver, whatever its identification left."""
        return [a for a in self._items if a.severity is Severity.DEFECT]

    def warnings(self) -> list[Assessment]:
        """Values the firmware changed or ignored, current the host may not have meant."""
        return [a for a in self._items if a.severity is Severity.WARNING]

    def from_driver(self) -> list[Assessment]:
        """The records the package driver's identification caused by design."""
        return [a for a in self._items if a.origin is Origin.DRIVER]

    def __repr__(self) -> str:
        return f"HazardReport({len(self)} records, {len(self.defects())} defect(s))"


class EmulatedBoard:
    """A timed emulated board served on one transport.  A program under test opens :attr:`name` (the
    in-process URL ``etactile://...``, the pty's path, the TCP server's ``socket://`` URL, or the USB
    device's ``usb-emulator://PATH``).  Every byte that reaches the board is kept (:attr:`received`), so
    the hazards the package's own driver causes by design are told from the program's on every
    transport."""

    def __init__(
        self,
        *,
        firmware: str | None = None,
        transport: str = "pty",
        board: str = "compact",
        switching_boards: int = 1,
        firmware_src: str | os.PathLike[str] | None = None,
    ) -> None:
        """``firmware``: the Python model's version (default v1.2).  ``firmware_src``: a firmware's own
        PlatformIO tree, built on this machine and served in its place (docs/firmware-host-build.md); it
        serves the version its state map declares, which ``firmware``, if given, must name."""
        if transport not in TRANSPORTS:
            raise ConfigurationError(
                f"etactile_board transport={transport!r}: use one of {', '.join(TRANSPORTS)}"
            )
        served = declared_firmware(firmware_src, "etactile_board firmware_src") if firmware_src else None
        if firmware_src is not None and firmware is not None and firmware != served:
            raise ConfigurationError(
                f"etactile_board firmware={firmware!r}, but firmware_src={str(firmware_src)!r} declares "
                f"{served or 'no version'} in its state map"
            )
        self.firmware = served or firmware or "v1.2"
        self.firmware_src = None if firmware_src is None else str(firmware_src)
        self.transport = transport
        self.url: str | None = None
        self.path: str | None = None
        self._cleanup: list[Callable[[], None]] = []
        self._received = bytearray()
        self.emulator: RealtimeEmulator
        if transport == "url":
            self.emulator = self._serve_url(self.firmware, board, switching_boards)
            return
        if transport == "usb":
            self.emulator = self._serve_usb(self.firmware, board, switching_boards)
            return
        recording = self._recording_board(board, switching_boards, self._rules(transport))
        self._received = recording.received
        self.emulator = recording
        if transport == "pty":
            from tactdeform_hw.emulator.serving.pty_server import PtyServer

            pty = PtyServer(recording, firmware=self.firmware)
            pty.start()
            self._cleanup.append(pty.stop)
            self.path = pty.path
        else:
            from tactdeform_hw.emulator.serving.tcp_server import TcpServer

            tcp = TcpServer(recording, port=0, firmware=self.firmware)
            tcp.start()
            self._cleanup.append(tcp.stop)
            self.url = tcp.url

    def _recording_board(self, board: str, switching_boards: int, rules: dict[str, Any]) -> RecordingBoard:
        """The served board that keeps its bytes: the firmware tree's host build, or the Python model."""
        if self.firmware_src is not None:
            from tactdeform_hw.emulator.hostbuild.timed import realtime_host_build

            built: RecordingBoard = realtime_host_build(
                self.firmware_src, board, switching_boards, cls=RecordingBoard, **rules
            )
            return built
        return RecordingBoard(board, switching_boards, firmware=self.firmware, **rules)

    @staticmethod
    def _rules(transport: str) -> dict[str, Any]:
        """The serving rules' keywords: the Wi-Fi build's on TCP, the USB build's otherwise."""
        from tactdeform_hw.emulator.serving.realtime import WIFI_TCP

        return {"rules": WIFI_TCP} if transport == "tcp" else {}

    def _serve_url(self, firmware: str, board: str, switching_boards: int) -> RealtimeEmulator:
        from tactdeform_hw.device import open_port
        from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import (
            forget_shared,
            shared_emulator,
            watch_shared,
        )

        shared = f"board-{uuid.uuid4().hex[:8]}"
        source = (
            f"firmware_src={urlparse.quote(self.firmware_src)}"
            if self.firmware_src is not None
            else f"firmware={firmware}"
        )
        self.url = f"etactile://{shared}?{source}&board={board}&switching_boards={switching_boards}"
        first = open_port(self.url, timeout=0.1)
        first.open()  # creates the shared board every later port of this URL talks to
        self._cleanup += [lambda: forget_shared(shared), first.close]
        self._cleanup.append(watch_shared(shared, self._keep))
        emu = shared_emulator(shared)
        assert isinstance(emu, RealtimeEmulator)
        return emu

    def _serve_usb(self, firmware: str, board: str, switching_boards: int) -> RealtimeEmulator:
        """The board's USB device on a socket of its own (:class:`~.usb_server.UsbServer`); a program
        opens ``usb-emulator://PATH`` with pyusb, as ``tactdeform-hw emulate --usb`` serves it."""
        from tactdeform_hw.emulator.serving.usb_server import UsbServer

        if self.firmware_src is not None:
            from tactdeform_hw.emulator.hostbuild.timed import realtime_host_build

            emu: RealtimeEmulator = realtime_host_build(self.firmware_src, board, switching_boards)
        else:
            emu = RealtimeEmulator(board, switching_boards, firmware=firmware)
        usb = UsbServer(emu, firmware=firmware, hook=self._keep)
        usb.start()
        self._cleanup.append(usb.stop)
        self.url = usb.name
        return emu

    def _keep(self, direction: str, data: bytes, t: float) -> None:
        """A transport's byte hook: keep what reached the board."""
        if direction == "host->dev":
            self._received += data

    @property
    def received(self) -> bytes:
        """Every byte that reached the board since it was made (what :attr:`Hazard.offset` counts while
        no byte is lost in the receive queue)."""
        return bytes(self._received)

    @property
    def name(self) -> str:
        """What a program opens: the pty's path, or the URL."""
        return self.path if self.path is not None else str(self.url)

    def close(self) -> None:
        while self._cleanup:
            self._cleanup.pop()()

    # --- what the board did ------------------------------------------------------------------------

    def now_us(self) -> float:
        """The board's device time now (µs since power-up), the clock of :meth:`delivered`."""
        with self.emulator.lock:
            return self.emulator.advance_now()

    def settle(self, timeout_s: float = 2.0) -> bool:
        """Wait until the board has read every byte that reached it."""
        return settle(self.emulator, timeout_s=timeout_s)

    def delivered(self, since_us: float = 0.0, until_us: float | None = None) -> list[DeliveredPulse]:
        """Every pulse delivered in ``[since_us, until_us)`` (:func:`delivered_pulses`)."""
        return delivered_pulses(self.emulator, since_us, until_us)

    def state(self) -> BoardState:
        """The firmware's registers now."""
        return self.emulator.state()

    @property
    def hazards(self) -> HazardReport:
        """Every hazard recorded, each with severity and origin (``driver`` or ``host``, from the bytes
        :attr:`received` on every transport)."""
        spans = driver_spans(self.received, self.firmware)
        with self.emulator.lock:
            records = list(self.emulator.hazards)
        return HazardReport([assess(h, spans) for h in records])

    # --- assertions --------------------------------------------------------------------------------

    def assert_no_pulse_above(self, ua: float, *, since_us: float = 0.0) -> None:
        """No delivered pulse from ``since_us`` on carried more than ``ua`` µA."""
        over = [p for p in self.delivered(since_us) if p.current_ua > ua]
        if over:
            raise AssertionError(
                f"{len(over)} delivered pulse(s) above the limit of {ua:g} µA; first: {over[0]}; "
                f"largest: {max(over, key=lambda p: p.current_ua)}"
            )

    def assert_off_within(
        self, ms: float, *, since_us: float | None = None, observe_ms: float = 50.0
    ) -> None:
        """No pulse carrying current starts later than ``ms`` after ``since_us`` (default: now, the
        call).  Waits until ``ms + observe_ms`` have passed on the board, so that a pulse that should not
        come has the time to come."""
        start = self.now_us() if since_us is None else since_us
        deadline_us = start + ms * 1000.0
        end_us = deadline_us + observe_ms * 1000.0
        while self.now_us() < end_us:
            time.sleep(min(0.01, max(0.0, (end_us - self.now_us()) / 1e6)))
        late = [p for p in self.delivered(deadline_us) if p.current_ua > 0]
        if late:
            raise AssertionError(
                f"{len(late)} pulse(s) with current later than {ms:g} ms after "
                f"t={start / 1000:.3f} ms (the limit t={deadline_us / 1000:.3f} ms); first: {late[0]}"
            )

    def assert_no_defect(self) -> None:
        """The board hit no firmware defect (records of severity ``defect``)."""
        found = self.hazards.defects()
        if found:
            shown = "\n  ".join(str(a) for a in found[:10])
            more = f"\n  ... and {len(found) - 10} more" if len(found) > 10 else ""
            raise AssertionError(f"the emulated board hit {len(found)} firmware defect(s):\n  {shown}{more}")
