"""The device layer on firmware v2, where v2 differs: per-electrode heights and the stimulation mode,
one waveform per frame, recovery by the sync check and the 2 s timeout, v2's stop — judged on what the
emulated board holds (untimed) and on the pulses it delivered (the timed v2 model).  What the driver
promises on every version runs over the registry in ``test_device_dialects.py``, ``test_device_driver.py``,
``test_device_timed.py`` and ``test_identification.py``."""

from __future__ import annotations

import random

import pytest

from tactdeform_hw.device.driver.base import LinkState
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice, open_device
from tactdeform_hw.device.driver.v2 import V2Dialect, off_packet
from tactdeform_hw.device.safety.guard import SafetyGuard
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.faults import TimedPort
from tactdeform_hw.emulator.serving.in_process import EmulatorPort
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2
from tactdeform_hw.errors import LimitError, SafetyError
from tactdeform_hw.protocol import commands as c12
from tactdeform_hw.protocol.commands import V2_COMMANDS as c2
from tactdeform_hw.protocol.firmware import V2, OpcodeV2
from tactdeform_hw.protocol.reader import iter_commands

from .safety_helpers import defects

REGIONS = [400, 800, 1200, 1600, 2000, 2000, 2000, 2000, 2000]


class V2Board(TimedEmulatorV2):
    """The timed v2 model with the host-side reply buffer :class:`TimedPort` reads from."""

    def __init__(self) -> None:
        super().__init__()
        self._host_rx = bytearray()
        self.drop_replies = 0  # replies lost on the way to the host (the first ``drop_replies`` bytes)

    def read_tx(self, size: int | None = None) -> bytes:  # type: ignore[override]
        got = super().read_tx()
        while got and self.drop_replies:
            got = got[1:]
            self.drop_replies -= 1
        self._host_rx += got
        n = len(self._host_rx) if size is None else min(size, len(self._host_rx))
        out = bytes(self._host_rx[:n])
        del self._host_rx[:n]
        return out

    @property
    def in_waiting(self) -> int:
        self._host_rx += self.read_tx()
        return len(self._host_rx)

    def reset(self, why: str = "reset") -> None:
        self.emulator.reset()


def _timed_v2(
    guard: SafetyGuard | None = None, *, robust: bool = False
) -> tuple[EtactileKitDevice, TimedPort, V2Board]:
    board = V2Board()
    port = TimedPort(board, robust_encoding=robust)  # type: ignore[arg-type]
    dev = EtactileKitDevice(port, firmware="v2", guard=guard)
    return dev, port, board


def _untimed(fw: str) -> tuple[EmulatorPort, Emulator]:
    emu = Emulator(firmware=fw)
    return EmulatorPort(emu), emu


def _no_live_hazards(emu: Emulator) -> None:
    """Only the probe's zeros (unknown bytes) and the count raised over channels an earlier pattern left,
    which the driver does in mode 2 with sense height 0: every pulse of those scans has height 0."""
    assert [h.kind.value for h in defects(emu.hazards) if h.kind.value != "stale_channels"] == []


# --- configure, frames, all-off, close ---------------------------------------------------------------------


def test_configure_send_all_off_close_on_the_untimed_v2_url() -> None:
    dev = open_device("etactile://?firmware=v2&timed=0", firmware="v2")
    emu = dev.port.emulator  # type: ignore[attr-defined]
    assert isinstance(dev.dialect, V2Dialect) and dev.link_state is LinkState.IN_STEP
    dev.configure(
        StimConfig(
            electrode_count=4,
            current_ua=1000,
            pulse_width_us=150,
            discharge_us=40,
            rate_hz=200,
            polarity="cathodic",
        )
    )
    s = emu.state()
    assert (s.electrode_num, s.stim_mode, s.pulse_width_us, s.discharge_time_us, s.polarity) == (
        4,
        0,
        150,
        40,
        0,
    )
    assert list(s.stim_pattern[:4]) == [0, 0, 0, 0]
    dev.send_pattern([1, 0, 1, 0])
    assert list(emu.state().stim_pattern[:4]) == [100, 0, 100, 0] and emu.state().stim_mode == 0
    dev.send_pattern([0, 2, 2, 0])
    assert list(emu.state().stim_pattern[:4]) == [0, 100, 100, 0] and emu.state().stim_mode == 1
    dev.all_off()
    s = emu.state()
    assert list(s.stim_pattern[:4]) == [0, 0, 0, 0] and s.stim_mode in (0, 1)
    dev.close()
    assert list(emu.state().stim_pattern[:4]) == [0, 0, 0, 0] and emu.state().stim_mode != 2
    _no_live_hazards(emu)


