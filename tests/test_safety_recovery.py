"""Closed-loop recovery, judged on the pulses the timed emulator delivered.

Each finding the recovery answers has a test here, over USB full speed and a UART, with the loss-tolerant
encoding and without: a resync into a full queue (the mechanism that delivered DAC code 4095), queue
overflows after resync, reconnect and hardware_reset, a queue model that forgot bytes in flight, the
biphasic worst case, a reset without drain, boot wait or proof, and a pattern in flight landing on
firmware just reset.  Every transition of the recovery state machine is walked on both links, and the
proof sequence runs once over a real pty.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
import serial

from tactdeform_hw.clock import SimulatedClock
from tactdeform_hw.device import EtactileKitDevice, StimConfig
from tactdeform_hw.device.driver.base import TRANSITIONS, LinkState
from tactdeform_hw.device.driver.dialect import worst_scan_s
from tactdeform_hw.device.driver.firmware_probe import UnidentifiedBoardError
from tactdeform_hw.device.driver.pacing import Pacer, estimate_scan_us, firmware_period_us
from tactdeform_hw.device.safety.guard import SafetyGuard
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.faults import TimedPort
from tactdeform_hw.emulator.firmware.hazards import HazardKind
from tactdeform_hw.emulator.serving.in_process import EmulatorPort
from tactdeform_hw.emulator.serving.pty_server import PtyServer
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.errors import TactDeformError
from tactdeform_hw.protocol import commands as p

from .safety_helpers import defects

LINKS = ["usb", "uart"]
ENCODINGS = [False, True]
BOTH = [(link, robust) for link in LINKS for robust in ENCODINGS]
IDS = [f"{link}-{'robust' if robust else 'plain'}" for link, robust in BOTH]


def session(link: str, robust: bool, n: int = 32, boards: int = 1) -> tuple[TimedPort, EtactileKitDevice]:
    emu = TimedEmulator("compact", boards, link=link)
    port = TimedPort(emu, link=link, robust_encoding=robust)
    return port, EtactileKitDevice(port, guard=SafetyGuard())


def big_config(robust: bool, current_ua: int = 400) -> StimConfig:
    """The whole queue in one pattern (255 electrodes; 244 under robust encoding, whose payload bytes must
    stay below 0xF5), with a scan long enough to hold the parser off for tens of milliseconds."""
    n = 244 if robust else 255
    return StimConfig(
        electrode_count=n, current_ua=current_ua, pulse_width_us=200, discharge_us=10, rate_hz=7
    )


def max_delivered_ua(emu: TimedEmulator) -> float:
    """The largest current any pulse carried: the DAC code's current or the skin model's, whichever is
    larger (a pulse at code 4095 counts as 40.95 mA even where the compliance voltage limits it)."""
    table = emu.reports.pulse_table()
    if table["code"].size == 0:
        return 0.0
    return float(np.maximum(table["current_ua"], table["code"] * 10.0).max())


def assert_clean(port: TimedPort, limit_ua: float) -> None:
    emu = port.emulator
    port.advance(0.05)
    assert max_delivered_ua(emu) <= limit_ua + 1e-6
    assert emu.losses == [], [lo.describe() for lo in emu.losses[:3]]
    assert not [
        h
        for h in defects(emu.hazards)
        if h.kind not in (HazardKind.TORN_PATTERN, HazardKind.SENSE_CURRENT, HazardKind.U16_WAITING)
    ]
    assert all(c.in_sync for c in emu.commands)


def states(dev: EtactileKitDevice, since: int = 0) -> list[str]:
    return [t[2] for t in list(dev.transitions)[since:]]


# --- the control: what an open-loop resync into a full queue does on this firmware --------------------------


def test_control_a_height_cut_by_a_full_queue_becomes_4095() -> None:
    """The mechanism the recovery prevents, on the emulated firmware alone: while a long scan holds the
    parser off, a write fills the queue; of "pulse height 0" only ``fb 00`` fits and the rest of the packet
    is discarded; the next command's byte ``f9`` then completes the height as 0xF900, clamped to 4095."""
    emu = TimedEmulator("compact", 8, link="usb")
    cfg = (
        b"\xfc\xff" + b"\xfe" + bytes([1]) + bytes(254) + b"\xfa\xc8\x00" + b"\xf6\x07\x00" + b"\xfb\x28\x00"
    )
    for i in range(0, len(cfg), 3):
        emu.write(cfg[i : i + 3])
        emu.advance(2000)
    emu.advance(300_000)
    assert emu.state().pulse_height == 40 and emu.state().stim_pattern[0] == 1
    # at an alarm: the scan (255 channels) holds the parser off for ~100 ms
    emu.advance_to(emu.next_alarm / 1000 + 10)
    emu.write(bytes(254) + b"\xfb\x00\x00")  # a resync's zeros, then height 0: the last byte does not fit
    emu.advance(200_000)
    emu.write(b"\xf9\x00")  # sense height 0: its command byte becomes the height's high byte
    emu.advance(400_000)
    assert emu.losses and emu.state().pulse_height == 4095
    assert max_delivered_ua(emu) >= 40_950 - 1e-6


