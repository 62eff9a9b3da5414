"""A calibration profile's ``mapping`` binds each calibrated intensity to the hardware channel it names.

An eTactileKit calibration profile calibrates electrode ``id`` on hardware channel ``mapping``; the current
felt on that channel is what was calibrated.  So every pulse a channel receives stays within the
calibrated current of the electrode wired to it, on both firmware versions, on the command line and in
Python; a profile whose mapping disagrees with the device's (the array file's ``Mapping_func``, or the
identity without one) is refused before the device is opened, and nothing reaches the board; writing a
profile keeps its mapping.  Deliveries are judged on the pulses the emulated boards' scans delivered.
"""

from __future__ import annotations

import json
import random
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tactdeform_hw.cli import main
from tactdeform_hw.cli.replay_log import replay
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice, open_device
from tactdeform_hw.device.participant.mapping import ChannelMapping
from tactdeform_hw.device.participant.regions import TACTDEFORM_POSITIONS_MM
from tactdeform_hw.device.safety.guard import SafetyGuard
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.faults import TimedPort
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.errors import SafetyError
from tactdeform_hw.formats import calibration_profile as cp
from tactdeform_hw.protocol import commands as p1
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER
from tactdeform_hw.render.array import ElectrodeArray

from .safety_helpers import RecordingPort
from .test_v2_driver import V2Board

FIRMWARES = ("v1.2", "v2")
N = 32
#: Electrode i on hardware channel 31 - i, and a random permutation with a fixed seed.
REVERSED: tuple[int, ...] = tuple(N - 1 - i for i in range(N))
SHUFFLED: tuple[int, ...] = tuple(random.Random(20261127).sample(range(N), N))
PERMUTATIONS = {"reversed": REVERSED, "shuffled": SHUFFLED}
#: Each electrode's calibrated current (µA, by id): all different, 400 to 2000 µA, the highest 2000.
CAPS_UA: tuple[int, ...] = tuple(400 + 50 * ((7 * i) % N) for i in range(N))
REQUEST_UA = max(CAPS_UA)
REGIONS = tuple(int(r) for r in ElectrodeArray.tactdeform().regions)
SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "etactilekit-formats"


def calibration(mapping: Sequence[int], caps_ua: Sequence[int]) -> dict[str, Any]:
    """An upstream calibration profile: electrode i wired to ``mapping[i]`` at ``caps_ua[i]``."""
    return {
        "format": "etactilekit_calibration_profile",
        "version": "1.0",
        "created_at": "2026-11-27T10:00:00",
        "layout": {"name": "Finger pad", "slug": "finger-pad", "electrode_count": len(mapping)},
        "electrodes": [
            {"id": i, "label": f"E{i}", "mapping": ch, "intensity": DEFAULT_TRANSFER.to_code(ua, "cap")}
            for i, (ch, ua) in enumerate(zip(mapping, caps_ua))
        ],
    }


def array_file(mapping: Sequence[int]) -> dict[str, Any]:
    """The TactDeform pad (its own positions, application order) wired by ``Mapping_func``."""
    return {
        "outline": [],
        "electrodes": [{"x": x, "y": y} for x, y in TACTDEFORM_POSITIONS_MM],
        "Electrodes_Number": len(mapping),
        "Mapping_func": list(mapping),
        "electrode_radius": 0.7,
    }


def write(path: Path, doc: dict[str, Any]) -> Path:
    path.write_text(json.dumps(doc))
    return path


def cap_of_channel(mapping: Sequence[int], caps_ua: Sequence[int]) -> dict[int, int]:
    return {ch: caps_ua[i] for i, ch in enumerate(mapping)}


def finding() -> dict[str, Any]:
    """The profile of the finding: electrode i on channel 31 - i; electrode 31 (channel 0) at DAC code 10
    (100 µA), every other electrode at 3000 µA."""
    d = calibration(REVERSED, [3000] * N)
    d["electrodes"][31]["intensity"] = 10
    return d


# --- the emulated boards, and the pulses they delivered ------------------------------------------------


