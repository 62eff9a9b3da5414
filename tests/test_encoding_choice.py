"""The encoding a user chooses: ``open_device(..., robust_encoding=...)`` and every device command's
``--encoding`` reach the pacer; the plain encoding stays the default, byte for byte; and a port that
declares a link that can lose bytes (a UART) under the plain encoding is warned of in the log and the
audit log, since one lost byte there can set a full-scale pulse until the recovery (docs/safety.md)."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import pytest

from tactdeform_hw.cli import main
from tactdeform_hw.device import open_device
from tactdeform_hw.device.driver.audit import AuditLog
from tactdeform_hw.device.driver.pacing import Pacer, PacingPolicy
from tactdeform_hw.emulator.faults import TimedPort
from tactdeform_hw.errors import ConfigurationError

SEND = ["send", "--pattern", "1,0,2", "--electrodes", "3", "--current", "500"]


def sent_hex(path: Path) -> list[str]:
    """Every write's bytes in the audit log, in order."""
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    return [rec["hex"] for rec in lines if "hex" in rec]


def test_the_encoding_option_reaches_the_pacer_and_plain_stays_the_default_byte_for_byte(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    logs = {}
    for encoding in (None, "plain", "robust"):
        logs[encoding] = tmp_path / f"{encoding}.jsonl"
        extra = ["--encoding", encoding] if encoding else []
        assert main([*SEND, "--audit-log", str(logs[encoding]), *extra]) == 0
    plain = sent_hex(logs[None])
    assert plain and plain == sent_hex(logs["plain"])
    robust = sent_hex(logs["robust"])
    assert len(robust) > len(plain)  # heights and patterns written twice, each command padded
    assert any(h.endswith("0000") for h in robust) and robust != plain


def test_open_device_takes_the_encoding_and_the_port_keeps_its_own_by_default() -> None:
    with open_device("emulator", robust_encoding=True) as dev:
        assert dev.pacer.robust
    with open_device("emulator") as dev:
        assert not dev.pacer.robust


def test_an_encoding_that_disagrees_with_the_pacer_given_is_refused_before_anything_is_sent() -> None:
    port = TimedPort(link="uart", robust_encoding=False)
    with pytest.raises(ConfigurationError, match="robust_encoding=True disagrees with the pacer given"):
        from tactdeform_hw.device import EtactileKitDevice

        EtactileKitDevice(port, pacer=Pacer(policy=PacingPolicy()), robust_encoding=True)
    assert not port.is_open and port.emulator.host_offset == 0


def warnings_of(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and "lose bytes" in r.getMessage()
    ]


@pytest.mark.parametrize(
    ("url", "robust", "warned"),
    [
        ("etactile://?link=uart&timed=0", None, True),
        ("etactile://?link=uart&timed=0", False, True),
        ("etactile://?link=uart&timed=0", True, False),
        ("etactile://?timed=0", None, False),  # USB: CRC-checked
    ],
)
def test_the_plain_encoding_on_a_port_that_loses_bytes_is_warned_of(
    url: str, robust: bool | None, warned: bool, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    audit = AuditLog(tmp_path / "audit.jsonl")
    with open_device(url, robust_encoding=robust, audit=audit, guardian=False) as dev:
        assert dev.pacer.robust is bool(robust)
    audit.close()
    events: list[dict[str, Any]] = [
        json.loads(line) for line in (tmp_path / "audit.jsonl").read_text().splitlines()
    ]
    recorded = [e for e in events if e.get("event") == "plain_encoding_on_lossy_link"]
    assert bool(warnings_of(caplog)) is warned and bool(recorded) is warned
    if warned:
        assert "--encoding robust" in recorded[0]["message"] and "full-scale" in warnings_of(caplog)[0]


def test_a_timed_uart_declares_that_it_loses_bytes_and_usb_does_not() -> None:
    assert TimedPort(link="uart").loses_bytes and not TimedPort(link="usb").loses_bytes
