"""Property tests: arbitrary streams never break the emulator or the decoder; encoders round-trip."""

from __future__ import annotations

from hypothesis import assume, given, settings
from hypothesis import strategies as st

from tactdeform_hw.emulator import Emulator
from tactdeform_hw.protocol import commands as c
from tactdeform_hw.protocol.constants import Opcode
from tactdeform_hw.protocol.decoder import OK, decode

# Streams biased toward command bytes so that the interesting paths (locks, truncation) are reached.
byte = st.one_of(st.integers(0xF5, 0xFF), st.integers(0, 3), st.integers(0, 255))
streams = st.lists(byte, max_size=400).map(bytes)


@settings(max_examples=300, deadline=None)
@given(data=streams, cuts=st.lists(st.integers(0, 400), max_size=20))
def test_any_split_reaches_the_same_state(data: bytes, cuts: list[int]) -> None:
    whole = Emulator()
    tx_whole = whole.feed(data)
    split = Emulator()
    points = sorted({min(c, len(data)) for c in cuts} | {0, len(data)})
    tx_split = b"".join(split.feed(data[a:b]) for a, b in zip(points, points[1:]))
    assert split.state() == whole.state()
    assert tx_split == tx_whole


@settings(max_examples=200, deadline=None)
@given(data=streams)
def test_call_by_call_equals_fast_path(data: bytes) -> None:
    fast = Emulator()
    tx = fast.feed(data)
    slow = Emulator()
    slow.parser.receive(data)
    for _ in range(len(data) + 2):
        if slow.parser.step().name in ("IDLE", "LOCKED", "STUCK_U16"):
            break
    assert slow.state() == fast.state()
    assert slow.parser.take_tx() == tx


@settings(max_examples=200, deadline=None)
@given(data=streams)
def test_decoder_never_raises_and_accounts_for_every_byte(data: bytes) -> None:
    items = decode(data)
    assert b"".join(i.raw for i in items) == data


u8_ops = st.sampled_from([Opcode.ELECTRODE_NUM, Opcode.SENSE_HEIGHT, Opcode.SENSE_WIDTH, Opcode.DISCHARGE])
u16_ops = st.sampled_from([Opcode.PULSE_HEIGHT, Opcode.PULSE_WIDTH, Opcode.FREQUENCY])


@settings(max_examples=200, deadline=None)
@given(op=u8_ops, value=st.integers(0, 255))
def test_u8_round_trip(op: Opcode, value: int) -> None:
    data = c.build(op, value)
    (item,) = decode(data)
    assert item.status == OK and item.opcode == op and item.value == value
    assert c.parse(data)["value"] == value


@settings(max_examples=200, deadline=None)
@given(op=u16_ops, value=st.integers(1, 65535))
def test_u16_round_trip(op: Opcode, value: int) -> None:
    data = c.build(op, value, use_compiled=True)
    (item,) = decode(data)
    assert item.status == OK and item.value == value


@settings(max_examples=100, deadline=None)
@given(levels=st.lists(st.integers(0, 255), min_size=1, max_size=255))
def test_pattern_round_trip(levels: list[int]) -> None:
    data = c.encode_pattern(levels)
    items = decode(c.encode_electrode_num(len(levels)) + data)
    assert items[1].status == OK and list(items[1].value) == levels  # type: ignore[arg-type]
    emu = Emulator()
    emu.feed(c.encode_electrode_num(len(levels)) + data)
    assert list(emu.state().stim_pattern[: len(levels)]) == levels


@settings(max_examples=50, deadline=None)
@given(polarity=st.integers(0, 1))
def test_polarity_round_trip(polarity: int) -> None:
    (item,) = decode(c.encode_polarity(polarity))
    assert item.value == polarity


@settings(max_examples=300, deadline=None)
@given(prefix=streams, waiting=streams)
def test_the_parsers_plan_is_what_its_call_does(prefix: bytes, waiting: bytes) -> None:
    """From any state (reached by ``prefix``), ``plan(waiting)`` says how many waiting bytes the next
    call reads and how it ends: the call on all of them ends so and reads that many, and the call on
    exactly those bytes (what the timed model hands over) ends the same, a spin on a half u16 aside."""
    from copy import deepcopy

    from tactdeform_hw.emulator import CallResult

    emu = Emulator()
    emu.feed(prefix)
    # the plan's premise: what waits is not yet handed over
    assume(emu.parser.pending == 0 or emu.parser.locked)
    n, outcome = emu.parser.plan(waiting)
    whole, part = deepcopy(emu.parser), deepcopy(emu.parser)
    whole.receive(waiting)
    before = whole.offset
    assert whole.step() is outcome and whole.offset - before == n
    part.receive(waiting[:n])
    assert part.step() is (CallResult.PROGRESS if outcome is CallResult.STUCK_U16 else outcome)
    assert part.pending == 0 or part.locked
