"""The interlock: every command the device layer writes, judged as the firmware reads it.

:class:`WireInterlock` is called from ``Device._send``, the single place bytes leave for the transport, and
keeps a shadow of the firmware's registers (:class:`Shadow`).  It refuses a command whose effect would
break a limit of the participant's policy (:class:`~tactdeform_hw.device.safety.guard.SafetyGuard`)
whatever code path produced it, so a future method that forgets the guard is stopped at the wire.  It
judges the firmware's reading of the bytes (:mod:`tactdeform_hw.protocol.reader`, from where the parser
stands), and where the device's queue may be full, every reading a discarded USB packet tail could cause.
What a register in force means for the current a channel receives is the firmware's own
(:data:`~tactdeform_hw.device.safety.readings.READINGS`, one per spec).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

from tactdeform_hw.device.safety.readings import EPS, READINGS
from tactdeform_hw.errors import SafetyError
from tactdeform_hw.protocol.constants import PATTERN_BUFFER_SIZE
from tactdeform_hw.protocol.firmware import DEFAULT_FIRMWARE, FirmwareSpec
from tactdeform_hw.protocol.reader import COMMAND, ParserState, ReadCommand, read_commands
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER, CurrentTransfer

if TYPE_CHECKING:
    from tactdeform_hw.device.participant.mapping import ChannelMapping
    from tactdeform_hw.device.safety.guard import SafetyGuard

#: The interlock follows at most this many states that lost packet tails could leave; beyond it the
#: parser's position counts as unknown (only a resync and an answer from the board bring it back).
MAX_ALTERNATIVES = 32
AT_BOUNDARY = ParserState(None)


@dataclass
class Shadow:
    """What the firmware's registers hold as far as the host can know (None: unknown), and where its
    parser stands (``parse``: a command boundary, a command in progress; None: not known)."""

    electrode_num: int | None = None
    height_code: int | None = None
    sense_code: int | None = None
    polarity: int | None = None
    width_us: int | None = None
    sense_width_us: int | None = None
    pattern: list[int | None] = field(default_factory=lambda: [None] * PATTERN_BUFFER_SIZE)
    parse: ParserState | None = AT_BOUNDARY
    #: How this state could come about when it is not the nominal one (for refusal messages).
    how: str = field(default="", compare=False)
    #: Firmware v2's stimulation mode (v1.2 has none; None: unknown).
    stim_mode: int | None = None

    def copy(self) -> Shadow:
        """A copy whose pattern can be changed without changing this one's.  Every write copies the shadow
        it reads from, so it copies the fields as they stand, whatever they are (``dataclasses.replace``
        costs several times as much), and then the pattern."""
        new = Shadow.__new__(Shadow)
        fields = new.__dict__
        fields.update(self.__dict__)
        fields["pattern"] = self.pattern[:]
        return new

    def key(self) -> tuple[Any, ...]:
        return (
            self.electrode_num,
            self.height_code,
            self.sense_code,
            self.polarity,
            self.width_us,
            self.sense_width_us,
            tuple(self.pattern),
            self.parse,
            self.stim_mode,
        )


class WireState(NamedTuple):
    """What :meth:`WireInterlock.check_wire` concludes a write leads to: the firmware's state if every byte
    arrives (``nominal``), the other states lost packet tails could leave (``alternatives``), and whether
    the device's queue may be full (``unproven``: after a resync's zeros or an unknown state, until the
    board has answered a request)."""

    nominal: Shadow
    alternatives: tuple[Shadow, ...] = ()
    unproven: bool = False


class WireInterlock:
    """The wire layer of the guard: the shadow of the firmware's registers, and the check of each write
    against the limits of ``limits`` (see the module docstring)."""

    def __init__(self, limits: SafetyGuard) -> None:
        self.limits = limits
        #: The firmware version whose reading of the bytes the interlock follows.
        self.firmware: FirmwareSpec = DEFAULT_FIRMWARE
        self._wire = WireState(Shadow())
        self._hw_limits_cache: tuple[Any, ...] | None = None

    def refuse(self, rule: str, message: str, **detail: Any) -> SafetyError:
        """A refusal, recorded in the policy's log (rule ``rule``); the caller raises it."""
        return self.limits.refusal(rule, message, **detail)

    def shadow(self) -> Shadow:
        """A copy of what the interlock believes the firmware holds (if every byte arrived)."""
        return self._wire.nominal.copy()

    @property
    def wire_state(self) -> WireState:
        """Every state the interlock believes the firmware can be in."""
        return self._wire

    def mark_unknown(self) -> None:
        """The firmware's state can no longer be known (a failed write, a reconnect, a reset): registers
        and the parser's position unknown, the device's queue possibly full, until the board answers."""
        self._wire = WireState(Shadow(parse=None), (), True)

    def note_in_step(self, electrode_num: int | None = None) -> None:
        """The board answered a request (0xF5's byte, 0xFF's two bytes per channel) just after the host's
        last write: its parser read that request at a command boundary and its queue holds nothing more.
        Registers on which the possible states disagree become unknown; ``electrode_num`` when the answer
        proved it (a measure reply of two bytes per channel)."""
        states = (self._wire.nominal, *self._wire.alternatives)
        merged = states[0].copy()
        for other in states[1:]:
            for name in (
                "electrode_num",
                "height_code",
                "sense_code",
                "polarity",
                "width_us",
                "sense_width_us",
                "stim_mode",
            ):
                if getattr(other, name) != getattr(merged, name):
                    setattr(merged, name, None)
            merged.pattern = [a if a == b else None for a, b in zip(merged.pattern, other.pattern)]
        if electrode_num is not None:
            merged.electrode_num = electrode_num
        merged.parse = AT_BOUNDARY
        merged.how = ""
        self._wire = WireState(merged, (), False)

    def commit(self, state: WireState) -> bool:
        """Take ``state`` (from :meth:`check_wire`) as the firmware's once its write succeeded; True when
        it differs from the state before (a rewrite of the same registers changes nothing)."""
        changed = state != self._wire
        self._wire = state
        return changed

    def hw_limits(self, mapping: ChannelMapping | None, num: int) -> tuple[tuple[int, ...], int]:
        """Each hardware channel's limit, and the lowest of them."""
        # the key holds the mapping itself (compared by value), never its id: an id can be reused
        lim = self.limits
        key = (mapping, num, lim.cap_ua, lim.regions_ua, lim.region_of, lim.channels)
        cached = self._hw_limits_cache
        if cached is not None and cached[0] == key:
            return cached[1], cached[2]
        if mapping is None:
            limits = tuple(self.limits.electrode_limits(num))
        else:
            app = self.limits.electrode_limits(mapping.electrodes)
            hw = [0] * num  # a hardware channel no electrode maps to must never stimulate
            for i, ch in enumerate(mapping.app_to_hw):
                if ch < num:
                    hw[ch] = app[i]
            limits = tuple(hw)
        if lim.channels is not None:
            # the calibrated limit belongs to the hardware channel the electrode was calibrated on: bound each
            # channel by it directly, whatever mapping the bytes were built with
            cal = lim.channels
            limits = tuple(min(v, cal.channel_limit_ua(ch)) for ch, v in enumerate(limits))
        low = min(limits, default=0)
        self._hw_limits_cache = (key, limits, low)
        return limits, low

    def check_wire(
        self,
        data: bytes,
        *,
        mapping: ChannelMapping | None = None,
        transfer: CurrentTransfer = DEFAULT_TRANSFER,
        room: int | None = None,
    ) -> WireState:
        """Refuse a write whose effect on the firmware would break a limit; return the states it leads to
        (commit them with :meth:`commit` once the write succeeded).

        The write is judged as the firmware reads it (:func:`~tactdeform_hw.protocol.reader.read_commands`,
        from where its parser stands), in every state the interlock follows, and — where the device's
        queue may be full — as it would be read if a USB packet of it lost its tail.  ``room`` is how many
        bytes of this write the caller's worst-case queue model is certain the device accepts (None: the
        whole write); while the queue may be full (``unproven``: after a resync's zeros or an unknown state,
        until :meth:`note_in_step`) no byte is certain.  Bytes that are not commands and requests the board
        answers are always allowed: they are how the driver makes an unknown state safe and proves it.
        Everything else must leave every state within every limit, unknown registers counting as their
        worst case.
        """
        data = bytes(data)
        wire = self._wire
        cmin = self.firmware.command_byte_min
        if data and data[0] < cmin:
            # A resync: the host no longer trusts its picture of the firmware.  Enough non-command bytes to
            # fill the longest payload finish any command in progress, so the parser ends at a command
            # boundary (a locked one reads nothing more at all); the registers are unknown; and the zeros
            # may fill the device's queue, so every later write may lose packet tails until the board has
            # answered a request (note_in_step).
            run = 0
            while run < len(data) and data[run] < cmin:
                run += 1
            longest = self.firmware.max_electrodes * self.firmware.pattern_bytes_per_electrode
            self._wire = WireState(Shadow(parse=AT_BOUNDARY if run >= longest else None), (), True)
            try:
                return (
                    self.check_wire(data[run:], mapping=mapping, transfer=transfer, room=room)
                    if run < len(data)
                    else self._wire
                )
            finally:
                self._wire = wire
        cut_from = 0 if wire.unproven else room
        if not wire.alternatives and (cut_from is None or cut_from >= len(data)):
            # the per-frame path: one state, every byte certain to arrive
            return WireState(
                self._read(wire.nominal, data, mapping, transfer, strict=True, how=""), (), wire.unproven
            )
        nominal: Shadow | None = None
        seen: dict[tuple[Any, ...], Shadow] = {}
        for i, state in enumerate((wire.nominal, *wire.alternatives)):
            result = self._read(state, data, mapping, transfer, strict=i == 0, how=state.how)
            if i == 0:
                nominal = result
            else:
                seen.setdefault(result.key(), result)
            if cut_from is not None and cut_from < len(data):
                for lost, kept in tail_losses(data, max(0, cut_from), self.firmware.usb_packet_bytes):
                    how = (
                        f"bytes {lost[0]}-{lost[1] - 1} of a {len(data)}-byte write discarded by a full "
                        "device queue"
                    )
                    if state.how:
                        how = f"{state.how}; then {how}"
                    alt = self._read(state, kept, mapping, transfer, strict=False, how=how)
                    seen.setdefault(alt.key(), alt)
        assert nominal is not None
        seen.pop(nominal.key(), None)
        alternatives = tuple(seen.values())
        if len(alternatives) > MAX_ALTERNATIVES:
            alternatives = (Shadow(parse=None, how="too many possible losses to follow"),)
        return WireState(nominal, alternatives, wire.unproven)

    def _read_unknown(self, data: bytes) -> None:
        """From an unknown parser position only bytes that cannot complete a current-carrying value are
        allowed: non-command bytes and the requests the board answers (the probe that proves a resync)."""
        table = self.firmware.by_opcode
        for i, b in enumerate(data):
            spec = table.get(b)
            if spec is not None and spec.kind is not None:
                raise self.refuse(
                    "interlock",
                    f"command 0x{b:02X} at byte {i} while the firmware's state is unknown (its parser may be "
                    "in the middle of a command, whose value these bytes could complete; its electrode "
                    "count is unknown): resync and let the board answer first",
                )

    def _read(
        self,
        sh0: Shadow,
        data: bytes,
        mapping: ChannelMapping | None,
        transfer: CurrentTransfer,
        *,
        strict: bool,
        how: str,
    ) -> Shadow:
        """The state ``data`` leads to from ``sh0``; refuses if any limit breaks on the way.  ``strict``
        (the nominal reading): the write must also end at a command boundary and never lock the parser."""
        sh = sh0.copy()
        sh.how = how
        pos = sh.parse
        if pos is None:
            self._read_unknown(data)
            return sh
        fw = self.firmware
        if pos.opcode is not None or pos.locked:
            start: ParserState | None = ParserState(
                sh.electrode_num, pos.opcode, pos.needed, pos.got, pos.locked
            )
        else:
            start = None
        reading = read_commands(data, sh.electrode_num, fw, start)
        end = reading.state
        if strict and not end.at_boundary:
            self._refuse_open_end(reading.commands, end)
        table = fw.by_opcode
        channels = READINGS[fw]
        when = f" (if {how})" if how else ""
        for c in reading.commands:
            if c.kind != COMMAND or c.opcode is None:
                continue
            spec = table[c.opcode]
            kind = spec.kind
            if kind is None:
                continue
            if kind == "pattern":
                levels = c.levels
                if levels:
                    channels.check_pattern_ramp(self, sh.pattern, levels, c.start, "pattern" + when, transfer)
                if levels:
                    sh.pattern[c.start : c.start + len(levels)] = levels
                    if any(levels):
                        self._verify(sh, "pattern" + when, mapping, transfer)
                continue
            if not c.complete:
                continue
            self._apply(sh, spec.register, c, when, mapping, transfer)
        if end.needed < 0:
            sh.parse = None  # a pattern whose length nobody knows: the position is lost
        elif end.at_boundary:
            sh.parse = AT_BOUNDARY
        else:
            sh.parse = ParserState(None, end.opcode, end.needed, end.got, end.locked)
        return sh

    def _refuse_open_end(self, commands: Sequence[ReadCommand], end: ParserState) -> None:
        last = commands[-1] if commands else None
        name = f"0x{end.opcode:02X}" if end.opcode is not None else "?"
        if end.locked:
            raise self.refuse("interlock", "pattern with electrode count 0 would lock the firmware's parser")
        if end.needed < 0:
            raise self.refuse(
                "interlock", "pattern while the firmware's electrode count is unknown (resync first)"
            )
        if end.opcode is not None and self.firmware.by_opcode[end.opcode].kind == "pattern":
            num = end.needed // self.firmware.pattern_bytes_per_electrode
            raise self.refuse(
                "interlock",
                f"pattern of {len(end.got)} byte(s) for electrode count {num} would desynchronise",
            )
        got = len(last.payload) if last is not None else 0
        raise self.refuse("interlock", f"command {name} cut short ({got} of {end.needed} payload bytes)")

    def _apply(
        self,
        sh: Shadow,
        register: str | None,
        c: ReadCommand,
        when: str,
        mapping: ChannelMapping | None,
        transfer: CurrentTransfer,
    ) -> None:
        value = c.value
        if register == "pulse_height":
            assert value is not None
            before = sh.height_code
            sh.height_code = value
            if value:
                prev_ua = transfer.to_ua(before) if before is not None else 0.0
                new_ua = transfer.to_ua(value)
                if (
                    self.limits.ramp_ua_per_frame is not None
                    and new_ua > prev_ua + self.limits.ramp_ua_per_frame + EPS
                ):
                    raise self.refuse(
                        "interlock",
                        f"pulse height {new_ua:g} µA{when} rises more than "
                        f"{self.limits.ramp_ua_per_frame} µA above {prev_ua:g} µA",
                    )
                self._verify(sh, "pulse height" + when, mapping, transfer)
        elif register == "stim_mode":
            sh.stim_mode = value
            self._verify(sh, "stimulation mode" + when, mapping, transfer)
        elif register == "sense_pulse_height":
            sh.sense_code = value
            if value:
                self._verify(sh, "sense height" + when, mapping, transfer)
        elif register == "polarity":
            if sh.polarity != value and self._current_can_flow(sh):
                raise self.refuse(
                    "polarity_change",
                    f"polarity change{when} while current can flow (pulse height and an active channel, or a "
                    "sense current); switch everything off first",
                )
            sh.polarity = value
        elif register == "electrode_num":
            sh.electrode_num = value
            self._verify(sh, "electrode count" + when, mapping, transfer)
        elif register == "pulse_width":
            if value is not None:
                sh.width_us = value
            self._verify(sh, "pulse width" + when, mapping, transfer)
        elif register == "sense_pulse_width":
            sh.sense_width_us = value
            self._verify(sh, "sense width" + when, mapping, transfer)
        # discharge and frequency carry no current

    def _current_can_flow(self, sh: Shadow) -> bool:
        return READINGS[self.firmware].current_can_flow(sh)

    def _verify(
        self, sh: Shadow, what: str, mapping: ChannelMapping | None, transfer: CurrentTransfer
    ) -> None:
        """Every channel the firmware scans receives at most its limit; unknowns count as their worst."""
        READINGS[self.firmware].verify(self, sh, what, mapping, transfer)


def tail_losses(data: bytes, first: int, packet: int) -> list[tuple[tuple[int, int], bytes]]:
    """What a full device queue can leave of ``data`` (cut by the host into ``packet``-byte USB packets)
    when it may discard from byte ``first`` on: for each byte ``j`` from there, the rest of its packet
    lost, or everything from ``j`` on lost (the queue stayed full).  Each entry: (lost range, bytes kept)."""
    out: list[tuple[tuple[int, int], bytes]] = []
    n = len(data)
    for j in range(first, n):
        end = min(n, (j // packet + 1) * packet)
        out.append(((j, end), data[:j] + data[end:]))
        if end < n:
            out.append(((j, n), data[:j]))
    return out


__all__ = ["AT_BOUNDARY", "MAX_ALTERNATIVES", "Shadow", "WireInterlock", "WireState", "tail_losses"]
