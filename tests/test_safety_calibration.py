"""Calibration (state machine and CLI), the audit log and replay-log."""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest

from tactdeform_hw.cli import main
from tactdeform_hw.cli.replay_log import replay
from tactdeform_hw.device.driver.audit import AuditLog, read_log
from tactdeform_hw.device.participant.calibration import MATCH_ORDER, Calibration, Phase, parse_key_script
from tactdeform_hw.device.participant.profiles import load_profile
from tactdeform_hw.errors import ConfigurationError


def test_procedure_from_zero_in_10ua_steps() -> None:
    cal = Calibration("P01", max_ua=500)
    s = cal.stimulus()
    assert s.phase is Phase.CENTRE_UP and s.current_ua == 0 and s.regions == (4,)
    seen = [cal.press("+").current_ua for _ in range(25)]
    assert seen[:3] == [10, 20, 30] and seen[-1] == 250
    lv = cal.stimulus().levels()
    # the centre's 4 electrodes
    assert sum(lv) == 4 and [i for i, v in enumerate(lv) if v] == [12, 13, 18, 19]
    s = cal.press("a")  # discomfort at 250 µA
    assert s.phase is Phase.CENTRE_DOWN and s.current_ua == 240 and cal.cap_ua == 240
    assert cal.press("+").current_ua == 240  # never back above the step below discomfort
    for _ in range(4):
        cal.press("-")
    s = cal.press("a")  # clear and pain-free at 200
    assert s.phase is Phase.MATCH and s.current_ua == 0 and s.regions == (MATCH_ORDER[0],)
    s = cal.press("c")
    assert s.regions == (4,) and s.current_ua == 200  # feel the centre again
    s = cal.press("c")
    assert s.regions == (0,) and s.current_ua == 0
    for i, _region in enumerate(MATCH_ORDER):
        for _ in range(10 + i):
            cal.press("+")
        s = cal.press("a")
    assert s.phase is Phase.GLOBAL and s.regions == tuple(range(9))
    assert cal.regions_ua == [100, 110, 120, 130, 200, 140, 150, 160, 170]
    assert s.current_ua == 100  # the whole array at the lowest region: one pulse height per scan
    for _ in range(6):
        cal.press(">")  # shift together, bounded by the cap (240 - 200 = 40 µA of room)
    assert cal.regions_ua == [140, 150, 160, 170, 240, 180, 190, 200, 210]
    cal.press("a")
    assert cal.phase is Phase.DONE and cal.stimulus().current_ua == 0
    prof = cal.profile(contact_mode="uniform")
    assert prof.cap_ua == 240 and prof.regions_ua[4] == 240 and prof.contact_mode == "uniform"
    with pytest.raises(ConfigurationError, match="done"):
        cal.press("+")


def test_refusals_and_quit() -> None:
    cal = Calibration("P02")
    with pytest.raises(ConfigurationError, match="raise the current first"):
        cal.press("a")
    with pytest.raises(ConfigurationError, match="not a calibration key"):
        cal.press("x")
    cal.press("+")
    s = cal.press("q")
    assert s.phase is Phase.ABORTED and s.current_ua == 0 and s.levels() == [0] * 32
    with pytest.raises(ConfigurationError, match="not done"):
        cal.profile()
    with pytest.raises(Exception, match="max_ua"):
        Calibration("P03", max_ua=10_010)
    cal = Calibration("P04", max_ua=30)
    assert cal.run(["+"] * 10).current_ua == 30  # the ceiling bounds every step
    assert parse_key_script("+++ # three\nenter - quit") == ["+", "+", "+", "a", "-", "q"]


KEYS = "+" * 20 + " a  - - a\n" + "+" * 12 + " a " + ("+" * 14 + " a ") * 7 + " + a"


