"""The study report: ``report.json``, ``summary.md``, one frames file per trial and pictures of the array.

Directory layout (``--out DIR``)::

    report.json            everything below, machine-readable (format "tactdeform-hw study report", v1)
    summary.md             one table row per trial, the failed checks spelt out, the notes
    frames/<trial>.jsonl   the trial's frames in the format of ``tactdeform-hw render --frames``
                           (``t`` from the trial's start)
    pictures/<trial>.png   the trial's patterns in order (every distinct frame sent, up to 8), on the array
    pictures/<trial>.gif   with ``gif=True``: the trial as an animation (real durations)
    pictures/overview.png  every trial's strip, one row each

Pictures need the ``plot`` extra (matplotlib, Pillow); without it the JSON, the Markdown and the frames
are still written and ``report.json`` says why the pictures are missing.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

from ..errors import ConfigurationError, MissingDependencyError
from ..render.geometry import TEXTURE_NAMES
from .checks import Check
from .runner import StudyRun, TrialRun

REPORT_FORMAT = "tactdeform-hw study report"
REPORT_VERSION = 1
MAX_TILES = 8
TILE_PX = (330, 300)
CAPTION_PX = 34


# --- per trial -------------------------------------------------------------------------------------------


def _r(x: float, nd: int = 4) -> float:
    return round(float(x), nd)


def state_sequence(run: TrialRun) -> list[dict[str, Any]]:
    """Run-length summary of the renderer's state over the trial (times from the trial's start)."""
    out: list[dict[str, Any]] = []
    for rec in run.records:
        t = rec.t_s - run.t0_s
        if out and out[-1]["state"] == rec.state:
            out[-1]["to_s"] = _r(t)
            out[-1]["records"] += 1
        else:
            if out:
                out[-1]["to_s"] = _r(t)
            out.append({"state": rec.state, "from_s": _r(t), "to_s": _r(t), "records": 1})
    return out


def electrode_on_time(run: TrialRun, count: int) -> list[float]:
    """Seconds each electrode was on in the frames the device held (sent frame to the next one)."""
    sent = [r for r in run.records if r.sent]
    out = [0.0] * count
    for k, rec in enumerate(sent):
        end = sent[k + 1].t_s if k + 1 < len(sent) else run.t1_s
        dt = max(0.0, end - rec.t_s)
        for i, v in enumerate(rec.electrodes):
            if v:
                out[i] += dt
    return [_r(v, 3) for v in out]


def _seen(values: list[Any]) -> dict[str, int]:
    return {
        str(k): n
        for k, n in sorted(Counter(v for v in values if v is not None).items(), key=lambda kv: str(kv[0]))
    }


def trial_json(run: TrialRun, result: StudyRun) -> dict[str, Any]:
    t = run.trial
    d: dict[str, Any] = {
        "index": t.index,
        "id": t.id,
        "condition": t.condition,
        "description": t.description,
        "scenario": t.to_json(),
        "approach": t.approach,
        "skipped": run.skipped,
        "passed": run.passed,
    }
    if run.skipped is not None:
        return d
    sent = [r for r in run.records if r.sent]
    contact = [r for r in run.records if r.state in ("approaching", "interacting")]
    n = result.array.channel_mapping().hw_channels
    commands = Counter(name for w in run.writes for name in w.command_names(n))
    d.update(
        {
            "time_s": [_r(run.t0_s), _r(run.t1_s)],
            "duration_s": _r(run.t1_s - run.t0_s),
            "wall_s": _r(run.wall_s, 3),
            "poses": len(run.poses),
            "frames": {
                "records": len(run.records),
                "sent": len(sent),
                "interpolated": sum(1 for r in sent if r.interpolated),
                "distinct_patterns": len({tuple(r.electrodes) for r in sent}),
            },
            "states": dict(run.summary.get("states", {})),
            "state_sequence": state_sequence(run),
            "contexts_seen": _seen([r.context for r in contact]),
            "frames_sent_by_context": _seen([r.context or r.state for r in sent if any(r.electrodes)]),
            "features_seen": _seen([r.feature for r in contact]),
            "orientations_seen": _seen([r.orientation for r in contact]),
            "textures_seen": _seen(
                [TEXTURE_NAMES.get(r.texture, r.texture) if r.texture is not None else None for r in contact]
            ),
            "electrodes_activated": sorted({i for r in sent for i, v in enumerate(r.electrodes) if v}),
            "electrode_on_time_s": electrode_on_time(run, result.array.count),
            "commands_sent": dict(sorted(commands.items())),
            "bytes_sent": sum(len(w.data) for w in run.writes),
            "delivered": None
            if run.delivered is None
            else {k: v for k, v in run.delivered.items() if not k.startswith("_")},
            "delivered_note": None if run.delivered is not None else (result.timed_note or "no timed replay"),
            "emulator_hazards": list(run.hazards) if run.verified else None,
            **(
                {
                    "heights_readback": None
                    if run.heights_checked is None
                    else {
                        "frames": run.heights_checked,
                        "mismatches": run.height_mismatches,
                        "first_mismatch": run.first_height_mismatch,
                    }
                }
                if result.heights_per_electrode
                else {}
            ),
            "timing_hazards": list(run.timed_hazards) if run.delivered is not None else None,
            "renderer": {
                k: run.summary.get(k)
                for k in (
                    "teleports",
                    "dropped",
                    "mismatches",
                    "first_mismatch",
                    "step_us_median",
                    "step_us_p99",
                )
            },
            "tracking_drops": dict(run.tracking_drops),
            "checks": [c.to_json() for c in run.checks],
            "failed_checks": [c.name for c in run.checks if c.passed is False],
        }
    )
    return d


def frames_lines(run: TrialRun) -> list[str]:
    """The trial's frames as ``render --frames`` lines, ``t`` from the trial's start."""
    lines = []
    for rec in run.records:
        obj = rec.to_json()
        if obj["t"] is not None:
            obj["t"] = round(obj["t"] - run.t0_s, 6)
        lines.append(json.dumps(obj, separators=(",", ":")))
    return lines


# --- the whole report ----------------------------------------------------------------------------------


def summary_json(result: StudyRun, design: list[Check]) -> dict[str, Any]:
    ran = [r for r in result.trials if r.skipped is None]
    failed = [r for r in ran if r.passed is False]
    failed_checks = Counter(c.name for r in ran for c in r.checks if c.passed is False)
    unchecked = Counter(c.name for r in ran for c in r.checks if c.passed is None)
    delivered = [r.delivered for r in ran if r.delivered is not None]
    design_ok = all(c.passed is not False for c in design)
    return {
        "trials": len(result.trials),
        "run": len(ran),
        "skipped": len(result.trials) - len(ran),
        "passed": sum(1 for r in ran if r.passed),
        "failed": len(failed),
        "failed_trials": [r.trial.id for r in failed],
        "failed_checks": dict(sorted(failed_checks.items())),
        "not_checked": dict(sorted(unchecked.items())),
        "design_ok": design_ok,
        # a skipped trial's checks never ran: the study did not pass them
        "all_passed": bool(ran) and not failed and design_ok and len(ran) == len(result.trials),
        "poses": sum(len(r.poses) for r in ran),
        "frames_sent": sum(int(r.summary.get("frames_sent", 0)) for r in ran),
        "pattern_buffer_mismatches": sum(int(r.summary.get("mismatches", 0)) for r in ran),
        "emulator_hazards": sum(len(r.hazards) for r in ran),
        "timing_hazards": sum(len(r.timed_hazards) for r in ran),
        "max_current_ua": max((d["max_current_ua"] for d in delivered), default=None),
        "total_charge_nc": _r(sum(d["total_charge_nc"] for d in delivered), 1) if delivered else None,
        "session_s": _r(max((r.t1_s for r in ran), default=0.0)),
        "wall_s": _r(result.wall_s, 2),
    }


def report_json(result: StudyRun, design: list[Check]) -> dict[str, Any]:
    arr = result.array
    return {
        "format": REPORT_FORMAT,
        "version": REPORT_VERSION,
        "generated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "study": result.study.to_json(),
        "device": result.device,
        "firmware": result.firmware,
        "participant": result.participant,
        "current_ua": result.current_ua,
        "current_source": result.current_source,
        "limits_ua": list(result.limits_ua),
        "sent": result.sent,
        "rate_hz": result.rate_hz,
        "array": {
            "name": arr.name,
            "electrodes": arr.count,
            "pitch_mm": arr.pitch_mm,
            "mapping": list(arr.channel_mapping().app_to_hw),
        },
        "design_checks": [c.to_json() for c in design],
        "summary": summary_json(result, design),
        "timed": {"available": result.timed, "note": result.timed_note, "summary": result.timed_summary},
        "notes": list(result.study.notes) + list(result.notes),
        "trials": [trial_json(r, result) for r in result.trials],
    }


def markdown(report: dict[str, Any]) -> str:
    s = report["summary"]
    study = report["study"]
    verdict = (
        "PASSED"
        if s["all_passed"]
        else "INCOMPLETE"
        if s["skipped"] and not s["failed"] and s["design_ok"]
        else "FAILED"
    )
    lines = [
        f"# {study['title']}",
        "",
        f"**{verdict}**: {s['passed']} of {s['run']} trial(s) passed"
        + (f", {s['skipped']} skipped" if s["skipped"] else "")
        + f" · device `{report['device']}` · firmware {report['firmware']}"
        + f" · current {report['current_ua']} µA ({report['current_source']})"
        + (f" · participant {report['participant']}" if report["participant"] else "")
        + f" · seed {study['seed']}{' · quick' if study['quick'] else ''}",
        "",
        f"{s['poses']} poses at {report['rate_hz']:g} Hz ({s['session_s']:.1f} s of session), "
        f"{s['frames_sent']} frames sent, {s['pattern_buffer_mismatches']} pattern-buffer mismatch(es), "
        f"{s['emulator_hazards']} emulator hazard(s), {s['timing_hazards']} timing hazard(s); max "
        # no wall time: it differs from run to run, and the report of a seeded study must not
        f"{s['max_current_ua']} µA, {s['total_charge_nc']} nC delivered in all.",
        "",
    ]
    for c in report["design_checks"]:
        mark = {True: "ok", False: "FAILED", None: "not checked"}[c["passed"]]  # a subset or quick run
        lines.append(f"Design: {mark} — {c['detail']}")
    lines += [
        "",
        "| # | trial | result | frames sent | features | textures | max µA | charge nC | failed checks |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for t in report["trials"]:
        if t["skipped"]:
            lines.append(f"| {t['index']} | {t['id']} | skipped | | | | | | {t['skipped']} |")
            continue
        d = t.get("delivered") or {}
        feats = ", ".join(f"{k}×{v}" for k, v in t["features_seen"].items()) or "—"
        tex = ", ".join(f"{k}×{v}" for k, v in t["textures_seen"].items()) or "—"
        res = "pass" if t["passed"] else "**FAIL**"
        lines.append(
            f"| {t['index']} | {t['id']} | {res} | {t['frames']['sent']} | {feats} | {tex} | "
            f"{d.get('max_current_ua', '—')} | {d.get('total_charge_nc', '—')} | "
            f"{', '.join(t['failed_checks']) or ''} |"
        )
    failures = [
        (t, c) for t in report["trials"] if not t["skipped"] for c in t["checks"] if c["passed"] is False
    ]
    if failures:
        lines += ["", "## Failed checks", ""]
        for t, c in failures:
            lines.append(f"- {t['id']}: `{c['name']}` — {c['detail']}")
    if s["not_checked"]:
        lines += ["", "Not checked here: " + ", ".join(f"`{k}` ({v})" for k, v in s["not_checked"].items())]
    if report["notes"]:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in report["notes"]]
    pics = report.get("pictures") or {}
    if pics.get("overview"):
        lines += ["", f"![overview]({pics['overview']})"]
    elif pics.get("note"):
        lines += ["", f"Pictures: {pics['note']}"]
    return "\n".join(lines) + "\n"


# --- pictures --------------------------------------------------------------------------------------------


class _Tiles:
    """Array pictures drawn once per distinct (pattern, title, label) and reused."""

    def __init__(self, result: StudyRun, tmp: Path) -> None:
        self.result = result
        self.tmp = tmp
        self.cache: dict[tuple[Any, ...], Any] = {}

    def get(self, levels: tuple[int, ...], title: str, label: str) -> Any:
        from PIL import Image

        from ..viz.array_picture import draw_array_png

        key = (levels, title, label)
        hit = self.cache.get(key)
        if hit is None:
            path = self.tmp / f"tile{len(self.cache)}.png"
            draw_array_png(self.result.array, levels, path, title=title, label=label, size_px=TILE_PX)
            with Image.open(path) as im:
                hit = im.convert("RGB")
            self.cache[key] = hit
        return hit


def _key_frames(run: TrialRun, most: int = MAX_TILES) -> tuple[list[Any], int]:
    """The distinct frames sent (consecutive repeats and all-off frames left out), thinned evenly to
    ``most``; and how many there were."""
    frames = []
    last = None
    for rec in run.records:
        if not rec.sent or not any(rec.electrodes) or tuple(rec.electrodes) == last:
            continue
        last = tuple(rec.electrodes)
        frames.append(rec)
    n = len(frames)
    if n > most:
        pick = sorted({round(i * (n - 1) / max(1, most - 1)) for i in range(most)})
        frames = [frames[i] for i in pick]
    return frames, n


def draw_trial_strip(run: TrialRun, tiles: _Tiles, path: Path) -> dict[str, Any]:
    from PIL import Image, ImageDraw

    frames, total = _key_frames(run)
    header = f"{run.trial.id}: {run.trial.description}  [{'pass' if run.passed else 'FAIL'}]"
    if total > len(frames):
        header += f"  ({len(frames)} of {total} distinct frames)"
    w, h = TILE_PX
    if not frames:
        canvas = Image.new("RGB", (max(w, 640), 60), "white")
        draw = ImageDraw.Draw(canvas)
        draw.text((8, 8), header, fill="black")
        draw.text((8, 32), "no electrode was switched on in this trial", fill="#aa0000")
        canvas.save(path, format="PNG")
        return {"path": path, "tiles": 0, "distinct_frames": 0}
    canvas = Image.new("RGB", (max(w * len(frames), 640), 24 + h + CAPTION_PX), "white")
    draw = ImageDraw.Draw(canvas)
    draw.text((8, 6), header, fill="black" if run.passed else "#aa0000")
    for k, rec in enumerate(frames):
        what = rec.feature or ""
        if rec.orientation:
            what += f" {rec.orientation}"
        title = f"{rec.state}" + (f" · {rec.context}" if rec.context and rec.context != rec.state else "")
        tile = tiles.get(tuple(int(v) for v in rec.electrodes), title, what.strip() or rec.approach)
        canvas.paste(tile, (k * w, 24))
        cap = f"t = {rec.t_s - run.t0_s:.3f} s"
        if rec.texture:
            cap += f" · {TEXTURE_NAMES.get(rec.texture, rec.texture)}"
        if rec.interpolated:
            cap += " · interp."
        draw.text((k * w + 10, 24 + h + 8), cap, fill="#222222")
    canvas.save(path, format="PNG")
    return {"path": path, "tiles": len(frames), "distinct_frames": total}


def draw_overview(result: StudyRun, path: Path) -> dict[str, Any]:
    """Every trial that ran in one grid that fits a screen (see :mod:`tactdeform_hw.viz.study_overview`):
    up to four of its distinct frames each, thinned evenly, captioned with their time and state."""
    from ..viz.study_overview import MAX_FRAMES, OverviewFrame, OverviewTrial, draw_study_overview

    trials = []
    for run in result.trials:
        if run.skipped is not None:
            continue
        frames, total = _key_frames(run, MAX_FRAMES)
        trials.append(
            OverviewTrial(
                title=run.trial.id,
                passed=bool(run.passed),
                frames=tuple(
                    OverviewFrame(
                        tuple(int(v) for v in rec.electrodes),
                        f"{rec.t_s - run.t0_s:.2f} s {_STATE_SHORT.get(rec.state, rec.state)}",
                    )
                    for rec in frames
                ),
            )
        )
    info = draw_study_overview(
        result.array.positions_mm,
        result.array.radius_mm,
        trials,
        path,
        title=f"{result.study.name}: {len(trials)} trial(s)",
    )
    return {
        "path": info.path,
        "size_px": list(info.size_px),
        "grid": [info.columns, info.rows],
        "min_font_pt": info.min_font_pt,
    }


_STATE_SHORT = {"approaching": "appr.", "interacting": "contact", "idle": "idle"}


def draw_pictures(result: StudyRun, out: Path, *, gif: bool = False) -> dict[str, Any]:
    """Strips (and with ``gif`` animations) of every trial, and the overview; returns what was drawn,
    relative to ``out``, or a note saying why nothing was."""
    pics = out / "pictures"
    try:
        from ..viz._plot import require

        require("drawing study pictures")
    except MissingDependencyError as exc:
        return {"note": f"pictures skipped: {exc}"}
    pics.mkdir(parents=True, exist_ok=True)
    drawn: dict[str, Any] = {"trials": {}}
    strips: list[Path] = []
    with tempfile.TemporaryDirectory(prefix="tactdeform-study-") as tmp:
        tiles = _Tiles(result, Path(tmp))
        for run in result.trials:
            if run.skipped is not None:
                continue
            info = draw_trial_strip(run, tiles, pics / f"{run.trial.id}.png")
            strips.append(info["path"])
            entry: dict[str, Any] = {
                "strip": str(info["path"].relative_to(out)),
                "tiles": info["tiles"],
                "distinct_frames": info["distinct_frames"],
            }
            if gif:
                entry.update(_trial_gif(run, result, pics / f"{run.trial.id}.gif", out))
            drawn["trials"][run.trial.id] = entry
        drawn["tiles_drawn"] = len(tiles.cache)
    if strips:
        overview = draw_overview(result, pics / "overview.png")
        drawn["overview"] = str(overview["path"].relative_to(out))
        drawn["overview_size_px"] = overview["size_px"]
    return drawn


def _trial_gif(run: TrialRun, result: StudyRun, path: Path, out: Path) -> dict[str, Any]:
    from ..viz.array_picture import draw_frames_gif

    lines = [json.loads(s) for s in frames_lines(run)]
    try:
        info = draw_frames_gif(
            result.array,
            lines,
            path,
            current_ua=result.current_ua or None,
            title=run.trial.id,
            size_px=(360, 340),
        )
    except ConfigurationError as exc:
        return {"gif_note": str(exc)}
    return {"gif": str(info.path.relative_to(out)), "gif_frames": info.frames, "gif_notes": list(info.notes)}


# --- writing ---------------------------------------------------------------------------------------------


#: What a study writes in its ``--out`` directory (an earlier report's entries, cleared by ``--force``).
REPORT_ENTRIES = ("report.json", "summary.md", "trials.jsonl", "frames", "pictures")


def earlier_report(out: str | Path) -> list[str]:
    """The entries of an earlier study's report in ``out`` (none when the directory is new or empty of
    them)."""
    root = Path(out)
    return [name for name in REPORT_ENTRIES if (root / name).exists()]


def clear_earlier_report(out: str | Path) -> list[str]:
    """Remove an earlier report's entries from ``out`` (only those: other files stay), so the new report
    never sits beside an old trial's frames or pictures; the names removed."""
    import shutil

    root = Path(out)
    removed = earlier_report(root)
    for name in removed:
        path = root / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    return removed


