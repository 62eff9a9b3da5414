"""A UART's bytes delivered as bursts: the timed models see exactly what one delivery per byte gives.

A UART delivers each byte on its own (:meth:`UartLink.schedule`); the timed models take a write's bytes as
one :class:`ByteBurst` and move at once the bytes that arrive before anything else happens.  These tests
hold that to exactness: the same random host traffic (commands, runs of zeros, noise, replies asked for,
reboots with bytes in flight, a main loop that stops reading so the queue overflows, a locked v1.2 parser)
through a plain UART and through a filter that passes every byte on its own must leave both models with
the same books -- every hazard, command report, loss, scan and pulse, every reply byte at the same time.
"""

from __future__ import annotations

import random
from typing import Any

import pytest

from tactdeform_hw.emulator.faults import Fault, FaultKind, FaultyLink
from tactdeform_hw.emulator.timed.link import (
    ByteBurst,
    Delivery,
    LinkFilter,
    LinkModel,
    UartLink,
    UsbFsLink,
    expanded,
)
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2
from tactdeform_hw.emulator.timed.timing import TimingModel
from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.protocol.commands import V1_2_COMMANDS as C1
from tactdeform_hw.protocol.commands import V2_COMMANDS as C2


class OneByOne(LinkFilter):
    """The wrapped link's deliveries unchanged, one per byte: the event-per-byte path of the models."""


def test_a_burst_is_the_deliveries_a_uart_schedules() -> None:
    rng = random.Random(5)
    one, burst = UartLink(), UartLink()
    t = 0
    for _ in range(200):
        data = bytes(rng.randrange(256) for _ in range(rng.randint(1, 40)))
        t += rng.choice((0, 1, 10_000, 500_000))
        off = rng.choice((-1, rng.randrange(10_000)))
        want = one.schedule(data, t, off)
        got = burst.schedule_bursts(data, t, off)
        assert len(got) == 1 and isinstance(got[0], ByteBurst)
        assert expanded(got[0]) == want
    assert UartLink().schedule_bursts(b"", 0) == []
    with pytest.raises(ConfigurationError, match="one arrival time per byte"):
        ByteBurst(b"ab", [1], 0, 0)


def test_a_burst_gives_its_bytes_in_order_and_says_what_is_still_on_its_way() -> None:
    b = UartLink(baud=1_000_000).schedule_bursts(b"abcdef", 1000, 7)[0]
    assert isinstance(b, ByteBurst)
    assert b.times == [11_000, 21_000, 31_000, 41_000, 51_000, 61_000]
    assert (b.t_ns, b.data, b.host_offset, len(b)) == (11_000, b"abcdef", 7, 6)
    assert b.pop() == Delivery(11_000, b"a", 7, 1000)
    assert b.end_before(40_999) == 3  # up to the byte arriving at 31 µs
    # another queued entry at 31 µs: a later sequence number comes after this burst's byte there, an
    # earlier one before it
    assert b.end_before(60_000, (31_000, 9), seq=4) == 3
    assert b.end_before(60_000, (31_000, 2), seq=4) == 2
    assert b.host_offsets(3) == range(8, 10)
    assert b.take(3) == b"bc"
    assert (b.t_ns, b.data, b.host_offset, len(b)) == (41_000, b"def", 10, 3)
    assert b.deliveries() == [
        Delivery(t, bytes([v]), h, 1000) for t, v, h in zip(b.times[3:], b"def", (10, 11, 12))
    ]


@pytest.mark.parametrize("seed", range(6))
def test_a_faulty_link_lets_a_burst_through_only_where_no_byte_would_change(seed: int) -> None:
    """Faults due, delayed chunks still ahead: the bytes as :meth:`FaultyLink.schedule` gives them."""
    rng = random.Random(seed)
    kinds = [FaultKind.DROP, FaultKind.CORRUPT, FaultKind.DUPLICATE, FaultKind.DELAY]
    faults = [
        Fault(rng.choice(kinds), rng.uniform(0.0, 0.05), count=rng.choice((1, 2)), delay_s=0.002)
        for _ in range(4)
    ]
    one = FaultyLink(UartLink(), faults, seed=seed)
    burst = FaultyLink(UartLink(), faults, seed=seed)
    t, off = 0, 0
    for _ in range(60):
        data = bytes(rng.randrange(256) for _ in range(rng.randint(1, 30)))
        t += rng.choice((0, 100_000, 1_000_000, 3_000_000))
        want = one.schedule(data, t, off)
        got = [d for item in burst.schedule_bursts(data, t, off) for d in expanded(item)]
        assert got == want
        off += len(data)
    assert burst.injected == one.injected and one.injected


