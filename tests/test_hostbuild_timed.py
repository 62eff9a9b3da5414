"""A host-built firmware behind the timed models' API: the driver, the servers and the URL handler run it.

The tiny test firmware is no eTactileKit: its state map declares no version, so a board state is refused
and the driver's identification refuses the board.  With an upstream v1.2 tree
(``TACTDEFORM_HW_UPSTREAM_V1_2``) the driver identifies, configures and stimulates the firmware's own code,
and the pulses it delivers match the Python model's but for the documented equivalences: every start
shifted by one constant (the firmware starts its timer after its boot's stack detection, the model at 0)
and every pulse 0.2 µs longer (the two chip-select writes between the DAC changes, 0.1 µs each).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from tactdeform_hw.device import EtactileKitDevice, open_device
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.firmware_probe import FirmwareMismatchError
from tactdeform_hw.emulator.faults import TimedPort
from tactdeform_hw.emulator.firmware.scan import POWER_ON_LEVELS, PulseKind
from tactdeform_hw.emulator.hostbuild import find_compiler
from tactdeform_hw.emulator.hostbuild.statemap import StateMap
from tactdeform_hw.emulator.hostbuild.timed import HostBuildTimedModel
from tactdeform_hw.emulator.records.trace import MemorySink
from tactdeform_hw.emulator.serving.pty_server import PtyServer
from tactdeform_hw.emulator.serving.realtime import RealtimeEmulator
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.errors import (
    ConfigurationError,
    DeviceGoneError,
    FirmwareBuildError,
    TransportError,
)

TINY = Path(__file__).parent / "data" / "firmware_tiny"
TINY_MAP = StateMap.from_toml(TINY / "hostbuild_state.toml")

try:
    find_compiler()
    HAVE_CXX = True
except FirmwareBuildError:
    HAVE_CXX = False

pytestmark = pytest.mark.skipif(not HAVE_CXX, reason="no C++ compiler on PATH (c++, g++ or clang++)")

#: The pulse the driver asks for in the comparison: electrodes 3 and 10 monophasic, 20 biphasic.
PATTERN = tuple(1 if i in (3, 10) else 2 if i == 20 else 0 for i in range(32))


def _v1_2_tree() -> Path:
    raw = os.environ.get("TACTDEFORM_HW_UPSTREAM_V1_2")
    if not raw:
        pytest.skip("set TACTDEFORM_HW_UPSTREAM_V1_2 to the v1.2 PlatformIO tree (platform_io_project)")
    tree = Path(raw)
    if not (tree / "src").is_dir():
        pytest.skip(f"TACTDEFORM_HW_UPSTREAM_V1_2={raw} holds no PlatformIO tree (src/)")
    return tree


def test_a_firmware_without_a_declared_version_has_no_board_state() -> None:
    model = HostBuildTimedModel(TINY, state_map=TINY_MAP)
    model.advance_to(3000)
    assert model.firmware is None
    with pytest.raises(ConfigurationError, match="firmware = 'v1.2' or 'v2'.*electrode_num"):
        model.state()


def test_the_tiny_firmware_replies_through_the_link() -> None:
    """'E' n replies n + 1, once the USB link has carried the bytes and the firmware's loop read them."""
    model = HostBuildTimedModel(TINY, state_map=TINY_MAP)
    model.write(b"E\x29", at_us=0)
    assert model.in_flight == 2
    assert model.run_until_idle()
    assert model.read_tx() == b"\x2a"
    assert model.in_flight == 0


def test_the_large_board_runs_the_firmwares_large_branch_upstream_v1_2() -> None:
    """``board="large"`` builds the tree with ``ETACTILEKIT_BOARD`` (its own cached build): the firmware's
    stack detection then counts 8 HV513 per board, as the Python model of the large board does."""
    tree = _v1_2_tree()
    for boards in (1, 2):
        large = HostBuildTimedModel(tree, "large", boards)
        large.advance_to(5000)
        compact = HostBuildTimedModel(tree, "compact", boards)
        assert large.state().hv513_num == TimedEmulator("large", boards).state().hv513_num == 8 * boards
        assert compact.host.built.key != large.host.built.key