class Board:
    """A device on the timed model of one firmware, and the largest current each channel received."""

    def __init__(self, firmware: str, guard: SafetyGuard, mapping: ChannelMapping) -> None:
        self.firmware = firmware
        if firmware == "v2":
            self.v2 = V2Board()
            self.port = TimedPort(self.v2)  # type: ignore[arg-type]
        else:
            self.v1 = TimedEmulator("compact", 1, link="usb")
            self.port = TimedPort(self.v1, link="usb")
        self.dev = EtactileKitDevice(self.port, firmware=firmware, guard=guard, mapping=mapping)

    def peaks_ua(self, since_s: float) -> dict[int, float]:
        """Each channel's highest delivered current since ``since_s`` (the DAC code's current or the
        skin model's, whichever is larger); channels that received nothing are absent."""
        if self.firmware == "v2":
            return {ch: ua for ch, ua in self.v2.peak_current_ua(since_us=since_s * 1e6).items() if ua > 0}
        t = self.v1.reports.pulse_table(since_s * 1e6)
        cur = np.maximum(t["current_ua"], t["code"] * 10.0) if t["code"].size else np.zeros(0)
        out: dict[int, float] = {}
        for ch, ua in zip(t["channel"].astype(int).tolist(), cur.tolist()):
            if ua > 0:
                out[ch] = max(out.get(ch, 0.0), float(ua))
        return out


def guard_for(mapping: Sequence[int], caps_ua: Sequence[int]) -> SafetyGuard:
    prof = cp.calibration_from_dict(calibration(mapping, caps_ua), "cal.json")
    return cp.calibration_guard(prof, REGIONS, mapping=ChannelMapping(tuple(mapping), N))


@pytest.mark.parametrize("firmware", FIRMWARES)
@pytest.mark.parametrize("perm", sorted(PERMUTATIONS))
def test_every_channel_stays_within_the_electrode_wired_to_it(firmware: str, perm: str) -> None:
    mapping = PERMUTATIONS[perm]
    limit = cap_of_channel(mapping, CAPS_UA)
    board = Board(firmware, guard_for(mapping, CAPS_UA), ChannelMapping(mapping, N))
    dev, port = board.dev, board.port
    dev.configure(StimConfig(electrode_count=N, current_ua=REQUEST_UA, pulse_width_us=200))
    rng = random.Random(7)
    frames = [[1 if j == i else 0 for j in range(N)] for i in range(N)]  # each electrode alone
    frames += [[1 if rng.random() < 0.3 else 0 for _ in range(N)] for _ in range(6)]
    seen: dict[int, float] = {}
    for levels in frames:
        dev.send_pattern(levels)
        port.advance(0.004)  # the frame reaches the board
        t = port.now_s
        port.advance(0.02)
        peaks = board.peaks_ua(t)
        active = {mapping[i] for i, v in enumerate(levels) if v}
        assert set(peaks) <= active, "only the channels of active electrodes receive current"
        for ch, ua in peaks.items():
            assert ua <= limit[ch] + 1e-6, (ch, ua, limit[ch])
            seen[ch] = max(seen.get(ch, 0.0), ua)
        if sum(levels) == 1:
            (i,) = (k for k, v in enumerate(levels) if v)
            # alone, an electrode gets exactly its own calibration, on the channel it is wired to
            assert peaks == {mapping[i]: float(CAPS_UA[i])}
    assert set(seen) == set(range(N))  # every channel stimulated: the check is about real pulses
    dev.close()


def test_the_interlock_holds_each_channel_to_its_calibration_whatever_the_bytes_mapping() -> None:
    """The interlock reads hardware channels: bytes that put 2000 µA on channel 0 (electrode 31 of the
    finding, calibrated at 100 µA) are refused whatever mapping they were built with."""
    prof = cp.calibration_from_dict(finding(), "cal.json")
    guard = cp.calibration_guard(prof, REGIONS, mapping=ChannelMapping(REVERSED, N))

    def frame(code: int) -> bytes:
        return (
            p1.encode_pulse_height(0)
            + p1.encode_sense_height(0)
            + p1.encode_pulse_width(200)
            + p1.encode_electrode_num(N)
            + p1.encode_pattern([0] * N)
            + p1.encode_pulse_height(code)
            + p1.encode_pattern([1] + [0] * (N - 1))  # on hardware channel 0
        )

    for mapping in (None, ChannelMapping.identity(N), ChannelMapping(REVERSED, N)):
        with pytest.raises(SafetyError, match="channel 0 would receive 2000 µA, above its limit of 100 µA"):
            guard.interlock.check_wire(frame(200), mapping=mapping)
        guard.interlock.check_wire(frame(10), mapping=mapping)  # 100 µA on channel 0: its calibration


