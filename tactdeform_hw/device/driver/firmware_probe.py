"""Which firmware runs the board, proved by a reply only that version gives, before any stimulating byte.

Neither firmware has a version query, and silence proves nothing (a busy Wi-Fi board, a locked parser, a
port with no board behind it, a reply lost), so a board is driven in a version only after a reply that only
that version gives; anything else is "unknown", and unknown is a refusal that names the device.

The board may be in any parser state when a session starts: a command cut by an earlier program, a v1.2
parser locked by a pattern with zero electrodes, a full queue.  The identification therefore runs in
three steps, each using only bytes that mean "less current" wherever either firmware reads them:

1. **Wait out v2's command timeout** (:data:`SETTLE_S`, nothing written).  v2 applies a payload only when
   it is complete, and discards a command still incomplete 2 s after its byte was read.  A pattern cut by
   an earlier program (killed mid-write, or a Wi-Fi client that left) holds that program's heights: any
   byte written before the timeout could complete it and make them current.  After the wait the v2
   parser is at a command boundary.  (A port whose board has received no byte since power-on — an
   in-process emulator just made — declares ``board_untouched`` and skips the wait: no earlier program
   can have left anything.)
2. **Every current off** (:data:`PROBE` without its sync check), in 64-byte writes with a gap between
   them, slow enough for v1.2's 256-byte queue even while it scans:

   ``00 00 FB 00 00``  completes a u8 or u16 in progress (v1.2 has no timeout) with zeros, then v1.2's
                       pulse height 0 at once — a half-received v1.2 height keeps its low byte only for
                       the moment it takes to read these five bytes; v2 reads mode 0 and an unknown byte;
   ``00 × 510``        completes any command still in progress on either version (the longest payload
                       is v2's 2 × 255 pattern bytes): a zero is a pattern value of 0, an electrode count
                       of 0, a mode of 0, a sense height of 0, a width or rate either version stores as 0
                       or ignores;
   ``FC 00``           electrode count 0: neither firmware scans a channel any more;
   ``FB 00 00``        v1.2: pulse height 0; v2: mode 0 (off really is off) and an unknown byte;
   ``F9 00``           sense height 0 on both.
3. **The signature** (:data:`SIGNATURE`, ``00 00 F5 F4 F5``): the two zeros complete anything a lost
   packet tail may have cut; 0xF5 is answered by both versions with the HV513 count ``h``, 0xF4 only by
   v2, with the electrode count (0 after step 2).  v2 answers ``h 00 h``, v1.2 ``h h``:

   * ``h 00 h`` proves v2 — and the count 0, so every byte of step 2 was read from a boundary;
   * ``h h`` proves v1.2: both 0xF5 were read as commands, so the 0xF4 between them was read as a command
     too, and only v1.2 ignores it (with ``h`` = 0 a third byte is waited for, which only v2 would send);
   * anything else — silence, a short or garbled reply, an echo — is not an answer either version gives.

   It is tried twice (an unlucky timeout or packet loss can spoil one); a second failure is
   :class:`UnidentifiedBoardError`.

Every suffix of the sequence, read from a command boundary, ends at a boundary with the count 0 (tests hold
it to that), so a lost tail or a discard by a timeout leaves either firmware off.  A locked v1.2 parser
reads nothing: it is unknown, and the error says so (the reset line, or a power cycle, brings it back).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from tactdeform_hw.errors import ProtocolError
from tactdeform_hw.protocol.firmware import FIRMWARES, V2, FirmwareSpec, OpcodeV2

if TYPE_CHECKING:
    from tactdeform_hw.clock import Clock
    from tactdeform_hw.device.driver.audit import AuditLog
    from tactdeform_hw.device.driver.dialect import LinkOps
    from tactdeform_hw.device.links.port import PortLink

#: Zeros that complete the longest payload of every modelled firmware (v2: 2 × 255 pattern bytes).
FLUSH_ZEROS = max(f.max_electrodes * f.pattern_bytes_per_electrode for f in FIRMWARES.values()) + 2
# electrode count 0; v1.2 pulse height 0 (v2: mode 0 and an unknown byte); sense height 0 — the same bytes
# on both versions, as the tables show (tests hold them to it)
SAFE_TAIL = bytes((OpcodeV2.ELECTRODE_NUM, 0, OpcodeV2.STIM_MODE, 0, 0, OpcodeV2.SENSE_HEIGHT, 0))
SYNC_CHECK = bytes((OpcodeV2.SYNC_CHECK,))
#: v2's own recovery (:mod:`.v2`) and its guardian stop: zeros first, because there a pattern of the
#: session's own may be in progress, then the safe tail and the sync check.
PROBE = bytes(FLUSH_ZEROS) + SAFE_TAIL + SYNC_CHECK
HV513_REQUEST = bytes((OpcodeV2.HV513_COUNT,))
#: Step 2 of the identification (see the module docstring): v1.2's height 0 first, then the zeros and the
#: safe tail.  Sent only after :data:`SETTLE_S`, when no v2 command can be pending any more.
IDENT_OFF = bytes(2) + SAFE_TAIL[2:5] + bytes(FLUSH_ZEROS - 2) + SAFE_TAIL
#: Step 3: two zeros, then 0xF5 0xF4 0xF5 — ``h 00 h`` from v2, ``h h`` from v1.2.
SIGNATURE = bytes(2) + HV513_REQUEST + SYNC_CHECK + HV513_REQUEST
CHUNK_BYTES = 64
#: How long nothing is written before the identification: v2's command timeout (a cut command is
#: discarded this long after its byte was read), plus a margin for the parser to reach bytes still queued.
SETTLE_S = (V2.command_timeout_us or 0) / 1e6 + 0.2


class FirmwareMismatchError(ProtocolError):
    """The board runs another firmware than the driver speaks (or answered what no firmware would)."""


class UnidentifiedBoardError(FirmwareMismatchError):
    """No reply that only one firmware version gives: the board is not driven at all.  ``reply`` is what
    came back to the last attempt (empty: silence)."""

    def __init__(self, device: str, reply: bytes, hint: str = "") -> None:
        self.device = device
        self.reply = reply
        heard = f"answered {reply.hex(' ')}" if reply else "did not answer"
        super().__init__(
            f"{device}: the firmware identification {heard}, which neither eTactileKit firmware (v1.2, v2) "
            f"would; the board is not driven"
            + (f" ({hint})" if hint else "")
            + "; only bytes that stop current were sent"
        )


@dataclass(frozen=True)
class Detection:
    """What the identification proved, and the bytes it cost (the device counts them as its own writes).
    ``hv513_count`` is the board's answer to 0xF5; ``reply`` the whole signature reply."""

    firmware: FirmwareSpec
    attempts: int
    reply: bytes
    bytes_sent: int = 0
    hv513_count: int = 0
    settle_s: float = 0.0

    @property
    def name(self) -> str:
        return self.firmware.name


