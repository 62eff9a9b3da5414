"""Torn patterns on a host build, found from the pattern the interrupt saw and the bytes the queue kept.

The finder is pure (:class:`TornPatternWatch`): these tests hand it a stream and the scans' snapshots.
With an upstream v1.2 tree (``TACTDEFORM_HW_UPSTREAM_V1_2``) the host build finds the firmware's own torn
scans on a stream of patterns over a UART.
"""

from __future__ import annotations

import os
import random
from pathlib import Path

import pytest

from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind
from tactdeform_hw.emulator.hostbuild.torn import TornPatternWatch
from tactdeform_hw.protocol.commands import commands_for
from tactdeform_hw.protocol.firmware import FIRMWARES, get_firmware

V1_2 = get_firmware("v1.2", "firmware")


def _pattern(fw_name: str, levels: list[int]) -> bytes:
    return commands_for(get_firmware(fw_name, "firmware")).encode_pattern(levels)


@pytest.mark.parametrize("fw", FIRMWARES.values(), ids=lambda f: f.name)
def test_a_scan_on_part_of_the_new_pattern_is_torn(fw: object) -> None:
    """Old 0 1 0 1, new h h h h: a scan on h h 0 1 took the first two channels new.  Channel 1 kept its
    height, so the stored count is seen only between 1 and 2."""
    h = 1 if fw.name == "v1.2" else 700  # type: ignore[attr-defined]
    watch = TornPatternWatch(fw, [0, h, 0, h, 0, 0], electrode_num=4)  # type: ignore[arg-type]
    watch.read(_pattern(fw.name, [h, h, h, h]), 100)  # type: ignore[attr-defined]
    watch.scan(1.0, [0, h, 0, h, 0, 0], 4)
    watch.scan(2.0, [h, h, 0, h, 0, 0], 4)
    watch.scan(3.0, [h, h, h, h, 0, 0], 4)
    (torn,) = watch.torn
    assert (torn.t_us, torn.new_channels, torn.new_channels_up_to, torn.channels) == (2.0, 1, 2, 4)
    assert torn.command_host_offset == 100 and torn.changed == ((0, 0, h),)
    assert watch.unexplained == 0


def test_a_scan_waits_for_the_bytes_of_its_pattern() -> None:
    """The scan is seen before the command's bytes are read (they were still on the link): it is judged
    when they are."""
    watch = TornPatternWatch(V1_2, [0, 0, 0], electrode_num=3)
    watch.scan(5.0, [2, 0, 0], 3)
    assert watch.torn == []
    data = _pattern("v1.2", [2, 2, 2])
    watch.read(data[:2], 0)  # the opcode and the first element: the pattern is not complete yet
    assert watch.torn == []
    watch.read(data[2:], 2)
    assert [t.new_channels for t in watch.torn] == [1]


def test_whole_patterns_and_unseen_tears_are_not_torn() -> None:
    """A scan on a whole pattern, old or new, is not torn, nor one whose stored channels kept their
    heights (nothing shows), nor a scan in a mode that uses no height."""
    watch = TornPatternWatch(V1_2, [1, 0, 0], electrode_num=3)
    watch.read(_pattern("v1.2", [1, 2, 2]), 0)
    watch.read(_pattern("v1.2", [0, 0, 0]), 4)
    watch.scan(1.0, [1, 0, 0], 3)
    watch.scan(2.0, [1, 2, 2], 3)
    watch.scan(3.0, [0, 2, 2], 3, reads_pattern=False)
    watch.scan(4.0, [0, 0, 0], 3)
    assert watch.torn == [] and watch.unexplained == 0


def test_a_snapshot_no_pattern_explains_is_counted_not_reported() -> None:
    watch = TornPatternWatch(V1_2, [0, 0], electrode_num=2)
    watch.read(_pattern("v1.2", [1, 1]), 0)
    watch.scan(1.0, [2, 2], 2)  # no command stored 2 2 (the queue's bytes were lost, say)
    assert watch.unexplained == 0  # it may still be explained by bytes to come
    watch.scan(2.0, [1, 1], 2)
    assert watch.unexplained == 1 and watch.torn == []
    watch.scan(3.0, [0, 2], 2)
    watch.close()
    assert watch.unexplained == 2


def test_v2_stores_the_clamped_height() -> None:
    """v2 clamps a height above 4095 before storing it: the torn scan shows the clamped value."""
    v2 = get_firmware("v2", "firmware")
    watch = TornPatternWatch(v2, [0, 0, 0], electrode_num=3)
    over = (5000).to_bytes(2, "little")
    watch.read(_pattern("v2", [0, 0, 0])[:1] + over * 3, 0)  # past what the encoder sends
    watch.scan(1.0, [4095, 0, 0], 3)
    assert [(t.new_channels, t.changed) for t in watch.torn] == [(1, ((0, 0, 4095),))]