# --- the finding: a mapping the device does not follow -------------------------------------------------


@pytest.fixture
def no_port(monkeypatch: pytest.MonkeyPatch) -> list[RecordingPort]:
    """Every port a command opens, recording what it writes (an in-process board of the v1.2 firmware)."""
    opened: list[RecordingPort] = []

    def fake_open_port(name: str, **_kw: Any) -> RecordingPort:
        port = RecordingPort(Emulator(firmware="v2" if "v2" in name else "v1.2"))
        opened.append(port)
        return port

    monkeypatch.setattr("tactdeform_hw.device.driver.serial_driver.open_port", fake_open_port)
    return opened


def _written(ports: list[RecordingPort]) -> int:
    return sum(len(w) for port in ports for w in port.writes)


@pytest.mark.parametrize("firmware", FIRMWARES)
def test_send_refuses_a_profile_wired_otherwise_than_the_device(
    firmware: str, tmp_path: Path, no_port: list[RecordingPort], capsys: pytest.CaptureFixture[str]
) -> None:
    cal = write(tmp_path / "cal.json", finding())
    pattern = ",".join(["1"] + ["0"] * (N - 1))
    device = ["--device", f"etactile://?firmware={firmware}&timed=0", "--firmware", firmware]
    argv = ["send", "--participant", str(cal), "--pattern", pattern, "--current-ua", "2000", *device]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"tactdeform-hw send: error: calibration profile {cal}: electrode 0 is calibrated ")
    assert "on hardware channel 31 but the identity mapping" in err and "wires it to channel 0" in err
    assert err.rstrip().endswith("nothing was sent")
    assert no_port == [] and _written(no_port) == 0  # the device was never opened: no byte reached it
    # an array file whose Mapping_func is not the profile's: refused the same way, naming both channels
    ident = write(tmp_path / "ident.json", array_file(range(N)))
    assert main([*argv, "--array", str(ident)]) == 1
    err = capsys.readouterr().err
    assert "hardware channel 31 but --array ident.json's Mapping_func wires it to channel 0" in err
    assert _written(no_port) == 0


