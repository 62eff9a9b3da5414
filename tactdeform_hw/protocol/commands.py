"""Every eTactileKit command and reply as a ``construct`` format, built from each firmware's table.

A firmware version's wire format is data (:mod:`.firmware`): each command's opcode, name, payload kind and
register.  :func:`commands_for` turns one :class:`~.firmware.FirmwareSpec` into its formats (one per
command, the generic ``AnyCommand``, the field names) and its fast encoders, once per spec, so a version
added to :data:`~.firmware.FIRMWARES` gets them with no new code.  The formats use only ``this``
expressions so that ``.compile()`` works on them; a pattern's length comes from the build/parse keyword
``electrode_num`` (the firmware takes it from its register at the moment the command byte is read).

The ``encode_*`` methods are the host's fast path.  They validate every value against the firmware's and
the hardware's limits (naming field, value and limit on failure) and pack with plain ``bytes``; the
protocol tests hold them byte-identical to the construct formats over many random inputs, plain and
compiled, so construct stays the definition and the fast path only its cheaper spelling.

The module-level names (``encode_pattern``, ``build``, ``AnyCommand``, ...) are those of v1.2, the default
firmware; :data:`V2_COMMANDS` carries v2's under the same names.
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any, NamedTuple

import construct as cs
from construct import this

from ..errors import ConfigurationError, DecodeError, LimitError
from .constants import U16_MAX
from .firmware import KIND_SIZE, V1_2, V2, CommandSpec, FirmwareSpec
from .units import check_int

#: Values of the stimulation-mode register (v2's 0xFB): what one scan does on every channel.
STIM_MODE_MONOPHASIC = 0
STIM_MODE_BIPHASIC = 1
STIM_MODE_IMPEDANCE = 2  # the sense pulse on every channel, the pattern ignored
STIM_MODES: Mapping[str, int] = MappingProxyType(
    {"mono": STIM_MODE_MONOPHASIC, "bi": STIM_MODE_BIPHASIC, "impedance": STIM_MODE_IMPEDANCE}
)

#: The electrode count passed to build/parse: the length of patterns and measure replies.
_ELECTRODE_NUM = this._params.electrode_num
#: Little-endian unsigned integers by size in bytes.
_INT_LE: Mapping[int, Any] = MappingProxyType({1: cs.Int8ul, 2: cs.Int16ul})

# --- replies (device to host) ----------------------------------------------------------------------------

MeasureReply = cs.Struct("adc" / cs.Array(_ELECTRODE_NUM, cs.Int16ul))
Hv513CountReply = cs.Struct("hv513_count" / cs.Int8ul)
SyncReply = cs.Struct("electrode_num" / cs.Int8ul)


def parse_measure_reply(data: bytes, electrode_num: int) -> list[int]:
    """ADC codes, one per channel, from a 0xFF reply of exactly ``2 * electrode_num`` bytes."""
    if len(data) != 2 * electrode_num:
        raise DecodeError(f"measure reply: expected {2 * electrode_num} bytes, got {len(data)}")
    # :data:`MeasureReply` spelled as one unpack (tested equal): the driver reads a reply at every proof
    return list(struct.unpack(f"<{electrode_num}H", data))


def parse_hv513_reply(data: bytes) -> int:
    """The HV513 chip count from a 0xF5 reply (one byte)."""
    if len(data) != 1:
        raise DecodeError(f"HV513 count reply: expected 1 byte, got {len(data)}")
    return int(Hv513CountReply.parse(data).hv513_count)


def parse_sync_reply(data: bytes) -> int:
    """The electrode count from a sync-check reply (v2's 0xF4; one byte: ``(byte)ElectrodeNum``)."""
    if len(data) != 1:
        raise DecodeError(f"sync reply: expected 1 byte, got {len(data)}")
    return int(SyncReply.parse(data).electrode_num)


def build_measure_reply(adc: Sequence[int]) -> bytes:
    """The bytes the firmware writes for a measure request (the reference :func:`encode_measure_reply` is
    held to)."""
    return bytes(MeasureReply.build({"adc": list(adc)}, electrode_num=len(adc)))


def encode_measure_reply(adc: Sequence[int]) -> bytes:
    """Fast spelling of :data:`MeasureReply` (tested byte-identical): one u16 LE per channel, packed in
    one call (the emulator answers every measure request with it)."""
    return struct.pack(f"<{len(adc)}H", *adc)


def encode_sync_reply(electrode_num: int) -> bytes:
    """What the firmware writes for a sync check (used by the emulator's tests): ``(byte)ElectrodeNum``."""
    return bytes(SyncReply.build({"electrode_num": electrode_num & 0xFF}))


# --- formats and encoders, per firmware --------------------------------------------------------------------


def field_name(command: CommandSpec) -> str | None:
    """The name of a command's value in its construct format (None: no payload): the pattern's elements
    are ``levels`` unless the table names them (v2: ``heights``); a u8/u16 is named for its register."""
    if command.kind is None:
        return None
    if command.field is not None:
        return command.field
    if command.kind == "pattern":
        return "levels"
    return command.register or command.name.lower()


class _Scalar(NamedTuple):
    """What the fast encoder needs for one u8/u16 command: its byte, its size and the host's bounds."""

    opcode: int
    size: int
    lo: int
    hi: int


class FirmwareCommands:
    """One firmware's commands: construct formats and fast encoders, all read from its table.

    Obtain it with :func:`commands_for` (built once per firmware).  The attribute names are those of the
    module-level v1.2 names, so a caller holding either spells a command the same way.  A command this
    version lacks is refused naming the registers it has (v1.2 has no stimulation mode, v2 no global pulse
    height).
    """

    STIM_MODE_MONOPHASIC = STIM_MODE_MONOPHASIC
    STIM_MODE_BIPHASIC = STIM_MODE_BIPHASIC
    STIM_MODE_IMPEDANCE = STIM_MODE_IMPEDANCE
    STIM_MODES = STIM_MODES
    MeasureReply = MeasureReply
    Hv513CountReply = Hv513CountReply
    SyncReply = SyncReply
    parse_measure_reply = staticmethod(parse_measure_reply)
    parse_hv513_reply = staticmethod(parse_hv513_reply)
    parse_sync_reply = staticmethod(parse_sync_reply)
    build_measure_reply = staticmethod(build_measure_reply)
    encode_measure_reply = staticmethod(encode_measure_reply)
    encode_sync_reply = staticmethod(encode_sync_reply)

    def __init__(self, firmware: FirmwareSpec) -> None:
        self.firmware = firmware
        #: Name of each command's value field, by opcode (None: no payload).
        self.FIELD_NAME: dict[int, str | None] = {int(c.opcode): field_name(c) for c in firmware.commands}
        #: Each command's format, by opcode.
        self.FORMATS: dict[int, Any] = {int(c.opcode): self._format(c) for c in firmware.commands}
        pattern = firmware.pattern_command
        self.PatternCommand: Any = self.FORMATS[pattern.opcode]
        #: Any single command: the opcode byte picks the payload.  Keys are plain ints (a Switch keyed by
        #: an IntEnum breaks once compiled, construct issue 913).  Unknown opcodes carry no payload, as on
        #: the device.
        self.AnyCommand: Any = cs.Struct(
            "opcode" / cs.Int8ul,
            "payload"
            / cs.Switch(
                this.opcode,
                {int(c.opcode): self._payload(c) for c in firmware.commands if c.kind is not None},
                cs.Pass,
            ),
        )
        self._compiled: dict[int, Any] = {}
        self._requests: dict[str, bytes] = {
            c.reply: bytes([c.opcode]) for c in firmware.commands if c.reply is not None
        }
        self._scalars = {
            c.register: self._scalar(c)
            for c in firmware.commands
            if c.register is not None and c.kind in KIND_SIZE
        }
        self._pattern_prefix = bytes([pattern.opcode])
        self._pattern_width = firmware.pattern_bytes_per_electrode
        self._pattern_max = firmware.pattern_level_max()
        self._pattern_label = pattern.field or "pattern"

    def __repr__(self) -> str:
        return f"FirmwareCommands({self.firmware.name})"

    # --- the formats ----------------------------------------------------------------------------------------

    def _payload(self, c: CommandSpec) -> Any:
        if c.kind == "pattern":
            width = self.firmware.pattern_bytes_per_electrode
            return cs.Bytes(_ELECTRODE_NUM) if width == 1 else cs.Array(_ELECTRODE_NUM, _INT_LE[width])
        return _INT_LE[KIND_SIZE[c.kind or "u8"]]

    def _format(self, c: CommandSpec) -> Any:
        opcode = "opcode" / cs.Const(bytes([c.opcode]))
        name = field_name(c)
        if name is None:
            return cs.Struct(opcode)
        return cs.Struct(opcode, name / self._payload(c))

    def compiled(self, opcode: int) -> Any:
        """The compiled form of a command's format (compiled once, on first use)."""
        fmt = self._compiled.get(opcode)
        if fmt is None:
            fmt = self.FORMATS[self.firmware.command(opcode).opcode].compile()
            self._compiled[opcode] = fmt
        return fmt

    def build(
        self, opcode: int, value: Any = None, *, electrode_num: int | None = None, use_compiled: bool = False
    ) -> bytes:
        """Build one command with construct (the reference the ``encode_*`` methods are held to)."""
        c = self.firmware.command(opcode)
        fmt = self.compiled(c.opcode) if use_compiled else self.FORMATS[c.opcode]
        field = self.FIELD_NAME[c.opcode]
        obj: dict[str, Any] = {} if field is None else {field: value}
        kwargs: dict[str, Any] = {}
        if c.kind == "pattern" and field is not None:
            elements = bytes(value) if self._pattern_width == 1 else list(value)
            obj[field] = elements
            kwargs["electrode_num"] = len(elements) if electrode_num is None else electrode_num
        try:
            return bytes(fmt.build(obj, **kwargs))
        except cs.ConstructError as exc:
            raise LimitError(f"{c.name.lower()}.{field}", value, str(exc).splitlines()[-1]) from exc

    def parse(self, data: bytes, *, electrode_num: int = 0) -> dict[str, Any]:
        """One whole command (opcode first) → ``{"opcode": int, "value": ...}`` (a pattern of one byte per
        electrode: its bytes; of wider elements: a list of ints)."""
        try:
            c = self.AnyCommand.parse(data, electrode_num=electrode_num)
        except cs.ConstructError as exc:
            raise DecodeError(f"cannot parse {self.firmware.name} command {data.hex()}: {exc}") from exc
        value = list(c.payload) if isinstance(c.payload, list) else c.payload
        return {"opcode": int(c.opcode), "value": value}

    # --- the fast path --------------------------------------------------------------------------------------

    def _scalar(self, c: CommandSpec) -> _Scalar:
        """The host's bounds for a u8/u16: the payload's range, refused above the firmware's clamp (it
        would store less than asked) and at 0 where the firmware ignores 0 (nothing would change)."""
        size = KIND_SIZE[c.kind or "u8"]
        hi = (1 << (8 * size)) - 1
        if c.max_value is not None:
            hi = min(hi, c.max_value)
        if c.register == "electrode_num":
            hi = min(hi, self.firmware.max_electrodes)
        return _Scalar(c.opcode, size, 1 if c.zero_ignored else 0, hi)

    def request(self, reply: str) -> bytes:
        """The one-byte request answered by ``reply`` ("measure", "hv513", "sync")."""
        request = self._requests.get(reply)
        if request is None:
            have = ", ".join(sorted(self._requests))
            raise ConfigurationError(
                f"firmware {self.firmware.name} has no command answering {reply!r} ({have})"
            )
        return request

    @property
    def MEASURE_REQUEST(self) -> bytes:  # the name callers know from the module level
        return self.request("measure")

    @property
    def HV513_COUNT_REQUEST(self) -> bytes:
        return self.request("hv513")

    @property
    def SYNC_CHECK(self) -> bytes:
        return self.request("sync")

    def encode_value(
        self, register: str, value: object, field: str, *, lo: int | None = None, hi: int | None = None
    ) -> bytes:
        """The u8/u16 command setting ``register`` to ``value``; ``field`` names the value in errors and
        ``lo``/``hi`` replace the table's bounds (see :meth:`_scalar`)."""
        s = self._scalars.get(register)
        if s is None:
            self.firmware.opcode_of(register)  # refuses a register this version lacks, naming those it has
            raise ConfigurationError(
                f"firmware {self.firmware.name} sets {register!r} with no u8/u16 command"
            )
        v = check_int(field, value, s.lo if lo is None else lo, s.hi if hi is None else hi)
        if s.size == 1:
            return bytes((s.opcode, v))
        return bytes((s.opcode, v & 0xFF, v >> 8))

    def encode_pattern(
        self,
        levels: bytes | bytearray | Sequence[int],
        *,
        electrode_num: int | None = None,
        limit: int | None = None,
        field: str | None = None,
    ) -> bytes:
        """The pattern command: its byte, then one element per electrode (v1.2: a level byte, 1 monophasic,
        2 biphasic, else the sense pulse; v2: a u16 DAC code).  ``limit`` is the caller's ceiling below the
        firmware's own clamp (the hardware's 10 mA, a participant's cap).  ``electrode_num`` (the device's
        register), when given, must equal the length: a shorter pattern desynchronises the parser, a
        longer one leaks into the next command."""
        name = self._pattern_label if field is None else field
        top = self._pattern_max if limit is None else min(limit, self._pattern_max)
        width = self._pattern_width
        if width == 1:
            if isinstance(levels, (int, str)) or not isinstance(levels, (bytes, bytearray, Sequence)):
                raise LimitError(name, levels, f"a sequence of integers from 0 to {top}")
            try:
                payload = bytes(levels)
            except (TypeError, ValueError) as exc:
                for i, v in enumerate(levels):
                    check_int(f"{name}[{i}]", v, 0, top)
                raise LimitError(name, levels, f"a sequence of integers from 0 to {top}") from exc
            if top < self._pattern_max:
                for i, v in enumerate(payload):
                    check_int(f"{name}[{i}]", v, 0, top)
            self._check_length(name, len(payload), electrode_num)
            return self._pattern_prefix + payload
        if isinstance(levels, (int, str, bytes, bytearray)) or not isinstance(levels, Sequence):
            raise LimitError(name, levels, f"a sequence of integers from 0 to {top}")
        self._check_length(name, len(levels), electrode_num)
        out = bytearray(self._pattern_prefix)
        for i, h in enumerate(levels):
            out += check_int(f"{name}[{i}]", h, 0, top).to_bytes(width, "little")
        return bytes(out)

    def _check_length(self, name: str, n: int, electrode_num: int | None) -> None:
        if n > self.firmware.max_electrodes:
            raise LimitError(f"{name} length", n, f"at most {self.firmware.max_electrodes} channels")
        if electrode_num is not None and n != electrode_num:
            raise LimitError(f"{name} length", n, f"exactly electrode_num = {electrode_num}")

    def encode_polarity(self, polarity: int) -> bytes:
        """1 anodic, 0 cathodic.  Values above 1 are refused (the firmware would clamp them)."""
        return self.encode_value("polarity", polarity, "polarity")

    def encode_electrode_num(self, electrode_num: int) -> bytes:
        """The electrode count: the pattern's length from the next pattern command on."""
        return self.encode_value("electrode_num", electrode_num, "electrode_num")

    def encode_pulse_height(self, dac_code: int, *, limit: int = U16_MAX) -> bytes:
        """The global pulse height as a DAC code (v1.2).  Callers pass the hardware limit (10 mA → code 1000
        by default)."""
        return self.encode_value("pulse_height", dac_code, "pulse_height", hi=limit)

    def encode_stim_mode(self, mode: int) -> bytes:
        """The stimulation mode (v2): 0 monophasic, 1 biphasic (first phase at the configured polarity), 2
        impedance only.  Values above the firmware's clamp are refused."""
        return self.encode_value("stim_mode", mode, "stim_mode")

    def encode_pulse_width(self, width_us: int) -> bytes:
        """Stimulation pulse width in µs.  0 is refused where the firmware ignores it (v1.2); v2 stores it
        (and still gives a ≈ 6.6 µs pulse at the pattern height)."""
        return self.encode_value("pulse_width", width_us, "pulse_width_us")

    def encode_sense_height(self, raw: int) -> bytes:
        """Sense pulse height as sent, 0-255: v1.2 stores ``raw << 2`` as the DAC code, v2 stores it as is."""
        return self.encode_value("sense_pulse_height", raw, "sense_height")

    def encode_sense_width(self, width_us: int) -> bytes:
        return self.encode_value("sense_pulse_width", width_us, "sense_width_us")

    def encode_discharge(self, discharge_us: int) -> bytes:
        return self.encode_value("discharge_time", discharge_us, "discharge_us")

    def encode_frequency(self, rate_hz: int) -> bytes:
        """Stimulation rate in Hz; 0 is refused because the firmware ignores it."""
        return self.encode_value("frequency", rate_hz, "rate_hz")


@functools.lru_cache(maxsize=32)
def commands_for(firmware: FirmwareSpec) -> FirmwareCommands:
    """The commands of ``firmware`` (built on first use, then shared: specs hash by identity)."""
    return FirmwareCommands(firmware)


#: The two modelled versions' commands.
V1_2_COMMANDS = commands_for(V1_2)
V2_COMMANDS = commands_for(V2)

# --- v1.2's names at module level ---------------------------------------------------------------------------

FIELD_NAME = V1_2_COMMANDS.FIELD_NAME
FORMATS = V1_2_COMMANDS.FORMATS
AnyCommand = V1_2_COMMANDS.AnyCommand
PatternCommand = V1_2_COMMANDS.PatternCommand
MEASURE_REQUEST = V1_2_COMMANDS.MEASURE_REQUEST
HV513_COUNT_REQUEST = V1_2_COMMANDS.HV513_COUNT_REQUEST
compiled = V1_2_COMMANDS.compiled
build = V1_2_COMMANDS.build
parse = V1_2_COMMANDS.parse
encode_pattern = V1_2_COMMANDS.encode_pattern
encode_polarity = V1_2_COMMANDS.encode_polarity
encode_electrode_num = V1_2_COMMANDS.encode_electrode_num
encode_pulse_height = V1_2_COMMANDS.encode_pulse_height
encode_pulse_width = V1_2_COMMANDS.encode_pulse_width
encode_sense_height = V1_2_COMMANDS.encode_sense_height
encode_sense_width = V1_2_COMMANDS.encode_sense_width
encode_discharge = V1_2_COMMANDS.encode_discharge
encode_frequency = V1_2_COMMANDS.encode_frequency
