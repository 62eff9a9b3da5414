"""The one contract every firmware version's parser keeps, so the models above it never ask which
version they drive.

A parser is the firmware's ``runEtactileKit()`` and the receive queue it reads: bytes arrive
(:meth:`FirmwareParser.receive`), the main loop calls it (:meth:`FirmwareParser.call` at the command
timer's time: a version whose parser reads no timer ignores it), replies are taken
(:meth:`FirmwareParser.take_tx`).  The untimed fast path (:meth:`FirmwareParser.run`) is equivalent to
calling until a call neither reads nor writes; :meth:`FirmwareParser.poll_until` is the idle polling
between arrivals (it matters only where a pending command times out).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from tactdeform_hw.emulator.firmware.hazards import Hazard
from tactdeform_hw.protocol.firmware import FirmwareSpec


@dataclass(frozen=True)
class CallOutcome:
    """What one parser call did: bytes read from the queue, bytes written, whether it ended with the
    one-tick sleep."""

    consumed: int
    wrote: int
    slept: bool

    @property
    def quiet(self) -> bool:
        """Neither consumed nor wrote a byte: the driving loop stops here."""
        return self.consumed == 0 and self.wrote == 0


#: Bytes read that an arrival never forgets (past them, it drops what was read once that is most of ``rx``).
_KEEP_READ_BYTES = 4096


class ByteQueue:
    """The bytes a parser has been handed and the bytes it wrote, as both versions' parsers keep them:
    ``rx`` from absolute offset ``base``, read up to ``pos``; ``tx`` until taken."""

    def __init__(self) -> None:
        self.rx = bytearray()
        self.pos = 0  # index of the next unread byte in rx
        self.base = 0  # absolute offset (bytes handed over since power-on) of rx[0]
        self.tx = bytearray()

    @property
    def pending(self) -> int:
        """Bytes queued and not read yet."""
        return len(self.rx) - self.pos

    @property
    def offset(self) -> int:
        """Absolute offset of the next byte to be read."""
        return self.base + self.pos

    def take_tx(self) -> bytes:
        """The bytes written since the last take."""
        out = bytes(self.tx)
        self.tx.clear()
        return out

    def keeps_read_bytes(self, reads: int) -> bool:
        """Whether the bytes read so far stay in ``rx`` through ``reads`` more reads, whatever arrives
        meanwhile (an arrival forgets them only past :data:`_KEEP_READ_BYTES`): then when bytes arrive
        during those reads does not change ``rx``, ``base`` or ``pos``."""
        return self.pos + reads <= _KEEP_READ_BYTES

    def _drop_read(self) -> None:
        """Forget bytes already read once they are most of the buffer (a long session stays bounded)."""
        if self.pos > _KEEP_READ_BYTES and self.pos * 2 > len(self.rx):
            del self.rx[: self.pos]
            self.base += self.pos
            self.pos = 0


class ParserBase(ByteQueue):
    """What both versions' parsers hold besides their registers and rules: the hazard list, the board's
    stack sensing (0xF5), and the hooks a model sets (``on_hv513_reinit``: the chain was re-clocked;
    ``on_command``: ``(opcode, value, offset)`` when a command takes effect; ``meant_as_command``: was
    the byte at this offset meant as a command?  A host whose intent is known (the timed emulator decodes
    what the host wrote) says so in each command-byte-as-payload record of v1.2, which reads payload
    bytes one by one: a legitimate value byte >= 0xF5 (electrode count 255, width 250 µs) is recorded
    with False, a desynchronisation with True; None where the intent is unknown)."""

    def __init__(
        self,
        hazards: list[Hazard],
        hv513_detect: Callable[[], int],
        on_hv513_reinit: Callable[[], None] | None,
        on_command: Callable[[int, object, int], None] | None,
    ) -> None:
        super().__init__()
        self.hazards = hazards
        self.hv513_detect = hv513_detect
        self.on_hv513_reinit = on_hv513_reinit
        self.on_command = on_command
        self.meant_as_command: Callable[[int], bool] | None = None


class FirmwareParser(Protocol):
    """The parser of one firmware version (see the module documentation)."""

    spec: FirmwareSpec
    hazards: list[Hazard]
    on_command: Callable[[int, object, int], None] | None
    on_hv513_reinit: Callable[[], None] | None
    #: Was the byte at this offset meant as a command?  Recorded in command-byte-as-payload hazards where
    #: the version reads payload bytes one by one (v1.2); unused elsewhere.
    meant_as_command: Callable[[int], bool] | None

    @property
    def pending(self) -> int:
        """Bytes queued and not read yet."""
        ...

    @property
    def offset(self) -> int:
        """Bytes read since power-on (the offset of the next byte to read)."""
        ...

    @property
    def locked(self) -> bool:
        """The parser will never read again (v1.2's pattern with electrode_num 0)."""
        ...

    @property
    def processing(self) -> bool:
        """A command's byte was read and its payload is not complete."""
        ...

    @property
    def dropped(self) -> int:
        """Bytes the parser's own receive queue dropped since power-on (0 where it has none)."""
        ...

    def receive(self, data: bytes) -> int:
        """Queue one arrival; return the bytes dropped."""
        ...

    def call(self, now_us: int) -> CallOutcome:
        """Exactly one main-loop call at command-timer time ``now_us``."""
        ...

    def run(self, now_us: int) -> None:
        """Call until a call neither reads nor writes (the untimed fast path)."""
        ...

    def poll_until(self, to_us: int, settle: bool) -> None:
        """The idle polls of the main loop up to just before ``to_us`` (and at ``to_us`` with
        ``settle``): where nothing arrives only a timeout can happen."""
        ...

    def note_pending(self, now_us: int) -> None:
        """Record a command left waiting for its payload after an arrival, where that is a hazard."""
        ...

    def take_tx(self) -> bytes:
        """The bytes written since the last take."""
        ...


__all__ = ["ByteQueue", "CallOutcome", "FirmwareParser", "ParserBase"]