# --- the models: the same books either way ---------------------------------------------------------------


def _piece_v1_2(rng: random.Random, n: int) -> tuple[bytes, int]:
    k = rng.randrange(12)
    if k == 0:
        n = rng.choice((0, 1, 8, 32, 64, 200))
        return C1.encode_electrode_num(n), n
    if k in (1, 2):
        return C1.encode_pattern([rng.randrange(4) for _ in range(n)]) if n else bytes((0xFE,)), n
    if k == 3:
        return C1.encode_pulse_width(rng.choice((20, 100, 250))), n
    if k == 4:
        return C1.encode_frequency(rng.choice((50, 125, 400, 2000))), n
    if k == 5:
        return C1.encode_pulse_height(rng.randrange(0, 4096)), n
    if k == 6:
        return C1.MEASURE_REQUEST, n
    if k == 7:
        return C1.HV513_COUNT_REQUEST, n
    if k == 8:
        return bytes(rng.randint(1, 600)), n
    if k == 9:
        return bytes(rng.randrange(256) for _ in range(rng.randint(1, 80))), n
    if k == 10:
        return C1.encode_sense_height(rng.randrange(0, 64)) + C1.encode_discharge(rng.randrange(0, 100)), n
    return C1.encode_polarity(rng.randrange(2)), n


def _piece_v2(rng: random.Random, n: int) -> tuple[bytes, int]:
    k = rng.randrange(12)
    if k == 0:
        n = rng.choice((0, 1, 8, 32, 100, 255))
        return C2.encode_electrode_num(n), n
    if k in (1, 2):
        return C2.encode_pattern([rng.randrange(0, 300) for _ in range(n)]), n
    if k == 3:
        return C2.encode_pulse_width(rng.choice((20, 100, 250))), n
    if k == 4:
        return C2.encode_frequency(rng.choice((50, 125, 400, 2000))), n
    if k == 5:
        return C2.encode_stim_mode(rng.randrange(3)), n
    if k == 6:
        return C2.MEASURE_REQUEST, n
    if k == 7:
        return bytes((0xF4,)) if rng.random() < 0.5 else C2.HV513_COUNT_REQUEST, n
    if k == 8:
        return bytes(rng.randint(1, 1200)), n
    if k == 9:
        return bytes(rng.randrange(256) for _ in range(rng.randint(1, 80))), n
    if k == 10:
        return C2.encode_sense_height(rng.randrange(0, 64)) + C2.encode_discharge(rng.randrange(0, 100)), n
    return bytes((0xFE,)) + bytes(rng.randint(0, 40)), n  # a pattern cut short


