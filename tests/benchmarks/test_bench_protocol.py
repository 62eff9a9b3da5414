"""Host-side cost of the protocol and the emulator (run: pytest tests/benchmarks --benchmark-enable).

Each figure has its baseline in the same run: the construct encoders (plain and compiled) for the fast
pattern encoder, the UART line rate for the emulator's feed rate.
"""

from __future__ import annotations

import random
import time

import pytest
import serial

from tactdeform_hw.device import EtactileKitDevice, StimConfig
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.serving.pty_server import PtyServer
from tactdeform_hw.protocol import commands as c
from tactdeform_hw.protocol.constants import BAUD_RATE, UART_BITS_PER_BYTE, Opcode

LEVELS = [1, 0, 2, 1] * 8


def test_encode_pattern_fast(benchmark) -> None:  # type: ignore[no-untyped-def]
    out = benchmark(c.encode_pattern, LEVELS, electrode_num=32)
    assert out == c.build(Opcode.PATTERN, LEVELS)


def test_encode_pattern_construct_compiled(benchmark) -> None:  # type: ignore[no-untyped-def]
    out = benchmark(c.build, Opcode.PATTERN, LEVELS, use_compiled=True)
    assert out == c.encode_pattern(LEVELS, electrode_num=32)


def test_encode_pattern_construct_plain(benchmark) -> None:  # type: ignore[no-untyped-def]
    out = benchmark(c.build, Opcode.PATTERN, LEVELS)
    assert out == c.encode_pattern(LEVELS, electrode_num=32)


def mixed_stream(n_bytes: int = 1_000_000, seed: int = 7) -> bytes:
    """What a renderer session sends: a configuration, then mostly 32-electrode patterns, with pulse
    height changes, measure requests and the occasional stray byte."""
    rng = random.Random(seed)
    out = bytearray(b"\xfc\x20\xfd\x01\xfa\xc8\x00\xf7\x2d\xf6\x7d\x00\xfb\x64\x00")
    while len(out) < n_bytes:
        r = rng.random()
        if r < 0.80:
            out += c.encode_pattern([rng.choice((0, 1, 2)) for _ in range(32)])
        elif r < 0.90:
            out += c.encode_pulse_height(rng.randint(0, 1000))
        elif r < 0.95:
            out += b"\xff"
        elif r < 0.98:
            out += c.encode_frequency(rng.randint(50, 200))
        else:
            out += bytes([rng.randint(0, 0xF4)])
    return bytes(out)


STREAM = mixed_stream()


def _feed_all() -> Emulator:
    emu = Emulator()
    for i in range(0, len(STREAM), 4096):
        emu.feed(STREAM[i : i + 4096])
    return emu


def test_emulator_feed_throughput(benchmark) -> None:  # type: ignore[no-untyped-def]
    emu = benchmark(_feed_all)
    assert emu.state().electrode_num == 32 and not emu.locked
    if benchmark.stats is None:  # --benchmark-disable: ran once as a plain test
        return
    stats = benchmark.stats.stats
    mb_s = len(STREAM) / stats.median / 1e6
    uart_mb_s = BAUD_RATE / UART_BITS_PER_BYTE / 1e6
    benchmark.extra_info["feed_MB_per_s"] = round(mb_s, 2)
    benchmark.extra_info["times_uart_line_rate"] = round(mb_s / uart_mb_s, 1)


@pytest.fixture(scope="module")
def pty_device():  # type: ignore[no-untyped-def]
    server = PtyServer(Emulator()).start()
    port = serial.Serial(None, BAUD_RATE, timeout=1)
    port.port = server.path
    dev = EtactileKitDevice(port)
    dev.configure(StimConfig(current_ua=500))
    yield dev, server
    dev.close()
    server.stop()


def test_pattern_round_trip_over_pty(benchmark, pty_device) -> None:  # type: ignore[no-untyped-def]
    """Driver write → emulator state updated, through a real pseudo-terminal."""
    dev, server = pty_device
    regs = server.emulator.registers
    flip = [0]

    def round_trip() -> None:
        flip[0] ^= 1
        level = flip[0]
        dev.send_pattern([level] * 32)
        deadline = time.perf_counter() + 1.0
        while regs.stim_pattern[31] != level:
            time.sleep(0)  # let the server thread take the GIL instead of waiting out the switch interval
            if time.perf_counter() > deadline:
                raise AssertionError("pattern never reached the emulator")

    benchmark.pedantic(round_trip, rounds=300, warmup_rounds=10)
    assert list(regs.stim_pattern[:32]) == [flip[0]] * 32  # the last pattern sent is the one the board holds


def test_pattern_round_trip_over_pty_transport_only(benchmark, pty_device) -> None:  # type: ignore[no-untyped-def]
    """The same round trip without the driver's pacing: the pty and the emulator alone.  The difference to
    the driver's figure is the pacer waiting for the device's next parser window (one per scan period)."""
    dev, server = pty_device
    regs = server.emulator.registers
    port = dev.port
    frames = [c.encode_pattern([level] * 32) for level in (0, 1)]
    flip = [0]

    def round_trip() -> None:
        flip[0] ^= 1
        port.write(frames[flip[0]])
        deadline = time.perf_counter() + 1.0
        while regs.stim_pattern[31] != flip[0]:
            time.sleep(0)
            if time.perf_counter() > deadline:
                raise AssertionError("pattern never reached the emulator")

    benchmark.pedantic(round_trip, rounds=300, warmup_rounds=10)
    assert list(regs.stim_pattern[:32]) == [flip[0]] * 32  # the last pattern sent is the one the board holds
