"""The guard and the interlock: every current passes them, whichever public method or path sends it."""

from __future__ import annotations

import datetime as dt
import inspect
import json
import random
from pathlib import Path
from typing import Any

import pytest

from tactdeform_hw import protocol as p
from tactdeform_hw.device import ChannelMapping, Device, EtactileKitDevice, StimConfig
from tactdeform_hw.device.driver.audit import AuditLog
from tactdeform_hw.device.participant.profiles import ParticipantProfile
from tactdeform_hw.device.safety.guard import TACTDEFORM_REGION_OF, SafetyGuard, grid_regions
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.errors import LimitError, ProtocolMisuseError, SafetyError
from tactdeform_hw.protocol.decoder import decode
from tactdeform_hw.protocol.firmware import DEFAULT_FIRMWARE, FIRMWARES

from .safety_helpers import RecordingPort

REGIONS = (1500, 1400, 1500, 1300, 1200, 1300, 1500, 1400, 1500)
PROFILE = ParticipantProfile("P01", 2000, REGIONS, dt.date(2024, 5, 1))
CENTRE = [1 if r == 4 else 0 for r in TACTDEFORM_REGION_OF]
CORNER = [1 if r == 0 else 0 for r in TACTDEFORM_REGION_OF]
ALL = [1] * 32


def device(
    guard: SafetyGuard | None = None, firmware: str = DEFAULT_FIRMWARE.name, **kw: object
) -> tuple[EtactileKitDevice, RecordingPort]:
    port = RecordingPort(Emulator(firmware=firmware))
    dev = EtactileKitDevice(port, guard=guard or SafetyGuard.from_profile(PROFILE), **kw)  # type: ignore[arg-type]
    port.opening = list(port.writes)  # the proof at open (zeros, 0xF5, heights 0)
    port.writes.clear()  # the tests look at what follows
    return dev, port


def height(port: RecordingPort) -> int:
    return port.emulator.state().pulse_height * 10


def test_region_map_is_the_tactdeform_array() -> None:
    assert len(TACTDEFORM_REGION_OF) == 32
    counts = [TACTDEFORM_REGION_OF.count(r) for r in range(9)]
    assert counts == [3, 4, 3, 4, 4, 4, 3, 4, 3]  # corner regions lose their corner electrode
    assert TACTDEFORM_REGION_OF[:4] == (0, 1, 1, 2)  # fingertip row, left to right
    assert grid_regions(3, 3, skip_corners=False) == tuple(range(9))


def test_frame_height_is_the_lowest_active_region_and_lowering_comes_first() -> None:
    dev, port = device()
    dev.configure(StimConfig(current_ua=1500))
    assert height(port) == 1500  # nothing active yet: cap and charge only
    dev.send_pattern(CORNER)
    assert height(port) == 1500 and dev.current_ua == 1500
    n = len(port.writes)
    dev.send_pattern(CENTRE)  # the centre's limit is 1200: the height goes down BEFORE the pattern
    names = [decode(w, 32)[0].name for w in port.writes[n:]]
    assert names == ["PULSE_HEIGHT", "PATTERN"] and height(port) == 1200
    n = len(port.writes)
    dev.send_pattern(CORNER)  # back up: the pattern first, the height after
    names = [decode(w, 32)[0].name for w in port.writes[n:]]
    assert names == ["PATTERN", "PULSE_HEIGHT"] and height(port) == 1500
    dev.send_pattern(ALL)
    assert height(port) == 1200 and dev.target_ua == 1500
    clips = [e for e in dev.guard.log if e["event"] == "clipped"]
    assert clips and clips[-1]["rule"] == "region" and clips[-1]["region"] == 4
    dev.close()


