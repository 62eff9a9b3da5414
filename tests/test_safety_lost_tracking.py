"""Lost tracking stays lost, judged on the pulses the timed board models delivered, on both firmware versions.

A finger rests on a surface and is stimulated; then the tracker fails: a clock that keeps running backwards,
one that steps back once, one that stands still, NaN or infinity in a field.  Samples keep arriving at the
tracker's 72 Hz, whatever their stamps.  After the first bad sample no pulse may start later than the
device's no-frame watchdog plus one scan period, for as long as the tracker stays bad; once its samples are
valid again and move forward in time, stimulation comes back only after ``resume_after_valid_samples`` of
them in a row.  The same holds through ``Renderer.run`` and through ``tactdeform-hw render`` replaying a
recorded file with ``--invalid-rows replay``; and a clean trajectory renders exactly the frames it did.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tactdeform_hw.device import EtactileKitDevice, StimConfig
from tactdeform_hw.device.safety.failsafe import DEFAULT_WATCHDOG_S, FailSafe
from tactdeform_hw.emulator.faults import TimedPort
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2
from tactdeform_hw.errors import LimitError
from tactdeform_hw.protocol.firmware_math import firmware_period_us
from tactdeform_hw.render.array import ElectrodeArray
from tactdeform_hw.render.pipeline import RESUME_AFTER_VALID_SAMPLES, Renderer

from .render_fakes import PAD_DOWN, FakeFloor, hold_poses, line_poses

FIRMWARES = ["v1.2", "v2"]
DT = 1.0 / 72.0
RATE_HZ = 125
#: No pulse may start later than this after the first bad sample: the watchdog's time and the scan that
#: was under way when its all-off arrived (docs/safety.md, "watchdog").
BOUND_S = DEFAULT_WATCHDOG_S + firmware_period_us(RATE_HZ) / 1e6
N = RESUME_AFTER_VALID_SAMPLES
AT = np.array([0.0, 0.0, -3.0])  # resting 3 mm into the floor: deep enough to stimulate at once


class Bench:
    """A timed board, its device with the fail-safe watchdog polled in simulated time, a renderer pressed
    onto the floor.  ``step`` delivers one sample ``DT`` after the one before, whatever its stamp."""

    def __init__(self, fw: str, **renderer_kw: Any) -> None:
        emu = TimedEmulatorV2("compact", 1) if fw == "v2" else TimedEmulator("compact", 1)
        self.emu = emu
        self.port = TimedPort(emu, link="usb")
        array = ElectrodeArray.tactdeform()
        self.dev = EtactileKitDevice(self.port, firmware=fw, mapping=array.channel_mapping())
        self.fs = FailSafe(self.dev, thread=False, signals=False, at_exit=False).start()
        self.port.hooks.append(lambda t: self.fs.poll(t))
        self.renderer = Renderer(
            FakeFloor(),
            self.dev,
            array=array,
            stim_config=StimConfig(electrode_count=32, current_ua=800, rate_hz=RATE_HZ),
            **renderer_kw,
        )
        self.renderer.start()
        self.arrival = self.port.now_s + 0.01
        self.t = 0.0
        press = line_poses(0.0, (0, 0, 2.0), tuple(AT), 20.0, 72.0, PAD_DOWN)
        for pose in press + hold_poses(press[-1][0] + DT, tuple(AT), 0.5, 72.0, PAD_DOWN):
            self.step(pose)
        assert self.pulses_between(self.arrival - 0.2, self.arrival).size, "the press never stimulated"

    def step(self, pose: tuple[Any, Any, Any]) -> float:
        """Deliver a sample one tracking period after the last; returns its arrival (simulated s)."""
        self.arrival += DT
        self.port.advance_to(self.arrival)
        self.renderer.step(pose)
        if isinstance(pose[0], float) and math.isfinite(pose[0]):
            self.t = max(self.t, pose[0])
        return self.arrival

    def pulses_between(self, t0_s: float, t1_s: float = math.inf) -> np.ndarray:
        """Start times (s) of the pulses that carried current, starting within [t0_s, t1_s)."""
        table = self.emu.reports.pulse_table()
        start = table["start_us"] / 1e6
        live = (table["code"] > 0) & (start >= t0_s) & (start < t1_s)
        return np.asarray(start[live])

    def settle(self) -> float:
        """Let the board run on a little after the last sample; returns the end of the record."""
        self.port.advance(0.05)
        self.fs.stop()
        return float(self.port.now_s)


def hold(t_s: float) -> tuple[float, np.ndarray, tuple[float, float, float, float]]:
    return (t_s, AT.copy(), PAD_DOWN)


def assert_off_after(b: Bench, t_bad: float, t_end: float) -> None:
    late = b.pulses_between(t_bad + BOUND_S, t_end)
    assert late.size == 0, f"{late.size} pulses, the first {late[0] - t_bad:.3f} s after the first bad sample"


def resumes_after_the_run(b: Bench, t_bad: float, first_valid: float) -> None:
    """Nothing from the bound to the arrival of the run's last sample; stimulation again after it."""
    t_run_end = first_valid + (N - 1) * DT
    assert b.pulses_between(t_bad + BOUND_S, t_run_end).size == 0
    again = b.pulses_between(t_run_end)
    assert again.size, "stimulation never resumed after a sustained run of valid samples"
    assert again[0] >= t_run_end