def signature_reply(firmware: FirmwareSpec, hv513_count: int, count: int = 0) -> bytes:
    """What ``firmware`` answers to :data:`SIGNATURE` read from a command boundary, from its table: the
    HV513 count for each command that replies it, the electrode count ``count`` for a sync check, nothing
    for a byte the version ignores.  (v2: ``h count h``; v1.2: ``h h``.)"""
    out = bytearray()
    for byte in SIGNATURE:
        command = firmware.by_opcode.get(byte)
        if command is not None and command.reply == "hv513":
            out.append(hv513_count & 0xFF)
        elif command is not None and command.reply == "sync":
            out.append(count & 0xFF)
    return bytes(out)


def classify(reply: bytes, *, count: int = 0) -> FirmwareSpec | None:
    """The firmware a complete answer to :data:`SIGNATURE` proves, or None (see the module docstring).
    ``count`` is the electrode count in force, which v2's 0xF4 answers (0 during the identification).
    Every version in the table registry is asked; tests hold their answers apart for every HV513 count
    and electrode count, so at most one matches."""
    if not reply:
        return None
    for firmware in FIRMWARES.values():
        if reply == signature_reply(firmware, reply[0], count):
            return firmware
    return None


def needs_third_byte(first_two: bytes, *, count: int = 0) -> bool:
    """Whether the answer's first two bytes still leave a longer answer possible, so its third byte must
    be waited for: only two bytes that are already one version's whole answer, and the start of no
    other's, end the reading (``h h`` with ``h`` ≠ the count is v1.2 already: v2's second byte is the
    count)."""
    if len(first_two) != 2:
        return False
    answers = [signature_reply(firmware, first_two[0], count) for firmware in FIRMWARES.values()]
    complete = first_two in answers
    longer = any(len(a) > 2 and a.startswith(first_two) for a in answers)
    return longer or not complete


def _signature_reply(read: Callable[[int], bytes]) -> bytes:
    """Read the answer to :data:`SIGNATURE` (two bytes, and a third where v2 is still possible)."""
    got = read(2)
    return got + read(1) if needs_third_byte(got) else got


def detect_firmware(
    write: Callable[[bytes], object],
    read: Callable[[int], bytes],
    discard: Callable[[], object] = lambda: None,
    *,
    device: str = "the board",
    settle_s: float = SETTLE_S,
    gap_s: float = 0.01,
    sleep: Callable[[float], object] = time.sleep,
) -> Detection:
    """Identify the firmware behind ``write``/``read`` (``read(n)`` returns what came within the port's
    timeout, b"" when nothing did) by a reply only one version gives; raise :class:`UnidentifiedBoardError`
    after two attempts without one.  ``settle_s`` is step 1's wait (0 for a board that has received no
    byte since power-on)."""
    if settle_s > 0:
        sleep(settle_s)
    reply = b""
    for attempt in (1, 2):
        for i in range(0, len(IDENT_OFF), CHUNK_BYTES):
            write(IDENT_OFF[i : i + CHUNK_BYTES])
            sleep(gap_s)
        discard()
        write(SIGNATURE)
        reply = _signature_reply(read)
        found = classify(reply)
        if found is not None:
            return Detection(
                found,
                attempt,
                reply,
                attempt * (len(IDENT_OFF) + len(SIGNATURE)),
                hv513_count=reply[0],
                settle_s=settle_s,
            )
        discard()
    silent = "a locked v1.2 parser answers nothing until the board is reset or power-cycled"
    raise UnidentifiedBoardError(device, reply, "" if reply else silent)