def test_every_intermediate_firmware_state_is_within_the_limits() -> None:
    """Torn or not, no scan between two writes can combine a pattern with a height too high for it."""
    limits = SafetyGuard.from_profile(PROFILE).electrode_limits(32)
    rng = random.Random(7)
    emu = Emulator()
    port = RecordingPort()
    port.emulator = emu
    dev = EtactileKitDevice(port, guard=SafetyGuard.from_profile(PROFILE))
    worst = 0.0
    checked = 0

    def check() -> None:
        nonlocal worst, checked
        s = emu.state()
        h = s.pulse_height * 10
        for ch in range(s.electrode_num):
            if s.stim_pattern[ch] in (1, 2):
                worst = max(worst, h / limits[ch])
                assert h <= limits[ch], (ch, h, limits[ch])
        checked += 1

    orig = port.write

    def write(data: bytes) -> int:
        n = orig(data)
        check()
        return n

    port.write = write  # type: ignore[method-assign]
    dev.configure(StimConfig(current_ua=2000))
    refused = 0
    for _ in range(300):
        levels = [rng.choice((0, 0, 0, 1, 1, 2)) for _ in range(32)]
        try:
            dev.send_pattern(levels)
        except SafetyError:  # a frame whose scan would fill the period: refused, nothing written
            refused += 1
        if rng.random() < 0.2:
            dev.set_current(rng.randrange(0, 201) * 10)
    dev.close()
    assert checked > 300 and worst <= 1.0 and refused < 150


def test_charge_pulse_width_polarity_sense_and_scan_refusals_write_nothing() -> None:
    cases = [
        (SafetyGuard(), StimConfig(current_ua=10_000, pulse_width_us=400), "charge"),
        (
            SafetyGuard.from_profile(PROFILE),
            StimConfig(current_ua=1000, pulse_width_us=250),
            "wider than the calibrated",
        ),
        (
            SafetyGuard.from_profile(PROFILE),
            StimConfig(current_ua=1000, polarity="cathodic"),
            "calibrated 'anodic'",
        ),
        (
            SafetyGuard.from_profile(PROFILE),
            StimConfig(current_ua=0, sense_current_ua=1240, sense_width_us=10),
            "lowest electrode limit",
        ),
        (
            SafetyGuard(max_charge_nc=10.0),
            StimConfig(current_ua=0, sense_current_ua=40, sense_width_us=255),
            "sense pulse",
        ),
        (SafetyGuard(), StimConfig(electrode_count=255, current_ua=0, pulse_width_us=65535), "watchdog"),
        (SafetyGuard.from_profile(PROFILE), StimConfig(current_ua=2010), "exceeds the cap of 2000"),
    ]
    for guard, cfg, text in cases:
        dev, port = device(guard)
        with pytest.raises(SafetyError, match=text):
            dev.configure(cfg)
        assert port.writes == []
        assert guard.log[-1]["event"] == "refused"
        dev.close()


def test_charge_limit_from_profile() -> None:
    prof = ParticipantProfile("P02", 2000, REGIONS, dt.date(2024, 5, 1), max_charge_nc=200.0)
    dev, port = device(SafetyGuard.from_profile(prof))
    with pytest.raises(SafetyError, match="charge"):
        dev.configure(StimConfig(current_ua=1010))  # 1010 µA × 200 µs = 202 nC
    dev.configure(StimConfig(current_ua=1000))
    dev.close()


def test_ramp_limits_increases_per_frame_and_restarts_from_zero() -> None:
    prof = ParticipantProfile("P03", 2000, REGIONS, dt.date(2024, 5, 1), ramp_ua_per_frame=400)
    dev, port = device(SafetyGuard.from_profile(prof))
    dev.configure(StimConfig(current_ua=1500))
    seen = [height(port)]
    for _ in range(5):
        dev.send_pattern(CORNER)
        seen.append(height(port))
    assert seen == [400, 800, 1200, 1500, 1500, 1500]
    dev.suspend()  # a fail-safe stop keeps the frame and the target
    assert height(port) == 0 and list(port.emulator.state().stim_pattern[:32]) == [0] * 32
    for expect in (400, 800):
        dev.keepalive()  # the owner is back: resume, ramped
        assert height(port) == expect
        assert list(port.emulator.state().stim_pattern[:32]) == CORNER
    dev.set_current(500)  # decreases are never limited
    assert height(port) == 500
    assert any(e["rule"] == "ramp" for e in dev.guard.log)
    dev.all_off()
    dev.send_pattern(CORNER)
    assert height(port) == 0  # all_off set the target to 0: nothing until the caller sets a current
    dev.close()


