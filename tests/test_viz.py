"""Array pictures (PNG, GIF) and timing diagrams: valid files, the right frames, the right colours where
the electrodes are."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from tactdeform_hw.errors import ConfigurationError, MissingDependencyError
from tactdeform_hw.formats import Frame, PatternSequence, PatternStep
from tactdeform_hw.render.array import ElectrodeArray

pytest.importorskip("matplotlib", reason="the plot extra (matplotlib) is not installed")
Image = pytest.importorskip("PIL.Image", reason="the plot extra (pillow) is not installed")

from tactdeform_hw.viz.array_picture import (  # noqa: E402
    PictureFrame,
    draw_array_gif,
    draw_array_png,
    draw_frames_gif,
    frames_from_frames,
    frames_from_sequence,
)
from tactdeform_hw.viz.timing_diagram import draw_timing_png  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def rgb_at(img, xy) -> np.ndarray:
    x, y = (int(round(v)) for v in xy)
    return np.asarray(img.convert("RGB"), dtype=int)[y, x]


def is_grey(c: np.ndarray) -> bool:
    return int(c.max() - c.min()) < 12 and 150 < c.mean() < 235


def is_warm(c: np.ndarray) -> bool:
    r, g, b = c
    return r >= 120 and r - b >= 60 and r - g >= 60


def is_purple(c: np.ndarray) -> bool:
    r, g, b = c
    return b > g + 25 and r > g


@pytest.fixture(scope="module")
def pad() -> ElectrodeArray:
    return ElectrodeArray.tactdeform()


def test_png_shows_on_off_and_biphasic_at_electrode_centres(pad: ElectrodeArray, tmp_path: Path) -> None:
    levels = [0] * 32
    levels[0], levels[13], levels[31] = 1, 2, 1
    info = draw_array_png(pad, levels, tmp_path / "a.png", current_ua=3000)
    data = info.path.read_bytes()
    assert data[:8] == PNG_MAGIC
    img = Image.open(info.path)
    assert img.size == info.size_px == (640, 600)
    assert info.centres_px.shape == (32, 2) and info.radius_px > 5
    for i in range(32):
        c = rgb_at(img, info.centres_px[i])
        if levels[i] == 1:
            assert is_warm(c), (i, c)
        elif levels[i] == 2:
            assert is_purple(c), (i, c)
        else:
            assert is_grey(c), (i, c)
    # Real geometry: x right, y (toward the fingertip) up, distances to scale.
    pos = pad.positions_mm
    right = int(np.argmax(pos[:, 0]))
    top = int(np.argmax(pos[:, 1]))
    assert info.centres_px[right, 0] == max(info.centres_px[:, 0])
    assert info.centres_px[top, 1] == min(info.centres_px[:, 1])
    px_per_mm_x = (info.centres_px[:, 0].max() - info.centres_px[:, 0].min()) / np.ptp(pos[:, 0])
    px_per_mm_y = (info.centres_px[:, 1].max() - info.centres_px[:, 1].min()) / np.ptp(pos[:, 1])
    assert px_per_mm_x == pytest.approx(px_per_mm_y, rel=0.01)
    assert info.radius_px == pytest.approx(pad.radius_mm * px_per_mm_x, rel=0.02)
    # Just outside a disc is background, not electrode colour.
    outside = info.centres_px[0] + [info.radius_px * 1.3, 0]
    assert not is_warm(rgb_at(img, outside))


def test_png_colour_follows_current(pad: ElectrodeArray, tmp_path: Path) -> None:
    low = draw_array_png(pad, [1] * 32, tmp_path / "low.png", current_ua=500)
    high = draw_array_png(pad, [1] * 32, tmp_path / "high.png", current_ua=9500)
    c_low = rgb_at(Image.open(low.path), low.centres_px[5])
    c_high = rgb_at(Image.open(high.path), high.centres_px[5])
    assert is_warm(c_low) and is_warm(c_high)
    assert c_high.sum() < c_low.sum() - 60  # a stronger current is a darker red


def test_gif_frames_durations_and_pixels(pad: ElectrodeArray, tmp_path: Path) -> None:
    a = tuple(1 if i < 4 else 0 for i in range(32))
    b = tuple(1 if i >= 28 else 0 for i in range(32))
    seq = PatternSequence(
        (PatternStep(a, 200, 100), PatternStep(b, 120, 0), PatternStep(b, 80, 0), PatternStep(a, 300, 0))
    )
    frames = frames_from_sequence(seq, current_ua=2000)
    assert [f.levels for f in frames] == [a, (0,) * 32, b, b, a]  # the OFF phase is its own frame
    info = draw_array_gif(pad, frames, tmp_path / "seq.gif", size_px=(400, 380))
    # b twice in a row is one GIF frame lasting both steps.
    assert info.frames == 4 and info.durations_ms == (200, 100, 200, 300)
    img = Image.open(info.path)
    assert img.format == "GIF" and img.size == (400, 380) and img.n_frames == 4
    got = []
    for k in range(img.n_frames):
        img.seek(k)
        got.append(img.info["duration"])
        on = [is_warm(rgb_at(img, info.centres_px[i])) for i in range(32)]
        off = [is_grey(rgb_at(img, info.centres_px[i])) for i in range(32)]
        expected = [a, (0,) * 32, b, a][k]
        assert on == [bool(v) for v in expected], k
        assert off == [not v for v in expected], k
    assert got == [200, 100, 200, 300]


def test_gif_from_frames_record_holds_short_frames(pad: ElectrodeArray, tmp_path: Path) -> None:
    recs = [
        Frame(k / 72.0, tuple(1 if i == k else 0 for i in range(32)), "approaching", "face") for k in range(6)
    ]
    recs.append(Frame(6 / 72.0, recs[-1].electrodes, sent=False))
    frames = frames_from_frames(recs)
    assert len(frames) == 6 and frames[0].label.startswith("t = 0.000 s · approaching · face")
    info = draw_array_gif(pad, frames, tmp_path / "f.gif", size_px=(320, 300))
    # The last sent frame is held to the end of the record (one more frame) plus one frame interval.
    assert info.frames == 6 and info.durations_ms == (20,) * 5 + (28,)
    assert any("held 20 ms" in n for n in info.notes)
    slow = draw_array_gif(pad, frames, tmp_path / "slow.gif", size_px=(320, 300), speed=0.25)
    assert slow.durations_ms == (56,) * 5 + (111,)  # 13.9 ms at quarter speed
    capped = draw_array_gif(pad, frames, tmp_path / "c.gif", size_px=(320, 300), max_frames=3)
    assert capped.frames <= 3 and Image.open(capped.path).n_frames == capped.frames
    assert any("resampled" in n for n in capped.notes)


def test_picture_input_errors(pad: ElectrodeArray, tmp_path: Path) -> None:
    with pytest.raises(ConfigurationError, match="5 level"):
        draw_array_png(pad, [0] * 5, tmp_path / "x.png")
    with pytest.raises(ConfigurationError, match="no frame"):
        draw_array_gif(pad, [], tmp_path / "x.gif")
    with pytest.raises(ConfigurationError, match="speed"):
        draw_array_gif(pad, [PictureFrame((0,) * 32)], tmp_path / "x.gif", speed=0)
    with pytest.raises(ConfigurationError, match="current_ua=nan"):
        draw_array_png(pad, [1] * 32, tmp_path / "x.png", current_ua=float("nan"))
    with pytest.raises(ConfigurationError, match="size_px"):
        draw_array_png(pad, [0] * 32, tmp_path / "x.png", size_px=(10, 10))


def test_missing_matplotlib_names_the_extra(pad: ElectrodeArray, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)
    with pytest.raises(MissingDependencyError) as err:
        draw_array_png(pad, [0] * 32, tmp_path / "x.png")
    assert err.value.extra == "plot" and "[plot]'" in str(err.value)
    with pytest.raises(MissingDependencyError):
        draw_timing_png([{"channel": 0, "start_us": 0, "width_us": 10}], [], tmp_path / "t.png")


# --- timing diagrams ----------------------------------------------------------------------------------------


def synthetic_trace(per_channel_us: float, period_us: float = 8000.0, cycles: int = 3, channels: int = 32):
    pulses, cyc = [], []
    t = 0.0
    for _ in range(cycles):
        for ch in range(channels):
            pulses.append(
                {"channel": ch, "start_us": t + ch * per_channel_us + 5, "width_us": 200, "current_ua": 2000}
            )
        dur = channels * per_channel_us + 20
        cyc.append({"start_us": t, "duration_us": dur, "overrun": dur > period_us})
        t += max(dur, period_us)
    return pulses, cyc


def red_pixels(img, top_rows: int | None = None) -> int:
    a = np.asarray(img.convert("RGB"), dtype=int)
    if top_rows is not None:
        a = a[:top_rows]
    r, g, b = a[..., 0], a[..., 1], a[..., 2]
    return int(np.sum((r > 200) & (g < 60) & (b < 60)))


def test_timing_png_marks_overruns_only_when_there_are_some(tmp_path: Path) -> None:
    ok_p, ok_c = synthetic_trace(245)
    ok = draw_timing_png(ok_p, ok_c, tmp_path / "ok.png", period_us=8000, max_cycles=2)
    assert ok.path.read_bytes()[:8] == PNG_MAGIC
    assert ok.overruns_drawn == 0 and ok.channels == tuple(range(32))
    img_ok = Image.open(ok.path)
    assert img_ok.size == ok.size_px and img_ok.size[0] == 1100

    bad_p, bad_c = synthetic_trace(255)  # 32 × 255 + 20 µs > 8000 µs
    bad = draw_timing_png(bad_p, bad_c, tmp_path / "bad.png", period_us=8000, max_cycles=2)
    assert bad.overruns_drawn == 2
    img_bad = Image.open(bad.path)
    # The overrun mark is the saturated red of the band above the channel rows; pulses are a darker red.
    assert red_pixels(img_bad, top_rows=120) > 50
    assert red_pixels(img_ok, top_rows=120) == 0


def test_timing_window_and_units(tmp_path: Path) -> None:
    pulses, cycles = synthetic_trace(245, cycles=5, channels=4)
    two = draw_timing_png(pulses, cycles, tmp_path / "w.png", max_cycles=2)
    assert two.cycles_drawn == 2 and two.pulses_drawn == 8
    assert two.window_us[0] < 0 and two.window_us[1] == 16000
    # ns-named fields (the emulator keeps integer ns) give the same picture as µs ones.
    ns = [
        {"channel": p["channel"], "start_ns": p["start_us"] * 1000, "width_ns": 200_000, "current_ua": 2000}
        for p in pulses
    ]
    ns_c = [
        {"start_ns": c["start_us"] * 1000, "duration_ns": c["duration_us"] * 1000, "overrun": False}
        for c in cycles
    ]
    two_ns = draw_timing_png(ns, ns_c, tmp_path / "w_ns.png", max_cycles=2)
    assert two_ns.window_us == pytest.approx(two.window_us) and two_ns.pulses_drawn == two.pulses_drawn
    assert np.array_equal(np.asarray(Image.open(two.path)), np.asarray(Image.open(two_ns.path)))
    with pytest.raises(ConfigurationError, match="nothing to draw"):
        draw_timing_png([], [], tmp_path / "e.png")
    with pytest.raises(ConfigurationError, match=r"pulses\[0\]: missing 'channel'"):
        draw_timing_png([{"start_us": 0, "width_us": 1}], [], tmp_path / "e.png")


# --- real emulator traces and the command-line hooks --------------------------------------------------------


def test_timing_from_the_timed_emulator_reports(tmp_path: Path) -> None:
    from tactdeform_hw import protocol as p
    from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
    from tactdeform_hw.viz.timing_diagram import draw_reports_png

    emu = TimedEmulator()
    pattern = bytes([1] * 16 + [2] * 8 + [0] * 8)
    for cmd in (
        p.encode_electrode_num(32),
        p.encode_pattern(pattern),
        p.encode_pulse_width(200),
        p.encode_discharge(50),
        p.encode_frequency(125),
        p.encode_pulse_height(200),
    ):
        emu.write(cmd)
        emu.advance(3000)
    emu.advance(40_000)
    reports = emu.reports
    first_overrun = next(c.index for c in reports.cycles() if c.overrun)
    info = draw_reports_png(reports, tmp_path / "emu.png", max_cycles=2)
    assert info.overruns_drawn >= 1 and info.cycles_drawn == 2
    # The window opens one cycle before the first overrun and holds exactly the pulses of those cycles.
    shown = reports.cycles(first_overrun - 1, first_overrun + 1)
    assert info.window_us[0] < shown[0].start_us < info.window_us[1]
    expected = reports.pulse_table(shown[0].start_us, info.window_us[1])["channel"].size
    assert info.pulses_drawn == expected > 0
    assert red_pixels(Image.open(info.path), top_rows=120) > 0


def test_timing_cli_png_marks_the_paper_overrun(tmp_path: Path, capsys) -> None:
    import json

    from tactdeform_hw.cli import main

    for discharge, overruns in ((45, 0), (50, 3)):
        out = tmp_path / f"d{discharge}.png"
        argv = ["timing", "--discharge-us", str(discharge), "--cycles", "3", "--png", str(out), "--json"]
        assert main(argv) == (3 if overruns else 0)  # exit status 3: the scan overruns its period
        png = json.loads(capsys.readouterr().out)["png"]
        assert png["overruns"] == overruns and png["cycles"] == 3
        assert out.read_bytes()[:8] == PNG_MAGIC
        assert (red_pixels(Image.open(out), top_rows=120) > 0) == bool(overruns)


def test_play_and_export_draw_gifs(tmp_path: Path, capsys) -> None:
    import json

    from tactdeform_hw.cli import main
    from tactdeform_hw.formats import write_pattern_file

    a = tuple(1 if i % 2 else 0 for i in range(32))
    seq = PatternSequence((PatternStep(a, 100, 50), PatternStep((0,) * 31 + (2,), 100)))
    pattern = write_pattern_file(seq, tmp_path / "p.json")
    gif = tmp_path / "p.gif"
    assert main(["play", str(pattern), "--dry-run", "--json", "--gif", str(gif)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["gif"]["frames"] == 3 and Image.open(gif).n_frames == 3

    lines = [{"t": k * 0.1, "electrodes": list(a if k % 2 else (0,) * 32), "sent": True} for k in range(4)]
    frames = tmp_path / "f.jsonl"
    frames.write_text("".join(json.dumps(x) + "\n" for x in lines))
    gif2 = tmp_path / "f.gif"
    assert main(["export", str(frames), "-o", str(tmp_path / "f.json"), "--gif", str(gif2), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["gif"]["frames"] == 4
    assert Image.open(gif2).n_frames == 4

    sixty_four = write_pattern_file(PatternSequence((PatternStep((1,) * 64, 10),)), tmp_path / "64.json")
    assert main(["play", str(sixty_four), "--dry-run", "--gif", str(tmp_path / "x.gif")]) == 1
    assert "give --array" in capsys.readouterr().err


def test_render_cli_gif_shows_what_the_device_held(tmp_path: Path, capsys) -> None:
    import json

    from tactdeform_hw.cli import main
    from tactdeform_hw.formats import read_frames_file
    from tactdeform_hw.formats.frames import delivered_spans

    frames, gif = tmp_path / "face.jsonl", tmp_path / "face.gif"
    argv = [
        "render",
        "--scene",
        "cube",
        "--trajectory",
        "approach-face",
        "--frames",
        str(frames),
        "--gif",
        str(gif),
        "--current-ua",
        "1500",
        "--json",
        "--quiet",
    ]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    spans = delivered_spans(read_frames_file(frames))
    runs = [spans[0][0].electrodes]
    for f, _, _ in spans[1:]:
        if f.electrodes != runs[-1]:
            runs.append(f.electrodes)
    img = Image.open(gif)
    assert summary["gif"]["frames"] == img.n_frames == len(runs) >= 2
    assert img.size == (480, 450)


# --- text that fits the picture -----------------------------------------------------------------------------


def test_a_long_gif_title_is_fitted_to_the_480_px_picture(pad: ElectrodeArray, tmp_path: Path) -> None:
    records = [
        {"t": k / 72.0, "electrodes": [1 if i == k else 0 for i in range(32)], "sent": True} for k in range(3)
    ]
    title = "recordings/2025-03-14/P07/session-3/approach-edge-d2.csv over task1"
    info = draw_frames_gif(pad, records, tmp_path / "t.gif", title=title)
    width = info.size_px[0]
    assert width == 480
    left, top, right, bottom = info.title_box_px
    assert 0 <= left and right <= width and 0 <= top < bottom  # measured on the drawn text
    assert info.title == title or "…" in info.title
    short = draw_frames_gif(pad, records, tmp_path / "s.gif", title="approach-face over cube")
    assert short.title == "approach-face over cube"  # a title that fits is left as it is


def test_a_timing_diagrams_overrun_label_and_title_stay_inside(tmp_path: Path) -> None:
    pulses, cycles = synthetic_trace(255, cycles=3)
    # the window ends just before the second cycle's overrun begins: its label is anchored past the
    # right edge of the plot (where the overrun begins)
    end_us = cycles[1]["start_us"] + 7800
    info = draw_timing_png(
        pulses,
        cycles,
        tmp_path / "t.png",
        period_us=8000,
        window_us=(0.0, end_us),
        width_px=700,
        title="scan of 32 electrodes at 125 Hz, 255 µs per channel: the scan overruns its period",
    )
    plot_left, _, plot_right, _ = info.plot_box_px
    labels = [(text, box) for text, box in info.text_boxes_px if text.startswith("overrun +")]
    assert len(labels) == info.overruns_drawn == 2
    for text, (left, _, right, _) in labels:
        assert plot_left <= left and right <= plot_right, (text, left, right, info.plot_box_px)
    title, (left, _, right, _) = info.text_boxes_px[0]
    assert 0 <= left and right <= info.size_px[0], (title, left, right)
