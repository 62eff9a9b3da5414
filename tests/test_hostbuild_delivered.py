"""Delivered pulses decoded from pin and DAC events (the host build's safety view), checked on the golden
scan traces the firmware's own interrupt code produced (tests/data/scan_traces_*.jsonl)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tactdeform_hw.emulator.hostbuild.delivered import ChainDecoder, DeliveredPulse
from tactdeform_hw.errors import LimitError

DATA = Path(__file__).parent / "data"


def _trace(file: str, name: str) -> dict[str, Any]:
    for line in (DATA / file).read_text().splitlines():
        t = json.loads(line)
        if t["name"] == name:
            return t
    raise AssertionError(name)


BOOT_LEVELS = {1: 1, 3: 1}  # the traces start after boot: hv513Init left BL and POL high (protocol.md)


def _decode(trace: dict[str, Any], chain_outputs: int) -> list[DeliveredPulse]:
    dec = ChainDecoder(chain_outputs, levels=BOOT_LEVELS)
    for t_us, kind, pin, value in trace["events"]:
        t_ns = round(t_us * 1000)
        if kind == "GPIO":
            dec.gpio(t_ns, pin, value)
        else:
            dec.dac(t_ns, value)
    return dec.pulses


def test_tactdeform_scan_delivers_one_pulse_per_electrode() -> None:
    pulses = _decode(_trace("scan_traces_v12.jsonl", "tactdeform_32mono_w200_d45_125hz"), 32)
    assert [p.outputs for p in pulses] == [(ch,) for ch in range(32)]
    assert {(p.code, p.polarity) for p in pulses} == {(100, 1)}
    # DAC up 3.3 µs into one exchange, down 3.3 µs into the one after the 190 µs wait; the two chip-select
    # writes between them cost 0.05 µs each: 6.6 + 190 + 0.2
    assert {round(p.width_us, 6) for p in pulses} == {196.8}
    assert pulses[0].start_us == 5.7


def test_biphasic_cathodic_gives_two_phases_of_opposite_polarity() -> None:
    pulses = _decode(_trace("scan_traces_v12.jsonl", "biphasic_all_n4_cathodic"), 32)
    assert [(p.outputs, p.polarity) for p in pulses] == [((ch,), pol) for ch in range(4) for pol in (1, 0)]


def test_channels_past_the_chain_deliver_nothing() -> None:
    trace = _trace("scan_traces_v12.jsonl", "n40_hv4_second_scan")
    pulses = _decode(trace, 32)
    assert [p.outputs for p in pulses] == [(ch,) for ch in range(32)]


def test_blanking_and_zero_code_stop_the_current() -> None:
    dec = ChainDecoder(8)
    for t, pin, level in ((0, 2, 0), (10, 5, 1), (20, 4, 1), (30, 4, 0), (40, 2, 1), (50, 1, 1)):
        dec.gpio(t, pin, level)  # LE low, DIN 1, one clock, LE high: output 0 selected; BL high
    dec.dac(100, 50)
    dec.gpio(300, 1, 0)  # BL low: all outputs off
    dec.gpio(400, 1, 1)  # BL high again, the code still 50
    dec.dac(500, 0)
    assert dec.pulses == [
        DeliveredPulse(0.1, 0.3, 50, (0,), 0),
        DeliveredPulse(0.4, 0.5, 50, (0,), 0),
    ]


def test_no_chain_means_no_outputs() -> None:
    pulses = _decode(_trace("scan_traces_v12.jsonl", "hv0_n4"), 0)
    assert pulses == []
    with pytest.raises(LimitError, match="chain_outputs=-1"):
        ChainDecoder(-1)