def test_polarity_changes_only_while_everything_is_off() -> None:
    dev, port = device(SafetyGuard())
    dev.configure(StimConfig(current_ua=500, polarity="anodic"))
    dev.send_pattern(ALL)
    with pytest.raises(SafetyError, match="polarity change"):
        dev.configure(StimConfig(current_ua=500, polarity="cathodic"))
    dev.all_off()
    dev.configure(StimConfig(current_ua=500, polarity="cathodic"))
    assert port.emulator.state().polarity == 0
    n = len(port.writes)
    dev.send_pattern(ALL)
    with pytest.raises(SafetyError, match="polarity change while current can flow"):
        dev._send(p.encode_polarity(1))  # the interlock, below every public method
    assert len(port.writes) == n + 1
    dev.close()


def test_interlock_refuses_unsafe_bytes_whatever_sends_them() -> None:
    dev, port = device()
    dev._needs_resync = True  # as after a failed write: nothing is proved
    with pytest.raises(ProtocolMisuseError, match="not proved in step"):
        dev._send(p.encode_pattern([1] * 32))
    dev.resync()  # proved in step, heights 0; the electrode count is still unknown
    with pytest.raises(SafetyError, match="electrode count is unknown"):
        dev._send(p.encode_pattern([1] * 32))
    with pytest.raises(SafetyError, match="pulse width is unknown"):
        dev._send(p.encode_pulse_height(10))
    dev.configure(StimConfig(current_ua=1000))
    n = len(port.writes)
    for data, text in [
        (p.encode_pulse_height(201), "above the cap"),
        (p.encode_pulse_height(201) + p.encode_pulse_height(0), "above the cap"),
        (p.encode_pattern(CENTRE) + p.encode_pulse_height(130), "above its limit of 1200"),
        (p.encode_electrode_num(0) + p.encode_pattern(b""), "lock"),
        (b"\xfb\x10", "cut short"),
        (p.encode_sense_height(255), "sense current"),
    ]:
        with pytest.raises(SafetyError, match=text):
            dev._send(data)
    assert len(port.writes) == n  # nothing reached the port
    assert all(e["event"] == "refused" for e in list(dev.guard.log)[-6:])
    dev.close()


def test_unmapped_hardware_channels_can_never_stimulate() -> None:
    mapping = ChannelMapping.from_list([0, 2], hw_channels=4)
    dev, port = device(SafetyGuard(), mapping=mapping)
    dev.configure(StimConfig(electrode_count=4, current_ua=500))
    dev.send_pattern([1, 1])
    with pytest.raises(SafetyError, match="channel 1"):
        dev._send(p.encode_pattern([1, 1, 1, 0]))
    dev.close()


#: Every public method of Device and what proves it cannot deliver more than the guard allows.
COVERED = {
    "configure": "refusals above, region clip on the first frame",
    "set_current": "cap refusal, region clip",
    "send_pattern": "region clip, ordering",
    "keepalive": "resumes through the same frame logic (ramp test)",
    "suspend": "only removes current",
    "all_off": "only removes current",
    "measure": "no current command",
    "probe": "a measure",
    "hv513_count": "no current command",
    "heights_in_force": "read-only: the v2 heights the firmware should hold",
    "firmware": "read-only: the version the device speaks",
    "speak": "sends nothing; a change of version leaves the interlock knowing no register",
    "frames_sent": "property",
    "guardian": "property: the guardian process, which only switches off",
    "kind": "a name for messages",
    "port": "the port every write goes to, through the device's own send path",
    "resync": "resync tests: configuration again through configure",
    "reconnect": "resync",
    "verify_firmware": "the identification's signature and off bytes only (tests/test_identification.py)",
    "hardware_reset": "resync",
    "close": "all-off",
    "config": "property",
    "current_ua": "property",
    "target_ua": "property",
    "audit": "property",
    "needs_resync": "property",
    "link_state": "property",
    "boot_s": "a wait before the first byte after a reset",
    "unknown_reply_s": "a wait for a reply",
    "resync_bound_s": "arithmetic, no bytes",
    "probe_bound_s": "arithmetic, no bytes",
    "unproved_spans": "a record, no bytes",
    "suspended": "property",
    "stimulating": "property",
    "closed": "property",
    "electrodes": "property",
    "refresh": "rewrites the height and pattern in force, through the interlock (test_safety_failsafe)",
    "mark_unknown": "sends nothing; the next write starts with a resync",
    "last_pattern": "property",
    "busy": "property",
    "writing": "property",
    "pacer": "property: the wire's pacer, which only spaces the writes",
    "mapping": "the wire's: the interlock reads the same mapping the frames are built with",
    "transfer": "the wire's: the interlock reads the same transfer the heights are coded with",
    "last_state_write": "property: a time, no bytes",
}