def _drive(emu: Any, seed: int, firmware: str) -> list[Any]:
    """Random host traffic on ``emu``; what a host and a judge could see at every step."""
    rng = random.Random(seed)
    piece = _piece_v1_2 if firmware == "v1.2" else _piece_v2
    seen: list[Any] = []
    n = 0
    last_write = 0.0
    for _ in range(70):
        k = rng.random()
        if k < 0.5:
            data, n = piece(rng, n)
            at = max(emu.now_us, last_write) + rng.choice((0.0, 0.0, 3.0, 250.0, 1500.0))
            emu.write(data, at)
            last_write = at
        elif k < 0.85:
            emu.advance_to(emu.now_us + rng.choice((5.0, 40.0, 300.0, 1000.0, 4000.0, 30_000.0)))
        elif k < 0.93:
            seen.append(("tx", emu.now_us, emu.read_tx(rng.choice((None, 1, 5)))))
        elif k < 0.95:
            emu.reset("test")
        elif k < 0.97 and firmware == "v1.2":  # noise among the bytes in flight, e.g. at a byte's own time
            gap = rng.choice((0.0, 10.85, 21.7, 100.0))
            emu.deliver(bytes(rng.randrange(256) for _ in range(rng.randint(1, 3))), emu.now_us + gap)
        elif k < 0.97:  # a host cuts a pattern and goes; the next one's bytes complete it
            last_write = max(emu.now_us, last_write)
            emu.write(bytes((0xFE, 1, 0)), last_write)
            emu.new_client(f"host {len(seen)}")
        elif k < 0.985:
            emu.stop_reading()
        seen.append(("step", emu.now_us, emu.next_event_us(), emu.in_flight, emu.in_waiting, emu.state()))
    emu.advance_to(emu.now_us + 50_000.0)
    seen.append(("tx", emu.now_us, emu.read_tx()))
    seen.append([(h.kind, h.offset, h.detail, h.time_us) for h in emu.hazards])
    seen.append(list(emu.losses))
    seen.append(list(emu.commands))
    seen.append({k: v.tolist() for k, v in emu.reports.pulse_table().items()})
    if firmware == "v1.2":
        seen += [list(emu.runs), list(emu.tx_log), emu.queue.high_water, list(emu.host.segments)]
        seen += [emu.arrival_us(h) for h in range(0, emu.host_offset, 7)]
    else:
        seen += [list(emu.scans), list(emu.applied), emu.reboots]
    return seen


class CallByCallV2(TimedEmulatorV2):
    """The v2 model with every main-loop call made on its own (no chunk of unknown-byte calls, no run of
    idle polls)."""

    def _skip_unknown(self, t: int, alarm: int, target: int) -> bool:
        return False

    def _idle_polls(self, t: int, alarm: int, target: int) -> bool:
        return False


def _model(firmware: str, link: LinkModel, tx_link: LinkModel, boot_us: float, cls: Any = None) -> Any:
    if firmware == "v1.2":
        return TimedEmulator(link=link, tx_link=tx_link, model=TimingModel(boot_us=boot_us))
    return (cls or TimedEmulatorV2)(link=link, tx_link=tx_link, model=TimingModel(boot_us=boot_us))


@pytest.mark.parametrize("firmware", ["v1.2", "v2"])
def test_bursts_leave_the_same_books_as_one_delivery_per_byte(firmware: str) -> None:
    reasons: set[str] = set()
    kinds: set[str] = set()
    for seed in range(8):
        boot_us = (0.0, 700.0)[seed % 2]
        per_byte = _model(firmware, OneByOne(UartLink()), OneByOne(UartLink()), boot_us)
        bursts = _model(firmware, UartLink(), UartLink(), boot_us)
        want = _drive(per_byte, seed, firmware)
        got = _drive(bursts, seed, firmware)
        assert got == want, f"seed {seed}"
        reasons |= {lo.reason for lo in bursts.losses}
        kinds |= {h.kind.value for h in bursts.hazards}
    # the traffic reached what it is meant to test: bytes lost to a full queue, to a reboot under way and
    # in flight at a reset; replies; on v1.2 bytes arriving at a locked parser
    assert {"queue_full", "rebooting", "reboot"} <= reasons
    assert "hv513_reinit" in kinds
    assert firmware == "v2" or "unread_while_locked" in kinds


@pytest.mark.parametrize("link", ["uart", "usb"])
def test_v2_runs_of_unknown_bytes_in_chunks_as_call_by_call(link: str) -> None:
    """The v2 model's chunks of calls that each skip one unknown byte (the zeros of a flush) and its runs
    of idle polls give what one call at a time gives, over either link (bursts against one delivery per
    byte on a UART)."""
    make = UartLink if link == "uart" else UsbFsLink
    unknown = 0
    for seed in range(8, 14):
        boot_us = (0.0, 700.0)[seed % 2]
        one = _model("v2", OneByOne(make()), OneByOne(make()), boot_us, CallByCallV2)
        fast = _model("v2", make(), make(), boot_us)
        assert _drive(fast, seed, "v2") == _drive(one, seed, "v2"), f"seed {seed}"
        unknown += sum(h.detail["count"] for h in fast.hazards if h.kind.value == "unknown_bytes")
    assert unknown > 2000  # the zeros were skipped in long runs