def test_every_byte_the_v2_driver_writes_reads_as_v2_commands_and_never_mode_2_with_a_sense_height() -> None:
    port, emu = _untimed("v2")
    dev = EtactileKitDevice(port, firmware="v2")
    dev.configure(StimConfig(electrode_count=8, current_ua=500, sense_current_ua=100, sense_width_us=20))
    dev.send_pattern([1] * 8)
    dev.set_current(700)
    dev.send_pattern([2] * 8)
    dev.resync()
    dev.send_pattern([1, 0] * 4)
    dev.close()
    stream = bytes(emu.parser.rx) if hasattr(emu.parser, "rx") else b""
    sense, mode = 0, 0
    for c in iter_commands(stream, 0, firmware=V2):
        if c.opcode == OpcodeV2.SENSE_HEIGHT and c.complete:
            sense = c.value or 0
        if c.opcode == OpcodeV2.STIM_MODE and c.complete:
            mode = c.value or 0
            assert mode != 2 or sense == 0
        assert c.opcode != OpcodeV2.PULSE_WIDTH or c.read_value != 0  # 0 is stored on v2: never sent
    assert stream and emu.state().stim_mode != 2
    _no_live_hazards(emu)


def test_mixed_mono_and_biphasic_frame_is_refused_before_any_byte() -> None:
    port, emu = _untimed("v2")
    dev = EtactileKitDevice(port, firmware="v2")
    dev.configure(StimConfig(electrode_count=4, current_ua=500))
    before = len(emu.parser.rx)
    with pytest.raises(LimitError, match="one waveform per frame"):
        dev.send_pattern([1, 2, 0, 0])
    assert len(emu.parser.rx) == before
    dev.close()


def test_per_electrode_limits_are_exact_on_the_timed_v2_model() -> None:
    guard = SafetyGuard(2000, regions_ua=REGIONS)
    dev, port, board = _timed_v2(guard)
    dev.configure(StimConfig(electrode_count=32, current_ua=1500))
    t = port.now_s
    dev.send_pattern([1] * 32)
    port.advance(0.05)
    peak = board.peak_current_ua(since_us=t * 1e6)
    limits = guard.electrode_limits(32)
    assert peak == {ch: float(min(1500, limits[ch])) for ch in range(32)}
    assert len(set(peak.values())) > 2  # regional, not the frame's lowest limit
    dev.all_off()
    t_off = port.now_s
    port.advance(0.05)
    assert board.peak_current_ua(since_us=(t_off + 0.02) * 1e6) == {}
    dev.close()
    _no_live_hazards(board.emulator)


def test_each_electrode_ramps_from_its_own_height() -> None:
    guard = SafetyGuard(2000, ramp_ua_per_frame=300)
    dev, port, board = _timed_v2(guard)
    dev.configure(StimConfig(electrode_count=4, current_ua=1000))
    seen = []
    for _ in range(5):
        dev.send_pattern([1, 1, 0, 0])
        port.advance(0.01)
        seen.append(board.state().stim_pattern[:4])
    assert [s[0] for s in seen] == [30, 60, 90, 100, 100]
    dev.send_pattern([1, 1, 1, 0])  # electrode 2 starts soft while 0 and 1 stay
    port.advance(0.01)
    assert list(board.state().stim_pattern[:4]) == [100, 100, 30, 0]
    t = port.now_s
    port.advance(0.05)
    assert max(board.peak_current_ua(since_us=t * 1e6).values()) <= 1000
    dev.close()