def test_no_public_method_is_unreviewed() -> None:
    public = {n for n, _ in inspect.getmembers(Device) if not n.startswith("_")}
    assert public <= set(COVERED), (
        f"new public Device member(s) {public - set(COVERED)}: add them to the guard tests"
    )


@pytest.mark.parametrize(
    "call",
    [
        lambda d: d.set_current(2010),
        lambda d: d.set_current(-10),
        lambda d: d.set_current(float("nan")),
        lambda d: d.set_current(1205),
        lambda d: d.set_current("1000"),
        lambda d: d.configure(StimConfig(current_ua=2100)),
        lambda d: d.configure(StimConfig(current_ua=True)),  # type: ignore[arg-type]
        lambda d: d.send_pattern([3] * 32),
        lambda d: d.send_pattern([1] * 31),
    ],
)
def test_every_public_path_refuses_before_writing(call) -> None:  # type: ignore[no-untyped-def]
    dev, port = device()
    dev.configure(StimConfig(current_ua=1000))
    dev.send_pattern(CENTRE)
    n = len(port.writes)
    with pytest.raises((SafetyError, LimitError, ProtocolMisuseError)):
        call(dev)
    assert len(port.writes) == n
    assert height(port) <= 1200
    assert dev.guard.log[-1]["event"] == "refused"  # every refusal is logged
    dev.close()


def test_resync_follows_the_protocol_reference_order() -> None:
    dev, port = device(SafetyGuard())
    dev.configure(StimConfig(current_ua=300))
    dev.send_pattern(ALL)
    port.emulator.feed(b"\xfe" + b"\x01" * 10)  # a pattern cut short on the link
    port.emulator.feed(b"\xfb\xdc")  # and a half pulse height (0xDC would become 220 = 2.2 mA)
    n = len(port.writes)
    dev.resync()
    writes = port.writes[n:]
    k = next(i for i, w in enumerate(writes) if w[0] == 0xFB)
    probes = b"".join(writes[:k])  # nothing but zeros and requests before a reply proved a boundary
    assert set(probes) <= {0x00, 0xF5, 0xFF} and probes[-1] in (0xF5, 0xFF) and probes[0] == 0
    assert probes.count(0) >= 20  # enough zeros to finish the cut pattern
    # the request went into the cut pattern (no reply) until the zeros had finished it
    states = [t[2] for t in dev.transitions]
    assert states[-5:] == ["syncing", "flushing", "safe", "verifying", "in_step"]
    rest = [decode(w, 32)[0].name for w in writes[k:]]
    assert rest[:5] == ["PULSE_HEIGHT", "SENSE_HEIGHT", "ELECTRODE_NUM", "MEASURE", "PATTERN"]
    assert [x for x in rest if x != "MEASURE"][-1] == "PULSE_HEIGHT"  # no pattern after the configuration
    s = port.emulator.state()
    assert s.rx_pending == 0 and s.electrode_num == 32 and s.pulse_height == 30
    assert list(s.stim_pattern[:32]) == [0] * 32  # no pattern until the caller's next frame
    assert dev.suspended
    dev.keepalive()  # the owner's next frame brings the pattern back
    assert list(port.emulator.state().stim_pattern[:32]) == ALL