# --- the library: Renderer.step -----------------------------------------------------------------------------


@pytest.mark.parametrize("fw", FIRMWARES)
def test_a_clock_that_keeps_running_backwards_never_resumes_stimulation(fw: str) -> None:
    b = Bench(fw)
    t_last = b.t
    t_bad = b.step(hold(t_last - 0.001))
    for i in range(2, int(1.6 / DT)):
        b.step(hold(t_last - 0.001 * i))
    t_end = b.settle()
    assert t_end - t_bad >= 1.5
    assert_off_after(b, t_bad, t_end)
    s = b.renderer.summary
    assert s.lost_tracking == 1 and s.held_resuming == 0
    assert s.dropped == {"time-backwards": int(1.6 / DT) - 1}


@pytest.mark.parametrize("fw", FIRMWARES)
def test_a_clock_that_runs_backwards_with_forward_jitter_never_resumes(fw: str) -> None:
    """Backwards by a period, with every third sample a little ahead of the one before: never N forward
    samples in a row."""
    b = Bench(fw)
    t = b.t
    t_bad = None
    for i in range(1, int(1.6 / DT)):
        t += 0.004 if i % 3 == 0 else -DT
        arrived = b.step(hold(t))
        t_bad = arrived if t_bad is None else t_bad
    assert t_bad is not None
    t_end = b.settle()
    assert_off_after(b, t_bad, t_end)
    assert b.renderer.summary.held_resuming > 0  # the forward samples were seen, and held back


@pytest.mark.parametrize("fw", FIRMWARES)
def test_a_clock_that_steps_back_once_stops_then_resumes_only_after_the_run(fw: str) -> None:
    b = Bench(fw)
    t_new = b.t - 0.5  # the clock steps back half a second, then runs on from there
    t_bad = b.step(hold(t_new))
    first_valid = b.step(hold(t_new + DT))
    for i in range(2, 60):
        b.step(hold(t_new + i * DT))
    b.settle()
    resumes_after_the_run(b, t_bad, first_valid)
    s = b.renderer.summary
    assert s.lost_tracking == 1 and s.held_resuming == N - 1 and s.dropped == {"time-backwards": 1}


@pytest.mark.parametrize("fw", FIRMWARES)
def test_an_invalid_sample_in_the_run_starts_it_again(fw: str) -> None:
    b = Bench(fw)
    t_new = b.t - 0.5
    t_bad = b.step(hold(t_new))
    for i in range(1, N):  # one short of the run
        b.step(hold(t_new + i * DT))
    b.step((t_new + N * DT, np.array([math.nan, 0.0, -3.0]), PAD_DOWN))
    first_valid = b.step(hold(t_new + (N + 1) * DT))
    for i in range(N + 2, N + 40):
        b.step(hold(t_new + i * DT))
    b.settle()
    resumes_after_the_run(b, t_bad, first_valid)