def test_cli_writes_the_profile_from_a_key_script(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    keys = tmp_path / "keys.txt"
    keys.write_text(KEYS)
    out = tmp_path / "P09.toml"
    audit = tmp_path / "cal.jsonl"
    rc = main(
        [
            "calibrate",
            "--participant",
            str(out),
            "--keys",
            str(keys),
            "--max-ua",
            "300",
            "--audit-log",
            str(audit),
            "--json",
        ]
    )
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    prof = load_profile(out)
    # discomfort at 200, down two steps from 190 → centre 170, others 120 / 140, then all +10
    assert prof.participant == "P09" and prof.cap_ua == 190
    assert prof.regions_ua == (130, 150, 150, 150, 180, 150, 150, 150, 150)
    assert res["peak_ua"] == 200 and res["cap_ua"] == 190
    recs = list(read_log(audit))
    heights = [r["value"] for r in recs if r["type"] == "tx" and r["cmd"] == "PULSE_HEIGHT"]
    assert max(heights) == 20 and heights[-1] == 0  # never above discomfort, off at the end
    rep = replay(str(audit))
    assert rep["max_current_ua"] <= 200 and rep["final_state"]["pulse_height"] == 0


def test_cli_reads_keys_from_stdin_and_quits_without_profile(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr("sys.stdin", io.StringIO("+++ q"))
    monkeypatch.chdir(tmp_path)
    assert main(["calibrate", "--participant", "P10", "--keys", "-"]) == 1
    assert not (tmp_path / "P10.json").exists()
    monkeypatch.setattr("sys.stdin", io.StringIO("+++"))
    assert main(["calibrate", "--participant", "P10"]) == 1  # not a terminal: read as a script; unfinished


def test_audit_log_and_replay_of_a_send_session(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    audit = tmp_path / "send.jsonl"
    rc = main(
        [
            "send",
            "--pattern",
            "1,0,1,0",
            "--electrodes",
            "4",
            "--current-ua",
            "800",
            "--hold",
            "0.05",
            "--audit-log",
            str(audit),
        ]
    )
    assert rc == 0
    capsys.readouterr()
    rep = replay(str(audit))
    assert rep["max_current_ua"] == 800.0 and set(rep["channels"]) == {0, 2}
    ch = rep["channels"][0]
    assert ch["max_charge_nc"] == pytest.approx(800 * 196.6 / 1000, rel=0.02)  # the firmware's 196.6 µs pulse
    assert rep["losses"] == [] and rep["final_state"]["pulse_height"] == 0
    prof = tmp_path / "p.json"
    prof.write_text(
        json.dumps(
            {
                "version": 1,
                "participant": "P11",
                "cap_ua": 500,
                "regions_ua": [500] * 9,
                "pulse_width_us": 200,
                "polarity": "anodic",
                "contact_mode": "uniform",
                "calibrated_on": "2024-05-01",
            }
        )
    )
    assert main(["replay-log", str(audit), "--participant", str(prof), "--json"]) == 3  # 800 µA > 500 µA cap
    out = json.loads(capsys.readouterr().out)
    assert out["above_limit_count"] > 0 and out["above_limit"][0]["limit_ua"] == 500


def test_audit_log_format_errors(tmp_path: Path) -> None:
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"type": "tx", "t": 0}\n')
    with pytest.raises(ConfigurationError, match="line 1"):
        list(read_log(bad))
    bad.write_text("not json\n")
    with pytest.raises(ConfigurationError, match="line 1: not JSON"):
        list(read_log(bad))
    empty = tmp_path / "empty.jsonl"
    log = AuditLog(empty, note="x")
    log.close()
    with pytest.raises(ConfigurationError, match="no commands"):
        replay(str(empty))


def test_cli_guard_names_the_participant_being_calibrated(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import tactdeform_hw.device as device_pkg

    guards = []
    real_open = device_pkg.open_device

    def spy(*args: object, **kw: object) -> object:
        guards.append(kw["guard"])
        return real_open(*args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(device_pkg, "open_device", spy)
    monkeypatch.setattr("sys.stdin", io.StringIO("+ q"))
    monkeypatch.chdir(tmp_path)
    assert main(["calibrate", "--participant", "P11", "--keys", "-", "--max-ua", "300"]) == 1
    assert len(guards) == 1 and guards[0].participant == "P11" and guards[0].cap_ua == 300


def test_replay_log_uses_the_firmware_the_log_was_written_for(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    send = ["send", "--pattern", "1,0,1,0", "--electrodes", "4", "--current-ua", "800", "--hold-ms", "50"]
    v2_log, v12_log = tmp_path / "v2.jsonl", tmp_path / "v12.jsonl"
    assert (
        main(
            [
                *send,
                "--device",
                "etactile://?firmware=v2&timed=0",
                "--firmware",
                "v2",
                "--audit-log",
                str(v2_log),
            ]
        )
        == 0
    )
    assert main([*send, "--device", "emulator", "--firmware", "v1.2", "--audit-log", str(v12_log)]) == 0
    capsys.readouterr()
    # a v2 log on the v2 model: its u16 heights read as heights, the pulses delivered
    rep = replay(str(v2_log))
    assert rep["firmware"] == "v2" and rep["max_current_ua"] == 800.0 and set(rep["channels"]) == {0, 2}
    assert rep["channels"][0]["heights_ua"] == [800.0] and rep["final_state"]["stim_mode"] in (0, 1)
    assert replay(str(v2_log), firmware="v2")["channels"][2]["pulses"] == rep["channels"][2]["pulses"]
    # a v1.2 log still on the v1.2 model
    old = replay(str(v12_log), firmware="v1.2")
    assert old["firmware"] == "v1.2" and old["max_current_ua"] == 800.0 and set(old["channels"]) == {0, 2}
    assert "heights_ua" not in old["channels"][0] and old["final_state"]["pulse_height"] == 0
    # a log replayed as another firmware than it records: one line naming the option and both versions
    for log, asked, written in ((v2_log, "v1.2", "v2"), (v12_log, "v2", "v1.2")):
        assert main(["replay-log", str(log), "--firmware", asked]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"tactdeform-hw replay-log: error: --firmware {asked}:")
        assert f"written for firmware {written}" in err[0]
    # a firmware this package does not know: refused, never replayed on a model of another
    odd = tmp_path / "v3.jsonl"
    odd.write_text(v2_log.read_text().replace('"firmware":"v2"', '"firmware":"v3"'))
    assert main(["replay-log", str(odd)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "firmware 'v3' is not a known firmware version" in err[0]