def test_resync_survives_a_zero_landing_as_electrode_count() -> None:
    dev, port = device(SafetyGuard())
    dev.configure(StimConfig(current_ua=300))
    port.emulator.feed(b"\xfc")  # an electrode-count command whose value never came: the zeros give it 0
    dev.resync()
    assert not port.emulator.locked and port.emulator.state().electrode_num == 32
    dev.send_pattern(ALL)
    assert list(port.emulator.state().stim_pattern[:32]) == ALL


def test_resync_without_configuration_stops_every_current() -> None:
    emu = Emulator()
    # a previous session left this running
    emu.feed(
        p.encode_electrode_num(8)
        + p.encode_pattern([1] * 8)
        + p.encode_pulse_width(200)
        + p.encode_pulse_height(500)
        + p.encode_sense_height(10)
    )
    port = RecordingPort()
    port.emulator = emu
    dev = EtactileKitDevice(port)
    dev.resync()
    s = emu.state()
    assert s.pulse_height == 0 and s.sense_pulse_height == 0
    dev.close()


def _audited(firmware: str, tmp_path: Path) -> tuple[list[dict[str, Any]], list[bytes]]:
    """A session (a frame clipped by its region, a refused current, the close) with an audit log: the
    log's records and every write the port saw, from the identification on."""
    path = tmp_path / "audit.jsonl"
    log = AuditLog(path, participant="P01")
    dev, port = device(audit=log, firmware=firmware)
    dev.configure(StimConfig(current_ua=1500))
    dev.send_pattern(CENTRE)
    with pytest.raises(SafetyError):
        dev.set_current(5000)
    dev.close()
    log.close()
    return [json.loads(x) for x in path.read_text().splitlines()], port.opening + port.writes


@pytest.mark.parametrize("firmware", list(FIRMWARES))
def test_guard_events_reach_the_audit_log(firmware: str, tmp_path: Path) -> None:
    """Every byte written, in order, from the identification to the close, and the guard's clipping and
    refusal, on every version."""
    recs, writes = _audited(firmware, tmp_path)
    assert recs[0]["type"] == "session" and recs[0]["participant"] == "P01"
    tx = [r for r in recs if r["type"] == "tx"]
    assert "".join(r["hex"] for r in tx) == b"".join(writes).hex()
    assert all(r["ok"] and r["t"] >= 0 for r in tx) and [r["t"] for r in tx] == sorted(r["t"] for r in tx)
    safety = [r for r in recs if r["type"] == "safety"]
    assert {s["event"] for s in safety} == {"clipped", "refused"}
    assert tx[-1]["op"] == "close"


@pytest.mark.parametrize("firmware", list(FIRMWARES))
def test_the_audit_log_gives_back_every_write_as_written(firmware: str, tmp_path: Path) -> None:
    """docs/safety.md: one line per command written, the lines of a write of several commands (v2's cover)
    marked ``part`` [k, n]; ``replay-log`` joins them into the writes the port saw, byte for byte."""
    from tactdeform_hw.cli.replay_log import written

    recs, writes = _audited(firmware, tmp_path)
    tx = [r for r in recs if r["type"] == "tx"]
    assert [data for _, data in written(tx)] == writes
    parts = [r["part"] for r in tx if "part" in r]
    assert bool(parts) is (firmware == "v2")  # only v2 writes several commands at once
    assert all(1 <= k <= n and n > 1 for k, n in parts)


def test_raw_port_is_outside_the_driver() -> None:
    """The documented boundary: a second handle on the same emulated board writes around the driver.
    The guard protects the driver's API; whoever opens the port themselves has left it."""
    import serial

    from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import forget_shared, shared_emulator

    forget_shared()
    dev = EtactileKitDevice(
        serial.serial_for_url("etactile://bench-raw?timed=0", do_not_open=True), guard=SafetyGuard(cap_ua=500)
    )
    dev.configure(StimConfig(current_ua=500))
    raw = serial.serial_for_url("etactile://bench-raw?timed=0")
    raw.write(p.encode_pulse_height(900))
    assert shared_emulator("bench-raw").state().pulse_height == 900  # type: ignore[union-attr]
    raw.close()
    dev.close()
    assert shared_emulator("bench-raw").state().pulse_height == 0  # type: ignore[union-attr]
    forget_shared()


