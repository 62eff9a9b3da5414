"""What the firmware reads from a byte stream: the one reading every layer asks for.

The interlock judges a write by what the firmware will make of it, the audit log and the decoder name what
a capture did, the pacer tells commands with a payload from the rest, and the emulators' parsers are held
to the same reading by tests.  All of them read bytes through :func:`read_commands` (or
:func:`iter_commands`) with a firmware table from :mod:`.firmware`, so there is one definition of the
payload sizes, of the byte order of a u16, of the pattern's length (the electrode count in force when 0xFE
is read) and of the clamps the firmware applies before storing a value.

The reading is untimed: it says what the parser consumes from the bytes given, in order, as if they all
arrived (v2's 2 s timeout, which needs arrival times, belongs to the emulator).  It can start in the
middle of a command (``state``), so a stream can be read in pieces, or from the state a lost packet tail
would leave, and it says where it ends (:attr:`Reading.state`).
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from typing import NamedTuple

from .firmware import DEFAULT_FIRMWARE, KIND_SIZE, CommandSpec, FirmwareSpec

_SIZES = dict(KIND_SIZE)  # a plain dict: read for every command of every frame

COMMAND = "command"
UNKNOWN = "unknown"
UNREAD = "unread"


class ParserState(NamedTuple):
    """Where the firmware's parser stands between two reads.

    ``electrode_num`` is the count in force (None: not known to the host).  ``opcode`` is the command in
    progress (None at a command boundary), ``needed`` its payload size (-1: a pattern whose size cannot be
    known because the electrode count is not), ``got`` the payload bytes it has already read.  ``locked``:
    a v1.2 pattern with zero electrodes, which never completes.
    """

    electrode_num: int | None = 0
    opcode: int | None = None
    needed: int = 0
    got: bytes = b""
    locked: bool = False

    @property
    def at_boundary(self) -> bool:
        return self.opcode is None and not self.locked


class ReadCommand(NamedTuple):
    """One thing the firmware reads: a command (complete or not), a run of unknown bytes, or bytes a
    locked parser never reads.

    ``offset`` is the absolute offset of ``raw``'s first byte; ``raw`` the bytes of this item in the
    stream read (for a command resumed from an earlier read, only its remaining payload).  For u8/u16
    commands ``read_value`` is the payload as read (little-endian) and ``value`` what the firmware stores
    (after its clamp and shift; None when it ignores the value, e.g. a pulse width of 0 on v1.2, or when the
    payload is incomplete).  For patterns ``levels`` are the element values the firmware has stored, on
    channels from ``start`` on: v1.2 stores each byte as it arrives, so an incomplete pattern has levels;
    v2 stores the clamped u16 elements only when the payload is complete.  (A named tuple: the interlock
    reads every frame through this, and tuples are the cheapest records Python builds.)
    """

    offset: int
    opcode: int | None
    raw: bytes
    payload: bytes = b""
    value: int | None = None
    read_value: int | None = None
    levels: tuple[int, ...] | None = None
    start: int = 0
    complete: bool = True
    locked: bool = False
    resumed: bool = False
    kind: str = COMMAND

    @property
    def unknown(self) -> int:
        """Unknown bytes in this item (each ignored by the firmware, one byte consumed)."""
        return len(self.raw) if self.kind == UNKNOWN else 0


class Reading(NamedTuple):
    """Everything read from one stream, and where the parser stands afterwards."""

    commands: tuple[ReadCommand, ...]
    state: ParserState


def u16_at(buf: bytes | bytearray, i: int) -> int:
    """The little-endian u16 at ``buf[i]`` (low byte first, as the firmware reads it)."""
    return buf[i] | buf[i + 1] << 8


def _value(c: CommandSpec, payload: bytes) -> tuple[int, int | None]:
    v = payload[0] if len(payload) == 1 else u16_at(payload, 0)
    return v, c.stored(v)


def _pattern_levels(c: CommandSpec, fw: FirmwareSpec, payload: bytes) -> tuple[int, ...]:
    """The stored pattern elements from a pattern's payload bytes (whole elements only)."""
    if fw.pattern_bytes_per_electrode == 1:
        return tuple(payload)
    top = c.max_value
    out = []
    for k in range(0, len(payload) - 1, 2):
        v = u16_at(payload, k)
        out.append(v if top is None or v <= top else top)
    return tuple(out)


#: Writes up to this size are remembered: a session repeats the same frames and heights over and over, and
#: the reading is a pure function of the bytes, the parser's state and the firmware.
_CACHED_BYTES = 600


def read_commands(
    data: bytes,
    electrode_num: int | None = 0,
    firmware: FirmwareSpec = DEFAULT_FIRMWARE,
    state: ParserState | None = None,
    *,
    offset: int = 0,
) -> Reading:
    """Read ``data`` as ``firmware``'s parser does, from ``state`` (default: a command boundary with
    ``electrode_num`` in force); ``offset`` is the absolute offset of ``data[0]``."""
    if type(data) is not bytes:
        data = bytes(data)
    if state is None:
        state = ParserState(electrode_num)
    if len(data) <= _CACHED_BYTES:
        return _read_cached(data, firmware, state, offset)
    return _read(data, firmware, state, offset)


@functools.lru_cache(maxsize=1024)
def _read_cached(data: bytes, fw: FirmwareSpec, state: ParserState, offset: int) -> Reading:
    return _read(data, fw, state, offset)


