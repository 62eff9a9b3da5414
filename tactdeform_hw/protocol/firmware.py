"""Each eTactileKit firmware version's command table, as data: one definition per version.

Like a simulated instrument of pyvisa-sim, a firmware version is a value, not code: which bytes are
commands, what payload each reads, how the firmware clamps what it stores, what it answers, its power-on
registers, its receive queue, how its parser yields, and the timing constants of its scan.  The decoder,
the interlock, the pacer and the emulators all read these tables, so a second version is a second table
(and its tests), not a second copy of the parser.

The two versions modelled:

* ``v1.2`` (commit 936c6c08, the firmware TactDeform ran): one global pulse height (0xFB, u16, clamped to
  4095), one pattern byte per electrode (1 monophasic, 2 biphasic, anything else the sense pulse), payload
  applied byte by byte, a 1 ms sleep after every command with a payload, a 256-byte receive queue, a
  pattern with zero electrodes locks the parser, ``DAAD(0)`` at the start of each channel's discharge.
* ``v2`` (commit 71adee21, upstream's current firmware): 0xFB is the stimulation mode (u8, clamped to 2),
  the pattern carries one u16 DAC code per electrode (clamped to 4095), 0xF4 replies the electrode count,
  payloads are applied only when complete, a command not complete 2 s after its byte was read is
  discarded with everything queued, the parser yields only when it made no progress, a 1024-byte queue,
  no ``DAAD(0)`` in the discharge.

Adding a version: write its :class:`FirmwareSpec` below from its source (opcodes, payload kinds, clamps,
replies, power-on state, queue, parser rules, timing), add it to :data:`FIRMWARES`, and run the
table-driven tests (``tests/test_firmware_tables.py``) and the golden vectors of that version.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from types import MappingProxyType
from typing import Literal

from ..errors import ConfigurationError

PayloadKind = Literal["u8", "u16", "pattern"]
ReplyKind = Literal["measure", "hv513", "sync"]
YieldRule = Literal["after_payload", "when_idle"]


class Opcode(IntEnum):
    """Command bytes of v1.2, host to device.  Any other byte is ignored by the firmware (one byte
    consumed)."""

    MEASURE = 0xFF
    PATTERN = 0xFE
    POLARITY = 0xFD
    ELECTRODE_NUM = 0xFC
    PULSE_HEIGHT = 0xFB
    PULSE_WIDTH = 0xFA
    SENSE_HEIGHT = 0xF9
    SENSE_WIDTH = 0xF8
    DISCHARGE = 0xF7
    FREQUENCY = 0xF6
    HV513_COUNT = 0xF5


class OpcodeV2(IntEnum):
    """Command bytes of v2: 0xFB became the stimulation mode and 0xF4 the sync check."""

    MEASURE = 0xFF
    PATTERN = 0xFE
    POLARITY = 0xFD
    ELECTRODE_NUM = 0xFC
    STIM_MODE = 0xFB
    PULSE_WIDTH = 0xFA
    SENSE_HEIGHT = 0xF9
    SENSE_WIDTH = 0xF8
    DISCHARGE = 0xF7
    FREQUENCY = 0xF6
    HV513_COUNT = 0xF5
    SYNC_CHECK = 0xF4


#: Bytes per payload element of the fixed-size kinds (a pattern's size is electrodes × bytes per electrode).
KIND_SIZE: Mapping[str, int] = MappingProxyType({"u8": 1, "u16": 2})


@dataclass(frozen=True)
class CommandSpec:
    """One command byte: what it reads and what it stores.

    ``register`` names the firmware variable it sets (the golden vectors' ``expect`` names); ``max_value``
    is the firmware's upper clamp (``min(v, max_value)``; for a pattern, per element), ``shift`` a left
    shift applied before storing, ``zero_ignored`` a value of 0 that leaves the register unchanged.  A
    command without a payload has ``kind`` None and usually a ``reply``.
    """

    opcode: int
    name: str
    kind: PayloadKind | None
    register: str | None = None
    max_value: int | None = None
    shift: int = 0
    zero_ignored: bool = False
    reply: ReplyKind | None = None
    field: str | None = None

    def stored(self, value: int) -> int | None:
        """What the firmware stores for a complete payload ``value`` (None: the value is ignored)."""
        if self.zero_ignored and value == 0:
            return None
        if self.max_value is not None and value > self.max_value:
            value = self.max_value
        return value << self.shift


def busy_wait_ticks(us: int, min_us: int, ticks_per_us: float, offset_ticks: float) -> int:
    """The firmware's busy-wait ``delay(us)``: raise ``us`` to ``min_us``, then wait until the timer reaches
    ``int(us * 2.0 - 5.4)`` ticks (``ticks_per_us``, ``offset_ticks``), computed in double precision like
    the C expression.  A negative target (impossible with the firmware's constants) waits nothing."""
    if us < min_us:
        us = min_us
    return max(0, int(us * ticks_per_us - offset_ticks))


def pulse_wait_arg(width_us: int, offset_us: int) -> int | None:
    """``monophasic(h, w)`` busy-waits ``delay(w - 7)`` only when ``w >= 7`` (None: no wait)."""
    return width_us - offset_us if width_us >= offset_us else None


def discharge_wait_arg(discharge_us: int, offset_us: int) -> int | None:
    """The discharge busy-waits ``delay(d - 7)`` only when ``d > 7`` (None: no wait)."""
    return discharge_us - offset_us if discharge_us > offset_us else None


@dataclass(frozen=True)
class FirmwareTiming:
    """The scan's timing constants and the busy-wait rule, as the firmware's code and comments give them.

    ``spi_exchange_us`` is the firmware's own comment; ``gpio_write_us``, ``isr_entry_us`` and the parser
    costs are assumptions (the emulator's :class:`~tactdeform_hw.emulator.timed.timing.TimingModel` lets a
    user
    change them).  ``discharge_exchange``: whether the discharge starts with ``DAAD(0)`` (one exchange).
    """

    spi_exchange_us: float = 6.6
    dac_change_at_us: float = 3.3
    gpio_write_us: float = 0.05
    isr_entry_us: float = 2.0
    rtos_tick_us: float = 1000.0
    timer_ticks_per_us: int = 2  # 80 MHz APB / prescaler 40
    pulse_wait_offset_us: int = 7  # monophasic: busy-wait w - 7 µs only if w >= 7
    discharge_wait_offset_us: int = 7  # discharge: busy-wait d - 7 µs only if d > 7
    delay_min_us: int = 3  # delay(us) raises us below 3 to 3
    delay_ticks_per_us: float = 2.0  # target = int(us * 2.0 - 5.4) ticks of 0.5 µs
    delay_offset_ticks: float = 5.4
    discharge_exchange: bool = True
    chip_select_writes_per_exchange: int = 4
    watchdog_us: float = 300_000.0
    parser_call_us: float = 2.0
    parser_byte_us: float = 1.0
    hv513_detect_us: float = 1000.0

    @property
    def timer_tick_us(self) -> float:
        return 1.0 / self.timer_ticks_per_us

    def delay_ticks(self, us: int) -> int:
        """``delay(us)`` in timer ticks (see :func:`busy_wait_ticks`)."""
        return busy_wait_ticks(us, self.delay_min_us, self.delay_ticks_per_us, self.delay_offset_ticks)

    def busy_wait_us(self, us: int) -> float:
        """How long ``delay(us)`` waits, in µs (about ``us - 2.7``)."""
        return self.delay_ticks(us) / self.timer_ticks_per_us

    def pulse_wait_us(self, width_us: int) -> float:
        """The busy-wait inside a monophasic pulse of ``width_us`` (none below the offset)."""
        arg = pulse_wait_arg(width_us, self.pulse_wait_offset_us)
        return 0.0 if arg is None else self.busy_wait_us(arg)

    def discharge_wait_us(self, discharge_us: int) -> float:
        """The busy-wait with BL low during the discharge (only above the offset)."""
        arg = discharge_wait_arg(discharge_us, self.discharge_wait_offset_us)
        return 0.0 if arg is None else self.busy_wait_us(arg)


_U8_MAX = 255  # electrode_num is a u8
_DAC_MAX = 4095  # 12-bit current DAC


@dataclass(frozen=True, eq=False, kw_only=True)
class FirmwareSpec:
    """One firmware version: its command table, parser rules, link, power-on state and timing.

    Instances are compared and hashed by identity: each version is one module-level value.  The fields
    with defaults are the board's and the chip's (pattern buffer, u8 electrode count, 12-bit DAC, USB
    packet): every version so far shares them, and a version that differs states its own.
    """

    name: str
    commit: str
    commands: tuple[CommandSpec, ...]
    pattern_bytes_per_electrode: int
    rx_queue_bytes: int
    pattern_buffer_size: int = 256
    max_electrodes: int = _U8_MAX
    dac_max_code: int = _DAC_MAX
    usb_packet_bytes: int = 64
    #: v1.2 stores pattern bytes as they arrive; v2 applies a payload only when it is complete.
    partial_payload_applied: bool
    #: v1.2: 0xFE with electrode_num 0 never completes (the parser locks); v2: it completes at once.
    zero_pattern_locks: bool
    #: v1.2 sleeps a tick after every command with a payload; v2 only after a call that made no progress.
    yield_rule: YieldRule
    #: v2: a command not complete this long after its byte was read is discarded with everything queued.
    command_timeout_us: int | None
    #: v2: 0xF5 disables the stimulation timer while it senses the stack and replies.
    hv513_pauses_timer: bool
    power_on: Mapping[str, float | int]
    timing: FirmwareTiming = field(default_factory=FirmwareTiming)
    by_opcode: Mapping[int, CommandSpec] = field(init=False, repr=False)
    #: The lowest command byte: every byte below it is an unknown byte (ignored, one consumed).
    command_byte_min: int = field(init=False, repr=False)
    #: The command that carries the pattern (the one of kind "pattern").
    pattern_command: CommandSpec = field(init=False, repr=False)

    def __deepcopy__(self, memo: dict[int, object]) -> FirmwareSpec:
        """Itself: a version is one module-level value, compared by identity, so a copied emulator still
        runs the same version."""
        return self

    def __post_init__(self) -> None:
        table = {c.opcode: c for c in self.commands}
        if len(table) != len(self.commands):
            raise ConfigurationError(f"firmware {self.name}: an opcode appears twice in its command table")
        object.__setattr__(self, "by_opcode", MappingProxyType(table))
        object.__setattr__(self, "command_byte_min", min(table))
        patterns = [c for c in self.commands if c.kind == "pattern"]
        if len(patterns) != 1:
            raise ConfigurationError(
                f"firmware {self.name}: its command table has {len(patterns)} pattern commands (it needs one)"
            )
        object.__setattr__(self, "pattern_command", patterns[0])
        object.__setattr__(self, "power_on", MappingProxyType(dict(self.power_on)))

    # --- the table, in the shapes callers need --------------------------------------------------------------

    @property
    def payload_kind(self) -> dict[int, str | None]:
        """opcode → "u8", "u16", "pattern" or None (no payload)."""
        return {op: c.kind for op, c in self.by_opcode.items()}

    @property
    def payload_size(self) -> dict[int, int]:
        """opcode → fixed payload bytes (patterns, whose size depends on the electrode count, absent)."""
        return {
            op: KIND_SIZE.get(c.kind, 0) if c.kind else 0
            for op, c in self.by_opcode.items()
            if c.kind != "pattern"
        }

    def size_of(self, opcode: int, electrode_num: int) -> int | None:
        """Payload bytes the firmware reads after ``opcode`` with ``electrode_num`` in force (None: unknown
        byte)."""
        c = self.by_opcode.get(opcode)
        if c is None:
            return None
        if c.kind is None:
            return 0
        if c.kind == "pattern":
            return electrode_num * self.pattern_bytes_per_electrode
        return KIND_SIZE[c.kind]

    def size_table(self) -> dict[int, int]:
        """opcode → payload bytes, -1 for the pattern (its size is the electrode count's, taken when 0xFE
        is read): the shape the emulators' parser loops index."""
        return {
            op: -1 if c.kind == "pattern" else KIND_SIZE.get(c.kind, 0) if c.kind else 0
            for op, c in self.by_opcode.items()
        }

    def command(self, opcode: int) -> CommandSpec:
        try:
            return self.by_opcode[opcode]
        except KeyError:
            raise ConfigurationError(
                f"byte 0x{opcode:02X} is not a command of firmware {self.name} "
                f"(commands: {', '.join(f'0x{op:02X}' for op in sorted(self.by_opcode, reverse=True))})"
            ) from None

    def opcode_of(self, register: str) -> int:
        """The command that sets ``register`` (e.g. "pulse_height"); refuses a register this version lacks."""
        for c in self.commands:
            if c.register == register:
                return c.opcode
        have = sorted(c.register for c in self.commands if c.register)
        raise ConfigurationError(
            f"firmware {self.name} has no command setting {register!r} (it sets: {', '.join(have)})"
        )

    def value_max(self, register: str) -> int:
        """The largest value the firmware can store in ``register`` (its clamp, or the payload's range)."""
        c = self.command(self.opcode_of(register))
        if c.kind == "pattern":
            return self.pattern_level_max()
        top = c.max_value if c.max_value is not None else (1 << (8 * KIND_SIZE[c.kind or "u8"])) - 1
        return top << c.shift

    def reply_bytes(self, opcode: int, electrode_num: int) -> int:
        """How many bytes the firmware writes back for ``opcode`` (0 for commands without a reply)."""
        c = self.by_opcode.get(opcode)
        if c is None or c.reply is None:
            return 0
        if c.reply == "measure":
            return 2 * electrode_num
        return 1

    def sleeps_after(self, opcode: int | None, progressed: bool) -> bool:
        """Whether one parser call ends with a one-tick sleep.  ``opcode`` is the byte the call read as a
        command, or the command in progress it worked on (None: nothing was waiting); ``progressed``
        whether it consumed or wrote a byte.  v1.2 returns at once only after a reply or an unknown byte;
        v2 sleeps only after a call that made no progress."""
        if self.yield_rule == "when_idle":
            return not progressed
        if opcode is None:
            return True
        c = self.by_opcode.get(opcode)
        return c is not None and c.kind is not None

    def has_register(self, register: str) -> bool:
        """Whether a command of this version sets ``register`` (v1.2 has "pulse_height", v2 "stim_mode"):
        what other layers ask instead of comparing version names."""
        return any(c.register == register for c in self.commands)

    def opcode_replying(self, reply: ReplyKind) -> int | None:
        """The command whose answer is ``reply`` ("measure", "hv513", "sync"; None: this version has none)."""
        for c in self.commands:
            if c.reply == reply:
                return c.opcode
        return None

    @property
    def answers_sync_check(self) -> bool:
        """Whether a command answers the electrode count in force (v2's 0xF4)."""
        return self.opcode_replying("sync") is not None

    @property
    def pattern_holds_heights(self) -> bool:
        """Whether each pattern element is that channel's DAC code (v2) rather than a level with one global
        pulse height (v1.2): the table has no pulse-height register."""
        return not self.has_register("pulse_height")

    def pattern_level_max(self) -> int:
        """The largest value one pattern element can hold."""
        c = self.pattern_command
        if c.max_value is not None:
            return c.max_value
        return (1 << (8 * self.pattern_bytes_per_electrode)) - 1


#: The power-on registers both versions initialise alike (each adds the register only it has).
_POWER_ON: Mapping[str, float | int] = MappingProxyType(
    {
        "electrode_num": 0,
        "polarity": 1,
        "pulse_width": 0,
        "sense_pulse_height": 0,
        "sense_pulse_width": 0,
        "discharge_time": 0,
        "period_us": 10_000.0,
    }
)

V1_2 = FirmwareSpec(
    name="v1.2",
    commit="936c6c08",
    commands=(
        CommandSpec(Opcode.MEASURE, "MEASURE", None, reply="measure"),
        CommandSpec(Opcode.PATTERN, "PATTERN", "pattern", register="stim_pattern"),
        CommandSpec(Opcode.POLARITY, "POLARITY", "u8", register="polarity", max_value=1),
        CommandSpec(Opcode.ELECTRODE_NUM, "ELECTRODE_NUM", "u8", register="electrode_num"),
        CommandSpec(Opcode.PULSE_HEIGHT, "PULSE_HEIGHT", "u16", register="pulse_height", max_value=_DAC_MAX),
        CommandSpec(Opcode.PULSE_WIDTH, "PULSE_WIDTH", "u16", register="pulse_width", zero_ignored=True),
        CommandSpec(Opcode.SENSE_HEIGHT, "SENSE_HEIGHT", "u8", register="sense_pulse_height", shift=2),
        CommandSpec(Opcode.SENSE_WIDTH, "SENSE_WIDTH", "u8", register="sense_pulse_width"),
        CommandSpec(Opcode.DISCHARGE, "DISCHARGE", "u8", register="discharge_time"),
        CommandSpec(Opcode.FREQUENCY, "FREQUENCY", "u16", register="frequency", zero_ignored=True),
        CommandSpec(Opcode.HV513_COUNT, "HV513_COUNT", None, reply="hv513"),
    ),
    pattern_bytes_per_electrode=1,
    rx_queue_bytes=256,
    partial_payload_applied=True,
    zero_pattern_locks=True,
    yield_rule="after_payload",
    command_timeout_us=None,
    hv513_pauses_timer=False,
    power_on={**_POWER_ON, "pulse_height": 0},
    timing=FirmwareTiming(discharge_exchange=True, chip_select_writes_per_exchange=4),
)

V2 = FirmwareSpec(
    name="v2",
    commit="71adee21",
    commands=(
        CommandSpec(OpcodeV2.MEASURE, "MEASURE", None, reply="measure"),
        CommandSpec(
            OpcodeV2.PATTERN,
            "PATTERN",
            "pattern",
            register="stim_pattern",
            max_value=_DAC_MAX,
            field="heights",
        ),
        CommandSpec(OpcodeV2.POLARITY, "POLARITY", "u8", register="polarity", max_value=1),
        CommandSpec(OpcodeV2.ELECTRODE_NUM, "ELECTRODE_NUM", "u8", register="electrode_num", max_value=256),
        CommandSpec(OpcodeV2.STIM_MODE, "STIM_MODE", "u8", register="stim_mode", max_value=2),
        CommandSpec(OpcodeV2.PULSE_WIDTH, "PULSE_WIDTH", "u16", register="pulse_width"),
        CommandSpec(OpcodeV2.SENSE_HEIGHT, "SENSE_HEIGHT", "u8", register="sense_pulse_height"),
        CommandSpec(OpcodeV2.SENSE_WIDTH, "SENSE_WIDTH", "u8", register="sense_pulse_width"),
        CommandSpec(OpcodeV2.DISCHARGE, "DISCHARGE", "u8", register="discharge_time"),
        CommandSpec(OpcodeV2.FREQUENCY, "FREQUENCY", "u16", register="frequency", zero_ignored=True),
        CommandSpec(OpcodeV2.HV513_COUNT, "HV513_COUNT", None, reply="hv513"),
        CommandSpec(OpcodeV2.SYNC_CHECK, "SYNC_CHECK", None, reply="sync"),
    ),
    pattern_bytes_per_electrode=2,
    rx_queue_bytes=1024,
    partial_payload_applied=False,
    zero_pattern_locks=False,
    yield_rule="when_idle",
    command_timeout_us=2_000_000,
    hv513_pauses_timer=True,
    power_on={**_POWER_ON, "stim_mode": 0},
    timing=FirmwareTiming(discharge_exchange=False, chip_select_writes_per_exchange=2),
)

#: Every modelled firmware version by name.
FIRMWARES: Mapping[str, FirmwareSpec] = MappingProxyType({"v1.2": V1_2, "v2": V2})
DEFAULT_FIRMWARE = V1_2


def get_firmware(name: str | FirmwareSpec, field_name: str = "firmware") -> FirmwareSpec:
    """The table of firmware ``name``; an unknown name is refused naming the value and the choices."""
    if isinstance(name, FirmwareSpec):
        return name
    spec = FIRMWARES.get(name) if isinstance(name, str) else None
    if spec is None:
        raise ConfigurationError(
            f"{field_name}={name!r} is not a known firmware version (choices: {', '.join(FIRMWARES)})"
        )
    return spec