@pytest.mark.parametrize("command", ["play", "render", "study"])
def test_every_stimulating_command_refuses_a_profile_wired_otherwise(
    command: str, tmp_path: Path, no_port: list[RecordingPort], capsys: pytest.CaptureFixture[str]
) -> None:
    """``play`` without an array, ``render`` and ``study`` (the TactDeform array, electrode i on channel
    i) refuse the finding's profile before their device is opened."""
    cal = write(tmp_path / "cal.json", finding())
    seq = {
        "Execution": True,
        "Simulation": True,
        "Pattern_Data": [
            [
                {
                    "delay": {"ON": 20, "OFF": 0},
                    "pattern": [1] + [0] * (N - 1),
                    "params": {"frequency": 125, "stim_mode": 1},
                }
            ]
        ],
    }
    argv = {
        "play": ["play", str(write(tmp_path / "pattern.json", seq)), "--current-ua", "2000"],
        "render": ["render", "--scene", "cube", "--trajectory", "approach-face", "--quiet"],
        "study": ["study", "task1", "--quick", "--quiet", "--out", str(tmp_path / "study")],
    }[command]
    assert main([*argv, "--participant", str(cal)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"tactdeform-hw {command}: error: calibration profile {cal}: electrode 0 ")
    assert "calibrated on hardware channel 31" in err and "wires it to channel 0" in err
    assert err.count("\n") == 1 and no_port == [] and _written(no_port) == 0


@pytest.mark.parametrize("firmware", FIRMWARES)
def test_send_with_the_profiles_wiring_delivers_the_calibration_on_channel_0(
    firmware: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The finding's command with the array the profile was calibrated on: electrode 31 is on channel 0
    and gets its 100 µA; electrode 0 (channel 31) gets the 2000 µA asked for."""
    cal = write(tmp_path / "cal.json", finding())
    arr = write(tmp_path / "reversed.json", array_file(REVERSED))
    log = tmp_path / "session.jsonl"
    device = ["--device", f"etactile://?firmware={firmware}&timed=0", "--firmware", firmware]
    for active, channel, expected in ((31, 0, 100.0), (0, 31, 2000.0)):
        pattern = ",".join("1" if i == active else "0" for i in range(N))
        argv = ["send", "--participant", str(cal), "--array", str(arr), "--pattern", pattern]
        argv += ["--current-ua", "2000", "--hold-ms", "40", "--audit-log", str(log), *device]
        assert main(argv) == 0
        capsys.readouterr()
        table = replay(str(log))["_table"]
        live = table["current_ua"] > 0
        assert set(table["channel"][live].astype(int).tolist()) == {channel}
        assert float(table["current_ua"][live].max()) == expected
        assert int(live.sum()) > 3
        log.unlink()


@pytest.mark.parametrize("firmware", FIRMWARES)
def test_python_refuses_a_profile_wired_otherwise_than_the_device(firmware: str) -> None:
    prof = cp.calibration_from_dict(finding(), "cal.json")
    match = r"cal.json: electrode 0 is calibrated on hardware channel 31 but .* wires it to channel 0"
    with pytest.raises(SafetyError, match=match):
        cp.calibration_guard(prof, REGIONS)  # no mapping: the identity
    with pytest.raises(SafetyError, match=match):
        cp.check_mapping(prof, list(range(N)))
    # a guard built for the profile's wiring, given to a device driven without it
    guard = cp.calibration_guard(prof, REGIONS, mapping=ChannelMapping(REVERSED, N))
    port = RecordingPort(Emulator(firmware=firmware))
    with pytest.raises(SafetyError, match=match):
        EtactileKitDevice(port, firmware=firmware, guard=guard)
    with pytest.raises(SafetyError, match=match):
        open_device("emulator", firmware=firmware, guard=guard, mapping=ChannelMapping.identity(N))
    assert port.writes == []


@pytest.mark.parametrize("firmware", FIRMWARES)
def test_python_with_the_profiles_wiring_delivers_the_calibration_on_channel_0(firmware: str) -> None:
    prof = cp.calibration_from_dict(finding(), "cal.json")
    wired = ChannelMapping(prof.mapping(), N)
    board = Board(firmware, cp.calibration_guard(prof, REGIONS, mapping=wired), wired)
    board.dev.configure(StimConfig(electrode_count=N, current_ua=2000))
    board.dev.send_pattern([0] * (N - 1) + [1])  # electrode 31: hardware channel 0
    board.port.advance(0.004)
    t = board.port.now_s
    board.port.advance(0.03)
    assert board.peaks_ua(t) == {0: 100.0}
    board.dev.close()


@pytest.mark.parametrize("firmware", FIRMWARES)
def test_replay_log_judges_each_channel_by_the_electrode_calibrated_on_it(
    firmware: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A session sent under a looser profile (every electrode 2000 µA), judged afterwards against the
    finding's profile: every pulse on channel 0 (electrode 31, calibrated at 100 µA) is listed, none on
    channel 31 (electrode 0, 3000 µA)."""
    loose = write(tmp_path / "loose.json", calibration(REVERSED, [2000] * N))
    strict = write(tmp_path / "cal.json", finding())
    arr = write(tmp_path / "reversed.json", array_file(REVERSED))
    log = tmp_path / "session.jsonl"
    pattern = ",".join("1" if i in (0, 31) else "0" for i in range(N))
    device = ["--device", f"etactile://?firmware={firmware}&timed=0", "--firmware", firmware]
    argv = ["send", "--participant", str(loose), "--array", str(arr), "--pattern", pattern]
    assert main([*argv, "--current-ua", "2000", "--hold-ms", "40", "--audit-log", str(log), *device]) == 0
    capsys.readouterr()
    assert main(["replay-log", str(log), "--participant", str(strict), "--json"]) == 3
    out = json.loads(capsys.readouterr().out)
    channels = {int(k): v for k, v in out["channels"].items()}
    assert out["above_limit_count"] == channels[0]["pulses"] > 3
    assert [(b["channel"], b["electrode"], b["limit_ua"]) for b in out["above_limit_by_channel"]] == [
        (0, 31, 100.0)
    ]
    assert main(["replay-log", str(log), "--participant", str(loose), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["above_limit_count"] == 0


# --- the kit's own array files ------------------------------------------------------------------------------


def _shared(name: str) -> Path:
    path = SHARED / name
    if not path.exists():
        pytest.skip(f"{path} is not available (the shared reference data sits beside the repository)")
    return path


@pytest.mark.parametrize("firmware", FIRMWARES)
def test_the_kits_64_electrode_array_binds_its_mapping_func(
    firmware: str, tmp_path: Path, no_port: list[RecordingPort], capsys: pytest.CaptureFixture[str]
) -> None:
    from tactdeform_hw.formats import read_array_file

    grid = _shared("electrodes_64.json")
    mapping = read_array_file(grid).mapping_func
    assert mapping != tuple(range(64))
    wrong = write(tmp_path / "identity64.json", calibration(range(64), [500] * 64))
    pattern = ",".join(["1"] + ["0"] * 63)
    device = ["--device", f"etactile://?firmware={firmware}&timed=0", "--firmware", firmware]
    argv = ["send", "--array", str(grid), "--pattern", pattern, "--current-ua", "500", "--frequency-hz", "50"]
    argv += device
    assert main([*argv, "--participant", str(wrong)]) == 1
    err = capsys.readouterr().err
    assert (
        "electrode 0 is calibrated on hardware channel 0 but --array electrodes_64.json's Mapping_func" in err
    )
    assert f"wires it to channel {mapping[0]}" in err and _written(no_port) == 0
    right = write(tmp_path / "cal64.json", calibration(mapping, [500] * 64))
    assert main([*argv, "--participant", str(right)]) == 0
    assert _written(no_port) > 0


def test_the_kits_on_board_array_counts_its_mapping_from_channel_24(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    board = _shared("electrode_array_main_board.json")
    caps = [300, 400, 500, 600, 700, 800, 900, 1000]
    cal = write(tmp_path / "cal8.json", calibration(range(8), caps))
    log = tmp_path / "onboard.jsonl"
    argv = ["send", "--array", str(board), "--participant", str(cal), "--pattern", "1,0,0,0,0,0,0,0"]
    argv += ["--current-ua", "1000", "--hold-ms", "40", "--audit-log", str(log)]
    assert main(argv) == 0
    capsys.readouterr()
    table = replay(str(log))["_table"]
    live = table["current_ua"] > 0
    assert set(table["channel"][live].astype(int).tolist()) == {24}
    assert float(table["current_ua"][live].max()) == 300.0


# --- writing keeps the mapping -----------------------------------------------------------------------------


@pytest.mark.parametrize("perm", sorted(PERMUTATIONS))
def test_writing_a_calibration_profile_keeps_its_mapping(perm: str, tmp_path: Path) -> None:
    mapping = PERMUTATIONS[perm]
    prof = cp.calibration_from_dict(calibration(mapping, CAPS_UA), "cal.json")
    again = cp.load_calibration_profile(cp.save_calibration_profile(prof, tmp_path / "cal.json"))
    assert again.mapping() == mapping and again.to_dict() == prof.to_dict()
    # through a participant profile and back, with the array's wiring
    person = cp.to_participant(prof, REGIONS)
    back = cp.from_participant(person, REGIONS, mapping=prof.mapping())
    assert back.mapping() == mapping


KEYS = "+" * 20 + " a  - - a\n" + "+" * 12 + " a " + ("+" * 14 + " a ") * 7 + " + a"


def test_calibrate_writes_a_calibration_profile_with_the_arrays_mapping(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    keys = write_text(tmp_path / "keys.txt", KEYS)
    arr = write(tmp_path / "shuffled.json", array_file(SHUFFLED))
    out = tmp_path / "P11.json"
    etk = tmp_path / "P11-etactilekit.json"
    argv = ["calibrate", "--participant", str(out), "--keys", str(keys), "--max-ua", "300"]
    assert main([*argv, "--array", str(arr), "--calibration-out", str(etk), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["calibration_profile"] == str(etk)
    written = cp.load_calibration_profile(etk)
    assert written.mapping() == SHUFFLED
    # each electrode at its region's calibrated current
    regions = res["regions_ua"]
    assert list(written.currents_ua()) == [regions[r] for r in REGIONS]
    # the written profile is accepted with the array it was calibrated on, and refused without it
    pattern = ",".join(["1"] + ["0"] * (N - 1))
    send = ["send", "--participant", str(etk), "--pattern", pattern, "--current-ua", "100"]
    assert main([*send, "--array", str(arr)]) == 0
    assert main(send) == 1
    assert "wires it to channel 0" in capsys.readouterr().err


def write_text(path: Path, text: str) -> Path:
    path.write_text(text)
    return path
