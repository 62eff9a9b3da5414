"""What the device promises whatever firmware its board runs: every test here runs once per dialect of
the registry (:data:`~tactdeform_hw.device.driver.dialects.DIALECTS`), on an in-process emulator of that
version, and reads the board back through the version-independent readback."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import pytest

from tactdeform_hw import protocol as p
from tactdeform_hw.device import ChannelMapping, EtactileKitDevice, SafetyGuard, StimConfig
from tactdeform_hw.device.driver.dialect import Plan, Prove, Settle, Write
from tactdeform_hw.device.driver.dialects import DIALECTS
from tactdeform_hw.device.driver.firmware_probe import SYNC_CHECK
from tactdeform_hw.device.driver.readback import pattern_readback
from tactdeform_hw.device.driver.v2 import buffer_levels
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.serving.in_process import EmulatorPort
from tactdeform_hw.errors import LimitError, PortNotOpenError, ProtocolMisuseError, SafetyError
from tactdeform_hw.protocol.firmware import V1_2, V2, FirmwareSpec

from .safety_helpers import RecordingPort

SPECS = sorted(DIALECTS, key=lambda spec: spec.name)


@pytest.fixture(params=SPECS, ids=lambda spec: spec.name)
def spec(request: pytest.FixtureRequest) -> FirmwareSpec:
    return request.param  # type: ignore[no-any-return]


@pytest.fixture
def port(spec: FirmwareSpec) -> RecordingPort:
    return RecordingPort(Emulator(firmware=spec.name))


@pytest.fixture
def dev(port: RecordingPort) -> EtactileKitDevice:
    d = EtactileKitDevice(port)
    port.writes.clear()  # the identification and the proof at open: the tests look at what follows
    return d


def _levels(dev: EtactileKitDevice) -> tuple[int, ...]:
    read = pattern_readback(dev)
    assert read is not None
    return read()


def test_the_device_speaks_the_dialect_its_board_proved(spec: FirmwareSpec, dev: EtactileKitDevice) -> None:
    assert dev.dialect is DIALECTS[spec] and dev.firmware == spec.name
    assert dev.guard.firmware is spec


@pytest.mark.parametrize(
    ("call", "error"),
    [
        (lambda d: d.send_pattern([1] * 32), ProtocolMisuseError),  # before configure
        (lambda d: d.set_current(100), ProtocolMisuseError),
        (lambda d: d.measure(), ProtocolMisuseError),
        (lambda d: d.configure(StimConfig(electrode_count=0)), LimitError),
        (lambda d: d.configure(StimConfig(current_ua=10_010)), LimitError),
        (lambda d: d.configure(StimConfig(current_ua=155)), LimitError),
        (lambda d: d.configure(StimConfig(pulse_width_us=0)), LimitError),
        (lambda d: d.configure(StimConfig(rate_hz=0)), LimitError),
        (lambda d: d.configure(StimConfig(rate_hz=70_000)), LimitError),
        (lambda d: d.configure(StimConfig(discharge_us=256)), LimitError),
        (lambda d: d.configure(StimConfig(polarity="up")), LimitError),  # type: ignore[arg-type]
        (lambda d: d.configure(StimConfig(pulse_width_us=float("nan"))), LimitError),  # type: ignore[arg-type]
    ],
)
def test_refusals_before_configure_write_nothing(
    dev: EtactileKitDevice,
    port: RecordingPort,
    call: Callable[[EtactileKitDevice], Any],
    error: type[Exception],
) -> None:
    with pytest.raises(error):
        call(dev)
    assert port.writes == []


@pytest.mark.parametrize(
    ("levels", "error", "match"),
    [
        ([1] * 31, ProtocolMisuseError, "31 level"),
        ([1] * 33, ProtocolMisuseError, "33 level"),
        ([1] * 31 + [3], LimitError, r"pattern\[31\]"),
        ([1] * 31 + [-1], LimitError, r"pattern\[31\]"),
        ([1] * 31 + [1.0], LimitError, r"pattern\[31\]"),
        ([1] * 31 + [True], LimitError, r"pattern\[31\]"),
        (None, LimitError, "pattern"),
    ],
)
def test_pattern_refusals_write_nothing(
    dev: EtactileKitDevice, port: RecordingPort, levels: Any, error: type[Exception], match: str
) -> None:
    dev.configure(StimConfig(current_ua=100))
    before = list(port.writes)
    with pytest.raises(error, match=match):
        dev.send_pattern(levels)
    assert port.writes == before


def test_current_above_cap_is_refused_and_nothing_written(port: RecordingPort) -> None:
    dev = EtactileKitDevice(port, guard=SafetyGuard(cap_ua=2000))
    port.writes.clear()
    with pytest.raises(SafetyError):
        dev.configure(StimConfig(current_ua=2500))
    assert port.writes == []
    dev.configure(StimConfig(current_ua=2000))
    before = list(port.writes)
    with pytest.raises(SafetyError):
        dev.set_current(2010)
    assert port.writes == before
    dev.close()


def test_a_frame_reaches_the_board_and_close_leaves_it_off(
    dev: EtactileKitDevice, port: RecordingPort
) -> None:
    dev.configure(StimConfig(current_ua=1000))
    dev.send_pattern([1] * 8 + [0] * 24)
    assert _levels(dev) == (1,) * 8 + (0,) * 24 and dev.stimulating
    dev.close()
    dev.close()  # idempotent
    assert buffer_levels(port.emulator.state())[:32] == [0] * 32 and not port.is_open
    with pytest.raises(PortNotOpenError):
        dev.send_pattern([0] * 32)


def test_the_context_manager_switches_off_on_an_exception(port: RecordingPort) -> None:
    with pytest.raises(RuntimeError):
        with EtactileKitDevice(port) as dev:
            dev.configure(StimConfig(current_ua=500))
            dev.send_pattern([1] * 8 + [0] * 24)
            raise RuntimeError("renderer crashed")
    assert buffer_levels(port.emulator.state())[:32] == [0] * 32


def test_a_channel_mapping_reorders_to_hardware(port: RecordingPort) -> None:
    mapping = ChannelMapping.from_list([3, 2, 1, 0], hw_channels=4)
    dev = EtactileKitDevice(port, mapping=mapping)
    dev.configure(StimConfig(electrode_count=4, current_ua=100))
    dev.send_pattern([1, 1, 0, 0])
    assert buffer_levels(port.emulator.state())[:4] == [0, 0, 1, 1]
    assert _levels(dev) == (1, 1, 0, 0)
    with pytest.raises(LimitError, match="mapping"):
        dev.configure(StimConfig(electrode_count=8))
    dev.close()


def test_measure_and_hv513(dev: EtactileKitDevice) -> None:
    dev.configure(StimConfig(electrode_count=12))
    assert dev.measure() == [0] * 12
    assert dev.hv513_count() == 4
    dev.close()


def test_a_refused_frame_is_not_kept_for_keepalive(dev: EtactileKitDevice, port: RecordingPort) -> None:
    """A frame the guard refuses (32 biphasic channels: a scan longer than the 8 ms period) leaves the
    previous frame in force: keepalive neither resends the refused one nor raises."""
    dev.configure(StimConfig(current_ua=500))
    dev.send_pattern([1] * 8 + [0] * 24)
    fed = dev.last_frame_time
    with pytest.raises(SafetyError):
        dev.send_pattern([2] * 32)
    assert dev.last_frame_time == fed  # a refused frame does not feed the fail-safe watchdog
    before = list(port.writes)
    dev.keepalive()
    assert port.writes == before
    assert _levels(dev) == (1,) * 8 + (0,) * 24
    dev.close()


#: Per firmware: a configuration whose idle scan fills the period, the message, and one that fits.  v1.2
#: gives each off channel a sense pulse and a discharge (255 channels with the 45 µs discharge take about
#: 14.2 ms, more than 72 Hz's 13.9 ms); v2 pulses every channel each scan (32 at 200 µs exceed 5 ms).
IDLE_SCAN = {
    V1_2: (
        StimConfig(electrode_count=255, current_ua=400, rate_hz=72),
        "scan takes about 14",
        StimConfig(electrode_count=255, current_ua=400, rate_hz=60),
    ),
    V2: (
        StimConfig(electrode_count=32, current_ua=400, pulse_width_us=200, rate_hz=200),
        "scan takes about",
        StimConfig(electrode_count=32, current_ua=400, pulse_width_us=200, rate_hz=100),
    ),
}


def test_every_dialect_has_an_idle_scan_case() -> None:
    assert set(IDLE_SCAN) == set(DIALECTS)


def test_a_configuration_whose_idle_scan_fills_the_period_is_refused_before_a_byte(
    spec: FirmwareSpec, dev: EtactileKitDevice, port: RecordingPort
) -> None:
    refused, match, fits = IDLE_SCAN[spec]
    with pytest.raises(SafetyError, match=match):
        dev.configure(refused)
    assert port.writes == []
    dev.configure(fits)
    dev.close()


def test_a_refresh_is_the_dialects_plan_sent_as_planned(dev: EtactileKitDevice, port: RecordingPort) -> None:
    """The dialect plans a refresh from the state in force without writing; the device sends exactly
    those commands, and the board is left holding the same frame."""
    dev.configure(StimConfig(electrode_count=8, current_ua=600, sense_current_ua=0))
    dev.send_pattern([1, 0, 1, 0, 0, 1, 0, 0])
    before = _levels(dev)
    port.writes.clear()
    plan = dev.dialect.refresh(dev.wire.plan_context(), dev.state, sense=True)
    assert port.writes == [] and plan.writes
    dev.refresh()
    assert b"".join(port.writes) == _planned_bytes(dev, plan)
    assert _levels(dev) == before


def test_refresh_and_keepalive_rewrite_the_frame_in_force_and_suspend_stops_it(
    spec: FirmwareSpec, dev: EtactileKitDevice, port: RecordingPort
) -> None:
    """Something else wrote an all-off pattern to the board: ``refresh`` writes the frame in force again;
    ``suspend`` (a fail-safe stop) switches every channel off and keeps the frame, which ``keepalive``
    puts back."""
    dev.configure(StimConfig(electrode_count=3, current_ua=300))
    dev.send_pattern([1, 1, 0])
    assert _levels(dev) == (1, 1, 0)
    pattern_off = bytes([spec.opcode_of("stim_pattern")]) + bytes(3 * spec.pattern_bytes_per_electrode)
    port.emulator.feed(pattern_off)
    assert _levels(dev) == (0, 0, 0)
    dev.refresh()
    assert _levels(dev) == (1, 1, 0)
    dev.suspend()
    assert _levels(dev) == (0, 0, 0)
    dev.keepalive()
    assert _levels(dev) == (1, 1, 0)
    dev.close()


def _planned_bytes(dev: EtactileKitDevice, plan: Plan) -> bytes:
    """The bytes a plan stands for on this device's link (no loss-tolerant padding here)."""
    assert not dev.pacer.robust  # each write once, unpadded
    return b"".join(b"".join(w.commands) or w.data for w in plan.writes)