def test_replies_travel_back_over_the_link() -> None:
    """A reply byte reaches the host one UART byte time (10.85 µs at 921 600 baud) after the firmware wrote
    it, as the Python models' replies do; not the moment the firmware wrote it."""
    model = HostBuildTimedModel(TINY, state_map=TINY_MAP, link="uart")
    model.write(b"E\x29", at_us=0)
    assert model.run_until_idle()
    ((written_us, data),) = model.host.tx_log
    assert data == b"\x2a"
    model2 = HostBuildTimedModel(TINY, state_map=TINY_MAP, link="uart")
    model2.write(b"E\x29", at_us=0)
    model2.advance_to(written_us + 10.8)
    assert model2.in_waiting == 0
    model2.advance_to(written_us + 10.9)
    assert model2.read_tx() == b"\x2a"


def test_a_stopped_main_loop_reads_nothing_until_a_reset() -> None:
    """``stop_reading`` (the fault campaigns' hung main loop): the firmware keeps running but its reads find
    nothing, so 'E' gets no reply and its bytes wait in the queue; a power-up reads again."""
    model = HostBuildTimedModel(TINY, state_map=TINY_MAP)
    model.advance_to(2000)
    model.stop_reading()
    model.write(b"E\x29")
    model.advance(20_000)
    assert model.read_tx() == b""
    assert len(model.queue) == 2
    model.reset()
    model.write(b"E\x29")
    model.advance(20_000)
    assert model.read_tx() == b"\x2a"


def test_the_driver_refuses_a_served_firmware_that_is_no_etactilekit() -> None:
    board = RealtimeEmulator(timed=HostBuildTimedModel(TINY, state_map=TINY_MAP))  # type: ignore[arg-type]
    assert board.firmware is None
    server = PtyServer(board)
    server.start()
    try:
        with pytest.raises((FirmwareMismatchError, DeviceGoneError)) as refused:
            open_device(server.path, guardian=False, settle_s=0.05, timeout=0.2)
    finally:
        server.stop()
    # the identification's refusal; on a pty the driver's retry then finds no reset line (no RTS ioctl)
    chain: list[BaseException] = []
    exc: BaseException | None = refused.value
    while exc is not None:
        chain.append(exc)
        exc = exc.__cause__ or exc.__context__
    first = next(e for e in chain if isinstance(e, FirmwareMismatchError))
    assert "identification did not answer" in str(first) and "only bytes that stop current" in str(first)


def test_the_url_handler_serves_a_host_build() -> None:
    with pytest.raises(FirmwareMismatchError):
        open_device(f"etactile://?firmware_src={TINY}", guardian=False, settle_s=0.05, timeout=0.2)


def test_the_url_handler_refuses_an_untimed_host_build() -> None:
    with pytest.raises(
        TransportError, match="firmware_src= runs the built firmware in real time; drop timed=0"
    ):
        open_device(f"etactile://?firmware_src={TINY}&timed=0", guardian=False)


def _session(model: object, firmware: str = "v1.2") -> TimedPort:
    port = TimedPort(model, link="usb")  # type: ignore[arg-type]
    dev = EtactileKitDevice(port, firmware="auto", guardian=False)
    assert dev.firmware == firmware
    dev.configure(StimConfig(electrode_count=32, current_ua=1000))
    dev.send_pattern(PATTERN if firmware == "v1.2" else tuple(min(v, 1) for v in PATTERN))
    port.advance(0.1)
    dev.all_off()
    port.advance(0.05)
    return port


def test_the_driver_runs_upstream_v1_2_as_it_runs_the_model() -> None:
    tree = _v1_2_tree()
    built = _session(HostBuildTimedModel(tree)).emulator
    python = _session(TimedEmulator("compact", 1)).emulator
    assert built.state() == python.state()  # every register, read from the firmware's own variables
    a = built.reports.pulse_table()
    b = python.reports.pulse_table()
    live = np.nonzero(b["code"] > 0)[0]
    # the driver's calls end about 3 ms earlier on the host build (its replies have no link delay), so
    # the final all-off may land one scan (4 pulses: electrodes 3, 10 and 20's two phases) apart
    n = min(a["code"].size, live.size)
    assert n > 30 and abs(a["code"].size - live.size) <= 4
    live = live[:n]
    assert a["channel"][:n].tolist() == b["channel"][live].tolist()
    assert a["code"][:n].tolist() == b["code"][live].tolist()
    assert a["kind"][:n].tolist() == b["kind"][live].tolist()  # monophasic and both biphasic phases
    assert np.allclose(a["width_us"][:n], b["width_us"][live] + 0.2)  # the chip-select writes
    # one timer origin for the whole session: every scan is shifted alike, pulse by pulse.  Within a
    # scan the shifts differ by up to 10.6 us (987.85, 983.65, 977.65, 977.25 here): the pulse table's
    # start inside a scan is not yet the same instant in both records (docs/firmware-host-build.md)
    shift = (b["start_us"][live] - a["start_us"][:n]).reshape(-1, 4)
    assert np.allclose(shift, shift[0])