def test_the_interlock_refuses_a_height_above_an_electrodes_own_limit() -> None:
    port, emu = _untimed("v2")
    guard = SafetyGuard(2000, regions_ua=REGIONS)
    dev = EtactileKitDevice(port, firmware="v2", guard=guard)
    dev.configure(StimConfig(electrode_count=32, current_ua=0))
    before = len(emu.parser.rx)
    heights = [0] * 32
    heights[0] = 50  # 500 µA on electrode 0, whose region allows 400
    with pytest.raises(SafetyError, match="channel 0 would receive 500"):
        dev._send(c2.encode_pattern(heights))
    heights[0] = 40
    heights[12] = 200  # 2000 µA where 2000 is allowed (no ramp): passes
    dev._send(c2.encode_pattern(heights))
    with pytest.raises(SafetyError, match="mode 2"):
        dev._send(c2.encode_sense_height(10))
        dev._send(c2.encode_stim_mode(2))
    assert len(emu.parser.rx) - before == len(c2.encode_pattern(heights)) + 2
    dev.close()


def test_refresh_rewrites_the_mode_in_force_after_a_mode_2_misread() -> None:
    """v2's mode byte read as mode 2 (the sense pulse on every channel): ``refresh`` puts the frame's mode
    back with its heights (the version-neutral refresh, suspend and keepalive are in
    ``test_device_dialects.py``)."""
    port, emu = _untimed("v2")
    dev = EtactileKitDevice(port, firmware="v2")
    dev.configure(StimConfig(electrode_count=3, current_ua=300))
    dev.send_pattern([1, 1, 0])
    emu.feed(c2.encode_stim_mode(2))  # a mode byte mis-read: the sense pulse on every channel
    dev.refresh()
    assert emu.state().stim_mode == c2.STIM_MODE_MONOPHASIC
    assert list(emu.state().stim_pattern[:3]) == [30, 30, 0]
    dev.close()


def test_the_guardians_stop_on_v2_stops_current_from_any_parser_state() -> None:
    pkt = off_packet(32)
    for prefix in (b"", bytes([0xFE]), c2.encode_electrode_num(255) + bytes([0xFE, 1]), bytes([0xFA, 7])):
        emu = Emulator(firmware="v2")
        emu.feed(c2.encode_electrode_num(32) + c2.encode_pattern([100] * 32) + prefix)
        emu.feed(pkt)
        s = emu.state()
        assert s.electrode_num == 0 and s.stim_mode == 0 and not s.command_in_progress


# --- recovery -----------------------------------------------------------------------------------------------


def test_recovery_after_a_cut_pattern_on_v2_delivers_nothing_above_the_limits() -> None:
    guard = SafetyGuard(2000, regions_ua=REGIONS)
    dev, port, board = _timed_v2(guard)
    dev.configure(StimConfig(electrode_count=32, current_ua=1500))
    dev.send_pattern([1] * 32)
    assert dev.state.codes is not None
    cut = c2.encode_pattern(dev.state.codes)[:41]  # the driver's own write, cut inside a height
    board.write(cut)
    dev.mark_unknown()
    t = port.now_s
    dev.send_pattern([1] * 32)
    assert dev.link_state is LinkState.IN_STEP
    port.advance(0.05)
    peak = board.peak_current_ua(since_us=t * 1e6)
    limits = guard.electrode_limits(32)
    assert all(peak.get(ch, 0) <= limits[ch] for ch in range(32))
    assert list(board.state().stim_pattern[:32]) == [
        dev.transfer.to_code(min(1500, lim)) for lim in limits[:32]
    ]
    dev.close()