def _two_channel_frame(height_ua: int, pattern: list[int]) -> bytes:
    return (
        p.encode_pulse_height(0)
        + p.encode_sense_height(0)
        + p.encode_pulse_width(100)
        + p.encode_electrode_num(2)
        + p.encode_pattern([0, 0])
        + p.encode_pulse_height(height_ua // 10)
        + p.encode_pattern(pattern)
    )


def test_interlock_limits_follow_each_mapping_and_every_change_of_the_limits() -> None:
    """The interlock's per-channel limits are computed once and reused: a different mapping (even one
    created where a freed one lived), or limits changed on the guard, must never see stale ones."""
    guard = SafetyGuard(regions_ua=(1000, 500), region_of=(0, 1))
    frame = _two_channel_frame(800, [1, 0])  # 800 µA on hardware channel 0
    for _ in range(20):
        # channel 0 holds electrode 0 (limit 1000): allowed
        guard.interlock.check_wire(frame, mapping=ChannelMapping((0, 1), 2))
        # channel 0 holds electrode 1 (limit 500): refused, whatever the previous mapping object was
        with pytest.raises(SafetyError, match="channel 0 would receive 800"):
            guard.interlock.check_wire(frame, mapping=ChannelMapping((1, 0), 2))
    identity = ChannelMapping.identity(2)
    guard.interlock.check_wire(frame, mapping=identity)
    guard.regions_ua = (400, 500)  # a lowered limit takes effect at once
    with pytest.raises(SafetyError, match="above its limit of 400"):
        guard.interlock.check_wire(frame, mapping=identity)
    assert guard.electrode_limits(2) == [400, 500]
    guard.cap_ua = 300
    assert guard.electrode_limits(2) == [300, 300]
    with pytest.raises(SafetyError):
        guard.interlock.check_wire(_two_channel_frame(350, [0, 1]), mapping=identity)
    # a height above the lowest limit is still allowed on the channels whose own limit it fits
    guard = SafetyGuard(regions_ua=(1000, 500), region_of=(0, 1))
    guard.interlock.check_wire(_two_channel_frame(800, [1, 0]))
    with pytest.raises(SafetyError, match="channel 1 would receive 800"):
        guard.interlock.check_wire(_two_channel_frame(800, [0, 1]))


def test_a_rewrite_of_the_same_state_is_not_a_state_write() -> None:
    from tactdeform_hw.clock import SimulatedClock
    from tactdeform_hw.device.driver.pacing import Pacer

    clock = SimulatedClock()
    dev = EtactileKitDevice(RecordingPort(), guard=SafetyGuard(), pacer=Pacer(clock=clock))
    dev.configure(StimConfig(current_ua=1000))
    dev.send_pattern(CENTRE)
    t_first = dev.last_state_write
    assert t_first is not None
    clock.advance(1.0)
    dev.send_pattern(CENTRE)  # written again (send_pattern always writes), but the firmware holds it already
    assert dev.last_state_write == t_first
    clock.advance(1.0)
    dev.send_pattern(CORNER)
    assert dev.last_state_write is not None and dev.last_state_write > t_first + 1.0
    dev.close()


def test_interlock_refuses_a_sense_current_while_the_electrode_count_is_unknown() -> None:
    """A stray byte leaves every register unknown; a sense height of 0xF5 (9.8 mA on every channel not
    at 1 or 2) must then be refused, not waved through because the pulse height is 0."""
    from .safety_helpers import RecordingPort

    port = RecordingPort()
    dev = EtactileKitDevice(port, guard=SafetyGuard(cap_ua=2000))
    dev.configure(StimConfig(current_ua=500))
    before = list(port.writes)
    with pytest.raises(SafetyError, match="electrode count is unknown"):
        dev._send(b"\x00\xfb\x00\x00\xf9\xf5")
    assert port.writes == before
    assert port.emulator.state().sense_pulse_height == 0