#: What ``firmware=`` accepts: "auto" drives the version the board proves; a version drives only that one.
FIRMWARE_CHOICES = ("auto", "v1.2", "v2")


def check_firmware_choice(firmware: object) -> str:
    """``firmware`` as given, or :class:`~tactdeform_hw.errors.ConfigurationError` naming the choices."""
    if not isinstance(firmware, str) or firmware not in FIRMWARE_CHOICES:
        from tactdeform_hw.errors import ConfigurationError

        raise ConfigurationError(
            f"firmware={firmware!r}: use 'auto' (drive the version the board proves) or 'v1.2' or 'v2' "
            "(drive that version only, after the board has proved it); a board is never driven in a "
            "version it has not proved"
        )
    return firmware


def identify(
    link: PortLink, clock: Clock, audit: AuditLog | None, *, settle_s: float | None, boot_s: float
) -> Detection:
    """Prove which firmware runs the board behind ``link`` (:func:`detect_firmware`), its bytes in the
    audit log like any other.  A board that answers nothing may be hung and still stimulating: the reset
    line (where there is one) brings it to its power-on state and it is asked again (after ``boot_s``).
    Silence on a port that serves one client at a time is another program's connection:
    :class:`~tactdeform_hw.errors.BoardBusyError`.  ``settle_s`` None: v2's command timeout is waited out
    first, unless the port says its board has received nothing since power-on."""
    from tactdeform_hw.errors import BoardBusyError
    from tactdeform_hw.ports import board_untouched, serves_one_client

    name = link.name

    def write(data: bytes) -> None:
        link.write(data)
        if audit is not None:
            audit.tx(data, t=clock.now(), op="identify", logical=data)

    if settle_s is None:
        settle_s = 0.0 if board_untouched(link.port) else SETTLE_S

    def attempt(wait_s: float) -> Detection:
        return detect_firmware(
            write, link.read, link.discard_input, device=name, settle_s=wait_s, sleep=clock.sleep
        )

    try:
        try:
            return attempt(settle_s)
        except UnidentifiedBoardError as silent:
            if silent.reply or not link.can_reset() or not link.reset():
                raise
            if audit is not None:
                audit.event("identification_reset", why="no answer to the identification")
            clock.sleep(boot_s)
            return attempt(0.0)
    except UnidentifiedBoardError as exc:
        if serves_one_client(link.port) and not exc.reply:
            waited = settle_s + 2 * (float(getattr(link.port, "timeout", None) or 0.0) + 0.1)
            raise BoardBusyError(name, waited) from exc
        raise


def recheck_firmware(ops: LinkOps, firmware: FirmwareSpec, count: int | None, device: str) -> None:
    """At a proved command boundary, ask again which firmware answers (the identification's signature
    alone: ``count`` — the electrode count in force where the signature answers it, None where it does
    not (v1.2) — and the heights are the session's own, so nothing is waited out).  A board that now
    answers as another version than ``firmware``, or as none, is stopped with bytes that stop current on
    both versions and refused: :class:`FirmwareMismatchError`."""
    ops.discard_input()
    mark = ops.recovery_send(SIGNATURE, pad=False)
    got = ops.await_reply(2)
    if needs_third_byte(got, count=count or 0):
        got += ops.await_reply(1)
    found = classify(got, count=count or 0)
    if found is not None and found.name == firmware.name:
        ops.proved(mark)  # both 0xF5 were read as commands: every byte before them was read
        if count is not None:
            ops.guard.note_in_step(count)  # and 0xF4 answered the count in force
        return
    ops.suspect("the firmware check answered otherwise")
    ops.recovery_send(IDENT_OFF, pad=False)  # stops current wherever either firmware's parser stands
    raise FirmwareMismatchError(
        f"{device}: the board was driven as firmware {firmware.name}, but now answers the "
        f"firmware check {got.hex(' ') or 'with silence'}"
        + (f" (firmware {found.name})" if found is not None else "")
        + "; every current was switched off with bytes both versions read as off, and it is not driven"
    )


def check_firmware(expected: str, detection: Detection, device: str = "the board") -> None:
    """Refuse a board whose firmware is not the one the driver was told to speak."""
    if detection.name != expected:
        raise FirmwareMismatchError(
            f"{device}: the board runs firmware {detection.name} (it answered the identification "
            f"{detection.reply.hex(' ')}), but firmware={expected!r} was asked for; only bytes that stop "
            "current were sent"
        )