@pytest.mark.parametrize("fw", FIRMWARES)
def test_a_frozen_clock_stops_stimulation_and_resumes_only_after_the_run(fw: str) -> None:
    b = Bench(fw)
    frozen = b.t
    t_bad = b.step(hold(frozen))
    for _ in range(int(1.5 / DT)):
        b.step(hold(frozen))
    assert_off_after(b, t_bad, b.arrival)
    first_valid = b.step(hold(frozen + DT))
    for i in range(2, 40):
        b.step(hold(frozen + i * DT))
    b.settle()
    resumes_after_the_run(b, t_bad, first_valid)
    assert b.renderer.summary.dropped == {"time-repeated": int(1.5 / DT) + 1}


FIELDS = ["t_s", "x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz"]


def spoiled(t_s: float, field: str, value: float) -> tuple[float, np.ndarray, np.ndarray]:
    pos = AT.copy()
    quat = np.array(PAD_DOWN, dtype=float)
    if field == "t_s":
        t_s = value
    elif field.endswith("_mm"):
        pos["xyz".index(field[0])] = value
    else:
        quat["wxyz".index(field[1])] = value
    return (t_s, pos, quat)


@pytest.mark.parametrize("fw", FIRMWARES)
@pytest.mark.parametrize("field", FIELDS)
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
def test_nan_and_inf_in_any_field_stop_stimulation_and_resume_only_after_the_run(
    fw: str, field: str, value: float
) -> None:
    b = Bench(fw)
    t0 = b.t
    t_bad = b.step(spoiled(t0 + DT, field, value))
    for i in range(2, int(0.4 / DT)):
        b.step(spoiled(t0 + i * DT, field, value))
    assert_off_after(b, t_bad, b.arrival)
    k = int(0.4 / DT)
    first_valid = b.step(hold(t0 + k * DT))
    for i in range(k + 1, k + 40):
        b.step(hold(t0 + i * DT))
    b.settle()
    resumes_after_the_run(b, t_bad, first_valid)


@pytest.mark.parametrize("fw", FIRMWARES)
@pytest.mark.parametrize("bad", ["backwards", "frozen", "nan-x_mm", "inf-qw"])
def test_invalid_samples_never_feed_the_watchdog(fw: str, bad: str) -> None:
    """With the renderer's own switch-off put out of reach (lost_tracking_s 10 s), the device's no-frame
    watchdog alone stops stimulation: no invalid sample kept it fed."""
    b = Bench(fw, lost_tracking_s=10.0)
    t0 = b.t
    t_bad = None
    for i in range(1, int(0.6 / DT)):
        if bad == "backwards":
            pose = hold(t0 - 0.001 * i)
        elif bad == "frozen":
            pose = hold(t0)
        else:
            field, value = ("x_mm", math.nan) if bad == "nan-x_mm" else ("qw", math.inf)
            pose = spoiled(t0 + i * DT, field, value)
        arrived = b.step(pose)
        t_bad = arrived if t_bad is None else t_bad
    assert t_bad is not None
    t_end = b.settle()
    assert_off_after(b, t_bad, t_end)
    assert b.fs.watchdog_trips == 1 and b.renderer.summary.lost_tracking == 0


def test_resume_after_valid_samples_is_checked() -> None:
    for bad in (0, -1, 2.5, True, "6"):
        with pytest.raises(LimitError, match="resume_after_valid_samples"):
            Renderer(FakeFloor(), None, resume_after_valid_samples=bad)  # type: ignore[arg-type]


@pytest.mark.parametrize("fw", FIRMWARES)
def test_a_longer_run_holds_stimulation_back_longer(fw: str) -> None:
    b = Bench(fw, resume_after_valid_samples=20)
    t_new = b.t - 0.5
    t_bad = b.step(hold(t_new))
    first_valid = b.step(hold(t_new + DT))
    for i in range(2, 60):
        b.step(hold(t_new + i * DT))
    b.settle()
    assert b.pulses_between(t_bad + BOUND_S, first_valid + 19 * DT).size == 0
    assert b.pulses_between(first_valid + 19 * DT).size


# --- the library: Renderer.run ------------------------------------------------------------------------------


