"""Streaming decoder: an arbitrary host-to-device byte capture → the commands the firmware would read.

It reads bytes the way the firmware's parser does (the pattern length is the electrode count in force
when 0xFE is read; a pattern with zero electrodes never completes and leaves every later byte unread), so
a capture of a desynchronised session decodes to what the device really did, not to what the host meant.
Suspicious cases are marked instead of guessed away: unknown bytes, a capture that ends mid-command, a
pattern byte that looks like a command byte (the usual sign that an earlier command was cut short).
"""

from __future__ import annotations

from dataclasses import dataclass

from .constants import PAYLOAD_KIND, Opcode

OK = "ok"
TRUNCATED = "truncated"
UNKNOWN = "unknown"
LOCKED = "locked"
UNREAD = "unread"

_COMMAND_BYTE_MIN = min(Opcode)


@dataclass(frozen=True)
class DecodedCommand:
    """One command (or run of bytes) of a capture, with its absolute byte offset."""

    offset: int
    raw: bytes
    opcode: int | None
    name: str
    value: int | bytes | None
    status: str = OK
    note: str = ""

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
            if isinstance(self.value, bytes):
                text += f" levels=[{','.join(str(b) for b in self.value)}]"
            elif self.value is not None:
                field = self.name.lower()
                text += f" {field}={self.value}"
            if self.status == TRUNCATED:
                text += " TRUNCATED (the capture ends mid-command; the next bytes sent become its payload)"
            elif self.status == LOCKED:
                text += " LOCKS THE PARSER (electrode_num is 0: the command never completes)"
        if self.note:
            text += f"  [{self.note}]"
        return f"{self.offset:06d}  {hexbytes:<47}  {text}"

    def to_dict(self) -> dict[str, object]:
        value: object = list(self.value) if isinstance(self.value, bytes) else self.value
        return {
            "offset": self.offset,
            "raw": self.raw.hex(),
            "opcode": self.opcode,
            "name": self.name,
            "value": value,
            "status": self.status,
            "note": self.note,
        }


class StreamDecoder:
    """Incremental decoder; ``feed`` returns what completed, ``finish`` what the capture left open."""

    def __init__(self, electrode_num: int = 0) -> None:
        self.electrode_num = electrode_num
        self._buf = bytearray()
        self._offset = 0  # absolute offset of _buf[0]
        self._locked_at: int | None = None

    def feed(self, data: bytes) -> list[DecodedCommand]:
        self._buf += data
        out: list[DecodedCommand] = []
        buf = self._buf
        i = 0
        n = len(buf)
        if self._locked_at is not None:
            return out
        while i < n:
            op = buf[i]
            kind = PAYLOAD_KIND.get(op, "unknown")
            if kind == "unknown":
                j = i + 1
                while j < n and buf[j] not in PAYLOAD_KIND:
                    j += 1
                out.append(DecodedCommand(self._offset + i, bytes(buf[i:j]), None, "UNKNOWN", None, UNKNOWN))
                i = j
                continue
            name = Opcode(op).name
            if kind is None:
                out.append(DecodedCommand(self._offset + i, bytes(buf[i : i + 1]), op, name, None))
                i += 1
                continue
            if kind == "pattern":
                size = self.electrode_num
                if size == 0:
                    self._locked_at = self._offset + i
                    out.append(DecodedCommand(self._offset + i, bytes(buf[i : i + 1]), op, name, None, LOCKED))
                    i += 1
                    break
            else:
                size = 1 if kind == "u8" else 2
            if i + 1 + size > n:
                break  # wait for more bytes
            payload = bytes(buf[i + 1 : i + 1 + size])
            note = ""
            value: int | bytes
            if kind == "pattern":
                value = payload
                if payload and max(payload) >= _COMMAND_BYTE_MIN:
                    note = "pattern holds a command byte: an earlier command was probably cut short"
            elif kind == "u8":
                value = payload[0]
                if op == Opcode.ELECTRODE_NUM:
                    self.electrode_num = value
            else:
                value = payload[0] | payload[1] << 8
            out.append(DecodedCommand(self._offset + i, bytes(buf[i : i + 1 + size]), op, name, value, OK, note))
            i += 1 + size
        del buf[:i]
        self._offset += i
        return out

    def finish(self) -> list[DecodedCommand]:
        """Mark what is left: a truncated command at the end, or the bytes a locked parser never reads."""
        out: list[DecodedCommand] = []
        if not self._buf:
            return out
        if self._locked_at is not None:
            out.append(DecodedCommand(self._offset, bytes(self._buf), None, "UNREAD", None, UNREAD))
        else:
            op = self._buf[0]
            out.append(DecodedCommand(self._offset, bytes(self._buf), op, Opcode(op).name, None, TRUNCATED))
        self._offset += len(self._buf)
        self._buf.clear()
        return out


def decode(data: bytes, electrode_num: int = 0) -> list[DecodedCommand]:
    """Decode a whole capture, the open end included."""
    dec = StreamDecoder(electrode_num)
    return dec.feed(data) + dec.finish()


def parse_hex(text: str) -> bytes:
    """Bytes from a hex string that may contain spaces, colons, commas, newlines or ``0x`` prefixes."""
    cleaned = text.replace("0x", " ").replace("0X", " ")
    for sep in ":,;-\n\r\t":
        cleaned = cleaned.replace(sep, " ")
    return bytes.fromhex(cleaned)