class TrialLog:
    """Each trial's results written as soon as it has run: its frames in ``frames/ID.jsonl`` and one line
    of ``trials.jsonl`` (index, id, condition, poses, frames sent, mismatches, or why it was skipped).  A
    study stopped half-way (Ctrl-C) keeps every trial that ran, and :meth:`interrupted` writes a partial
    ``report.json`` and ``summary.md`` saying which trials ran and which did not."""

    def __init__(self, out: str | Path, study: Any) -> None:
        self.root = Path(out)
        self.study = study
        self.done: list[TrialRun] = []
        self.root.mkdir(parents=True, exist_ok=True)
        (self.root / "frames").mkdir(exist_ok=True)
        self._lines = self.root / "trials.jsonl"
        self._lines.write_text("", encoding="utf-8")

    def __call__(self, run: TrialRun) -> None:
        self.done.append(run)
        entry: dict[str, Any] = {
            "index": run.trial.index,
            "id": run.trial.id,
            "condition": run.trial.condition,
        }
        if run.skipped is not None:
            entry["skipped"] = run.skipped
        else:
            path = self.root / "frames" / f"{run.trial.id}.jsonl"
            path.write_text("\n".join(frames_lines(run)) + "\n", encoding="utf-8")
            entry.update(
                {
                    "poses": len(run.poses),
                    "frames_sent": int(run.summary.get("frames_sent", 0)),
                    "mismatches": int(run.summary.get("mismatches", 0)),
                    "frames_file": str(path.relative_to(self.root)),
                }
            )
        with self._lines.open("a", encoding="utf-8") as f:
            f.write(json.dumps(entry, default=_json_default) + "\n")

    def interrupted(self, why: str) -> dict[str, Any]:
        """The partial report of a study that did not finish: which trials ran, which did not."""
        ran = [r.trial.id for r in self.done if r.skipped is None]
        skipped = [r.trial.id for r in self.done if r.skipped is not None]
        done_ids = {r.trial.id for r in self.done}
        not_run = [t.id for t in self.study.trials if t.id not in done_ids]
        report = {
            "format": REPORT_FORMAT,
            "version": REPORT_VERSION,
            "complete": False,
            "interrupted": why,
            "study": self.study.to_json(),
            "trials_run": ran,
            "trials_skipped": skipped,
            "trials_not_run": not_run,
            "trials_file": "trials.jsonl",
        }
        (self.root / "report.json").write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
        lines = [
            f"# {self.study.title}",
            "",
            f"**INTERRUPTED** ({why}) after {len(self.done)} of {len(self.study.trials)} trial(s): no checks "
            "were made. Each trial that ran is in `trials.jsonl` and its frames in `frames/`.",
            "",
            f"- ran: {', '.join(ran) or 'none'}",
        ]
        if skipped:
            lines.append(f"- skipped: {', '.join(skipped)}")
        lines.append(f"- not run: {', '.join(not_run) or 'none'}")
        (self.root / "summary.md").write_text("\n".join(lines) + "\n", encoding="utf-8")
        return report


