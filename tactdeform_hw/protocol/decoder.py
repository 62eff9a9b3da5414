"""Streaming decoder: an arbitrary host-to-device byte capture → the commands the firmware would read.

It reads bytes the way the firmware's parser does (the pattern length is the electrode count in force
when 0xFE is read; a pattern with zero electrodes never completes and leaves every later byte unread), so
a capture of a desynchronised session decodes to what the device really did, not to what the host meant.
Suspicious cases are marked instead of guessed away: unknown bytes, a capture that ends mid-command, a
pattern byte that looks like a command byte (the usual sign that an earlier command was cut short).
"""

from __future__ import annotations

from dataclasses import dataclass

from .firmware import DEFAULT_FIRMWARE, FirmwareSpec
from .reader import UNKNOWN as _UNKNOWN_KIND
from .reader import ParserState, Reading, read_commands

OK = "ok"
TRUNCATED = "truncated"
UNKNOWN = "unknown"
LOCKED = "locked"
UNREAD = "unread"


@dataclass(frozen=True)
class DecodedCommand:
    """One command (or run of bytes) of a capture, with its absolute byte offset."""

    offset: int
    raw: bytes
    opcode: int | None
    name: str
    #: u8/u16: the value sent; pattern: its levels (the bytes on v1.2, the stored u16 heights on v2)
    value: int | bytes | tuple[int, ...] | None
    status: str = OK
    note: str = ""
    #: What the firmware stores for a u8/u16 value (after its clamp and shift; None: ignored or no value).
    stored: int | None = None

    def describe(self) -> str:
        """One readable line: offset, bytes, what the firmware made of them."""
        hexbytes = self.raw.hex(" ")
        if len(hexbytes) > 47:
            hexbytes = hexbytes[:44] + "..."
        if self.status == UNKNOWN:
            text = f"unknown byte(s) ×{len(self.raw)} (ignored by the firmware)"
        elif self.status == UNREAD:
            text = f"UNREAD ×{len(self.raw)}: the parser is locked and never reads these"
        else:
            text = self.name
            if isinstance(self.value, (bytes, tuple)):
                text += f" levels=[{','.join(str(b) for b in self.value)}]"
            elif self.value is not None:
                field = self.name.lower()
                text += f" {field}={self.value}"
                if self.stored != self.value and self.status == OK:
                    text += " (ignored)" if self.stored is None else f" (stored as {self.stored})"
            if self.status == TRUNCATED:
                text += " TRUNCATED (the capture ends mid-command; the next bytes sent become its payload)"
            elif self.status == LOCKED:
                text += " LOCKS THE PARSER (electrode_num is 0: the command never completes)"
        if self.note:
            text += f"  [{self.note}]"
        return f"{self.offset:06d}  {hexbytes:<47}  {text}"

    def to_dict(self) -> dict[str, object]:
        value: object = list(self.value) if isinstance(self.value, (bytes, tuple)) else self.value
        return {
            "offset": self.offset,
            "raw": self.raw.hex(),
            "opcode": self.opcode,
            "name": self.name,
            "value": value,
            "status": self.status,
            "note": self.note,
            "stored": self.stored,
        }


