"""Conformance of a firmware v2 target: the sync check, the measure reply, version detection, the
device layer driving per-electrode heights and the 2 s command timeout.  (The package's own suite adds an
upstream-style host replaying its golden vectors: ``tests/conformance/test_conformance_v2.py``.)  A test
module that star-imports this one gets the checks, the ``v2_target`` fixture and the hook that picks the
targets.

Emulated v2 targets (:data:`~.targets.V2_TARGETS`), each transport the v1.2 suite runs on, serving v2:
the pyserial URL handler with the untimed v2 emulator (``etactile://?firmware=v2&timed=0``) and with the
timed v2 board on the wall clock (``etactile://?firmware=v2``), a pseudo-terminal (``pty?firmware=v2``),
a TCP port with the Wi-Fi build's rules (``tcp?firmware=v2``) and the emulated USB device through pyusb
(``usb-emulator?firmware=v2``).  ``--device`` with a real v2 board (a serial port or ``usb:``) runs the
same checks on it, except the vector replay, which sets non-zero heights; ``--device`` naming a v1.2
emulated target skips this file.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest

from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.firmware_probe import detect_firmware
from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice
from tactdeform_hw.device.driver.v2 import V2Dialect
from tactdeform_hw.protocol.commands import V2_COMMANDS as c2
from tactdeform_hw.protocol.firmware import V2, OpcodeV2, get_firmware
from tactdeform_hw.testing.conformance.targets import (
    REPLY_TIMEOUT_S,
    V2_TARGETS,
    Target,
    built_target,
    chosen_device,
    target_params,
)

#: the wall-clock target that waits out the 2 s command timeout in the default run (one is enough to show
#: the timeout runs on a served board; every timed target runs it when named with ``--device``)
TIMEOUT_TARGET = "pty?firmware=v2"
#: the firmware these checks are about
CHECKED_FIRMWARE = "v2"


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "v2_target_name" in metafunc.fixturenames:
        metafunc.parametrize("v2_target_name", target_params(metafunc.config, CHECKED_FIRMWARE, V2_TARGETS))


@pytest.fixture
def v2_target(v2_target_name: str) -> Iterator[Target]:
    with built_target(v2_target_name) as t:
        yield t


def read_reply(port: object, n: int, timeout: float = REPLY_TIMEOUT_S) -> bytes:
    port.timeout = timeout  # type: ignore[attr-defined]
    out = b""
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        out += port.read(n - len(out))  # type: ignore[attr-defined]
    return out


def command_boundary(port: object) -> None:
    """Zeros that complete any command in progress (the longest payload is 2 × 255 bytes), then count 0."""
    port.write(bytes(512) + c2.encode_electrode_num(0))  # type: ignore[attr-defined]
    time.sleep(0.02)
    port.reset_input_buffer()  # type: ignore[attr-defined]


def test_v2_sync_check_replies_the_electrode_count(v2_target: Target, request: pytest.FixtureRequest) -> None:
    port = v2_target.open()
    try:
        command_boundary(port)
        worst = 0.0
        for n in (0, 1, 32, V2.max_electrodes):
            port.write(c2.encode_electrode_num(n))
            t0 = time.monotonic()
            port.write(c2.SYNC_CHECK)
            reply = read_reply(port, 1)
            worst = max(worst, time.monotonic() - t0)
            assert reply == bytes([n]), f"0xF4 after electrode count {n} answered {reply.hex() or 'nothing'}"
        port.write(c2.encode_electrode_num(0))
        request.node.user_properties.append(("v2 0xF4 reply latency (worst)", f"{worst * 1000:.2f} ms"))
    finally:
        port.close()


def test_v2_measure_reply_is_two_bytes_per_electrode(v2_target: Target) -> None:
    port = v2_target.open()
    try:
        command_boundary(port)
        for n in (1, 8, 32):
            port.write(c2.encode_electrode_num(n) + c2.encode_pattern([0] * n))
            port.reset_input_buffer()
            port.write(c2.MEASURE_REQUEST)
            assert len(read_reply(port, 2 * n)) == 2 * n
        port.write(c2.encode_electrode_num(0))
    finally:
        port.close()


def test_v2_is_detected_before_any_stimulating_byte(v2_target: Target) -> None:
    port = v2_target.open()
    try:
        port.write(
            c2.encode_electrode_num(32) + bytes([OpcodeV2.PATTERN, 0x10])
        )  # a pattern cut after one byte
        det = detect_firmware(port.write, lambda n: read_reply(port, n), port.reset_input_buffer)
        assert det.firmware is get_firmware(CHECKED_FIRMWARE)
        if v2_target.state is not None:
            s = v2_target.state()
            assert s.electrode_num == 0 and not s.command_in_progress
    finally:
        port.close()


def test_v2_driver_round_trip_with_per_electrode_heights(v2_target: Target) -> None:
    from tactdeform_hw.device.safety.guard import SafetyGuard

    port = v2_target.open()
    guard = SafetyGuard(2000, regions_ua=[400, 800, 1200, 1600, 2000, 2000, 2000, 2000, 2000])
    dev = EtactileKitDevice(port, firmware="v2", guard=guard, guardian=False, settle_s=v2_target.settle_s)
    try:
        assert isinstance(dev.dialect, V2Dialect)
        dev.configure(StimConfig(electrode_count=32, current_ua=1000))
        dev.send_pattern([1] * 32)
        assert len(dev.measure()) == 32
        if v2_target.state is not None:
            want = [dev.transfer.to_code(min(1000, lim)) for lim in guard.electrode_limits(32)]
            assert list(v2_target.state().stim_pattern[:32]) == want
        dev.all_off()
        v2_target.settle(12)  # a timed board reads the all-off after the link and its queue
        if v2_target.state is not None:
            assert list(v2_target.state().stim_pattern[:32]) == [0] * 32
            assert v2_target.state().stim_mode in (0, 1)
    finally:
        dev.close()


def test_v2_cut_command_is_discarded_after_two_seconds(
    v2_target: Target, request: pytest.FixtureRequest
) -> None:
    if not v2_target.timed:
        pytest.skip("the untimed emulator has no clock: the 2 s timeout needs a timed target")
    if not chosen_device(request.config) and v2_target.name != TIMEOUT_TARGET:
        pytest.skip(
            f"waits 2 s: checked on {TIMEOUT_TARGET} only (name this target with --device to check it)"
        )
    port = v2_target.open()
    try:
        command_boundary(port)
        port.write(bytes([OpcodeV2.PULSE_WIDTH]))  # a pulse width whose payload never comes
        port.write(c2.SYNC_CHECK)
        assert read_reply(port, 1, 0.2) == b"", "0xF4 answered while a command was pending"
        time.sleep(2.2)
        port.write(c2.SYNC_CHECK)
        assert read_reply(port, 1) == b"\x00"
    finally:
        port.close()