def test_pulse_kinds_are_the_firmwares_choice_at_each_scan_upstream_v1_2() -> None:
    """v1.2 chooses a channel's pulse by its pattern value when the scan reaches it: 1 monophasic, 2
    biphasic, anything else a sense pulse.  Here the sense height equals the pulse height (12), so a DAC
    code cannot tell them apart, and the configuration lands inside one long step: the kinds must still
    follow the pattern as each scan found it (channels 1 and 3 stimulate once the pattern is read,
    everything else is sensed)."""
    tree = _v1_2_tree()
    model = HostBuildTimedModel(tree)
    # 4 electrodes, sense height 3 << 2 = 12, sense width 30, pulse height 12, pulse width 30, then the
    # pattern (channel 1 monophasic, channel 3 biphasic) 20 ms later
    model.write(bytes([0xFC, 4, 0xF9, 3, 0xF8, 30, 0xFB, 12, 0, 0xFA, 30, 0]), at_us=0)
    model.write(bytes([0xFE, 0, 1, 0, 2]), at_us=20_000)
    model.advance_to(60_000)  # one step: the registers changed several times inside it
    table = model.reports.pulse_table()
    assert set(table["code"].tolist()) == {12}
    pattern_read = min(
        s.t_us for s in model.host.isr_samples() if s.register == "stim_pattern" and s.value == 2
    )
    before = table["start_us"] < pattern_read
    sense = int(PulseKind.SENSE)
    assert before.sum() > 0 and set(table["kind"][before].tolist()) == {sense}
    after = ~before
    by_channel = {ch: set(table["kind"][after & (table["channel"] == ch)].tolist()) for ch in range(4)}
    assert by_channel == {
        0: {sense},
        1: {int(PulseKind.MONO)},
        2: {sense},
        3: {int(PulseKind.BI_ANODIC), int(PulseKind.BI_CATHODIC)},
    }


def test_upstream_v1_2_served_on_a_pty_is_identified_and_stimulates() -> None:
    tree = _v1_2_tree()
    model = HostBuildTimedModel(tree)
    board = RealtimeEmulator(timed=model)  # type: ignore[arg-type]
    server = PtyServer(board)
    server.start()
    try:
        dev = open_device(server.path, guardian=False, settle_s=0.05, timeout=2.0)  # a loaded machine
        assert dev.firmware == "v1.2"
        dev.configure(StimConfig(electrode_count=32, current_ua=1000))
        dev.send_pattern(PATTERN)
        state = board.state()
        dev.close()
    finally:
        server.stop()
    assert state.electrode_num == 32
    with board.lock:
        pulses = model.delivered_pulses()
    assert {out for p in pulses for out in p.outputs} <= {3, 10, 20}
    assert {p.code for p in pulses} <= {100}
    assert all(abs(p.width_us - 196.8) < 1e-6 for p in pulses)


def test_emulate_refuses_firmware_src_with_untimed(capsys: pytest.CaptureFixture[str]) -> None:
    from tactdeform_hw.cli import main

    assert main(["emulate", "--pty", "--untimed", "--firmware-src", str(TINY)]) != 0
    err = capsys.readouterr().err
    assert "--firmware-src" in err and "--untimed" in err and "Traceback" not in err


def test_timing_refuses_a_tree_without_a_shipped_state_map(capsys: pytest.CaptureFixture[str]) -> None:
    from tactdeform_hw.cli import main

    assert main(["timing", "--firmware-src", str(TINY)]) != 0
    err = capsys.readouterr().err
    assert "--firmware-src" in err and "state map" in err and "Traceback" not in err