@pytest.mark.parametrize("fw", FIRMWARES)
def test_run_replays_a_backwards_clock_at_the_trackers_rate_and_never_resumes(fw: str) -> None:
    """``run`` paces the session on the samples' clock; where that stops advancing, one tracking period per
    sample still passes on the board (and the watchdog sees it)."""
    b = Bench(fw)
    t_last = b.t
    n = int(1.6 / DT)
    start = b.port.now_s
    b.renderer.run([hold(t_last - 0.001 * i) for i in range(1, n)])
    t_end = b.settle()
    assert t_end - start >= 1.5
    assert_off_after(b, start, t_end)
    assert b.renderer.summary.dropped == {"time-backwards": n - 1}


# --- the command line ---------------------------------------------------------------------------------------

CUBE_AT = (-50.0, -150.0)  # in front of the cube's face; z (mm) toward it, 353 is 1 mm into it


def cube_rows(fault: Callable[[int, float], tuple[float, float]] | None, n_after: int) -> list[list[float]]:
    """Approach the cube's face, rest on it 0.5 s, then ``n_after`` more rows whose (t, z) ``fault`` gives
    from the row index and the last clean time."""
    rows = []
    t = 0.0
    for i in range(30):
        rows.append([t, *CUBE_AT, 345.0 + 8.0 * i / 29, 1.0, 0.0, 0.0, 0.0])
        t += DT
    for _ in range(36):
        rows.append([t, *CUBE_AT, 353.0, 1.0, 0.0, 0.0, 0.0])
        t += DT
    last = rows[-1][0]
    for i in range(1, n_after + 1):
        tt, z = fault(i, last) if fault is not None else (last + i * DT, 353.0)
        rows.append([tt, *CUBE_AT, z, 1.0, 0.0, 0.0, 0.0])
    return rows


