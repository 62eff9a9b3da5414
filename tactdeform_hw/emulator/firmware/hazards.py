"""Structured records of firmware defects and hazards the emulated device ran into.

The emulator reproduces the firmware's defects faithfully; these records are how it tells the user that
it did.  Each event carries the absolute byte offset (bytes received since power-on) of the byte that
triggered it, so a capture can be lined up with ``tactdeform-hw decode``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any


class HazardKind(str, Enum):
    PARSER_LOCKED = "parser_locked"  # 0xFE with electrode_num 0: the parser never reads again
    UNREAD_WHILE_LOCKED = "unread_while_locked"  # bytes arrived that a locked parser will never read
    PATTERN_HOLDS_COMMAND_BYTE = "pattern_holds_command_byte"  # likely desync after a truncated command
    PAYLOAD_HOLDS_COMMAND_BYTE = "payload_holds_command_byte"  # a u8/u16 payload swallowed a command byte
    STALE_CHANNELS = "stale_channels"  # raising electrode_num brought back older pattern values
    U16_WAITING = "u16_waiting"  # main loop spinning on a half-received u16
    CLAMPED = "clamped"  # polarity > 1 or pulse height > 4095 clamped by the firmware
    IGNORED_ZERO = "ignored_zero"  # pulse width 0 or frequency 0 ignored
    UNKNOWN_BYTES = "unknown_bytes"  # bytes that are not commands (ignored, one each)
    CHANNELS_BEYOND_HV513 = "channels_beyond_hv513"  # electrode_num > 8 * hv513 count
    HV513_REINIT = "hv513_reinit"  # 0xF5 re-detects the stack and clears every HV513 output
    # Timing and link hazards (recorded by the timed model):
    QUEUE_OVERFLOW = "queue_overflow"  # receive queue full: the rest of a USB packet was discarded
    # a scan used part old, part new pattern (a stretch of like ones: one record)
    TORN_PATTERN = "torn_pattern"
    OVERRUN = "overrun"  # a scan took longer than the period
    WATCHDOG_RESET = "watchdog_reset"  # the interrupt ran > 300 ms: reboot to power-on state
    SENSE_CURRENT = "sense_current"  # channels off in the pattern still get a non-zero sense pulse
    U16_COMPLETED_LATE = "u16_completed_late"  # a u16's second byte came long after its first
    # Firmware v2:
    COMMAND_TIMEOUT = "command_timeout"  # a cut command timed out: every queued byte was discarded
    COMMAND_PENDING = "command_pending"  # a cut command waits: the next bytes sent become its payload
    # a new host's first bytes completed a command the previous one cut
    INHERITED_COMMAND = "inherited_command"
    SHORT_PULSE_WIDTH = "short_pulse_width"  # width 0-6 µs: the pulse is still one SPI exchange long
    MODE_SENSE_ALL = "mode_sense_all"  # mode 2: every channel gets the sense pulse, a zero pattern included


@dataclass(frozen=True)
class Hazard:
    kind: HazardKind
    offset: int
    detail: dict[str, Any] = field(default_factory=dict)
    time_us: float | None = None

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"kind": self.kind.value, "offset": self.offset, "detail": dict(self.detail)}
        if self.time_us is not None:
            d["time_us"] = self.time_us
        return d

    def __str__(self) -> str:
        at = f" t={self.time_us:.1f}us" if self.time_us is not None else ""
        return f"{self.kind.value} @byte {self.offset}{at}: {self.detail}"


class UnknownRuns:
    """A parser's record of unknown command bytes: one ``UNKNOWN_BYTES`` hazard per run of them, not one
    per byte (a resync's 256 zeros are one record).  The parser sets ``hazards``, ``_unknown_start``
    (-1) and ``_unknown_len`` (0)."""

    hazards: list[Hazard]
    _unknown_start: int
    _unknown_len: int

    def _note_unknown(self, offset: int) -> None:
        if self._unknown_len == 0:
            self._unknown_start = offset
        self._unknown_len += 1

    def _flush_unknown(self) -> None:
        if self._unknown_len:
            self.hazards.append(
                Hazard(HazardKind.UNKNOWN_BYTES, self._unknown_start, {"count": self._unknown_len})
            )
            self._unknown_len = 0


# --- how much a record matters, and whose bytes caused it ---------------------------------------------------


class Severity(str, Enum):
    """How much a hazard record matters to a program driving the board.

    ``info``: the firmware did what it was built to do and nothing was delivered other than asked (bytes
    it skips, the HV513 re-detection of 0xF5, a u16 half received for a moment).  ``warning``: the
    firmware changed or ignored a value the host asked for, or delivered current the host may not have
    meant (a clamped height, an ignored zero, the sense pulse on channels off, stale channels, a scan
    longer than the period); what reached the electrodes is in the delivered pulses.  ``defect``: a
    firmware defect was hit (the parser locked or out of step, bytes lost, a torn scan, a reboot, a cut
    command); a program should never cause one."""

    INFO = "info"
    WARNING = "warning"
    DEFECT = "defect"


#: The severity of each kind of record (the table a test or a report reads; every kind is in it).
SEVERITY: dict[HazardKind, Severity] = {
    HazardKind.UNKNOWN_BYTES: Severity.INFO,
    HazardKind.HV513_REINIT: Severity.INFO,
    HazardKind.U16_WAITING: Severity.INFO,
    HazardKind.CLAMPED: Severity.WARNING,
    HazardKind.IGNORED_ZERO: Severity.WARNING,
    HazardKind.STALE_CHANNELS: Severity.WARNING,
    HazardKind.SENSE_CURRENT: Severity.WARNING,
    HazardKind.OVERRUN: Severity.WARNING,
    HazardKind.SHORT_PULSE_WIDTH: Severity.WARNING,
    HazardKind.MODE_SENSE_ALL: Severity.WARNING,
    HazardKind.PARSER_LOCKED: Severity.DEFECT,
    HazardKind.UNREAD_WHILE_LOCKED: Severity.DEFECT,
    HazardKind.PATTERN_HOLDS_COMMAND_BYTE: Severity.DEFECT,
    HazardKind.PAYLOAD_HOLDS_COMMAND_BYTE: Severity.DEFECT,
    HazardKind.CHANNELS_BEYOND_HV513: Severity.DEFECT,
    HazardKind.QUEUE_OVERFLOW: Severity.DEFECT,
    HazardKind.TORN_PATTERN: Severity.DEFECT,
    HazardKind.WATCHDOG_RESET: Severity.DEFECT,
    HazardKind.U16_COMPLETED_LATE: Severity.DEFECT,
    HazardKind.COMMAND_TIMEOUT: Severity.DEFECT,
    HazardKind.COMMAND_PENDING: Severity.DEFECT,
    HazardKind.INHERITED_COMMAND: Severity.DEFECT,
}


class Origin(str, Enum):
    """Whose bytes a record came from.  ``driver``: the record lies within a byte span the package's own
    driver sent by design (its identification: zeros the parser skips, 0xF5 re-detecting the HV513s);
    ``host``: any other byte (the program's own, or the driver's outside those spans); ``unknown``: the
    caller could not say which bytes were the driver's."""

    DRIVER = "driver"
    HOST = "host"
    UNKNOWN = "unknown"


@dataclass(frozen=True)
class Assessment:
    """A hazard record with its severity and origin (see :func:`assess`)."""

    hazard: Hazard
    severity: Severity
    origin: Origin

    @property
    def kind(self) -> HazardKind:
        return self.hazard.kind

    @property
    def is_defect(self) -> bool:
        return self.severity is Severity.DEFECT

    def to_dict(self) -> dict[str, Any]:
        return {**self.hazard.to_dict(), "severity": self.severity.value, "origin": self.origin.value}

    def __str__(self) -> str:
        return f"[{self.severity.value}, from {self.origin.value}] {self.hazard}"


def severity_of(hazard: Hazard) -> Severity:
    """:data:`SEVERITY` of the record's kind, but a value byte >= 0xF5 the host meant as a value (an
    electrode count of 255, which the firmware reads as that value) is ``info``: the parser stayed in
    step."""
    if (
        hazard.kind is HazardKind.PAYLOAD_HOLDS_COMMAND_BYTE
        and hazard.detail.get("meant_as_command") is False
    ):
        return Severity.INFO
    return SEVERITY[hazard.kind]


def assess(hazard: Hazard, driver_spans: Sequence[tuple[int, int]] | None = None) -> Assessment:
    """The record's severity and origin.  ``driver_spans``: the ``[start, end)`` byte offsets (bytes
    received since power-on, as :attr:`Hazard.offset` counts them) the package's driver sent by design —
    its identification, which the device's audit log marks ``op="identify"``; a record triggered by a
    byte within one is the driver's.  ``None``: not known (origin ``unknown``)."""
    if driver_spans is None:
        origin = Origin.UNKNOWN
    elif any(lo <= hazard.offset < hi for lo, hi in driver_spans):
        origin = Origin.DRIVER
    else:
        origin = Origin.HOST
    return Assessment(hazard, severity_of(hazard), origin)