@pytest.mark.parametrize("mode_known", [True, False], ids=["mode-known", "after-a-failed-write"])
def test_the_all_off_is_the_dialects_plan_and_the_state_changes_only_as_it_is_written(
    dev: EtactileKitDevice, port: RecordingPort, mode_known: bool
) -> None:
    """The dialect plans the all-off from a copy of the state (the state in force is untouched until a
    write is written); the device sends exactly the planned bytes and the board is off."""
    dev.configure(StimConfig(electrode_count=8, current_ua=600))
    dev.send_pattern([1] * 8)
    if not mode_known:
        dev.state.mode = None  # as after a cut write on v2: the mode in force is unknown
    before = dataclasses.replace(dev.state)
    plan = dev.dialect.off(dev.state, dev.mapping, dev.pacer.scan_s)
    assert dev.state == before and plan.writes and plan.pace_after is not None
    port.writes.clear()
    dev.all_off()
    assert b"".join(port.writes) == _planned_bytes(dev, plan)
    assert dev.state.current_ua == 0 and dev.state.last_pattern == bytes(8)
    assert set(_levels(dev)) == {0}


def test_a_frame_and_a_change_of_current_are_the_dialects_plans_sent_as_planned(
    dev: EtactileKitDevice, port: RecordingPort
) -> None:
    """The dialect plans a frame and a change of current from a copy of the state in force, writing
    nothing; the device sends exactly the planned bytes and puts the planned state in force."""
    dev.configure(StimConfig(electrode_count=8, current_ua=600))
    dev.send_pattern([1, 0, 1, 0, 0, 0, 0, 0])
    for send, plan_of in (
        (
            lambda: dev.send_pattern([0, 1, 1, 0, 0, 1, 0, 0]),
            lambda: dev.dialect.frame(
                dev.wire.plan_context(), dev.state, [0, 1, 1, 0, 0, 1, 0, 0], force_pattern=True
            ),
        ),
        (
            lambda: dev.set_current(300),
            lambda: dev.dialect.set_current(
                dev.wire.plan_context(),
                dataclasses.replace(dev.state, target_ua=300, config=dev.config.with_current(300)),
                dev.state.application_levels(dev.mapping),
            ),
        ),
    ):
        before = dataclasses.replace(dev.state)
        plan = plan_of()
        assert dev.state == before and plan.writes and plan.refusal is None
        port.writes.clear()
        send()
        assert b"".join(port.writes) == _planned_bytes(dev, plan)
        after = dataclasses.replace(before, **plan.puts_before)
        for w in plan.writes:
            after = dataclasses.replace(after, **w.puts)
        assert (after.current_ua, after.last_pattern, after.frames_sent) == (
            dev.state.current_ua,
            dev.state.last_pattern,
            dev.state.frames_sent,
        )
    assert dev.current_ua == 300
    dev.close()