def write_csv(path: Path, rows: list[list[float]]) -> Path:
    lines = ["t_s,x_mm,y_mm,z_mm,qw,qx,qy,qz"] + [",".join(repr(float(v)) for v in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def cli_render(
    tmp_path: Path, csv: Path, fw: str, *extra: str
) -> tuple[int, dict[str, Any], list[dict[str, Any]]]:
    import contextlib
    import io

    from tactdeform_hw.cli import main

    frames = tmp_path / "frames.jsonl"
    device = ["--device", "etactile://?firmware=v2&timed=0"] if fw == "v2" else []
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(
            ["render", "--scene", "cube", "--trajectory", str(csv), "--current-ua", "800", "--json"]
            + ["--quiet", "--frames", str(frames), *device, *extra]
        )
    summary = json.loads(out.getvalue()) if rc == 0 else {}
    lines = [json.loads(x) for x in frames.read_text().splitlines()] if frames.exists() else []
    return rc, summary, lines


@pytest.mark.parametrize("fw", FIRMWARES)
def test_cli_replays_a_backwards_clock_and_stays_off(tmp_path: Path, fw: str) -> None:
    n = int(1.6 / DT)
    rows = cube_rows(lambda i, last: (last - 0.001 * i, 353.0), n)
    rc, summary, frames = cli_render(
        tmp_path, write_csv(tmp_path / "back.csv", rows), fw, "--invalid-rows", "replay"
    )
    assert rc == 0
    assert summary["dropped"] == {"time-backwards": n} and summary["lost_tracking"] == 1
    assert summary["mismatches"] == 0  # the emulator's pattern buffer held every sent frame
    clean = len(rows) - n
    assert any(any(f["electrodes"]) for f in frames[:clean]), "the rest on the face never stimulated"
    after = frames[clean:]
    assert [f["sent"] for f in after].count(True) == 1  # the all-off, and nothing after it
    assert all(not any(f["electrodes"]) for f in after[after.index(next(f for f in after if f["sent"])) :])
    assert all(not f["sent"] for f in after[after.index(next(f for f in after if f["sent"])) + 1 :])


@pytest.mark.parametrize("fw", FIRMWARES)
def test_cli_a_clock_that_steps_back_once_resumes_only_after_the_run(tmp_path: Path, fw: str) -> None:
    rows = cube_rows(lambda i, last: (last - 0.5 + i * DT, 353.0), 40)
    rc, summary, frames = cli_render(
        tmp_path, write_csv(tmp_path / "once.csv", rows), fw, "--invalid-rows", "replay"
    )
    assert rc == 0 and summary["mismatches"] == 0
    assert summary["lost_tracking"] == 1 and summary["held_resuming"] == N - 1
    clean = len(rows) - 40
    # the step back shows at the second row after it (later than the first, earlier than the last rendered)
    after = frames[clean:]
    off = next(i for i, f in enumerate(after) if f["sent"])
    assert not any(after[off]["electrodes"])
    on = next(i for i, f in enumerate(after) if f["sent"] and any(f["electrodes"]))
    assert all(not any(f["electrodes"]) for f in after[off:on])
    # the rows of the run are 1 .. N after the step back: the first stimulating frame is at its last or later
    assert after[on]["t"] >= rows[clean + N][0]


@pytest.mark.parametrize("fw", FIRMWARES)
@pytest.mark.parametrize("kind", ["frozen", "nan-z", "inf-qx"])
def test_cli_frozen_clock_and_non_finite_rows_switch_off(tmp_path: Path, fw: str, kind: str) -> None:
    n = 40

    def fault(i: int, last: float) -> tuple[float, float]:
        return (last, 353.0) if kind == "frozen" else (last + i * DT, math.nan if kind == "nan-z" else 353.0)

    rows = cube_rows(fault, n)
    if kind == "inf-qx":
        for r in rows[-n:]:
            r[5] = math.inf
    csv = write_csv(tmp_path / f"{kind}.csv", rows)
    rc, summary, frames = cli_render(tmp_path, csv, fw, "--invalid-rows", "replay")
    assert rc == 0 and summary["mismatches"] == 0 and summary["lost_tracking"] == 1
    assert sum(summary["dropped"].values()) == n
    after = frames[len(rows) - n :]
    sent = [f for f in after if f["sent"]]
    assert len(sent) == 1 and not any(sent[0]["electrodes"])
    # the all-off goes at the 6th bad row: 83 ms after the last good one, before the watchdog's 100 ms
    assert sent[0]["t"] is None or sent[0]["t"] - rows[-n - 1][0] <= DEFAULT_WATCHDOG_S


def test_cli_refuses_a_bad_row_before_anything_is_sent_unless_asked_to_replay(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from tactdeform_hw.cli import main

    rows = cube_rows(lambda i, last: (last - 0.001 * i, 353.0), 5)
    csv = write_csv(tmp_path / "back.csv", rows)
    frames = tmp_path / "frames.jsonl"
    rc = main(["render", "--scene", "cube", "--trajectory", str(csv), "--frames", str(frames), "--quiet"])
    err = capsys.readouterr().err
    assert rc != 0 and "column 't_s'" in err and "does not follow" in err and "Traceback" not in err
    assert not frames.exists()
    rc = main(["render", "--scene", "cube", "--trajectory", "approach-face", "--invalid-rows", "replay"])
    err = capsys.readouterr().err
    assert rc != 0 and "--invalid-rows" in err and "Traceback" not in err


def test_a_clean_trajectory_renders_the_same_frames() -> None:
    """The README's run: 4 frames sent, 0 mismatches, and the same frames whatever the replay mode."""
    import contextlib
    import io

    from tactdeform_hw.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(["render", "--scene", "cube", "--trajectory", "approach-face", "--json", "--quiet"])
    summary = json.loads(out.getvalue())
    assert rc == 0 and summary["frames_sent"] == 4 and summary["mismatches"] == 0
    assert summary["lost_tracking"] == 0 and summary["held_resuming"] == 0 and summary["dropped"] == {}


def test_a_clean_recorded_file_renders_the_same_frames_in_both_modes(tmp_path: Path) -> None:
    csv = write_csv(tmp_path / "clean.csv", cube_rows(None, 40))
    runs = []
    for extra in ((), ("--invalid-rows", "replay")):
        rc, summary, frames = cli_render(tmp_path, csv, "v1.2", *extra)
        assert rc == 0 and summary["lost_tracking"] == 0 and summary["held_resuming"] == 0
        runs.append(frames)
    assert runs[0] == runs[1] and any(any(f["electrodes"]) for f in runs[0])