class StreamDecoder:
    """Incremental decoder; ``feed`` returns what completed, ``finish`` what the capture left open.

    A command still waiting for payload bytes is held back and reported whole once they arrive, so a
    capture fed in pieces decodes as fed at once; only a run of unknown bytes split between two feeds is
    reported as two runs (the bytes and what the firmware does with them are the same)."""

    def __init__(self, electrode_num: int = 0, firmware: FirmwareSpec = DEFAULT_FIRMWARE) -> None:
        self.electrode_num = electrode_num
        self.firmware = firmware
        self._buf = bytearray()
        self._offset = 0  # absolute offset of _buf[0]
        self._locked = False
        self._cmin = firmware.command_byte_min

    def _read_buffer(self, data: bytes) -> Reading:
        """What the firmware reads from the bytes held back and ``data``, offsets from the buffer's start
        (a frame the interlock or an earlier feed read already is then found in the reader's cache)."""
        self._buf += data
        return read_commands(bytes(self._buf), firmware=self.firmware, state=ParserState(self.electrode_num))

    def feed_spans(self, data: bytes) -> list[tuple[int, int, int]]:
        """What :meth:`feed` does with ``data``, returning only (offset, opcode, end offset) of each command
        it would return with an opcode (complete, or locking the parser): the span of every command a host
        meant, which the timed emulators' books keep for each write, without the decoded records."""
        if self._locked:
            self._buf += data
            return []
        reading = self._read_buffer(data)
        base = self._offset
        out: list[tuple[int, int, int]] = []
        consumed = 0
        by_op = self.firmware.by_opcode
        count: tuple[int | None] | None = None  # the last complete electrode-count command's stored value
        for c in reading.commands:
            if c.kind == _UNKNOWN_KIND:
                pass
            elif c.opcode is None:
                break
            elif c.locked:
                self._locked = True
                out.append((base + c.offset, c.opcode, base + c.offset + len(c.raw)))
            elif not c.complete:
                break
            else:
                out.append((base + c.offset, c.opcode, base + c.offset + len(c.raw)))
                if by_op[c.opcode].register == "electrode_num":
                    count = (c.value,)
            consumed += len(c.raw)
        if not self._locked and count is not None:  # (as :func:`_num_after` reads the decoded records)
            self.electrode_num = count[0] if count[0] is not None else self.electrode_num
        del self._buf[:consumed]
        self._offset += consumed
        return out

    def feed(self, data: bytes) -> list[DecodedCommand]:
        if self._locked:
            self._buf += data
            return []
        reading = self._read_buffer(data)
        base = self._offset
        out: list[DecodedCommand] = []
        consumed = 0
        by_op = self.firmware.by_opcode
        for c in reading.commands:
            if c.kind == _UNKNOWN_KIND:
                out.append(DecodedCommand(base + c.offset, c.raw, None, "UNKNOWN", None, UNKNOWN))
            elif c.opcode is None:  # unread behind a locked parser: reported by finish()
                break
            elif c.locked:
                self._locked = True
                out.append(
                    DecodedCommand(base + c.offset, c.raw, c.opcode, by_op[c.opcode].name, None, LOCKED)
                )
            elif not c.complete:
                break  # wait for more bytes
            else:
                spec = by_op[c.opcode]
                note = ""
                value: int | bytes | tuple[int, ...] | None
                if spec.kind == "pattern":
                    width = self.firmware.pattern_bytes_per_electrode
                    value = c.payload if width == 1 else c.levels
                    if width > 1:
                        # v2: any byte is a valid half of a height; a height above the clamp is the sign
                        raw = tuple(
                            int.from_bytes(c.payload[i : i + width], "little")
                            for i in range(0, len(c.payload), width)
                        )
                        if c.levels is not None and raw != tuple(c.levels):
                            note = (
                                "pattern holds a height above the firmware's clamp: an earlier command was "
                                "probably cut short"
                            )
                    elif c.payload and max(c.payload) >= self._cmin:
                        note = "pattern holds a command byte: an earlier command was probably cut short"
                else:
                    value = c.read_value
                out.append(
                    DecodedCommand(base + c.offset, c.raw, c.opcode, spec.name, value, OK, note, c.value)
                )
            consumed += len(c.raw)
        if not self._locked:
            self.electrode_num = _num_after(self.electrode_num, out, self.firmware)
        del self._buf[:consumed]
        self._offset += consumed
        return out

    def finish(self) -> list[DecodedCommand]:
        """Mark what is left: a truncated command at the end, or the bytes a locked parser never reads."""
        out: list[DecodedCommand] = []
        if not self._buf:
            return out
        if self._locked:
            out.append(DecodedCommand(self._offset, bytes(self._buf), None, "UNREAD", None, UNREAD))
        else:
            op = self._buf[0]
            name = self.firmware.command(op).name
            out.append(DecodedCommand(self._offset, bytes(self._buf), op, name, None, TRUNCATED))
        self._offset += len(self._buf)
        self._buf.clear()
        return out


def _num_after(num: int, items: list[DecodedCommand], fw: FirmwareSpec) -> int:
    """The electrode count in force after ``items`` (the last complete electrode-count command)."""
    for item in reversed(items):
        if (
            item.opcode is not None
            and item.status == OK
            and fw.by_opcode[item.opcode].register == "electrode_num"
        ):
            return item.stored if item.stored is not None else num
    return num


def decode(
    data: bytes, electrode_num: int = 0, firmware: FirmwareSpec = DEFAULT_FIRMWARE
) -> list[DecodedCommand]:
    """Decode a whole capture, the open end included."""
    dec = StreamDecoder(electrode_num, firmware)
    return dec.feed(data) + dec.finish()


def parse_hex(text: str) -> bytes:
    """Bytes from a hex string that may contain spaces, colons, commas, newlines or ``0x`` prefixes."""
    cleaned = text.replace("0x", " ").replace("0X", " ")
    for sep in ":,;-\n\r\t":
        cleaned = cleaned.replace(sep, " ")
    return bytes.fromhex(cleaned)