# --- the findings, on the timed emulator -------------------------------------------------------------------


@pytest.mark.parametrize(("link", "robust"), BOTH, ids=IDS)
def test_resync_right_after_a_whole_queue_pattern_never_raises_a_current(link: str, robust: bool) -> None:
    cfg = big_config(robust)
    port, dev = session(link, robust, boards=8)
    dev.configure(cfg)
    levels = [1 if i % 3 == 0 else 0 for i in range(cfg.electrode_count)]
    for _ in range(3):
        dev.send_pattern(levels)  # the queue holds a whole pattern, and a scan holds the parser off
        dev.resync()  # ... and the resync comes at once
        dev.keepalive()
    assert_clean(port, cfg.current_ua)
    assert dev.link_state is LinkState.IN_STEP


@pytest.mark.parametrize(("link", "robust"), BOTH, ids=IDS)
@pytest.mark.parametrize("step", ["resync", "reconnect", "hardware_reset"])
def test_no_queue_overflow_after_resync_reconnect_or_reset(link: str, robust: bool, step: str) -> None:
    cfg = big_config(robust)
    port, dev = session(link, robust, boards=8)
    dev.configure(cfg)
    for i in range(4):
        dev.send_pattern([(i + k) % 2 for k in range(cfg.electrode_count)])
        getattr(dev, step)()
        dev.set_current(cfg.current_ua)
        dev.send_pattern([1] * cfg.electrode_count if i % 2 else [0] * cfg.electrode_count)
    dev.close()
    assert_clean(port, cfg.current_ua)


def test_pacer_keeps_bytes_in_flight_until_the_device_proves_them_read() -> None:
    clock = SimulatedClock()
    pacer = Pacer(clock=clock)
    pacer.set_timing(0.008, 0.0079)
    for _ in range(3):
        pacer.write(lambda _d: None, b"\xfe" + bytes(32))
    held = pacer.queue_estimate()
    assert held == 99
    pacer.reset()  # a reconnect or a reset: the queue is *not* assumed empty
    clock.advance(10.0)  # and no time passing drains it
    assert pacer.frozen and pacer.queue_estimate() == held
    mark = pacer.offset
    pacer.write(lambda _d: None, b"\xff")
    pacer.proven(mark)  # a reply to a request written at ``mark``: everything before it was read
    assert not pacer.frozen and pacer.queue_estimate() == 1


def test_pacer_fills_the_queue_with_a_margin_and_a_scan_may_block_right_after_arrival() -> None:
    clock = SimulatedClock()
    pacer = Pacer(clock=clock)
    pacer.set_timing(0.008, 0.0079)
    written: list[tuple[float, int]] = []
    for _ in range(12):
        pacer.write(lambda d: written.append((clock.now(), len(d))), b"\xfe" + bytes(32))
        assert pacer.queue_estimate() <= pacer.limit_bytes < 256
    # each pattern is counted until its arrival, a whole scan, and one parser call later
    t0, n0 = written[0]
    assert pacer._inflight and pacer.drained_by() > t0 + 0.0079


def test_worst_case_scan_counts_biphasic_channels() -> None:
    port, dev = session("usb", False)
    cfg = StimConfig(electrode_count=32, current_ua=500, pulse_width_us=100, discharge_us=10, rate_hz=60)
    dev.configure(cfg)
    mono = estimate_scan_us([1] * 32, 100, 10) / 1e6
    bi = estimate_scan_us([2] * 32, 100, 10) / 1e6
    assert bi > mono and worst_scan_s(cfg) == pytest.approx(min(bi, firmware_period_us(60) / 1e6 - 50e-6))


