"""Live tracking over loopback UDP into in-process boards: bad samples counted and never rendered, a stream
that stops switched off (judged on the pulses the real-time board delivered), a stopped or restarted
sender picked up again only after a sustained run of valid samples, Ctrl-C ending a live ``render`` with
everything off, the summary and status 130, the latency report's fields, the LSL inlet and outlet through
fakes, and a clear error naming the extra when pylsl is absent."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tactdeform_hw.device import StimConfig, open_device
from tactdeform_hw.device.safety.failsafe import DEFAULT_WATCHDOG_S
from tactdeform_hw.errors import ConfigurationError, LimitError, install_command
from tactdeform_hw.protocol.firmware_math import firmware_period_us
from tactdeform_hw.render.array import ElectrodeArray
from tactdeform_hw.render.live import (
    LiveRun,
    LslPatternOutlet,
    LslTrackingSource,
    UdpTrackingSource,
    open_tracking,
    parse_sample,
)
from tactdeform_hw.render.pipeline import RESUME_AFTER_VALID_SAMPLES, Renderer

from .render_fakes import PAD_DOWN, FakeFloor
from .safety_helpers import current_pulses_us

DT = 1.0 / 72.0
#: The floor is z ≤ 0; the finger rests 3 mm into it, 100 mm from the world origin (a point within 3 mm
#: of the origin is taken for metres).
AT = (100.0, 0.0, -3.0)
ABOVE = (100.0, 0.0, 20.0)
#: No current pulse may start later than this after the last valid sample: the device's no-frame watchdog
#: and the scan under way when the all-off arrived (the renderer itself switches off after 80 ms).
BOUND_S = DEFAULT_WATCHDOG_S + firmware_period_us(125) / 1e6


def line(t: float, p: tuple[float, float, float], q: tuple[float, ...] = PAD_DOWN) -> bytes:
    return (",".join(repr(float(v)) for v in (t, *p, *q))).encode()


class Stream:
    """A live run in a thread on a loopback UDP port, and a sender for it."""

    def __init__(self, renderer: Renderer, **kw: Any) -> None:
        self.source = UdpTrackingSource("127.0.0.1", 0)
        self.records: list[Any] = []
        self.live = LiveRun(renderer, self.source, on_record=self.records.append, **kw)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.thread = threading.Thread(target=self.live.run, daemon=True)
        self.thread.start()
        self.last_valid_s = 0.0

    def send(self, payload: bytes, valid: bool = True) -> None:
        self.sock.sendto(payload, self.source.address)
        if valid:
            self.last_valid_s = time.monotonic()
        time.sleep(DT)

    def press(self, t0: float = 0.0, n: int = 20) -> float:
        """Come down onto the floor and rest there; the time of the last sample."""
        t = t0
        for i in range(n):
            t = t0 + i * DT
            self.send(line(t, ABOVE if i < 2 else AT))
        return t

    def close(self) -> None:
        self.live.stop()
        self.thread.join(5)
        self.source.close()
        self.sock.close()


#: The instant board's renderer waits this long for a valid sample (default 80 ms) so that a busy machine
#: pausing the sender thread between two samples does not count as a stream that stopped.
LOST_S = 0.25


@pytest.fixture
def instant() -> Iterator[Any]:
    array = ElectrodeArray.tactdeform()
    with open_device("emulator", mapping=array.channel_mapping()) as dev:
        cfg = StimConfig(electrode_count=32, current_ua=800)
        yield Renderer(FakeFloor(), dev, array=array, stim_config=cfg, lost_tracking_s=LOST_S)


def test_parse_sample_reasons() -> None:
    assert parse_sample(b"1.0,2,3", 0.0) == "columns"
    assert parse_sample(b"", 0.0) == "columns"
    assert parse_sample(b"1,2,3,4,5,6,7,8,9", 0.0) == "columns"
    assert parse_sample(b"1,a,3,4,1,0,0,0", 0.0) == "text"
    assert parse_sample(b"\xff\xfe", 0.0) == "text"
    assert parse_sample(b"1,nan,300,4,1,0,0,0", 0.0) == "nan"
    assert parse_sample(b"1,inf,300,4,1,0,0,0", 0.0) == "nan"
    assert parse_sample(b"1,0.1,1.2,0.3,1,0,0,0", 0.0) == "metres"  # a hand 1.2 m up, sent in metres
    s = parse_sample(b"t_s,x_mm,y_mm,z_mm,qw,qx,qy,qz\n1,100,0,-3,1,0,0,0\n", 5.0)
    assert not isinstance(s, str)
    assert (s.t_s, s.position_mm, s.orientation, s.received_s) == (1.0, (100.0, 0.0, -3.0), (1, 0, 0, 0), 5.0)
    assert parse_sample([1, 100, 0, -3, 1, 0, 0, 0], 0.0) != "columns"  # an LSL sample's channels


def test_bad_datagrams_counted_never_rendered_and_never_keep_stimulation_on(instant: Renderer) -> None:
    st = Stream(instant)
    try:
        t = st.press()
        assert instant.device is not None and any(instant.device.last_pattern or ())
        rendered = instant.summary.poses
        for k in range(4):
            for b in (
                b"1,2,3",  # columns
                b"hello,world,1,2,3,4,5,6",  # text
                line(t + 1, (float("nan"), 0.0, -3.0)),  # nan
                line(t + 1, (0.1, 0.0, -0.003)),  # metres
                line(t - 1 - k, AT),  # the clock goes back
            ):
                st.send(b, valid=False)
        time.sleep(LOST_S)
    finally:
        st.close()
    stats = st.live.result.stats.as_dict()
    assert instant.summary.poses == rendered == stats["valid"] == 20
    assert stats["bad"] == {"columns": 4, "text": 4, "nan": 4, "metres": 4, "time-backwards": 4}
    # the bad samples did not hold the contact: the stream counted as stopped and everything went off
    assert st.live.result.stream_stops == 1
    assert instant.device.last_pattern is not None and not any(instant.device.last_pattern)
    off = [r for r in st.records if r.dropped == "lost-tracking"]
    assert len(off) == 1 and off[0].sent and off[0].t_s == t


def test_stream_that_stops_is_switched_off_on_delivered_pulses() -> None:
    array = ElectrodeArray.tactdeform()
    with open_device("etactile://live-stop", mapping=array.channel_mapping(), firmware="v1.2") as dev:
        from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import forget_shared, shared_emulator

        board = shared_emulator("live-stop")
        cfg = StimConfig(electrode_count=32, current_ua=800)
        r = Renderer(FakeFloor(), dev, array=array, stim_config=cfg)
        st = Stream(r)
        try:
            st.press(n=30)
            time.sleep(0.4)
            end_s = time.monotonic()
        finally:
            st.close()
        stopped_s = st.live.result.timings[-1].received_s  # the last valid sample, as the renderer got it
        t0 = board.t0
        before = current_pulses_us(board, (stopped_s - 0.2 - t0) * 1e6)
        after = current_pulses_us(board, (stopped_s - t0) * 1e6)
        late = [us for us in after if us / 1e6 + t0 > stopped_s + BOUND_S]
        forget_shared("live-stop")
    assert any(us / 1e6 + t0 < stopped_s for us in before), "the press never stimulated"
    assert end_s - stopped_s > 3 * BOUND_S
    assert late == [], f"{len(late)} pulses later than {BOUND_S * 1e3:.0f} ms after the stream stopped"
    assert st.live.result.stream_stops >= 1


def test_stopped_stream_resumes_only_after_a_sustained_run(instant: Renderer) -> None:
    st = Stream(instant)
    try:
        t = st.press()
        time.sleep(LOST_S + 0.1)  # the stream stops: all off
        assert instant.device is not None and not any(instant.device.last_pattern or ())
        sent_before = instant.summary.frames_sent
        for i in range(RESUME_AFTER_VALID_SAMPLES - 1):
            st.send(line(t + 1 + i * DT, AT))
        time.sleep(0.02)
        held = instant.summary.frames_sent
        st.send(line(t + 1 + RESUME_AFTER_VALID_SAMPLES * DT, AT))
        for i in range(10):
            st.send(line(t + 2 + i * DT, AT))
    finally:
        st.close()
    assert held == sent_before, "a pattern was sent before the run of valid samples was complete"
    assert instant.summary.held_resuming == RESUME_AFTER_VALID_SAMPLES - 1
    assert instant.summary.frames_sent > held and any(instant.device.last_pattern or ())


def test_restarted_sender_is_rebased_and_held_back(instant: Renderer) -> None:
    st = Stream(instant)
    try:
        st.press(t0=50.0)
        assert instant.device is not None and any(instant.device.last_pattern or ())
        # the sender restarts: its clock begins again at 0
        for i in range(RESUME_AFTER_VALID_SAMPLES + 1):
            st.send(line(i * DT, AT))
        time.sleep(0.02)
        held = [r for r in st.records if r.dropped == "resuming"]
    finally:
        st.close()
    stats = st.live.result.stats.as_dict()
    assert stats["bad"] == {"time-backwards": 1} and stats["restarts"] == 1
    off = [r for r in st.records if r.dropped == "lost-tracking"]
    assert len(off) == 1 and off[0].sent  # switched off at the restart
    assert len(held) == RESUME_AFTER_VALID_SAMPLES - 1
    times = [r.t_s for r in st.records]
    assert all(b >= a for a, b in zip(times, times[1:], strict=False)), "the renderer's time went back"


def test_latency_figures_and_lsl_outlet(instant: Renderer) -> None:
    pushed: list[list[float]] = []

    class FakeOutlet:
        def push_sample(self, values: list[float]) -> None:
            pushed.append(list(values))

    outlet = LslPatternOutlet("pads", 32, outlet=FakeOutlet())
    st = Stream(instant, outlet=outlet)
    try:
        st.press()
    finally:
        st.close()
    timings = st.live.result.timings
    assert len(timings) == 20
    for s in timings:
        d = s.to_json()
        assert set(d) == {"seq", "t_s", "state", "patterns"} | {
            "received_s", "computed_s", "written_s", "compute_ms", "write_ms"
        }  # fmt: skip
        assert d["received_s"] <= d["computed_s"]
        if d["written_s"] is not None:
            assert d["computed_s"] <= d["written_s"] and d["patterns"]
        else:
            assert d["patterns"] == []
    sent = [p for s in timings for p in s.patterns]
    assert len(sent) == instant.summary.frames_sent == len(pushed) > 0
    for values, pattern in zip(pushed, sent, strict=True):
        assert values[3:] == [800.0 * v for v in pattern]
        assert values[1] in (1.0, 2.0, 3.0)
    lat = st.live.result.latency()
    assert lat["received_to_computed"]["n"] == 20
    assert lat["received_to_written"]["n"] == sum(1 for s in timings if s.written_s is not None)


def test_lsl_inlet_through_a_fake() -> None:
    class FakeInlet:
        def __init__(self) -> None:
            self.samples: list[list[float]] = [[0.0, 100, 0, 20, *PAD_DOWN], [0.01, 0.1, 0, 0.2, 1, 0, 0, 0]]

        def pull_sample(self, timeout: float = 0.0) -> tuple[list[float] | None, float]:
            return (self.samples.pop(0), 0.0) if self.samples else (None, 0.0)

    src = LslTrackingSource("hand", inlet=FakeInlet())
    got = [src.receive(0.0) for _ in range(3)]
    assert got[2] is None
    assert [parse_sample(g[0], g[1]) == "metres" for g in got[:2] if g] == [False, True]


def test_lsl_without_pylsl_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    import builtins

    real = builtins.__import__

    def no_pylsl(name: str, *a: Any, **k: Any) -> Any:
        if name == "pylsl":
            raise ImportError("No module named 'pylsl'")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_pylsl)
    with pytest.raises(ConfigurationError, match=re.escape(install_command("lsl"))):
        open_tracking("lsl://hand")
    with pytest.raises(ConfigurationError, match="--lsl-out.*" + re.escape(install_command("lsl"))):
        LslPatternOutlet("pads", 32)


def test_tracking_url_refused() -> None:
    for bad in ("tcp://x:1", "udp://host", "udp://h:99999", "lsl://"):
        with pytest.raises(LimitError, match="--tracking"):
            open_tracking(bad)


def test_ctrl_c_ends_a_live_render_off_with_summary_and_130(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from tactdeform_hw.cli import main

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    report = tmp_path / "latency.jsonl"
    frames = tmp_path / "frames.jsonl"

    def sender() -> None:
        time.sleep(0.5)
        from tactdeform_hw import load_scene, make_trajectory
        from tactdeform_hw.render.trajectories import scene_for_trajectory

        scene = load_scene("cube")
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
            u.sendto(b"1,2,3", ("127.0.0.1", port))
            for p in make_trajectory("approach-face", scene_for_trajectory("approach-face", scene))[:120]:
                u.sendto(line(p.t_s, tuple(p.position_mm), tuple(p.orientation)), ("127.0.0.1", port))
                time.sleep(0.002)
        time.sleep(0.1)
        os.kill(os.getpid(), signal.SIGINT)

    th = threading.Thread(target=sender, daemon=True)
    th.start()
    code = main(
        ["render", "--scene", "cube", "--tracking", f"udp://127.0.0.1:{port}", "--current-ua", "1000",
         "--json", "--quiet", "--latency-report", str(report), "--frames", str(frames)]
    )  # fmt: skip
    th.join(5)
    out, err = capsys.readouterr()
    assert code == 130
    assert "stopped by SIGINT; every channel off" in err and "Traceback" not in err
    result = json.loads(out)
    assert result["live"]["bad"] == {"columns": 1} and result["live"]["valid"] == 120
    assert result["poses"] == 120 and result["frames_sent"] > 0 and result["mismatches"] == 0
    assert set(result["latency"]) == {"received_to_computed", "received_to_written"}
    assert result["latency"]["received_to_computed"]["n"] == 120
    lines = [json.loads(x) for x in report.read_text().splitlines()]
    assert len(lines) == 120 and lines[0]["seq"] == 1
    assert all(np.isfinite(x["compute_ms"]) for x in lines)
    written = [json.loads(x) for x in frames.read_text().splitlines()]
    assert sum(1 for f in written if f["sent"]) == result["frames_sent"]


@pytest.mark.parametrize(
    ("extra", "named"),
    [
        ([], "--trajectory"),
        (["--trajectory", "approach-face", "--tracking", "udp://127.0.0.1:0"], "--tracking"),
        (["--trajectory", "approach-face", "--latency-report", "x.jsonl"], "--latency-report"),
        (["--tracking", "udp://127.0.0.1:0", "--gif", "x.gif"], "--gif"),
        (["--tracking", "udp://127.0.0.1:0", "--realtime"], "--realtime"),
        (["--tracking", "tcp://127.0.0.1:9"], "--tracking"),
    ],
)
def test_live_options_refused_before_anything_is_opened(
    extra: list[str], named: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from tactdeform_hw.cli import main

    code = main(["render", "--scene", "cube", "--device", "etactile://?timed=0", *extra])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert err.startswith("tactdeform-hw render: error:") and named in err


@pytest.mark.parametrize(
    "extra", [["--tracking", "lsl://hand"], ["--tracking", "udp://127.0.0.1:0", "--lsl-out", "p"]]
)
def test_lsl_without_pylsl_is_refused_naming_the_extra(
    extra: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    try:
        import pylsl  # noqa: F401
    except ImportError:
        pass
    else:
        pytest.skip("pylsl is installed")
    from tactdeform_hw.cli import main

    code = main(["render", "--scene", "cube", *extra])
    err = capsys.readouterr().err
    assert code == 1 and install_command("lsl") in err and "Traceback" not in err
