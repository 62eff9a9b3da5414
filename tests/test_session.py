"""The session builder: profile, guard, wiring, delivery log, device and renderer, in the order that keeps
"nothing was sent" true, shared by the stimulating commands and the study runner."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path
from typing import Any

import pytest

from tactdeform_hw.device.participant.profiles import ParticipantProfile, save_profile
from tactdeform_hw.errors import ProfileError, SafetyError
from tactdeform_hw.render.manager import IDLE, ManagerConfig, PatternManager, State
from tactdeform_hw.session import Session, Wiring


def _calibration(count: int = 32, intensity: int = 250) -> dict[str, Any]:
    """An eTactileKit calibration profile wiring electrode i to channel 5i mod 32 (not the identity)."""
    return {
        "format": "etactilekit_calibration_profile",
        "version": "1.0",
        "layout": {"name": "Finger pad", "slug": "finger-pad", "electrode_count": count},
        "electrodes": [
            {"id": i, "label": f"E{i}", "mapping": (i * 5) % count, "intensity": intensity}
            for i in range(count)
        ],
    }


def test_a_malformed_profile_is_refused_when_the_session_is_made(tmp_path: Path) -> None:
    bad = tmp_path / "p.json"
    bad.write_text('{"participant": "P01", "cap_ua": "lots"}')
    with pytest.raises(ProfileError):
        Session(participant_file=str(bad), wiring=Wiring.tactdeform())


def test_a_guard_that_disagrees_with_the_wiring_is_refused_at_once_or_on_first_use(tmp_path: Path) -> None:
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(_calibration()))
    with pytest.raises(SafetyError, match="calibrated on hardware channel"):
        Session(participant_file=str(path))  # the identity wiring: electrode 1 is not on channel 1
    later = Session(participant_file=str(path), guard_now=False)  # a command checking its options first
    assert later.profile.cap_ua == 2500
    with pytest.raises(SafetyError, match="calibrated on hardware channel"):
        later.guard  # noqa: B018


def test_without_a_participant_the_guard_is_the_hardware_ceiling() -> None:
    session = Session(wiring=Wiring.tactdeform())
    assert session.profile is None and session.participant is None
    assert session.guard.cap_ua == 10_000


def test_the_delivery_log_records_the_wiring_after_the_commands_fields(tmp_path: Path) -> None:
    profile = ParticipantProfile("P07", 1500, (1500,) * 9, dt.date(2026, 1, 2))
    path = save_profile(profile, tmp_path / "p07.json")
    audit = tmp_path / "audit.jsonl"
    session = Session(participant_file=str(path), audit_path=audit, wiring=Wiring.tactdeform())
    with session.delivery_log(session.header("render"), requested_ua=900) as log:
        assert session.log is log
        assert log.report()["requested_ua"] == 900
    header = json.loads(audit.read_text().splitlines()[0])
    keys = [k for k in header if k not in ("type", "version", "started")]
    assert keys == [
        "command",
        "device",
        "participant_file",
        "participant",
        "mapping",
        "hw_channels",
        "positions_mm",
    ]
    assert header["participant"] == "P07" and header["participant_file"] == str(path)
    assert header["mapping"] == list(session.wiring.mapping.app_to_hw)


def test_the_session_opens_its_device_under_its_guard_and_log() -> None:
    session = Session(wiring=Wiring.tactdeform())
    log = session.delivery_log(session.header("test"))
    with session.open_device() as dev:
        assert dev.guard is session.guard
        assert dev.audit is log
        renderer = session.renderer(None, dev, current_ua=0)
        assert renderer.array is session.wiring.array


def test_the_manager_states_are_an_enum_and_its_outputs_carry_their_text() -> None:
    assert (
        State.IDLE == IDLE
        and State("idle") is State.IDLE
        and f"{State.APPROACHING}" == "approaching"
        and str(State.INTERACTING) == "interacting"
    )
    manager = PatternManager(config=ManagerConfig())
    assert manager.state is State.IDLE
    out = manager.update(0.0, (0.0, 0.0, 10.0), (1.0, 0.0, 0.0, 0.0), None)
    assert type(out.state) is str and out.state == IDLE