def _resume(
    data: bytes, fw: FirmwareSpec, op: int, state: ParserState, offset: int
) -> tuple[ReadCommand, ParserState]:
    """The rest of command ``op``, which ``state`` holds in progress, from the head of ``data``: the item
    read and the parser's state after it (at a command boundary when the payload is complete)."""
    c = fw.by_opcode[op]
    num = state.electrode_num
    got = state.got
    chunk = data[: state.needed - len(got)]
    whole = got + chunk
    done = len(whole) == state.needed
    if c.kind == "pattern":
        if fw.partial_payload_applied:
            levels: tuple[int, ...] | None = _pattern_levels(c, fw, chunk)
            start = len(got) // fw.pattern_bytes_per_electrode
        else:
            levels = _pattern_levels(c, fw, whole) if done else None
            start = 0
        item = ReadCommand(offset, op, chunk, chunk, None, None, levels, start, done, resumed=True)
    elif done:
        rv, sv = _value(c, whole)
        item = ReadCommand(offset, op, chunk, chunk, sv, rv, complete=True, resumed=True)
        if c.register == "electrode_num" and sv is not None:
            num = sv
    else:
        item = ReadCommand(offset, op, chunk, chunk, complete=False, resumed=True)
    return item, (ParserState(num) if done else ParserState(num, op, state.needed, whole))


def _read(data: bytes, fw: FirmwareSpec, state: ParserState, offset: int) -> Reading:
    table = fw.by_opcode
    bpe = fw.pattern_bytes_per_electrode
    num = state.electrode_num
    out: list[ReadCommand] = []
    n = len(data)
    if state.locked or (state.opcode is not None and state.needed < 0):
        if n:
            out.append(ReadCommand(offset, None, data, complete=False, locked=state.locked, kind=UNREAD))
        return Reading(tuple(out), state)
    i = 0
    if state.opcode is not None:
        item, state = _resume(data, fw, state.opcode, state, offset)
        out.append(item)
        if not state.at_boundary:
            return Reading(tuple(out), state)
        i = len(item.raw)
        num = state.electrode_num
    while i < n:
        b = data[i]
        spec = table.get(b)
        if spec is None:
            j = i + 1
            while j < n and data[j] not in table:
                j += 1
            out.append(ReadCommand(offset + i, None, data[i:j], kind=UNKNOWN))
            i = j
            continue
        kind = spec.kind
        if kind is None:
            out.append(ReadCommand(offset + i, b, data[i : i + 1]))
            i += 1
            continue
        if kind == "pattern":
            if num is None:
                # the size is the electrode count, which nobody knows: nothing after this can be read
                out.append(ReadCommand(offset + i, b, data[i : i + 1], complete=False))
                if i + 1 < n:
                    out.append(ReadCommand(offset + i + 1, None, data[i + 1 :], complete=False, kind=UNREAD))
                return Reading(tuple(out), ParserState(None, b, -1))
            need = num * bpe
            if need == 0 and fw.zero_pattern_locks:
                out.append(ReadCommand(offset + i, b, data[i : i + 1], complete=False, locked=True))
                if i + 1 < n:
                    out.append(
                        ReadCommand(
                            offset + i + 1, None, data[i + 1 :], complete=False, locked=True, kind=UNREAD
                        )
                    )
                return Reading(tuple(out), ParserState(num, b, 0, b"", locked=True))
            end = i + 1 + need
            payload = data[i + 1 : end]
            done = len(payload) == need
            if bpe == 1:
                levels = tuple(payload) if done or fw.partial_payload_applied else None
            elif done or fw.partial_payload_applied:
                levels = _pattern_levels(spec, fw, payload)
            else:
                levels = None
            out.append(ReadCommand(offset + i, b, data[i:end], payload, None, None, levels, 0, done))
            if not done:
                return Reading(tuple(out), ParserState(num, b, need, payload))
            i = end
            continue
        need = _SIZES[kind]
        end = i + 1 + need
        payload = data[i + 1 : end]
        if len(payload) < need:
            out.append(ReadCommand(offset + i, b, data[i:end], payload, complete=False))
            return Reading(tuple(out), ParserState(num, b, need, payload))
        rv = payload[0] if need == 1 else u16_at(payload, 0)
        sv = spec.stored(rv)
        out.append(ReadCommand(offset + i, b, data[i:end], payload, sv, rv))
        if spec.register == "electrode_num" and sv is not None:
            num = sv
        i = end
    return Reading(tuple(out), ParserState(num))


def iter_commands(
    data: bytes, electrode_num: int | None = 0, firmware: FirmwareSpec = DEFAULT_FIRMWARE
) -> Iterator[ReadCommand]:
    """Each command, unknown-byte run and unread run the firmware reads from ``data``, from a command
    boundary (:func:`read_commands` also starts mid-command and returns where the parser ends)."""
    return iter(read_commands(data, electrode_num, firmware).commands)


def payload_size(opcode: int, electrode_num: int, firmware: FirmwareSpec = DEFAULT_FIRMWARE) -> int | None:
    """Payload bytes the firmware reads after ``opcode`` (None: not a command byte)."""
    return firmware.size_of(opcode, electrode_num)


def first_command(
    data: bytes, electrode_num: int | None = None, firmware: FirmwareSpec = DEFAULT_FIRMWARE
) -> ReadCommand | None:
    """The first item the firmware reads from ``data`` (None for no bytes).  A pattern's size is taken
    from ``electrode_num`` or, when that is None, from the bytes given."""
    if not data:
        return None
    c = firmware.by_opcode.get(data[0])
    if c is not None and c.kind == "pattern" and electrode_num is None:
        electrode_num = (len(data) - 1) // firmware.pattern_bytes_per_electrode
    items = read_commands(data, electrode_num, firmware).commands
    return items[0] if items else None
