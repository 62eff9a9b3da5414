"""Delivered pulses decoded from pin and DAC events (the host build's safety view), checked on the golden
scan traces the firmware's own interrupt code produced (tests/data/scan_traces_*.jsonl)."""

from __future__ import annotations

import json
import random
from pathlib import Path
from typing import Any

import pytest

from tactdeform_hw.emulator.hostbuild import build, find_compiler
from tactdeform_hw.emulator.hostbuild.delivered import ChainDecoder, DeliveredPulse
from tactdeform_hw.emulator.hostbuild.emulator import HostBuildEmulator
from tactdeform_hw.errors import FirmwareBuildError, LimitError

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


# --- the shim's own decoder against this reference ----------------------------------------------------------

CHAIN_FIRMWARE = DATA / "firmware_chain"


def _cxx() -> str:
    try:
        find_compiler()
    except FirmwareBuildError as exc:
        return str(exc)
    return ""


needs_cxx = pytest.mark.skipif(bool(_cxx()), reason=f"no C++ compiler: {_cxx()}")


@pytest.fixture(scope="module")
def chain_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    where = tmp_path_factory.mktemp("fwcache")
    build(CHAIN_FIRMWARE, state_map=None, cache=where)
    return where


def _reference(emu: HostBuildEmulator, chain_outputs: int) -> list[DeliveredPulse]:
    """The pin and DAC events the host build recorded, through :class:`ChainDecoder`."""
    dec = ChainDecoder(chain_outputs)
    for e in emu.shim_events():
        t_ns = round(e.t_us * 1000)
        if e.kind == "GPIO":
            dec.gpio(t_ns, e.a, e.b)
        elif e.kind == "SPI":
            dec.dac(t_ns + emu.timing.dac_at_ns, (e.b >> 2) & 0xFFF)
    return dec.pulses


@needs_cxx
@pytest.mark.parametrize(("seed", "chain_outputs"), [(1, 8), (2, 8), (3, 3), (4, 1), (5, 0), (6, 32)])
def test_the_shim_decodes_the_chain_exactly_as_the_reference(
    chain_cache: Path, seed: int, chain_outputs: int
) -> None:
    """Random actions on the chain's pins and the DAC: the pulses the shim decoded while the firmware ran are
    the reference decoder's, pulse for pulse (times, codes, outputs, polarity)."""
    rng = random.Random(seed)
    emu = HostBuildEmulator(
        CHAIN_FIRMWARE, state_map=None, cache=chain_cache, chain_outputs=chain_outputs, stack_reading=0
    )
    t = 100.5
    for _ in range(40):
        emu.write(bytes(rng.randrange(256) for _ in range(rng.randint(1, 60))), at_us=t)
        t += rng.uniform(50, 3000)
        emu.advance_to(t)
    emu.advance_to(t + 5000)
    expected = _reference(emu, chain_outputs)
    assert len(expected) > (20 if chain_outputs else -1)
    assert emu.delivered_pulses() == expected
    arrays = emu.delivered_arrays()
    assert [arrays.outputs_of(i) for i in range(len(arrays))] == [p.outputs for p in expected]