def test_a_missing_sync_reply_waits_past_the_2s_timeout_then_proves_again() -> None:
    dev, port, board = _timed_v2()
    dev.configure(StimConfig(electrode_count=8, current_ua=600))
    dev.send_pattern([1] * 8)
    board.write(bytes([0xFA]))  # a cut command pending on the board
    board.drop_replies = 1  # and the probe's sync reply lost
    dev.mark_unknown()
    t0 = port.now_s
    dev.send_pattern([1] * 8)
    flushing = [t for t, _, new, _ in dev.transitions if new == LinkState.FLUSHING.value and t >= t0]
    proved = [t for t, _, new, _ in dev.transitions if new == LinkState.SAFE.value and t >= t0]
    assert flushing and proved and proved[-1] - flushing[0] > 2.0
    port.advance(0.01)
    assert list(board.state().stim_pattern[:8]) == [60] * 8 and not board.state().command_in_progress
    t = port.now_s
    port.advance(0.05)
    assert max(board.peak_current_ua(since_us=t * 1e6).values()) == 600
    dev.close()


def test_v12_bytes_never_reach_the_v2_dialect() -> None:
    assert c12.encode_pulse_height(100)[0] == OpcodeV2.STIM_MODE  # the same byte, another meaning
    port, emu = _untimed("v2")
    dev = EtactileKitDevice(port, firmware="v2")
    dev.configure(StimConfig(electrode_count=2, current_ua=100))
    dev.send_pattern([1, 1])
    dev.close()
    modes = [c.value for c in iter_commands(bytes(emu.parser.rx), 0, firmware=V2) if c.opcode == 0xFB]
    assert modes and set(modes) <= {0, 1, 2}


def test_cli_send_drives_a_v2_board_with_auto_and_reports_per_electrode_heights(
    capsys: pytest.CaptureFixture[str],
) -> None:
    import json

    from tactdeform_hw.cli import main

    argv = [
        "send",
        "--device",
        "etactile://?firmware=v2&timed=0",
        "--firmware",
        "auto",
        "--pattern",
        "1,1,0,1",
        "--electrodes",
        "4",
        "--current-ua",
        "300",
        "--hold-ms",
        "0",
        "--json",
    ]
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["emulator_pattern"] == [30, 30, 0, 30] and out["emulator_state"]["stim_mode"] == 0
    assert out["delivered"]["max_delivered_ua"] == 300
    assert [e["electrode"] for e in out["delivered"]["electrodes"]] == [0, 1, 3]
    argv[2], argv[4] = "etactile://?firmware=v1.2&timed=0", "v2"
    assert main(argv) != 0
    assert "runs firmware v1.2" in capsys.readouterr().err


def test_a_guardian_is_given_the_v2_stop() -> None:
    class _Guardian:
        stops: list[bytes] = []

        def set_stop(self, packet: bytes) -> bool:
            self.stops.append(packet)
            return True

    port, emu = _untimed("v2")
    dev = EtactileKitDevice(port)
    g = _Guardian()
    dev.guardians.guardian = g  # type: ignore[assignment]
    dev.speak(V2)
    assert g.stops == [off_packet(0)]
    dev.guardians.guardian = None
    dev.wire.closed = True
    # the stop leaves a v2 pattern in progress complete with zeros, and no height above 0
    emu.feed(c2.encode_electrode_num(8) + bytes([0xFE, 0x20]) + g.stops[0])
    assert list(emu.state().stim_pattern[:8]) == [0x20] + [0] * 7 and emu.state().electrode_num == 0