def write_report(
    result: StudyRun,
    design: list[Check],
    out: str | Path,
    *,
    pictures: bool = True,
    gif: bool = False,
) -> dict[str, Any]:
    """Write the report directory; return the report (as written to ``report.json``)."""
    root = Path(out)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigurationError(
            f"--out {str(root)!r}: cannot create the directory ({exc.strerror or exc})"
        ) from exc
    report = report_json(result, design)
    frames_dir = root / "frames"
    frames_dir.mkdir(exist_ok=True)
    by_id = {t["id"]: t for t in report["trials"]}
    for run in result.trials:
        if run.skipped is not None:
            continue
        path = frames_dir / f"{run.trial.id}.jsonl"
        path.write_text("\n".join(frames_lines(run)) + "\n", encoding="utf-8")
        by_id[run.trial.id]["frames_file"] = str(path.relative_to(root))
    if pictures:
        pics = draw_pictures(result, root, gif=gif)
        for tid, entry in pics.get("trials", {}).items():
            by_id[tid]["pictures"] = entry
        report["pictures"] = {k: v for k, v in pics.items() if k != "trials"}
    else:
        report["pictures"] = {"note": "pictures not drawn (--no-pictures)"}
    report = dict(_clean(report))
    (root / "report.json").write_text(
        json.dumps(report, indent=1, default=_json_default, allow_nan=False) + "\n", encoding="utf-8"
    )
    (root / "summary.md").write_text(markdown(report), encoding="utf-8")
    return report


def _clean(obj: Any) -> Any:
    """Non-finite floats become null (JSON has no NaN); containers are walked."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    return obj


def _json_default(obj: Any) -> Any:
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    try:
        import numpy as np

        if isinstance(obj, np.generic):
            return obj.item()
        if isinstance(obj, np.ndarray):
            return obj.tolist()
    except ImportError:  # pragma: no cover
        pass
    return str(obj)