@pytest.mark.parametrize(
    "configs",
    [
        [StimConfig(electrode_count=8, current_ua=600)],
        [
            StimConfig(electrode_count=8, current_ua=600),
            StimConfig(electrode_count=40, current_ua=900, rate_hz=50),
        ],
        [
            StimConfig(electrode_count=40, current_ua=900, rate_hz=50),
            StimConfig(electrode_count=8, current_ua=300),
        ],
    ],
    ids=["first", "count-rises", "count-falls"],
)
def test_a_configuration_is_the_dialects_plan_its_proofs_steps_of_it(
    dev: EtactileKitDevice, port: RecordingPort, configs: list[StimConfig]
) -> None:
    """The dialect plans a configuration from a copy of the state in force, writing nothing; the device
    sends exactly the planned writes, with nothing between them but the requests of the planned proofs."""
    for config in configs[:-1]:
        dev.configure(config)
        dev.send_pattern([1] + [0] * (config.electrode_count - 1))
    config = configs[-1]
    before = dataclasses.replace(dev.state)
    plan = dev.dialect.configure(dev.wire.plan_context(), dev.state, config, dev.wire.pace_in_force())
    assert dev.state == before and plan.refusal is None
    planned = [b"".join(w.commands) or w.data for w in plan.writes if isinstance(w, Write)]
    proofs = sum(isinstance(w, (Prove, Settle)) for w in plan.writes)
    assert planned and proofs
    port.writes.clear()
    dev.configure(config)
    requests = {p.MEASURE_REQUEST, p.HV513_COUNT_REQUEST, SYNC_CHECK}
    assert [w for w in port.writes if w not in requests] == planned
    assert len([w for w in port.writes if w in requests]) <= proofs
    assert dev.config == config
    dev.close()