@pytest.mark.parametrize(("link", "robust"), BOTH, ids=IDS)
def test_biphasic_frames_then_resync_lose_nothing(link: str, robust: bool) -> None:
    port, dev = session(link, robust)
    cfg = StimConfig(electrode_count=32, current_ua=800, pulse_width_us=100, discharge_us=10, rate_hz=100)
    dev.configure(cfg)
    for i in range(6):
        dev.send_pattern([2] * 32 if i % 2 else [2, 0] * 16)
        if i % 3 == 2:
            dev.resync()
            dev.keepalive()
    assert_clean(port, cfg.current_ua)


@pytest.mark.parametrize(("link", "robust"), BOTH, ids=IDS)
def test_hardware_reset_drains_resets_waits_for_boot_then_proves(link: str, robust: bool) -> None:
    port, dev = session(link, robust)
    cfg = StimConfig(current_ua=600)
    dev.configure(cfg)
    dev.send_pattern([1] * 32)  # in flight when the reset is asked for
    writes: list[tuple[float, bytes, str]] = []
    real_write = port.write

    def spy(data: bytes) -> int:
        writes.append((port.now_s, bytes(data), dev.link_state.value))
        return real_write(data)

    port.write = spy  # type: ignore[method-assign]
    resets: list[float] = []
    real_reset = port.pulse_reset

    def reset() -> None:
        resets.append(port.now_s)
        real_reset()

    port.pulse_reset = reset  # type: ignore[method-assign]
    k = len(dev.transitions)
    assert dev.hardware_reset()
    assert states(dev, k)[:5] == ["draining", "resetting", "booting", "suspect", "syncing"]
    assert states(dev, k)[-1] == "in_step" and "verifying" in states(dev, k)
    # drained: a proof was asked for before the reset and everything had crossed the link
    before = [w for w in writes if w[0] <= resets[0]]
    assert before and before[-1][1] in (b"\xff", b"\xf5") and before[-1][2] == "draining"
    assert port.emulator.losses == []  # nothing was in the queue when the reset cleared it
    # nothing written while the firmware boots; the first bytes after it are a proof request
    after = [w for w in writes if w[0] > resets[0]]
    assert after[0][0] >= resets[0] + dev.boot_s - 1e-9
    assert after[0][1][-1] == 0xF5 and not any(after[0][1][:-1])  # zeros, then 0xF5 (electrode count 0)
    assert_clean(port, cfg.current_ua)
    dev.close()


