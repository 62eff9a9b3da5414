"""The interlock judges what the firmware reads when the device's full queue discards the tail of a USB
packet: the next command's bytes become the cut command's value."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from tactdeform_hw import protocol as p
from tactdeform_hw.device import EtactileKitDevice, StimConfig
from tactdeform_hw.device.safety.guard import SafetyGuard
from tactdeform_hw.device.safety.interlock import Shadow, WireState, tail_losses
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.errors import SafetyError
from tactdeform_hw.protocol.units import CurrentTransfer

from .safety_helpers import RecordingPort

ON = [1, 1, 0, 0]


def stimulating(guard: SafetyGuard, height_ua: int = 1000) -> None:
    """Bring the guard's picture to four channels, two of them on at ``height_ua``."""
    for cmd in (
        p.encode_pulse_height(0),
        p.encode_sense_height(0),
        p.encode_pulse_width(200),
        p.encode_electrode_num(4),
        p.encode_pattern(ON),
        p.encode_pulse_height(height_ua // 10),
    ):
        guard.commit(guard.interlock.check_wire(cmd))


def test_the_old_resync_order_is_refused_while_the_queue_may_be_full() -> None:
    """256 zeros may fill the queue; `fb 00 00` may then lose its last byte (or two), and the sense height
    that follows is read as its value: 0xF900 → 4095 (or 0x00F9 = 249), with the old pattern in force."""
    guard = SafetyGuard(cap_ua=2000)
    stimulating(guard)
    guard.commit(guard.interlock.check_wire(bytes(256)))
    assert guard.wire_state.unproven
    # cut or not, it cannot raise a current
    guard.commit(guard.interlock.check_wire(p.encode_pulse_height(0)))
    assert len(guard.wire_state.alternatives) == 3  # `fb` alone, `fb 00`, or the whole packet lost
    with pytest.raises(
        SafetyError,
        match=r"\(if bytes 1-2 of a 3-byte write discarded by a full device queue\): pulse height 2490 µA",
    ):
        guard.interlock.check_wire(p.encode_sense_height(0))
    # with everything else known, the other reading: `fb 00` + `f9` → 0xF900, clamped to 4095
    guard = SafetyGuard(cap_ua=5000)
    stimulating(guard)
    guard.commit(guard.interlock.check_wire(p.encode_pulse_height(0), room=2))
    with pytest.raises(
        SafetyError,
        match=r"\(if bytes 2-2 of a 3-byte write discarded by a full device queue\): pulse height 40950 µA",
    ):
        guard.interlock.check_wire(p.encode_sense_height(0))
    # what the interlock predicts is what the firmware does with those bytes
    emu = Emulator()
    emu.feed(p.encode_electrode_num(4) + p.encode_pattern(ON) + b"\xfb\x00" + p.encode_sense_height(0))
    assert emu.state().pulse_height == 4095


def test_once_the_board_has_answered_the_same_order_is_allowed() -> None:
    guard = SafetyGuard(cap_ua=2000)
    stimulating(guard)
    guard.commit(guard.interlock.check_wire(bytes(256)))
    guard.commit(guard.interlock.check_wire(p.HV513_COUNT_REQUEST))
    guard.note_in_step()  # its reply came: the parser read it at a boundary, nothing waits behind it
    assert guard.wire_state == WireState(guard.wire_state.nominal) and not guard.wire_state.unproven
    for cmd in (
        p.encode_pulse_height(0),
        p.encode_sense_height(0),
        p.encode_electrode_num(4),
        p.encode_pattern([0] * 4),
    ):
        guard.commit(guard.interlock.check_wire(cmd))
    assert guard.wire_state.alternatives == ()


def test_a_cut_height_makes_the_next_pattern_refused() -> None:
    """With ``room`` from the caller's queue model: `fb 64 00` may keep only `fb 64`; the next pattern's
    0xFE is then read as the high byte (0xFE64 → 4095) while two channels are on."""
    guard = SafetyGuard(cap_ua=2000)
    stimulating(guard)
    guard.commit(guard.interlock.check_wire(p.encode_pulse_height(100), room=2))
    assert {a.parse.opcode for a in guard.wire_state.alternatives if a.parse} == {0xFB}
    with pytest.raises(SafetyError, match="40950 µA"):
        guard.interlock.check_wire(p.encode_pattern([1, 0, 0, 0]))
    # the same write with room for all of it leaves no doubt
    guard = SafetyGuard(cap_ua=2000)
    stimulating(guard)
    guard.commit(guard.interlock.check_wire(p.encode_pulse_height(100), room=3))
    guard.commit(guard.interlock.check_wire(p.encode_pattern([1, 0, 0, 0])))
    assert guard.wire_state.alternatives == ()


def test_a_cut_pattern_turns_the_next_command_into_channel_levels() -> None:
    """v1.2 stores pattern bytes as they arrive: a pattern cut after its first level takes the next
    command's bytes as the following channels' levels — a discharge time of 1 switches channel 2 on, at
    the height in force, above its region's limit."""
    guard = SafetyGuard(cap_ua=2000, regions_ua=(2000, 50), region_of=(0, 0, 1, 1))
    stimulating(guard, 1000)
    guard.commit(guard.interlock.check_wire(p.encode_pattern([1, 0, 0, 0]), room=2))
    with pytest.raises(SafetyError, match="channel 2 would receive 1000 µA, above its limit of 50"):
        guard.interlock.check_wire(p.encode_discharge(1))
    emu = Emulator()
    emu.feed(p.encode_electrode_num(4) + b"\xfe\x01" + p.encode_discharge(1))
    assert list(emu.state().stim_pattern[:4]) == [1, 0xF7, 1, 0]


def test_an_unknown_parser_position_allows_only_zeros_and_requests() -> None:
    guard = SafetyGuard()
    guard.mark_unknown()
    with pytest.raises(SafetyError, match="electrode count is unknown"):
        guard.interlock.check_wire(p.encode_pulse_height(0))
    guard.interlock.check_wire(b"\x00\x13")
    guard.interlock.check_wire(p.HV513_COUNT_REQUEST)
    guard.interlock.check_wire(p.MEASURE_REQUEST)
    # fewer zeros than the longest payload cannot finish a pattern in progress
    guard.commit(guard.interlock.check_wire(bytes(200)))
    assert guard.wire_state.nominal.parse is None
    guard.commit(guard.interlock.check_wire(bytes(256)))
    assert guard.wire_state.nominal.parse is not None and guard.wire_state.unproven


def test_tail_losses_follow_the_usb_packets() -> None:
    data = bytes(range(130))
    losses = dict(tail_losses(data, 10, 64))
    assert losses[(10, 64)] == data[:10] + data[64:]  # the rest of the first packet
    assert losses[(10, 130)] == data[:10]  # and the queue stayed full for the later packets
    assert losses[(70, 128)] == data[:70] + data[128:]
    assert losses[(129, 130)] == data[:129]
    assert min(j for j, _ in losses) == 10


def test_a_resync_sends_no_value_until_the_board_answers() -> None:
    port = RecordingPort()
    dev = EtactileKitDevice(port, guard=SafetyGuard())
    dev.configure(StimConfig(current_ua=400))
    dev.send_pattern([1] * 32)
    port.emulator.feed(b"\xfc\x00\xfe")  # a locked parser reads nothing, answers nothing
    n = len(port.writes)
    resets: list[int] = []
    pulse = dev.port_link.reset

    def counted() -> bool:
        resets.append(len(port.writes))
        return pulse()

    dev.port_link.reset = counted  # type: ignore[method-assign]
    dev.resync()
    # until the reset line freed the parser, only zeros and requests went out: nothing that carries a value
    assert resets, "a parser that never answers gets the reset line"
    before = b"".join(port.writes[n : resets[0]])
    assert before and set(before) <= {0, p.HV513_COUNT_REQUEST[0], p.MEASURE_REQUEST[0]}
    assert not dev.needs_resync and dev.probe()
    dev.close()


def test_steady_frames_keep_a_single_state() -> None:
    """Without doubt about the queue the interlock follows one state: the per-frame path stays cheap."""
    port = RecordingPort()
    dev = EtactileKitDevice(port, guard=SafetyGuard())
    dev.configure(StimConfig(current_ua=400))
    for k in range(10):
        dev.send_pattern([1 if (i + k) % 3 == 0 else 0 for i in range(32)])
    state = dev.guard.wire_state
    assert state.alternatives == () and not state.unproven
    dev.close()


# --- the loss model against the firmware's own parser ---------------------------------------------------

ONE_UA_PER_CODE = CurrentTransfer(ua_per_code=1.0)  # 4095 codes stay under the 10 mA ceiling: nothing refused


def _command(draw: st.DrawFn, n: int) -> bytes:
    kind = draw(st.sampled_from(["height", "sense", "width", "sense_width", "count", "pattern", "discharge"]))
    if kind == "height":
        return p.encode_pulse_height(draw(st.integers(0, 600)))
    if kind == "sense":
        return p.encode_sense_height(draw(st.integers(0, 60)))
    if kind == "width":
        return p.encode_pulse_width(draw(st.integers(1, 300)))
    if kind == "sense_width":
        return p.encode_sense_width(draw(st.integers(0, 100)))
    if kind == "count":
        return p.encode_electrode_num(draw(st.sampled_from([1, 3, 8, n])))
    if kind == "discharge":
        return p.encode_discharge(draw(st.integers(0, 60)))
    return p.encode_pattern(draw(st.lists(st.integers(0, 3), min_size=n, max_size=n)), electrode_num=n)


def _matches(s: Shadow, emu: Emulator) -> bool:
    """The firmware's registers agree with every register the interlock's state claims to know."""
    regs = emu.state()
    pairs = [
        (s.electrode_num, regs.electrode_num),
        (s.height_code, regs.pulse_height),
        (s.sense_code, regs.sense_pulse_height),
        (s.width_us, regs.pulse_width_us),
        (s.sense_width_us, regs.sense_pulse_width_us),
        (s.polarity, regs.polarity),
    ]
    if any(mine is not None and mine != theirs for mine, theirs in pairs):
        return False
    if any(mine is not None and mine != theirs for mine, theirs in zip(s.pattern, regs.stim_pattern)):
        return False
    return s.parse is None or s.parse.opcode == emu.parser.cmd


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(data=st.data())
def test_every_state_a_lost_tail_leaves_is_foreseen(data: st.DataObject) -> None:
    """Whatever tail of a write a full queue discards, the firmware ends in one of the interlock's states,
    and stays in one of them through the next write."""
    guard = SafetyGuard(max_charge_nc=1e9)
    emu = Emulator()
    count = data.draw(st.sampled_from([8, 70]))  # 70: a pattern of two USB packets
    setup = (
        p.encode_pulse_height(0),
        p.encode_sense_height(0),
        p.encode_polarity(1),
        p.encode_pulse_width(100),
        p.encode_sense_width(50),
        p.encode_electrode_num(count),
        p.encode_pattern(([1, 0, 2, 0, 0, 1, 0, 0] * 9)[:count]),
        p.encode_pulse_height(100),
    )
    for cmd in setup:
        guard.commit(guard.interlock.check_wire(cmd, transfer=ONE_UA_PER_CODE))
        emu.feed(cmd)
    first = data.draw(st.composite(lambda d: _command(d, count))())
    try:
        state = guard.interlock.check_wire(first, transfer=ONE_UA_PER_CODE, room=0)
    except SafetyError:
        assume(False)
    guard.commit(state)
    j = data.draw(st.integers(0, len(first) - 1))
    kept = first[:j] + (first[min(len(first), (j // 64 + 1) * 64) :] if data.draw(st.booleans()) else b"")
    emu.feed(kept)
    assert any(_matches(s, emu) for s in (state.nominal, *state.alternatives))
    n = state.nominal.electrode_num or 1
    second = data.draw(st.composite(lambda d: _command(d, n))())
    try:
        state = guard.interlock.check_wire(second, transfer=ONE_UA_PER_CODE)
    except SafetyError:
        assume(False)
    guard.commit(state)
    emu.feed(second)
    assert any(_matches(s, emu) for s in (state.nominal, *state.alternatives))


def test_all_off_on_a_board_that_does_not_answer_says_so() -> None:
    from tactdeform_hw.errors import ShortReplyError

    port = RecordingPort()
    dev = EtactileKitDevice(port, guard=SafetyGuard())
    dev.configure(StimConfig(current_ua=400))
    dev.send_pattern([1] * 32)
    port.emulator.feed(b"\xfc\x00\xfe")  # something locked the parser
    assert not dev.probe() and dev.needs_resync
    can_reset = dev.port_link.can_reset
    dev.port_link.can_reset = lambda: False  # type: ignore[method-assign]  # a transport without a reset line
    n = len(port.writes)
    with pytest.raises(ShortReplyError, match="after resync zeros"):
        dev.all_off()
    assert set(b"".join(port.writes[n:])) <= {0, p.HV513_COUNT_REQUEST[0], p.MEASURE_REQUEST[0]}
    dev.port_link.can_reset = can_reset  # type: ignore[method-assign]
    assert dev.hardware_reset() and dev.probe()
    dev.close()
