"""The upstream eTactileKit firmware, built on the host, against the golden vectors and scan traces.

The trees are not part of this repository: point ``TACTDEFORM_HW_UPSTREAM_V1_2`` (tag v1.2) and
``TACTDEFORM_HW_UPSTREAM_V2`` (commit 71adee21) at a checkout's ``2_Firmware/platform_io_project`` (or at
the repository root).  Without them these tests are skipped.

What is compared: the golden vectors' firmware variables, replies and queue (``expect``), and the scan
traces' GPIO/DAC events, interrupt duration and stored voltages, each scan measured from its interrupt's
entry (the traces start at the alarm).  The firmware is configured through its own parser, with the
interrupt held off until the configuration is in, so the logged scan is the first one after boot
(``prior_scans`` later ones for the second-scan traces), as the traces' "fresh process" convention says.
"""

from __future__ import annotations

import json
import math
import os
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tactdeform_hw.emulator.hostbuild import UPSTREAM_V1_2, UPSTREAM_V2, find_compiler
from tactdeform_hw.emulator.hostbuild.emulator import HostBuildEmulator
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL
from tactdeform_hw.errors import FirmwareBuildError

GOLDEN = Path(os.environ.get("TACTDEFORM_HW_GOLDEN", "/work/shared/golden"))

try:
    find_compiler()
    NO_CXX = ""
except FirmwareBuildError as exc:
    NO_CXX = str(exc)


def _tree(var: str) -> Path:
    if NO_CXX:
        pytest.skip(f"no C++ compiler: {NO_CXX}")
    raw = os.environ.get(var)
    if not raw:
        pytest.skip(
            f"{var} is not set (a checkout of aid-lab-org/eTactileKit's 2_Firmware/platform_io_project)"
        )
    path = Path(raw)
    if (path / "2_Firmware" / "platform_io_project").is_dir():
        path = path / "2_Firmware" / "platform_io_project"
    if not (path / "src").is_dir():
        pytest.skip(f"{var}={raw} holds no PlatformIO tree (src/)")
    return path


def _lines(name: str) -> list[dict[str, Any]]:
    path = GOLDEN / name
    if not path.is_file():
        pytest.skip(f"{path} is missing (set TACTDEFORM_HW_GOLDEN)")
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _same(key: str, got: Any, want: Any) -> bool:
    if key == "period_us":  # a float32 in the firmware; the vectors print it rounded
        return bool(np.float32(got) == np.float32(want))
    return bool(got == want)


def _diff(emu: HostBuildEmulator, expect: dict[str, Any], skip: tuple[str, ...] = ()) -> list[str]:
    got = emu.state()
    got["tx"] = emu.read().hex()
    return [k for k in expect if k not in skip and not _same(k, got.get(k), expect[k])]


# --- golden vectors -----------------------------------------------------------------------------------------


def test_v1_2_golden_vectors_through_the_host_build() -> None:
    tree = _tree("TACTDEFORM_HW_UPSTREAM_V1_2")
    vectors = _lines("protocol_vectors.jsonl")
    wrong = {}
    for i, v in enumerate(vectors):
        stream = bytes.fromhex(v["stream"])
        # all bytes arrive before the parser runs: a queue large enough to hold them
        emu = HostBuildEmulator(
            tree, state_map=UPSTREAM_V1_2, interrupts=False, rx_buffer_bytes=max(256, len(stream))
        )
        emu.write(stream, at_us=0)
        emu.advance_to((len(stream) + 20) * 1000.0)  # at least one byte per 1 ms loop pass
        bad = _diff(emu, v["expect"])
        if bad:
            wrong[i] = bad
    assert len(vectors) == 250 and wrong == {}


V2_T0_US = 5000.0  # arrivals start after boot; only differences of Timer2 readings matter to the parser


def test_v2_golden_vectors_through_the_host_build() -> None:
    """Every field; ``command_in_progress`` (a function-local static) is read through the symbol table.  A
    timeout case (the parser called last at ``final_time_us``) is read after the loop's first poll at or
    after that instant (+100 µs for the drain), since the loop looks at Timer2 only on its RTOS ticks: the
    vector at exactly 2 000 000 µs falls on a tick, where the command has not timed out yet, as in the
    vector.  One vector's clock the loop cannot keep: v2-0190 (random bytes, two 0xF5 among them) times out
    by 2 000 791 µs in the vector, but the board's loop spends 1 ms sensing the stack for each 0xF5 and
    reads the command byte about 2 ms after the bytes arrive, so at that time its command is still
    pending (its queue is empty either way)."""
    tree = _tree("TACTDEFORM_HW_UPSTREAM_V2")
    vectors = _lines("protocol_vectors_v2.jsonl")
    wrong = {}
    for v in vectors:
        emu = HostBuildEmulator(
            tree, state_map=UPSTREAM_V2, interrupts=False, stack_reading=v["board"]["stack_reading"]
        )
        emu.advance_to(V2_T0_US)
        arrivals = v.get("arrivals") or [[0, v["stream"]]]
        for t, hx in arrivals:
            if V2_T0_US + t > emu.now_us:
                emu.advance_to(V2_T0_US + t)
            emu.write(bytes.fromhex(hx), at_us=V2_T0_US + t)
        if v.get("final_time_us") is not None:
            tick_us = DEFAULT_MODEL.rtos_tick_us
            emu.advance_to(math.ceil((V2_T0_US + v["final_time_us"]) / tick_us) * tick_us + 100)
        else:  # until the parser has nothing left to do (far inside the 2 s timeout)
            last = None
            while (key := (emu.state()["rx_pending"], len(emu.tx_log))) != last:
                last = key
                emu.advance(5000)
        bad = _diff(emu, v["expect"])
        if bad:
            wrong[v["id"]] = bad
    assert len(vectors) == 300 and wrong == {"v2-0190": ["command_in_progress"]}


