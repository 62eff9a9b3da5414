"""The link operations a device hands its dialect are kept between operations, and built again whenever
anything they bind changed: a hook or a value replaced after frames is the one the next operation uses
(frames themselves are planned against the wire's values as they stand)."""

from __future__ import annotations

from dataclasses import fields

import pytest

from tactdeform_hw import protocol as p
from tactdeform_hw.device import EtactileKitDevice, StimConfig
from tactdeform_hw.device.driver.dialect import LinkOps
from tactdeform_hw.device.participant.mapping import ChannelMapping
from tactdeform_hw.device.safety.guard import SafetyGuard
from tactdeform_hw.device.safety.interlock import AT_BOUNDARY, Shadow
from tactdeform_hw.errors import ShortReplyError

from .safety_helpers import RecordingPort


def _prove(electrodes: int) -> None:
    pass


def _resetting() -> bool:
    return False


def _ops(dev: EtactileKitDevice) -> LinkOps:
    return dev.wire.link_ops(prove=_prove, recovery_prove=_prove, resetting=_resetting)


def test_link_ops_are_kept_while_nothing_they_bind_changes() -> None:
    dev = EtactileKitDevice(RecordingPort(), guard=SafetyGuard())
    assert _ops(dev) is _ops(dev)
    dev.close()


def test_link_ops_bind_what_their_names_say() -> None:
    dev = EtactileKitDevice(RecordingPort(), guard=SafetyGuard())
    ops = _ops(dev)
    wire = dev.wire
    expected = {
        "pacer": wire.current_pacer,
        "guard": wire.guard,
        "mapping": wire.mapping,
        "unknown_reply_s": wire.unknown_reply_s,
        "send": wire.send,
        "recovery_send": wire.recovery_send,
        "discard_input": wire.port_link.discard_input,
        "await_reply": wire.await_reply,
        "proved": wire.proved,
        "suspect": wire.link.suspect,
        "enter": wire.link.enter,
        "link_state": wire.link_state,
        "prove": _prove,
        "recovery_prove": _prove,
        "request": wire.request,
        "run": wire.run,
        "measured": wire.measured,
        "can_reset": wire.port_link.can_reset,
        "resetting": _resetting,
    }
    assert {f.name: getattr(ops, f.name) for f in fields(LinkOps)} == expected
    dev.close()


def test_a_hook_replaced_after_caching_is_the_one_the_link_ops_bind() -> None:
    dev = EtactileKitDevice(RecordingPort(), guard=SafetyGuard())
    before = _ops(dev)

    def no_reset_line() -> bool:
        return False

    dev.port_link.can_reset = no_reset_line  # type: ignore[method-assign]
    after = _ops(dev)
    assert after is not before and after.can_reset is no_reset_line
    del dev.port_link.can_reset
    assert _ops(dev).can_reset == dev.port_link.can_reset
    other = ChannelMapping.from_list(list(reversed(range(32))))
    dev.mapping = other
    assert _ops(dev).mapping is other

    def resetting_differently() -> bool:
        return True

    assert (
        dev.wire.link_ops(prove=_prove, recovery_prove=_prove, resetting=resetting_differently).resetting
        is resetting_differently
    )
    dev.close()


def test_a_reset_line_removed_after_frames_is_honoured_by_the_recovery() -> None:
    """The recovery at open fills the cache; after frames the transport loses its reset line: the
    recovery of a locked parser must not reach for it (a cache that kept the old hook would pulse it and
    succeed)."""
    port = RecordingPort()
    dev = EtactileKitDevice(port, guard=SafetyGuard())
    dev.configure(StimConfig(current_ua=400))
    for _ in range(3):
        dev.send_pattern([1] * 32)
    port.emulator.feed(b"\xfc\x00\xfe")  # something locked the parser
    dev.port_link.can_reset = lambda: False  # type: ignore[method-assign]
    dev.mark_unknown()
    n = len(port.writes)
    with pytest.raises(ShortReplyError):
        dev.keepalive()
    # nothing but the recovery's zeros and requests: no reset line, no pattern
    assert set(b"".join(port.writes[n:])) <= {0, p.HV513_COUNT_REQUEST[0], p.MEASURE_REQUEST[0]}
    del dev.port_link.can_reset
    assert dev.hardware_reset() and dev.probe()
    dev.close()


def test_a_mapping_changed_after_frames_is_the_one_the_next_frame_uses() -> None:
    port = RecordingPort()
    dev = EtactileKitDevice(port, guard=SafetyGuard())
    dev.configure(StimConfig(current_ua=400))
    frame = [1] + [0] * 31
    dev.send_pattern(frame)
    dev.send_pattern(frame)
    dev.mapping = ChannelMapping.from_list(list(reversed(range(32))))
    n = len(port.writes)
    dev.send_pattern(frame)
    patterns = [w for w in port.writes[n:] if w[:1] == bytes([p.Opcode.PATTERN])]
    assert patterns and patterns[-1][1:] == bytes([0] * 31 + [1])
    dev.close()


def test_a_shadow_copy_copies_every_field() -> None:
    """The copy is spelled out field by field: a field added to the shadow and not copied fails here."""
    values = {
        "electrode_num": 7,
        "height_code": 11,
        "sense_code": 13,
        "polarity": 1,
        "width_us": 17,
        "sense_width_us": 19,
        "pattern": [1, 2, None],
        "parse": AT_BOUNDARY,
        "how": "lost",
        "stim_mode": 2,
    }
    assert {f.name for f in fields(Shadow)} == set(values)
    original = Shadow(**values)  # type: ignore[arg-type]
    copied = original.copy()
    assert {f.name: getattr(copied, f.name) for f in fields(Shadow)} == values
    copied.pattern[0] = 0
    assert original.pattern[0] == 1