def test_timing_measures_the_budget_on_upstream_v1_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The TactDeform setting: the firmware's own scan is 7869.45 µs of its 8000 µs period (the Python
    model's budget says 7850.25: 0.6 µs a channel of chip-select writes it counts inside the exchange)."""
    import json

    from tactdeform_hw.cli import main

    tree = _v1_2_tree()
    events = tmp_path / "ev.json"
    vcd = tmp_path / "scan.vcd"
    argv = [
        "timing",
        "--firmware-src",
        str(tree),
        "--cycles",
        "2",
        "--events",
        str(events),
        "--vcd",
        str(vcd),
    ]
    assert main([*argv, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["firmware"] == "v1.2" and out["period_us"] == 8000 and out["scans"] == 2
    assert out["scan_us"]["max"] == pytest.approx(7869.45)
    assert out["margin_us"] == pytest.approx(130.55) and out["overrun"] is False
    ev = json.loads(events.read_text())
    assert sum(1 for e in ev if e[1] == "DAC" and e[3] > 0) == 2 * 32  # one pulse per electrode per scan
    assert "$var" in vcd.read_text()


def test_a_state_map_declares_its_firmware(tmp_path: Path) -> None:
    from tactdeform_hw.emulator.hostbuild.statemap import UPSTREAM_V1_2, UPSTREAM_V2

    assert (UPSTREAM_V1_2.firmware, UPSTREAM_V2.firmware) == ("v1.2", "v2")
    good = tmp_path / "good.toml"
    good.write_text('unit = "a.cpp"\nfirmware = "v2"\n[registers]\nx = "x"\n')
    assert StateMap.from_toml(good).firmware == "v2"
    bad = tmp_path / "bad.toml"
    bad.write_text('unit = "a.cpp"\nfirmware = 2\n[registers]\nx = "x"\n')
    with pytest.raises(ConfigurationError, match="firmware must be a version's name"):
        StateMap.from_toml(bad)


def test_the_driver_runs_upstream_v2_as_it_runs_the_model() -> None:
    """v2: the same registers but ``command_in_progress`` (a function-local static: ``None`` on the host
    build) and the same pulses, electrode by electrode and code by code."""
    from dataclasses import replace

    from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2

    raw = os.environ.get("TACTDEFORM_HW_UPSTREAM_V2")
    if not raw or not (Path(raw) / "src").is_dir():
        pytest.skip("set TACTDEFORM_HW_UPSTREAM_V2 to the v2 PlatformIO tree (platform_io_project)")
    built = _session(HostBuildTimedModel(raw), "v2").emulator
    python = _session(TimedEmulatorV2("compact", 1), "v2").emulator
    assert built.state().command_in_progress is None
    assert replace(built.state(), command_in_progress=False) == python.state()
    a = built.reports.pulse_table()
    b = python.reports.pulse_table()
    live = b["code"] > 0
    assert a["code"].size == int(live.sum()) > 20
    assert a["channel"].tolist() == b["channel"][live].tolist()
    assert a["code"].tolist() == b["code"][live].tolist()


def test_emulate_serves_upstream_v1_2_as_its_usb_device() -> None:
    """``emulate --usb --firmware-src``: the built firmware behind the emulated USB device, in its own
    process; the driver opens the printed name through pyusb, and the board reports what it delivered."""
    import signal
    import subprocess
    import sys

    pytest.importorskip("usb.core", reason="the USB device needs pyusb (pip install 'tactdeform_hw[usb]')")
    tree = _v1_2_tree()
    cmd = [sys.executable, "-m", "tactdeform_hw.cli", "emulate", "--usb", "--firmware-src", str(tree)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        name = proc.stdout.readline().strip()
        assert name.startswith("usb-emulator://"), proc.stderr.read() if proc.stderr else ""
        dev = open_device(name, guardian=False, settle_s=0.05)
        assert dev.firmware == "v1.2"
        dev.configure(StimConfig(electrode_count=8, current_ua=500, rate_hz=20))
        dev.send_pattern([0, 0, 1, 0, 0, 0, 0, 0])
        dev.all_off()
        dev.close()
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=10)
    assert "Traceback" not in err
    assert "firmware v1.2" in err, err


def _signals(sink: MemorySink) -> list[tuple[int, str, int]]:
    """The sink's signal changes after the power-on levels ``begin`` wrote, as (ns, name, value)."""
    return [(t, n, v) for t, n, v in sink.events if not n.startswith("MARK:")][len(POWER_ON_LEVELS) :]


def test_a_trace_of_a_host_build_is_the_firmwares_own_pin_and_dac_events() -> None:
    """A sink attached to a host build receives every pin and DAC event the firmware wrote, as the
    firmware's record has them (:meth:`HostBuildEmulator.events`), however the clock was advanced."""
    model = HostBuildTimedModel(TINY, state_map=TINY_MAP)
    sink = MemorySink()
    model.attach(sink)
    model.write(b"V\x23\x01", at_us=0)
    for step_us in (1.0, 333.0, 2500.0, 17.0, 4000.0):  # steps inside and across scans
        model.advance(step_us)
    expected = model.host.events()
    model.detach(sink)
    sink.close()  # a sink holds its last run until the next one or its close
    got = _signals(sink)
    assert got == [  # the chip select (pin 40) is no board signal
        (round(t_us * 1000), "DAC" if kind == "DAC" else "DIN", value)
        for t_us, kind, pin, value in expected
        if pin in ("DAC", 5)
    ]
    codes = [v for _t, n, v in got if n == "DAC"]
    assert len(codes) >= 9 and codes[-1] == 0x123  # one exchange per interrupt; the command's code lands
    assert [v for _t, n, v in got if n == "DIN"][:4] == [1, 0, 1, 0]  # TINY_PIN is the board's DIN pin


def test_a_host_build_trace_keeps_the_events_the_model_trims() -> None:
    """The model keeps only ``event_history_us`` of the firmware's record; the trace has every scan."""
    model = HostBuildTimedModel(TINY, state_map=TINY_MAP, event_history_us=2000.0)
    sink = MemorySink()
    model.attach(sink)
    for _ in range(40):
        model.advance(500.0)
    model.detach(sink)
    sink.close()
    isr_count = int(model.host.state()["isr_count"])
    got = _signals(sink)
    assert isr_count == 28  # 20 ms at the 700 µs period
    assert sum(1 for _t, n, _v in got if n == "DAC") == isr_count
    assert sum(1 for _t, n, v in got if n == "DIN" and v == 1) == isr_count


def test_a_host_build_trace_marks_losses_and_resets_and_continues_in_model_time() -> None:
    """A full receive queue's loss and a power-up are markers; the next copy's events come in the model's
    clock (shifted by its boot time), after the marker."""
    model = HostBuildTimedModel(TINY, state_map=TINY_MAP)
    sink = MemorySink()
    model.attach(sink)
    model.advance_to(2000)
    model.stop_reading()
    model.write(b"\x00" * 300)  # past the firmware's 128-byte queue
    model.advance(3000)
    model.reset("test")
    model.advance(3000)
    model.detach(sink)
    sink.close()  # a sink holds its last run until the next one or its close
    marks = [(t, n, d) for t, n, d in sink.events if n.startswith("MARK:")]
    loss = [m for m in marks if m[1] == "MARK:loss"]
    assert loss and sum(d["bytes"] for _t, _n, d in loss) == sum(lo.count for lo in model.losses)
    (reset,) = [m for m in marks if m[1] == "MARK:reset"]
    assert reset[0] == 5_000_000 and reset[2] == {"reason": "test"}
    after = [t for t, n, _v in _signals(sink) if n == "DAC" and t > reset[0]]
    first_dac_us = next(e[0] for e in model.host.events() if e[1] == "DAC")  # the new copy's own clock
    assert after and min(after) - model.boot_ns == round(first_dac_us * 1000)
    times = [t for t, _n, _v in sink.events]
    assert times == sorted(times)


def test_emulate_traces_a_host_build(tmp_path: Path) -> None:
    """``emulate --pty --trace F.json --firmware-src``: the served firmware's own events reach the file."""
    import json
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "t.json"
    cmd = [sys.executable, "-m", "tactdeform_hw.cli", "emulate", "--pty", "--quiet", "--trace", str(out)]
    proc = subprocess.Popen(
        [*cmd, "--firmware-src", str(TINY), "--state-map", str(TINY / "hostbuild_state.toml")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("/dev/")
        time.sleep(0.3)
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0 and "Traceback" not in err, err
    assert "trace written to" in err
    rows = json.loads(out.read_text())
    names = {r["name"] for r in rows if r["kind"] == "signal"}
    assert {"DAC", "DIN"} <= names
    assert sum(1 for r in rows if r["name"] == "DIN" and r["value"] == 1) >= 2  # scans ran while served