@pytest.mark.parametrize("seed", range(60))
def test_random_sessions_on_the_timed_v2_model_never_exceed_an_electrodes_limit(seed: int) -> None:
    """Random public calls (configure, frames mono and biphasic, set_current, keepalive, suspend, all_off,
    resync, refresh, time passing) on the timed v2 model, judged on every pulse it delivered: none above
    its own electrode's limit or the charge limit, and no firmware defect hit but the probe's unknown bytes
    and stale channels raised in mode 2 at sense height 0."""
    import random

    rng = random.Random(seed)
    n = rng.choice([4, 16, 32, 32])  # the compact board drives 32 outputs
    regions = n == 32 and rng.random() < 0.7
    cap = rng.choice([800, 1500, 3000])
    guard = SafetyGuard(
        cap,
        regions_ua=[min(cap, r) for r in REGIONS] if regions else None,
        ramp_ua_per_frame=rng.choice([None, 200, 500]),
    )
    dev, port, board = _timed_v2(guard, robust=seed % 2 == 1)  # odd seeds: the loss-tolerant encoding
    limits = guard.electrode_limits(n)
    cfg = StimConfig(
        electrode_count=n,
        current_ua=rng.randrange(0, cap + 1, 10),
        pulse_width_us=rng.choice([50, 100, 200]),
        rate_hz=rng.choice([60, 125, 200]),
    )
    try:
        dev.configure(cfg)
    except SafetyError as exc:  # every channel is pulsed each scan on v2: the scan must fit the period
        assert "scan" in str(exc)
        cfg = StimConfig(electrode_count=n, current_ua=cfg.current_ua, pulse_width_us=50, rate_hz=60)
        dev.configure(cfg)
    for _ in range(40):
        op = rng.random()
        if op < 0.45:
            kind = rng.choice([1, 2])
            try:
                dev.send_pattern([kind if rng.random() < 0.5 else 0 for _ in range(n)])
            except SafetyError as exc:  # v2 pulses every channel: a biphasic scan may not fit the period
                assert "scan" in str(exc)
        elif op < 0.55:
            dev.set_current(rng.randrange(0, cap + 1, 10))
        elif op < 0.62:
            dev.keepalive()
        elif op < 0.68:
            dev.suspend()
        elif op < 0.74:
            dev.all_off()
            dev.set_current(rng.randrange(0, cap + 1, 10))
        elif op < 0.78:
            dev.resync()
        elif op < 0.82:
            dev.refresh()
        else:
            port.advance(rng.uniform(0.0, 0.03))
    dev.close()
    port.advance(0.05)
    charge_ua = guard.charge_limit_ua(cfg.pulse_width_us)
    worst = {}
    for row in board.delivered():
        ch = row["channel"]
        assert row["current_ua"] <= min(limits[ch], charge_ua) + 1e-6, row
        worst[ch] = max(worst.get(ch, 0.0), row["current_ua"])
    assert [h.kind.value for h in defects(board.hazards) if h.kind.value != "stale_channels"] == []
    assert board.peak_current_ua(since_us=(port.now_s - 0.03) * 1e6) == {}  # closed: nothing any more


def test_cli_render_drives_a_v2_board_and_its_check_reads_heights(capsys: pytest.CaptureFixture[str]) -> None:
    from tactdeform_hw.cli import main

    rc = main(
        [
            "render",
            "--scene",
            "cube",
            "--trajectory",
            "approach-face",
            "--device",
            "etactile://?firmware=v2&timed=0",
            "--firmware",
            "auto",
            "--current-ua",
            "1000",
            "--quiet",
        ]
    )
    assert rc == 0, capsys.readouterr().err
    assert "0 mismatch(es) against the emulator" in capsys.readouterr().out


@pytest.mark.parametrize("seed", range(6))
def test_the_loss_tolerant_encoding_never_echoes_the_electrode_count(seed: int) -> None:
    """v1.2's loss-tolerant encoding repeats the electrode count after it; v2 never gets that echo (a count
    of 0xF4 would echo a sync check), on no path: configure, raise, recovery or a new program."""
    rng = random.Random(seed)
    dev, port, board = _timed_v2(robust=True)
    sent: list[bytes] = []
    write = port.write

    def logged(data: bytes) -> int:
        sent.append(bytes(data))
        return write(data)

    port.write = logged  # type: ignore[method-assign]
    for _ in range(12):
        n = rng.choice([1, 4, 16, 32])
        dev.configure(StimConfig(electrode_count=n, current_ua=500, pulse_width_us=100, rate_hz=60))
        dev.send_pattern([rng.choice([0, 1]) for _ in range(n)])
        getattr(dev, rng.choice(["resync", "reconnect", "hardware_reset", "keepalive", "all_off"]))()
    dev.close()
    wire = b"".join(sent)
    echoes = [
        i
        for i in range(len(wire) - 2)
        if wire[i] == 0xFC and 0 < wire[i + 1] <= 32 and wire[i + 2] == wire[i + 1]
    ]
    assert echoes == [], f"electrode count echoed at byte offsets {echoes[:5]}"