def test_the_host_build_records_the_firmwares_torn_scans_upstream_v1_2() -> None:
    """Patterns streamed over a UART into the built v1.2 firmware: its interrupt fires inside their
    storing, and the host build records those scans as torn, each naming a pattern command it sent."""
    from tactdeform_hw.emulator.hostbuild import find_compiler
    from tactdeform_hw.emulator.hostbuild.timed import HostBuildTimedModel

    raw = os.environ.get("TACTDEFORM_HW_UPSTREAM_V1_2")
    if not raw or not (Path(raw) / "src").is_dir():
        pytest.skip("set TACTDEFORM_HW_UPSTREAM_V1_2 to the v1.2 PlatformIO tree (platform_io_project)")
    find_compiler()
    c = commands_for(V1_2)
    model = HostBuildTimedModel(raw, link="uart")
    setup = c.encode_electrode_num(32) + c.encode_pulse_height(1000) + c.encode_frequency(500)
    model.advance_to(1000)
    model.write(setup)
    rng = random.Random(1)
    t_us, offsets = 20_000.0, []
    offset = len(setup)
    for _ in range(30):
        data = c.encode_pattern([rng.choice([0, 1, 2]) for _ in range(32)])
        model.advance_to(t_us)
        model.write(data)
        offsets.append(offset)
        offset += len(data)
        t_us += rng.uniform(1500, 4000)
    model.advance_to(t_us + 20_000)
    torn = [h for h in model.hazards if h.kind is HazardKind.TORN_PATTERN]
    assert len(torn) >= 5
    for h in torn:
        assert h.detail["command_host_offset"] in offsets
        assert 1 <= h.detail["new_channels"] <= h.detail["new_channels_up_to"] < 32


def _observable(hazards: list[Hazard], patterns: dict[int, tuple[list[int], list[int]]]) -> dict[float, int]:
    """The model's torn scans whose stored and unstored channels both changed (the only ones heights
    show): time -> channels stored, ``patterns`` giving each pattern command's (old, new) by host offset."""
    out: dict[float, int] = {}
    for h in hazards:
        if h.kind is not HazardKind.TORN_PATTERN:
            continue
        k = h.detail["new_channels"]
        old, new = patterns[h.detail["command_host_offset"]]
        if old[:k] != new[:k] and old[k:] != new[k:]:
            out[round(h.time_us, 1)] = k
    return out


@pytest.mark.parametrize(("link", "seed"), [("uart", 1), ("usb", 3)])
def test_the_model_tears_the_patterns_the_firmware_tears_upstream_v1_2(link: str, seed: int) -> None:
    """The same timed stream of 32-electrode patterns (500 Hz) into the built v1.2 firmware and into the
    Python model: the model's torn scans that show in the heights are the host build's, and the channels it
    had stored at each lie in the range the host build's heights allow.  (The model once stored fewer:
    its calls read only the bytes waiting when they began, and a read ending on the alarm was not counted.)"""
    from tactdeform_hw.emulator.hostbuild import find_compiler
    from tactdeform_hw.emulator.hostbuild.timed import HostBuildTimedModel
    from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator

    raw = os.environ.get("TACTDEFORM_HW_UPSTREAM_V1_2")
    if not raw or not (Path(raw) / "src").is_dir():
        pytest.skip("set TACTDEFORM_HW_UPSTREAM_V1_2 to the v1.2 PlatformIO tree (platform_io_project)")
    find_compiler()
    c = commands_for(V1_2)
    setup = c.encode_electrode_num(32) + c.encode_pulse_height(1000) + c.encode_frequency(500)
    rng = random.Random(seed)
    writes = [(1000.0, setup)]
    patterns: dict[int, tuple[list[int], list[int]]] = {}
    t_us, offset, old = 20_000.0, len(setup), [0] * 32
    for _ in range(40):
        new = [rng.choice([0, 1, 2]) for _ in range(32)]
        writes.append((t_us, c.encode_pattern(new)))
        patterns[offset] = (old, new)
        offset, old = offset + 33, new
        t_us += rng.uniform(1500, 4000)
    firmware = HostBuildTimedModel(raw, link=link)
    model = TimedEmulator(link=link)
    for side in (firmware, model):
        for at_us, data in writes:
            side.advance_to(at_us)
            side.write(data, at_us=at_us)
        side.advance_to(t_us + 20_000)
    seen = {
        round(h.time_us, 1): (h.detail["new_channels"], h.detail["new_channels_up_to"])
        for h in firmware.hazards
        if h.kind is HazardKind.TORN_PATTERN
    }
    mine = _observable(model.hazards, patterns)
    assert len(seen) >= 10
    assert sorted(mine) == sorted(seen)
    assert {t: k for t, k in mine.items() if not seen[t][0] <= k <= seen[t][1]} == {}