# --- scan traces --------------------------------------------------------------------------------------------


def _config_v1_2(c: dict[str, Any]) -> bytes:
    b = bytearray()
    if c["frequency_hz"] is not None:
        b += b"\xf6" + struct.pack("<H", c["frequency_hz"])
    b += bytes([0xFC, c["electrode_num"]])
    if c["electrode_num"]:
        b += b"\xfe" + bytes(c["stim_pattern"][: c["electrode_num"]])
    b += b"\xfb" + struct.pack("<H", c["pulse_height"])
    if c["pulse_width"]:  # 0 is ignored by the parser (and is the power-on value)
        b += b"\xfa" + struct.pack("<H", c["pulse_width"])
    b += bytes([0xF9, c["sense_pulse_height"] >> 2, 0xF8, c["sense_pulse_width"]])
    b += bytes([0xF7, c["discharge_time"], 0xFD, c["polarity"]])
    return bytes(b)


def _config_v2(c: dict[str, Any]) -> bytes:
    b = bytearray()
    if c["frequency_hz"] is not None:
        b += b"\xf6" + struct.pack("<H", c["frequency_hz"])
    b += bytes([0xFC, c["electrode_num"], 0xFB, c["stim_mode"]])
    if c["electrode_num"]:
        b += b"\xfe" + b"".join(struct.pack("<H", h) for h in c["stim_pattern"][: c["electrode_num"]])
    b += b"\xfa" + struct.pack("<H", c["pulse_width"])
    b += bytes([0xF9, c["sense_pulse_height"], 0xF8, c["sense_pulse_width"]])
    b += bytes([0xF7, c["discharge_time"], 0xFD, c["polarity"]])
    return bytes(b)


def _scan_trace(tree: Path, trace: dict[str, Any], version: str) -> list[str]:
    c = trace["config"]
    kw: dict[str, Any] = {"interrupts": False, "rx_buffer_bytes": 1024}
    if c["hv513_num"] == 1:  # one HV513: the large board's branch with one board stacked
        kw |= {"stack_reading": 3732, "defines": {"ETACTILEKIT_BOARD": "", "SERIAL_COMMUNICATION": ""}}
    else:
        kw["hv513_count"] = c["hv513_num"]
    emu = HostBuildEmulator(tree, state_map=UPSTREAM_V1_2 if version == "v1.2" else UPSTREAM_V2, **kw)
    emu.write(_config_v1_2(c) if version == "v1.2" else _config_v2(c), at_us=0)
    emu.advance_to(30_000)
    assert emu.state()["hv513_num"] == c["hv513_num"]
    emu.clear_events()
    emu.set_interrupts(True)
    emu.advance_to(30_000 + 2 * 70_000)
    enter, ret = emu.scans()[c["prior_scans"]]
    t0 = int(round(enter * 1000))
    got = [[(int(round(e[0] * 1000)) - t0) / 1000, *e[1:]] for e in emu.events() if enter < e[0] <= ret]
    want = [[round(e[0] * 1000) / 1000, *e[1:]] for e in trace["events"]]
    n = c["electrode_num"]
    st = emu.state()
    if version == "v1.2":
        volts = st["voltage"][:n]
    else:
        raw = st["voltage_bytes"]
        volts = [raw[2 * i] | raw[2 * i + 1] << 8 for i in range(n)]
    bad = []
    if got != want:
        bad.append("events")
    if int(round((ret - enter) * 1000)) != int(round(trace["isr_return_us"] * 1000)):
        bad.append("isr_return_us")
    if volts != trace["voltage"][:n]:
        bad.append("voltage")
    return bad


def test_v1_2_scan_traces_through_the_host_build() -> None:
    tree = _tree("TACTDEFORM_HW_UPSTREAM_V1_2")
    traces = _lines("scan_traces_v12.jsonl")
    wrong = {t["name"]: bad for t in traces if (bad := _scan_trace(tree, t, "v1.2"))}
    assert len(traces) == 22 and wrong == {}


def test_v2_scan_traces_through_the_host_build() -> None:
    tree = _tree("TACTDEFORM_HW_UPSTREAM_V2")
    traces = _lines("scan_traces_v2.jsonl")
    wrong = {t["name"]: bad for t in traces if (bad := _scan_trace(tree, t, "v2"))}
    assert len(traces) == 21 and wrong == {}


def test_v1_2_delivered_pulses_of_the_tactdeform_setting() -> None:
    """What the board delivered, decoded from the host build's own pin and DAC events from boot on."""
    tree = _tree("TACTDEFORM_HW_UPSTREAM_V1_2")
    emu = HostBuildEmulator(tree, state_map=UPSTREAM_V1_2)
    config = {**_TACTDEFORM, "frequency_hz": 125, "sense_pulse_height": 0, "sense_pulse_width": 0}
    emu.write(_config_v1_2(config), at_us=0)
    emu.advance_to(40_000)
    (start, ret), *_ = [s for s in emu.scans() if s[0] > 10_000]  # a scan after the configuration
    pulses = [p for p in emu.delivered_pulses() if start <= p.start_us <= ret]
    assert [p.outputs for p in pulses] == [(ch,) for ch in range(32)]
    assert {(p.code, p.polarity, round(p.width_us, 6)) for p in pulses} == {(100, 1, 196.8)}
    assert emu.delivered_pulses()[0].start_us >= 9010.25  # nothing before the first scan


_TACTDEFORM = {
    "electrode_num": 32,
    "stim_pattern": [1] * 32,
    "pulse_height": 100,
    "pulse_width": 200,
    "discharge_time": 45,
    "polarity": 1,
}
