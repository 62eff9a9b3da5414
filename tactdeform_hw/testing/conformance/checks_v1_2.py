"""Host-observable protocol behaviour of an eTactileKit controller (or its emulator), firmware v1.2.

A test module that star-imports this one (``from tactdeform_hw.testing.conformance.checks_v1_2 import *``)
gets the checks, their fixtures and the hook that picks the targets (:mod:`.targets`).

Each check uses only what a host can see — bytes written, bytes read, and when — so the same suite runs
on the emulator in CI and on a board at the bench (see ``docs/firmware-guide-conformance.md``).  Where a
target is emulated, checks also look inside the firmware's registers to show that what the host saw is
what happened.

Safety on a board: no check sets a non-zero pulse height with any channel on; each test starts from
the resynchronisation sequence with pulse height 0, sense height 0 and every channel off; nothing that
would lock the parser (a pattern with 0 electrodes) is sent to a board.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from tactdeform_hw.device import EtactileKitDevice, StimConfig
from tactdeform_hw.protocol import Opcode, decode, encode_electrode_num
from tactdeform_hw.protocol.constants import MAX_ELECTRODES, RX_QUEUE_SIZE
from tactdeform_hw.testing.conformance.targets import REPLY_TIMEOUT_S, Target, report_fixture, target_fixture  # noqa: F401
from tactdeform_hw.testing.conformance.targets import generate_v1_2_targets as pytest_generate_tests  # noqa: F401

Report = Callable[[str, str], None]

#: pulse height 0, sense height 0, pulse width 1 µs, sense width 0, discharge 0, 20 Hz
BASELINE = b"\xfb\x00\x00" + b"\xf9\x00" + b"\xfa\x01\x00" + b"\xf8\x00" + b"\xf7\x00" + b"\xf6\x14\x00"
BASELINE_COMMANDS = 6


class Probe:
    """Raw bytes to and from the target, with the timing a host sees."""

    def __init__(self, target: Target, port: Any) -> None:
        self.target = target
        self.port = port

    def send(self, data: bytes) -> None:
        self.port.write(data)

    def read(self, n: int, timeout: float = REPLY_TIMEOUT_S) -> bytes:
        self.port.timeout = timeout
        out = b""
        deadline = time.monotonic() + timeout
        while len(out) < n and time.monotonic() < deadline:
            out += self.port.read(n - len(out))
        return out

    def quiet(self) -> bytes:
        """Whatever arrives within the quiet window (b"" when the device stays silent)."""
        self.port.timeout = self.target.quiet_s
        return bytes(self.port.read(1))

    def request(self, data: bytes, n: int) -> tuple[bytes, float]:
        """Write ``data`` and read ``n`` reply bytes; the seconds from the write to the last byte."""
        t0 = time.monotonic()
        self.send(data)
        reply = self.read(n)
        return reply, time.monotonic() - t0

    def baseline(self, electrodes: int) -> None:
        """The resynchronisation sequence as a known, safe starting point: 256 zeros finish whatever
        was in progress; then pulse height 0 and sense height 0, the shortest pulses and no discharge
        wait at 20 Hz (so even 255 channels scan in a fraction of the period and the parser is not
        starved by whatever an earlier session configured), the electrode count, and an all-off pattern.
        Paced so the 256-byte receive queue never overflows."""
        self.send(bytes(RX_QUEUE_SIZE))
        self.target.settle(1)
        self.send(BASELINE + encode_electrode_num(electrodes))
        self.target.settle(BASELINE_COMMANDS + 1)
        self.send(b"\xfe" + bytes(electrodes))
        self.target.settle(1)
        self.port.reset_input_buffer()


@pytest.fixture
def probe(target: Target) -> Iterator[Probe]:
    port = target.open()
    try:
        yield Probe(target, port)
    finally:
        port.close()


def _ms(seconds: float) -> str:
    return f"{seconds * 1000:.2f} ms"


# --- the HV513 count ---------------------------------------------------------------------------------------


def test_hv513_reply(probe: Probe, target: Target, report: Report) -> None:
    """0xF5 answers with exactly one byte: a chip count the board formulas can produce; asking again
    gives the same count."""
    probe.baseline(8)
    reply, latency = probe.request(b"\xf5", 1)
    assert len(reply) == 1, "no reply to the HV513 count request (0xF5)"
    assert probe.quiet() == b"", "more than one byte came back for 0xF5"
    count = reply[0]
    assert count % 4 == 0 or count == 1, (
        f"HV513 count {count}: neither the compact ((n-1)*4) nor the large board formula"
    )
    again, _ = probe.request(b"\xf5", 1)
    assert again == reply, "the HV513 count changed between two requests"
    if target.hv513_expected is not None:
        assert count == target.hv513_expected
    report("HV513 count", str(count))
    report("0xF5 reply latency", _ms(latency))


# --- measure ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("electrodes", [1, 8, 32, MAX_ELECTRODES])
def test_measure_reply_length(probe: Probe, target: Target, electrodes: int, report: Report) -> None:
    """0xFF answers with exactly 2 bytes per electrode (u16 little-endian ADC codes, ``raw >> 2`` of a
    12-bit reading, so below 1024), then nothing."""
    probe.baseline(electrodes)
    reply, latency = probe.request(b"\xff", 2 * electrodes)
    assert len(reply) == 2 * electrodes, f"measure reply of {len(reply)} bytes for {electrodes} electrodes"
    assert probe.quiet() == b"", "bytes after the measure reply"
    codes = [int.from_bytes(reply[i : i + 2], "little") for i in range(0, len(reply), 2)]
    assert max(codes) < 1024, f"ADC code {max(codes)} does not fit raw >> 2 of a 12-bit reading"
    if target.state is not None:
        assert target.state().electrode_num == electrodes
    report(f"0xFF reply, {electrodes} electrodes", f"{len(reply)} bytes in {_ms(latency)}")


def test_measure_with_zero_electrodes_replies_nothing(probe: Probe, target: Target) -> None:
    """With electrode_num 0 the reply has no bytes (and the suite sends no pattern, which would lock)."""
    probe.baseline(4)
    probe.send(b"\xfc\x00")
    target.settle(1)
    probe.send(b"\xff")
    assert probe.quiet() == b""
    probe.send(b"\xfc\x04")  # back to a count a pattern can use
    target.settle(1)
    reply, _ = probe.request(b"\xf5", 1)
    assert len(reply) == 1


def test_measure_reply_timing(probe: Probe, target: Target, report: Report) -> None:
    """A measure request on an idle parser is answered at once: the host sees the link and at most one
    RTOS tick, well inside ``ETACTILE_REPLY_BUDGET_MS``."""
    probe.baseline(32)
    latencies = []
    for _ in range(5):
        reply, latency = probe.request(b"\xff", 64)
        assert len(reply) == 64
        latencies.append(latency)
        time.sleep(0.003)
    median = statistics.median(latencies)
    report(
        "0xFF round trip (min / median / max)",
        " / ".join(_ms(x) for x in (min(latencies), median, max(latencies))),
    )
    assert median <= target.reply_budget_s, (
        f"median measure round trip {_ms(median)} exceeds the budget {_ms(target.reply_budget_s)}"
    )


# --- silence after every other command ------------------------------------------------------------------

N = 8
SILENT = [
    ("polarity", b"\xfd\x01"),
    ("electrode_num", encode_electrode_num(N)),
    ("pulse_height_0", b"\xfb\x00\x00"),
    ("pulse_width", b"\xfa\xc8\x00"),
    ("pulse_width_0_ignored", b"\xfa\x00\x00"),
    ("sense_height_0", b"\xf9\x00"),
    ("sense_width", b"\xf8\x00"),
    ("discharge", b"\xf7\x2d"),
    ("frequency", b"\xf6\x7d\x00"),
    ("frequency_0_ignored", b"\xf6\x00\x00"),
    ("pattern_all_off", b"\xfe" + bytes(N)),
    ("unknown_0x00", b"\x00"),
    ("unknown_0x7f", b"\x7f"),
    ("unknown_0xf0", b"\xf0"),
    ("unknown_0xf4", b"\xf4"),
]


@pytest.mark.parametrize(("command", "data"), SILENT, ids=[c for c, _ in SILENT])
def test_silence_after_other_commands(probe: Probe, target: Target, command: str, data: bytes) -> None:
    """Commands other than 0xFF and 0xF5 (and bytes that are no command) get no reply, and consume
    exactly their payload: the next 0xF5 is still read as a command."""
    probe.baseline(N)
    probe.send(data)
    assert probe.quiet() == b"", f"{command} ({data.hex(' ')}) was answered"
    target.settle(1)
    reply, _ = probe.request(b"\xf5", 1)
    assert len(reply) == 1, f"after {command} the parser is out of step: 0xF5 was not answered"
    assert probe.quiet() == b""


# --- resynchronisation -----------------------------------------------------------------------------------


def test_truncated_pattern_swallows_the_next_command_and_zeros_resynchronise(
    probe: Probe, target: Target
) -> None:
    """A pattern cut short takes the next bytes as its payload (here an 0xF5, which then gets no reply);
    256 zeros finish it; pulse height 0 and an all-off pattern make the state known again."""
    probe.baseline(32)
    probe.send(b"\xfe" + bytes(10))  # 10 of 32 channel bytes
    target.settle(1)
    probe.send(b"\xf5")
    assert probe.quiet() == b"", "0xF5 was answered although it should be pattern payload (channel 10)"
    target.settle(1)
    if target.state is not None:
        assert target.state().stim_pattern[10] == Opcode.HV513_COUNT
    probe.send(bytes(RX_QUEUE_SIZE))
    target.settle(1)
    probe.send(b"\xfb\x00\x00" + b"\xfc\x20")
    target.settle(2)
    probe.send(b"\xfe" + bytes(32))
    target.settle(1)
    reply, _ = probe.request(b"\xf5", 1)
    assert len(reply) == 1, "not in step after the resynchronisation sequence"
    reply, _ = probe.request(b"\xff", 64)
    assert len(reply) == 64
    if target.state is not None:
        st = target.state()
        assert list(st.stim_pattern[:32]) == [0] * 32 and st.pulse_height == 0 and st.rx_pending == 0


def test_half_received_u16_is_completed_by_the_zeros(probe: Probe, target: Target) -> None:
    """A u16 whose low byte arrived keeps it when the zeros come (the spec's reason for sending pulse
    height 0 right after them).  The low byte here is 5 (a 50 µA code) and every channel is off."""
    probe.baseline(8)
    probe.send(b"\xfb\x05")
    target.settle(1)
    probe.send(bytes(RX_QUEUE_SIZE))
    target.settle(1)
    if target.state is not None:
        assert target.state().pulse_height == 5
    probe.send(b"\xfb\x00\x00")
    target.settle(1)
    reply, _ = probe.request(b"\xf5", 1)
    assert len(reply) == 1
    if target.state is not None:
        assert target.state().pulse_height == 0


def test_zero_electrode_pattern_locks_the_parser(probe: Probe, target: Target) -> None:
    """The firmware defect: 0xFE with electrode_num 0 never completes, and nothing is read after it."""
    if target.is_board:
        pytest.skip("would lock the board's parser until a power cycle; checked on the emulator only")
    probe.baseline(4)
    probe.send(b"\xfc\x00")
    target.settle(1)
    probe.send(b"\xfe")
    target.settle(1)
    probe.send(b"\xf5" + bytes(RX_QUEUE_SIZE) + b"\xf5")
    assert probe.quiet() == b"", "a locked parser answered"
    target.settle(1)
    if target.state is not None:
        assert target.state().rx_pending > 0


# --- the parser's rhythm ----------------------------------------------------------------------------------


def test_one_command_per_millisecond(probe: Probe, target: Target, report: Report) -> None:
    """Every command with a payload ends with a one-tick (1 ms) sleep: a measure request queued behind K
    such commands is answered about K ms later; behind K unknown bytes, at once."""
    if not target.timed:
        pytest.skip(
            f"{target.name} serves the untimed emulator (every byte is read at once); the rhythm is checked "
            "on the timed targets (etactile://, pty, tcp, usb-emulator) and on boards"
        )
    k = 20
    probe.baseline(4)

    def samples(data: bytes, n: int = 3) -> list[float]:
        out = []
        for _ in range(n):
            reply, latency = probe.request(data, 8)
            assert len(reply) == 8
            out.append(latency)
            time.sleep(0.002)
        return out

    alone_samples = samples(b"\xff", 5)
    alone = min(alone_samples)
    behind_commands = min(samples(b"\xf7\x00" * k + b"\xff"))  # discharge 0: no pulse gets longer
    behind_unknown = min(samples(bytes(200) + b"\xff"))
    extra = behind_commands - alone
    # The round trip's own jitter (a busy host delays when bytes are read and replies written) widens the
    # lower bound, by at most 5 ms: a parser reading two commands per tick (extra about 10 ms) still fails.
    jitter = min(max(alone_samples) - alone, 5e-3)
    report("0xFF alone", _ms(alone))
    report(
        f"0xFF behind {k} commands",
        f"{_ms(behind_commands)} (+{extra * 1000:.2f} ms, {extra * 1000 / k:.3f} ms/command)",
    )
    report("0xFF behind 200 unknown bytes", _ms(behind_unknown))
    assert extra >= (k - 2) * 1e-3 - jitter, (
        f"{k} commands delayed the reply by only {extra * 1000:.2f} ms (round-trip jitter "
        f"{jitter * 1000:.2f} ms): the firmware reads more than one command per millisecond"
    )
    assert extra <= k * 2.5e-3 + 0.020, (
        f"{k} commands delayed the reply by {extra * 1000:.2f} ms: more than one tick per command (is the "
        "RTOS tick 1 kHz?)"
    )
    assert behind_unknown - alone < extra / 2, (
        "unknown bytes cost the parser time: each should be skipped at once"
    )


# --- the fail-safe ---------------------------------------------------------------------------------------


class RecordingPort:
    """Passes everything to the port and keeps a copy of every byte written."""

    def __init__(self, port: Any) -> None:
        object.__setattr__(self, "_port", port)
        object.__setattr__(self, "written", bytearray())

    def write(self, data: bytes) -> Any:
        self.written.extend(bytes(data))
        return self._port.write(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._port, name)

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._port, name, value)


def _last_state(commands: list[Any], electrodes: int) -> tuple[bytes | None, int | None]:
    pattern = height = None
    for c in commands:
        if c.name == "PATTERN" and c.status == "ok":
            pattern = c.value
        elif c.name == "PULSE_HEIGHT" and c.status == "ok":
            height = c.value
    return pattern, height


def _check_all_off(target: Target, written: bytes, mark: int, electrodes: int) -> None:
    tail = decode(written[mark:], electrode_num=electrodes)
    pattern, height = _last_state(tail, electrodes)
    assert pattern == bytes(electrodes), (
        f"no all-off pattern was sent on close: {[c.describe() for c in tail]}"
    )
    assert height == 0, "the pulse height was not set to 0 on close"
    if target.state is not None:
        target.settle(2)
        st = target.state()
        assert list(st.stim_pattern[:electrodes]) == [0] * electrodes and st.pulse_height == 0


def _current(target: Target) -> int:
    # on a board nothing may flow: the check is on the bytes; on the emulator a current proves the reset
    return 0 if target.is_board else 1000


def test_fail_safe_on_close(target: Target) -> None:
    """Closing the driver leaves every channel off and the pulse height 0, and the board in step."""
    port = RecordingPort(target.make_port())
    dev = EtactileKitDevice(port, settle_s=target.settle_s)
    dev.resync()
    dev.configure(StimConfig(electrode_count=8, current_ua=_current(target)))
    target.settle(12)
    dev.send_pattern([1] * 8)
    target.settle(1)
    if target.state is not None:
        assert list(target.state().stim_pattern[:8]) == [1] * 8
    mark = len(port.written)
    dev.close()
    _check_all_off(target, bytes(port.written), mark, 8)
    p = target.open()
    try:
        probe = Probe(target, p)
        reply, _ = probe.request(b"\xf5", 1)
        assert len(reply) == 1, "the board is out of step after the driver closed"
    finally:
        p.close()


def test_fail_safe_on_exception(target: Target) -> None:
    """An exception inside ``with`` still sends all-off before the port closes."""
    port = RecordingPort(target.make_port())
    mark = 0
    with pytest.raises(RuntimeError, match="renderer crashed"):
        with EtactileKitDevice(port, settle_s=target.settle_s) as dev:
            dev.resync()
            dev.configure(StimConfig(electrode_count=8, current_ua=_current(target)))
            target.settle(12)
            dev.send_pattern([1, 2, 1, 0, 0, 1, 2, 1])
            mark = len(port.written)
            raise RuntimeError("renderer crashed")
    _check_all_off(target, bytes(port.written), mark, 8)