@pytest.mark.parametrize("cls", [TimedEmulatorV2, CallByCallV2])
def test_v2_an_alarm_due_as_an_unknown_byte_call_would_start_scans_first(cls: Any) -> None:
    """1010 zeros queued when the main loop wakes at 7 ms: calls of 3 µs each read one, the 1000th ends
    at 10 ms -- the first alarm -- so the scan runs before the next call and 10 zeros wait through it."""
    emu = cls(link="usb")
    emu.write(bytes(1010), 5500.0)  # the packets land from 6.05 ms: after the tick at 6 ms
    emu.advance_to(10_000.0)
    assert [s.start_ns for s in emu.scans] == [10_000_000]
    assert len(emu.queue) == 10
    emu.advance_to(emu.scans[0].end_ns / 1000 - 0.001)
    assert len(emu.queue) == 10
    emu.advance_to(emu.scans[0].end_ns / 1000)
    assert len(emu.queue) == 10  # the next call starts as the scan ends; it reads its byte 2 µs in
    emu.advance_to(emu.scans[0].end_ns / 1000 + 2.001)
    assert len(emu.queue) == 9


@pytest.mark.parametrize("byte_us", [1.0, 30.0])
def test_v1_2_bytes_arriving_during_ignored_calls_keep_their_books(byte_us: float) -> None:
    """Zeros over a UART while the main loop skips the ones already queued: the bytes that arrive
    meanwhile land with the run, each with its own arrival time, and the queue's high-water mark is
    the most bytes that waited at any arrival -- as one delivery per byte between the calls gives.  A
    parser slower than the UART (30 µs a byte) lets the queue overflow during such runs."""
    model = TimingModel(parser_byte_us=byte_us)

    def run(link: LinkModel) -> dict[str, Any]:
        emu = TimedEmulator(link=link, model=model)
        steps: list[Any] = []
        t = 1000.0
        for i in range(12):
            emu.write(bytes(60 + 37 * i), t + 83.0 * i)
            emu.write(C1.encode_polarity(i % 2), t + 83.0 * i + 5000.0)
            for step in range(12):
                emu.advance_to(t + 83.0 * i + 500.0 * step)
                steps.append((emu.now_us, emu.queue.high_water, len(emu.queue), emu.in_flight))
            t += 20_000.0
        emu.advance_to(t + 20_000.0)
        return {
            "steps": steps,
            "segments": list(emu.host.segments),
            "commands": list(emu.commands),
            "hazards": list(emu.hazards),
            "losses": list(emu.losses),
            "arrivals": [emu.arrival_us(h) for h in range(emu.host_offset)],
        }

    got, want = run(UartLink()), run(OneByOne(UartLink()))
    assert got == want
    assert len({row[1] for row in got["steps"]}) > 3  # the high-water mark rose step by step
    # bytes lost only where the parser reads slower than the UART delivers
    assert bool(got["losses"]) == (byte_us > 10.85)


@pytest.mark.parametrize("cls", [TimedEmulatorV2, CallByCallV2])
def test_v2_a_poll_due_with_the_alarm_runs_after_the_scan(cls: Any) -> None:
    """The first alarm (10 ms) falls on an RTOS tick: the scan runs first and the poll due then runs as
    it ends, so a sync check arriving during the scan is read then, not at the next tick."""
    emu = cls(link="uart")
    emu.write(bytes((0xF4,)), 9991.15)  # its stop bit ends at 10.002 ms, inside the scan
    emu.advance_to(12_000.0)
    scan = emu.scans[0]
    assert (scan.start_ns, scan.end_ns) == (10_000_000, 10_005_350)
    assert [(c.time_us, c.opcode) for c in emu.commands] == [(10_005.35, 0xF4)]