def test_a_configuration_refused_by_its_scan_sends_nothing_even_before_a_resync(
    spec: FirmwareSpec, dev: EtactileKitDevice, port: RecordingPort
) -> None:
    """The refusal comes before the recovery a link that is not proved in step needs: not a byte."""
    dev.configure(IDLE_SCAN[spec][2])
    dev.mark_unknown()
    port.writes.clear()
    with pytest.raises(SafetyError, match=IDLE_SCAN[spec][1]):
        dev.configure(IDLE_SCAN[spec][0])
    assert port.writes == []
    dev.close()


def test_a_frame_refused_after_a_change_of_mode_keeps_the_ramp_restarted() -> None:
    """Firmware v2: a change of waveform restarts the ramp from 0 before the guard can refuse the frame,
    and the restart holds when it does (the plan is the restart and the refusal, and no byte)."""
    rec = RecordingPort(Emulator(firmware="v2"))
    dev = EtactileKitDevice(rec)
    dev.configure(StimConfig(current_ua=500))
    dev.send_pattern([1] * 8 + [0] * 24)
    assert dev.state.heights_ua
    plan = dev.dialect.frame(dev.wire.plan_context(), dev.state, [2] * 32, force_pattern=True)
    assert isinstance(plan.refusal, SafetyError) and plan.puts_before == {"heights_ua": []}
    assert plan.writes == []
    n = len(rec.writes)
    with pytest.raises(SafetyError):
        dev.send_pattern([2] * 32)
    assert dev.state.heights_ua == [] and rec.writes[n:] == []
    dev.close()


@pytest.mark.parametrize("firmware", list(DIALECTS), ids=lambda f: f.name)
def test_an_integral_float_is_sent_as_the_integer_it_is(firmware: FirmwareSpec) -> None:
    """A configuration read from JSON may carry ``32.0``: it is held and sent as 32, never computed with as
    a float (found by fuzzing ``configure``: ``electrode_count=1.0`` crashed the guard's scan estimate)."""
    emu = Emulator(firmware=firmware.name)
    dev = EtactileKitDevice(EmulatorPort(emu), firmware=firmware.name)
    dev.configure(StimConfig(electrode_count=1.0, current_ua=500.0, rate_hz=125.0))  # type: ignore[arg-type]
    assert dev.config is not None and type(dev.config.electrode_count) is int
    assert emu.state().electrode_num == 1
    dev.close()
