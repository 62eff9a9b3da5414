"""Options written once and passed on: open_device's device options, the objects' surface options, and the
audit log's reading of each command handed to the delivery log."""

from __future__ import annotations

import inspect
import io

import pytest

from tactdeform_hw import protocol as p
from tactdeform_hw.device.driver import serial_driver
from tactdeform_hw.device.driver.audit import AuditLog, describe_command
from tactdeform_hw.device.driver.base import Device, DeviceOptions
from tactdeform_hw.device.driver.firmware_probe import FirmwareMismatchError
from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.render.geometry import DEFAULT_FEATURE_BAND_MM
from tactdeform_hw.render.mesh import TriangleMesh
from tactdeform_hw.render.primitives import Box, PlacedSolid, Sphere, SurfaceOptions
from tactdeform_hw.session.delivery import DeliveryLog


def test_every_device_option_is_a_keyword_of_the_device() -> None:
    params = inspect.signature(Device).parameters
    for name in DeviceOptions.__optional_keys__:
        assert params[name].kind is inspect.Parameter.KEYWORD_ONLY, name


@pytest.mark.parametrize(
    ("options", "error"),
    [
        ({"firmwre": "v2"}, TypeError),  # a misspelt option
        ({"firmware": "v3"}, ConfigurationError),
        ({"firmware": None}, ConfigurationError),
    ],
)
def test_open_device_refuses_before_any_port_exists(
    monkeypatch: pytest.MonkeyPatch, options: dict[str, object], error: type[Exception]
) -> None:
    created: list[str] = []
    monkeypatch.setattr(serial_driver, "open_port", lambda name, **kw: created.append(name))
    with pytest.raises(error) as info:
        serial_driver.open_device("emulator", **options)  # type: ignore[arg-type]
    assert created == []
    if error is TypeError:
        assert "'firmwre'" in str(info.value)


def test_open_device_passes_its_options_to_the_device() -> None:
    with serial_driver.open_device("emulator", firmware="v1.2", settle_s=0.0, guardian=False) as dev:
        assert dev.identification.firmware.name == "v1.2"
        assert dev.guardian is None
    with pytest.raises(FirmwareMismatchError):  # the in-process board runs v1.2
        serial_driver.open_device("emulator", firmware="v2", settle_s=0.0)


def _surface(solid: PlacedSolid) -> tuple[object, ...]:
    return solid.texture_level, solid.texture_regions, solid.feature_band_mm, solid.classify_features


def test_every_kind_of_object_takes_the_same_surface_options_and_defaults() -> None:
    assert _surface(Sphere("s", 10.0)) == _surface(Box("b", 10.0)) == (0, (), DEFAULT_FEATURE_BAND_MM, True)
    surface = SurfaceOptions(texture_level=2, feature_band_mm=3.0, classify_features=False)
    assert (
        _surface(Sphere("s", 10.0, **surface)) == _surface(Box("b", 10.0, **surface)) == (2, (), 3.0, False)
    )
    base = inspect.signature(PlacedSolid).parameters
    for name in SurfaceOptions.__optional_keys__:
        assert base[name].kind is inspect.Parameter.KEYWORD_ONLY, name
    assert "texture_level" not in inspect.signature(TriangleMesh).parameters  # passed on, not redeclared


class _Seen(AuditLog):
    def __init__(self) -> None:
        super().__init__(io.StringIO())
        self.seen: list[tuple[str, object]] = []

    def sent(self, name: str, value: object) -> None:
        self.seen.append((name, value))


def test_the_audit_log_hands_on_each_command_the_transport_took() -> None:
    log = _Seen()
    height = p.encode_pulse_height(100)
    log.tx(height, t=0.0)
    log.tx(height, t=0.1, ok=False)  # a failed write reached no firmware
    assert log.seen == [describe_command(height)] == [("PULSE_HEIGHT", 100)]


def test_the_delivery_log_reports_from_the_audit_logs_reading() -> None:
    with DeliveryLog(None) as log:
        log.tx(p.encode_pulse_height(100), t=0.0)  # 10 µA a code
        log.tx(p.encode_pulse_height(200), t=0.1, ok=False)
    report = log.report()
    assert report["max_height_ua"] == 1000
    assert report["pulse_heights_ua"] == [1000]
    assert report["pulse_height_changes"] == 1


def test_every_command_that_runs_a_firmware_tree_offers_it_alike() -> None:
    """``--firmware-src DIR`` is declared once (cli/options.py): emulate, timing and study take it with the
    same metavar, optional, ``None`` when not given; diff-firmware, which cannot run without a tree,
    requires it."""
    from tactdeform_hw.cli import build_parser

    commands = build_parser().commands
    taking = {name for name, sub in commands.items() if "--firmware-src" in sub.format_usage()}
    assert taking == {"emulate", "timing", "study", "diff-firmware"}
    for name in ("emulate", "timing", "study"):
        usage = " ".join(commands[name].format_usage().split())
        assert "[--firmware-src DIR]" in usage, name
        assert commands[name].get_default("firmware_src") is None, name
    usage = " ".join(commands["diff-firmware"].format_usage().split())
    assert "--firmware-src FIRMWARE_SRC" in usage and "[--firmware-src" not in usage