@pytest.mark.parametrize(("link", "robust"), BOTH, ids=IDS)
def test_a_pattern_in_flight_never_lands_on_firmware_just_reset(link: str, robust: bool) -> None:
    cfg = big_config(robust, current_ua=300)
    port, dev = session(link, robust, boards=8)
    dev.configure(cfg)
    for _ in range(2):
        dev.send_pattern([1, 0] * (cfg.electrode_count // 2) + [0] * (cfg.electrode_count % 2))
        assert dev.hardware_reset()  # the pattern is still on the link and in the queue
    assert not [h for h in port.emulator.hazards if h.kind is HazardKind.PARSER_LOCKED]
    assert_clean(port, cfg.current_ua)


@pytest.mark.parametrize("link", LINKS)
def test_no_value_before_a_proof_after_a_cut_write(link: str) -> None:
    """A write cut mid-command: from then on nothing but zeros and requests reaches the wire until the
    device answers, and the first value after the answer is a height of 0."""
    port, dev = session(link, True)
    dev.configure(StimConfig(current_ua=700))
    dev.send_pattern([1] * 32)
    port.write(b"\xfb\xdc")  # half a pulse height, as a cut write leaves it (0xDC would become 2.2 mA)
    dev._needs_resync = True
    seen: list[bytes] = []
    real_write = port.write

    def spy(data: bytes) -> int:
        seen.append(bytes(data))
        return real_write(data)

    port.write = spy  # type: ignore[method-assign]
    stamps: list[float] = []
    real_spy = port.write

    def stamp(data: bytes) -> int:
        stamps.append(port.now_s)
        return real_spy(data)

    port.write = stamp  # type: ignore[method-assign]
    t_fault = port.now_s
    dev.keepalive()  # resync first, then the frame again, ramped from 0
    first_value = next(i for i, w in enumerate(seen) if w[0] >= 0xF5 and w[0] not in (0xF5, 0xFF))
    assert set(b"".join(seen[:first_value])) <= {0x00, 0xF5, 0xFF}
    assert seen[first_value][:3] == b"\xfb\x00\x00"
    # the first zero completes the half height (any byte would: a zero gives the least, its low byte);
    # it lasts until that height 0 is read, a period or two later, and never above 2.55 mA
    port.advance(0.05)
    table = port.emulator.reports.pulse_table(t_fault * 1e6)
    over = table["current_ua"] > 700
    assert table["current_ua"].max() <= 2550
    if over.any():
        assert table["start_us"][over].max() / 1e6 <= stamps[first_value] + 2 * 0.008 + 0.002
    assert port.emulator.losses == [] and all(c.in_sync for c in port.emulator.commands[-10:])


# --- every transition, on both links ----------------------------------------------------------------------


class FlakyPort(TimedPort):
    """A timed port whose next write can be made to fail, or whose next replies vanish, while the driver
    is in a given state."""

    def __init__(self, *a: object, **kw: object) -> None:
        super().__init__(*a, **kw)  # type: ignore[arg-type]
        self.dev: EtactileKitDevice | None = None
        self.fail_write_in: set[str] = set()
        self.mute_in: dict[str, int] = {}  # state -> how many requests go unanswered
        self.swallow = False
        self.no_reset = False

    def _state(self) -> str:
        return self.dev.link_state.value if self.dev is not None else ""

    def write(self, data: bytes) -> int:
        st = self._state()
        if st in self.fail_write_in:
            self.fail_write_in.discard(st)
            raise serial.SerialException(f"write failed in {st}")
        self.swallow = False
        if self.mute_in.get(st) and data[-1:] in (b"\xff", b"\xf5"):
            self.mute_in[st] -= 1
            self.swallow = True
        return super().write(data)

    @property
    def in_waiting(self) -> int:
        if self.swallow:
            self.emulator.read_tx()
            return 0
        return super().in_waiting

    def read(self, size: int = 1) -> bytes:
        if self.swallow:
            self.emulator.read_tx()
            return b""
        return super().read(size)

    def pulse_reset(self) -> None:
        if self.no_reset:
            raise serial.SerialException("no reset line")
        super().pulse_reset()


def walk(link: str) -> set[tuple[str, str]]:
    """Scenarios that between them take every transition; the transitions seen."""
    port = FlakyPort(link=link, robust_encoding=True)
    dev = EtactileKitDevice(port)
    port.dev = dev
    seen: set[tuple[str, str]] = set()

    def attempt(fn: Callable[[], object]) -> None:
        try:
            fn()
        except TactDeformError:
            pass

    cfg = StimConfig(current_ua=500)
    dev.configure(cfg)  # SUSPECT → SYNCING → SAFE → IN_STEP at open (no electrode count yet)
    dev.send_pattern([1] * 32)
    dev.resync()  # IN_STEP → SUSPECT → SYNCING → SAFE → VERIFYING → IN_STEP
    port.write(b"\xfe" + b"\x01" * 12)  # a pattern cut short: the request becomes a level
    dev._needs_resync = True
    dev.keepalive()  # SYNCING → FLUSHING → SAFE
    port.fail_write_in = {"syncing"}
    attempt(dev.resync)  # SYNCING → SUSPECT
    port.fail_write_in = {"flushing"}
    port.write(b"\xfe" + b"\x01" * 12)
    attempt(dev.resync)  # FLUSHING → SUSPECT
    port.fail_write_in = {"safe"}
    attempt(dev.resync)  # SAFE → SUSPECT
    port.mute_in = {"verifying": 1}
    dev.resync()  # VERIFYING → SUSPECT, and the second round passes
    port.mute_in = {"verifying": 10}
    port.no_reset = True
    attempt(dev.resync)  # VERIFYING → FAILED; the reset line fails: RESETTING → SUSPECT
    port.no_reset = False
    port.mute_in = {}
    dev.resync()
    dev.port_link.can_reset = lambda: False  # type: ignore[method-assign]
    port.write(b"\xfc\x00\xfe")  # a locked parser, and no reset line
    dev._needs_resync = True
    attempt(dev.keepalive)  # ... → FAILED, and the error says so
    del dev.port_link.can_reset
    dev.resync()  # FAILED → SUSPECT → ... → FAILED → DRAINING: the reset line
    dev.hardware_reset()  # IN_STEP → DRAINING → RESETTING → BOOTING → SUSPECT
    port.mute_in = {"draining": 10}
    dev.hardware_reset()  # a drain without proof: DRAINING → SUSPECT → DRAINING
    port.write(b"\xfc\x00\xfe")  # a locked parser
    dev._needs_resync = True
    dev.keepalive()  # FLUSHING → FAILED → DRAINING (the reset line, at once)
    dev._needs_resync = True
    dev.hardware_reset()  # SUSPECT → DRAINING
    dev.close()
    for d in (dev,):
        for _, a, b, _ in d.transitions:
            seen.add((a, b))
    return seen


@pytest.mark.parametrize("link", LINKS)
def test_every_transition_of_the_recovery_is_taken(link: str) -> None:
    seen = walk(link)
    edges = {(a.value, b.value) for a, targets in TRANSITIONS.items() for b in targets}
    assert seen <= edges  # nothing outside the drawn machine
    assert edges - seen == set(), f"transitions never taken on {link}: {sorted(edges - seen)}"


# --- over a real pty ----------------------------------------------------------------------------------------


@pytest.fixture
def pty_server() -> Iterator[PtyServer]:
    server = PtyServer(Emulator()).start()
    yield server
    server.stop()


def test_closed_loop_proof_over_a_pty(pty_server: PtyServer) -> None:
    port = serial.Serial(None, 921600, timeout=0.5)
    port.port = pty_server.path
    dev = EtactileKitDevice(port)
    try:
        assert dev.link_state is LinkState.IN_STEP  # proved at open: zeros, 0xF5 answered, heights 0
        dev.configure(StimConfig(current_ua=500))
        dev.send_pattern([1] * 32)
        time.sleep(0.05)
        emu = pty_server.emulator
        emu.feed(b"\xfe" + b"\x01" * 10 + b"\xfb\xdc")  # a pattern cut short, a half height after it
        k = len(dev.transitions)
        dev.resync()
        assert states(dev, k) == ["suspect", "syncing", "flushing", "safe", "verifying", "in_step"]
        time.sleep(0.05)
        s = emu.state()
        assert s.electrode_num == 32 and s.pulse_height == 50 and list(s.stim_pattern[:32]) == [0] * 32
        assert not emu.locked and defects(emu.hazards) == [
            h for h in defects(emu.hazards) if h.kind is HazardKind.PATTERN_HOLDS_COMMAND_BYTE
        ]
        dev.keepalive()
        time.sleep(0.05)
        assert list(emu.state().stim_pattern[:32]) == [1] * 32
    finally:
        dev.close()


def test_a_board_that_never_answers_is_refused_with_nothing_but_off_bytes_written() -> None:
    """A port whose board never replies: it is never identified, so it is refused at open; what reached
    it were the identification's bytes, which stop current on both firmware versions, and no value."""

    class Mute(TimedPort):
        sent = bytearray()

        def write(self, data: bytes) -> int:
            self.sent.extend(data)
            return super().write(data)

        def read(self, size: int = 1) -> bytes:
            super().read(size)
            return b""

        @property
        def in_waiting(self) -> int:
            return 0

    port = Mute(link="usb")
    with pytest.raises(UnidentifiedBoardError, match="did not answer"):
        EtactileKitDevice(port)
    assert port.sent and set(port.sent) <= {0x00, 0xFC, 0xFB, 0xF9, 0xF5, 0xF4}
    assert all(nxt == 0 for b, nxt in zip(port.sent, port.sent[1:], strict=False) if b in (0xFC, 0xFB, 0xF9))
    assert not port.is_open


# --- close proves that nothing stimulates, not only that its bytes were read ------------------------------


class DuplicatingPort(TimedPort):
    """Duplicates the command byte of the next ``armed`` sense-height writes (``F9 00`` → ``F9 F9 00``: a
    sense height of 0xF9, about 10 mA on every channel the pattern has off) — a UART's duplicated byte,
    in each copy the loss-tolerant encoding writes."""

    armed = 0

    def write(self, data: bytes) -> int:
        if self.armed and data[:1] == p.encode_sense_height(0)[:1]:
            self.armed -= 1
            super().write(data[:1])
        return super().write(data)


@pytest.mark.parametrize("robust", [False, True])
def test_close_notices_a_duplicated_sense_height_byte_and_switches_off_again(robust: bool) -> None:
    """Campaign seed 9, fault session 155 (v1.2): the reply to close's proof has the right length, but the
    sense pulse goes on at 9.96 mA.  Close reads each channel back a scan later, sees the current, recovers
    and switches off again; nothing is delivered after close returns."""
    port = DuplicatingPort(link="uart", robust_encoding=robust)
    dev = EtactileKitDevice(port)
    dev.configure(StimConfig(electrode_count=32, current_ua=400, pulse_width_us=50, rate_hz=164))
    dev.send_pattern([1] * 8 + [0] * 24)
    port.advance(0.02)
    port.armed = 2 if robust else 1
    dev.close()
    assert not port.armed, "the sense height was never written"
    assert dev.link_state is LinkState.IN_STEP or dev.closed
    transitions = [why for _, _, _, why in dev.transitions]
    assert "a channel reads current after the all-off" in transitions
    closed_at = port.now_s
    port.is_open = True
    port.advance(0.05)
    emu = port.emulator
    assert emu.state().sense_pulse_height == 0
    table = emu.reports.pulse_table()
    after = table["start_us"] / 1e6 > closed_at
    assert after.any()  # the scans go on (count unchanged), at height 0
    assert not (table["current_ua"][after] > 0).any()
    assert not (table["code"][after] > 0).any()


def test_sessions_campaign_seed_9_session_155_holds() -> None:
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    import safety_campaign as sc

    res = sc.run_session(155, seed=9, faults=True, firmware="v1.2")
    assert "duplicate" in res.faults
    assert res.ok and res.unexplained == 0, res.first_violation


def test_refresh_rewrites_the_sense_height_on_v12() -> None:
    """A sense height the host did not set (a duplicated ``f9``) is a current on every channel the pattern
    has off; the fail-safe's refresh writes it back with the height and the pattern."""
    emu = Emulator()
    dev = EtactileKitDevice(EmulatorPort(emu))
    dev.configure(StimConfig(electrode_count=8, current_ua=500, sense_current_ua=40))
    dev.send_pattern([1, 0, 0, 0, 0, 0, 0, 1])
    set_by_host = emu.state().sense_pulse_height
    emu.feed(p.encode_sense_height(0xF9))
    assert emu.state().sense_pulse_height == 0xF9 << 2 != set_by_host
    dev.refresh()
    assert emu.state().sense_pulse_height == set_by_host
    dev.close()


@pytest.mark.parametrize(
    ("readback", "sense_ua", "rewritten"),
    [(True, 0, False), (True, 40, True), (False, 0, True)],
)
def test_the_failsafes_refresh_leaves_the_sense_height_to_its_readback_only_where_that_watches_it(
    readback: bool, sense_ua: int, rewritten: bool
) -> None:
    """Each ``f9`` written is one more byte a duplicate can turn into 10 mA: the refresh writes the sense
    height unless the readback already sees a sense current on the off channels (none configured)."""
    from tactdeform_hw.device.safety.failsafe import FailSafe

    emu = Emulator()
    dev = EtactileKitDevice(EmulatorPort(emu))
    dev.configure(StimConfig(electrode_count=8, current_ua=500, sense_current_ua=sense_ua))
    dev.send_pattern([1, 0, 0, 0, 0, 0, 0, 1])
    fs = FailSafe(
        dev, watchdog_s=None, refresh_interval_s=0.05, verify_readback=readback, thread=False, signals=False
    )
    emu.feed(p.encode_sense_height(0xF9))
    fs.poll(0.0)
    assert (emu.state().sense_pulse_height != 0xF9 << 2) is rewritten
    dev.close()


@pytest.mark.parametrize("name", ["emulator", "etactile://?firmware=v2"])
def test_a_recovery_keeps_the_bound_of_the_configuration_it_began_at(name: str) -> None:
    """Each version's recovery records its failing-resync bound before its first byte: a later, smaller
    configuration does not shrink the bound a fail-safe reads below the one a recovery ran under."""
    from tactdeform_hw.device import open_device

    def bound_after(resync_at_32: bool) -> tuple[float, float]:
        with open_device(name, guardian=False, settle_s=0.0) as dev:
            dev.configure(StimConfig(electrode_count=32, current_ua=500))
            at_32 = dev.resync_bound_s()
            if resync_at_32:
                dev.resync()
            dev.configure(StimConfig(electrode_count=1, current_ua=500))
            return at_32, dev.resync_bound_s()

    at_32, without = bound_after(resync_at_32=False)
    assert without < at_32  # one electrode alone has the smaller bound
    assert bound_after(resync_at_32=True) == (at_32, at_32)
