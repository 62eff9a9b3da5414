"""Pass/fail checks of what a trial delivered, against what the trial was meant to deliver.

Every check is computed from the recorded run — the poses, the renderer's frame records, the bytes
captured on the port, the emulator's pattern buffer and hazard list, and the timed emulator's pulses —
and compared with the trial's expectation or with an independent recomputation (the scene queried
again at the recorded pose, the base patterns rebuilt for the array).  A check is ``passed`` True or
False, or None when it could not be made here (no emulator behind the port, timed replay not run); the
detail says what was compared.

Checks on every trial
    ``tracking_accepted_every_sample``, ``no_tracking_teleports``, ``pattern_buffer_matched_every_sent_frame``
    (the emulator's pattern buffer after each sent frame), ``wire_carried_every_sent_frame`` (the
    patterns decoded from the captured bytes, in order), ``no_emulator_hazards``, ``all_off_after_trial``,
    ``started_and_ended_beyond_8cm`` (tasks 1 and 2: every approach starts and ends 8 cm or more from
    every surface, the withdrawal the study asked for between approaches),
    and from the timed replay ``scans_delivered_each_frame`` (the channels pulsed while a frame was held
    are the frame's electrodes), ``currents_within_limits`` and ``no_timing_hazards``.
Firmware v2 (every trial, besides the above)
    ``heights_matched_every_sent_frame`` (each electrode's height in the board's pattern buffer after each
    sent frame, against the height the driver put in force: the level readback only sees on and off) and,
    from the timed replay, ``heights_delivered_each_frame`` (every pulse on an electrode while a frame was
    held has the height the frame's bytes gave that electrode).  Every check above applies on v2 as well:
    the wire and the pulses are read with the v2 command table and the v2 timed model.
Task 1
    ``feature_rendered_matches`` (the feature under the finger is the trial's), ``edge_orientation_matches``,
    ``approach_frames_expand`` (each approach frame is one of the feature's expansion frames, starting at
    the first and one spacing further each time), ``contact_pattern_of_feature``.
Task 2
    ``feature_rendered_matches``, ``contact_pattern_matches_theta`` (eq. 4's shifted pattern of the
    trial's θ level, or the uniform pattern), ``stationary_only``.
Task 3 (per surface)
    ``texture_rendered_matches``, ``texture_shift_count`` (pattern shifts during the stroke against
    travel / (d·k) of eq. 7; none on a smooth surface), ``sliding_patterns_are_rightward_texture``,
    ``silent_while_stationary``.
Phase 2
    UA: ``ua_all_or_nothing`` and ``ua_on_exactly_inside`` (all electrodes on exactly when the pad centre
    is inside, re-queried); CAM: ``cam_matches_contact_area`` (each electrode on exactly when its own
    world position is inside, recomputed from the pose); TactDeform: ``features_expected``,
    ``texture_rendered_matches``.  Every TactDeform trial: ``frames_are_tactdeform_patterns``.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..render.geometry import TEXTURE_NAMES
from ..render.patterns import DIRECTIONS, EDGE_ORIENTATIONS, Pattern, PatternSet
from .runner import StudyRun, TrialRun, frame_heights, frame_intents

#: Latency allowed between a frame's write and its effect on every scan (pacing, the USB frame, the
#: parser's tick and the scan in progress) before the scans must show it.
SETTLE_S = 0.012
#: A frame must be held this long after settling for the "every electrode pulsed" half of the check.
FULL_SCAN_S = 0.016
#: Task 1 and 2 start and end their approaches this far from the surface; the study asked for > 8 cm.
WITHDRAW_MM = 80.0
WITHDRAW_STUDIES = ("task1", "task2")
CONTACT_STATES = ("approaching", "interacting")


@dataclass(frozen=True)
class Check:
    name: str
    passed: bool | None
    detail: str = ""

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "passed": self.passed, "detail": self.detail}


def _on(p: Sequence[int]) -> list[int]:
    return [i for i, v in enumerate(p) if v]


def _texture(level: int | None) -> str:
    return "none" if level is None else TEXTURE_NAMES.get(level, str(level))


def _fmt_set(items: Iterable[Any]) -> str:
    c = Counter(items)
    return ", ".join(f"{k}×{n}" for k, n in sorted(c.items(), key=lambda kv: str(kv[0]))) or "none"


def _segment_of(run: TrialRun) -> list[int]:
    """Segment index of every record."""
    seg_of_pose = np.zeros(len(run.poses), dtype=int)
    for k, (a, b) in enumerate(run.segment_spans):
        seg_of_pose[a:b] = k
        if k + 1 < len(run.segment_spans):
            seg_of_pose[b : run.segment_spans[k + 1][0]] = -1  # the move between segments
    return [int(seg_of_pose[i]) for i in run.record_pose]


def universe(ps: PatternSet) -> set[Pattern]:
    """Every pattern TactDeform can show on the array (all features, frames, θ levels, textures)."""
    out: set[Pattern] = {ps.off}
    keys = [("face", None), ("corner", None)] + [("edge", o) for o in EDGE_ORIENTATIONS]
    for f, o in keys:
        out.update(ps.frames(f, o))
        out.add(ps.static(f, o))
        for level in range(4):
            out.add(ps.contact(f, o, level))
        for k in (1, 2):
            for d in range(len(DIRECTIONS)):
                for phase in range(ps.mask_period(k)):
                    out.add(ps.sliding(f, o, d, k, phase))
    return out


# --- every trial -----------------------------------------------------------------------------------------


def common_checks(run: TrialRun, result: StudyRun) -> list[Check]:
    out: list[Check] = []
    drops = dict(run.tracking_drops)
    for k, v in (run.summary.get("dropped") or {}).items():
        drops[f"renderer:{k}"] = v
    out.append(
        Check(
            "tracking_accepted_every_sample",
            not drops,
            f"{len(run.poses)} samples" + (f", dropped: {drops}" if drops else ", none dropped"),
        )
    )
    tele = int(run.summary.get("teleports", 0))
    out.append(Check("no_tracking_teleports", tele == 0, f"{tele} teleport(s)"))
    sent = [r for r in run.records if r.sent]
    if run.verified:
        mism = int(run.summary.get("mismatches", 0))
        detail = f"{len(sent)} sent frame(s) compared with the emulator's pattern buffer, {mism} mismatch(es)"
        if mism:
            detail += f"; first: {run.summary.get('first_mismatch')}"
        out.append(Check("pattern_buffer_matched_every_sent_frame", mism == 0, detail))
    else:
        out.append(Check("pattern_buffer_matched_every_sent_frame", None, "no emulator behind the port"))
    if result.heights_per_electrode:
        out.append(heights_readback_check(run))
    wire = [p for _, p, phase in frame_intents(run, result.array) if phase == "render"]
    want = [tuple(r.electrodes) for r in sent]
    if wire == want:
        out.append(
            Check(
                "wire_carried_every_sent_frame", True, f"{len(wire)} pattern command(s) on the wire, in order"
            )
        )
    else:
        first = next((i for i, (a, b) in enumerate(zip(wire, want)) if a != b), min(len(wire), len(want)))
        out.append(
            Check(
                "wire_carried_every_sent_frame",
                False,
                f"{len(wire)} pattern command(s) on the wire for {len(want)} sent frame(s); first "
                f"difference at frame {first}",
            )
        )
    if run.verified:
        kinds = [h.get("kind") for h in run.hazards]
        out.append(Check("no_emulator_hazards", not kinds, "none" if not kinds else _fmt_set(kinds)))
    else:
        out.append(Check("no_emulator_hazards", None, "no emulator behind the port"))
    last = run.records[-1] if run.records else None
    end_ok = last is not None and last.state == "idle" and not any(last.electrodes)
    detail = f"last state {last.state if last else None}"
    if run.end_pattern is not None:
        end_ok = end_ok and not any(run.end_pattern)
        detail += f", emulator pattern has {sum(1 for v in run.end_pattern if v)} electrode(s) on"
    out.append(Check("all_off_after_trial", end_ok, detail))
    if result.study.name in WITHDRAW_STUDIES and run.scene is not None and run.segment_spans:
        dists = []
        for a, b in run.segment_spans:
            for i in (a, b - 1):
                dists.append(float(run.scene.query(np.asarray(run.poses[i].position_mm)).signed_distance_mm))
        out.append(
            Check(
                "started_and_ended_beyond_8cm",
                min(dists) >= WITHDRAW_MM,
                f"nearest surface at segment starts/ends: {min(dists):.1f} mm (needs ≥ {WITHDRAW_MM:g})",
            )
        )
    out.extend(timed_checks(run, result))
    return out


def timed_checks(run: TrialRun, result: StudyRun) -> list[Check]:
    names = ("scans_delivered_each_frame", "currents_within_limits", "no_timing_hazards")
    d = run.delivered
    if d is None:
        why = result.timed_note or "timed replay not available"
        return [Check(n, None, why) for n in names]
    table = d["_table"]
    mapping = result.array.channel_mapping()
    hw_to_app = {ch: i for i, ch in enumerate(mapping.app_to_hw)}
    stim = np.isin(table["kind"], (0, 1, 2))
    starts = table["start_us"][stim]
    chans = table["channel"][stim].astype(int)
    intents = frame_intents(run, result.array)
    end_us = d["window_s"][1] * 1e6
    checked_full = checked_subset = 0
    problems: list[str] = []
    for k, (t_us, levels, _phase) in enumerate(intents):
        nxt = intents[k + 1][0] if k + 1 < len(intents) else end_us
        lo = t_us + SETTLE_S * 1e6
        if nxt <= lo:
            continue
        sel = (starts >= lo) & (starts < nxt)
        got = {hw_to_app.get(int(c), -1) for c in chans[sel]}
        meant = set(_on(levels))
        checked_subset += 1
        extra = got - meant
        if extra:
            problems.append(f"frame at {t_us / 1e6:.3f} s: electrodes {sorted(extra)} pulsed but meant off")
        if nxt - lo >= FULL_SCAN_S * 1e6:
            checked_full += 1
            missing = meant - got
            if missing:
                problems.append(
                    f"frame at {t_us / 1e6:.3f} s: electrodes {sorted(missing)} meant on but never pulsed"
                )
    detail = (
        f"{checked_subset} frame(s) checked for pulses on electrodes meant off, {checked_full} held long "
        f"enough (≥ {1000 * (SETTLE_S + FULL_SCAN_S):.0f} ms) to check every electrode meant on was pulsed"
    )
    if problems:
        detail += (
            "; " + "; ".join(problems[:3]) + (f" (+{len(problems) - 3} more)" if len(problems) > 3 else "")
        )
    if checked_subset == 0:
        out = [Check("scans_delivered_each_frame", None, "no frame held long enough to be checked")]
    else:
        out = [Check("scans_delivered_each_frame", not problems, detail)]
    limits = result.limits_ua
    cur = table["current_ua"]
    over = []
    for ch, ua in zip(table["channel"][stim].astype(int).tolist(), cur[stim].tolist()):
        app = hw_to_app.get(ch)
        cap = min(limits[app], result.current_ua) if app is not None else 0
        if ua > cap + 1e-6:
            over.append((app, ua, cap))
    bad = over or d["sense_pulses_with_current"] or d["pulses_on_unmapped_channels"]
    detail = (
        f"max {d['max_current_ua']} µA (asked {result.current_ua} µA), max {d['max_charge_per_pulse_nc']} nC "
        f"per pulse; {len(over)} pulse(s) above the limit, {d['sense_pulses_with_current']} sense pulse(s) "
        f"with current, {d['pulses_on_unmapped_channels']} on unmapped channels"
    )
    out.append(Check("currents_within_limits", not bad, detail))
    kinds = [h.get("kind") for h in run.timed_hazards]
    out.append(Check("no_timing_hazards", not kinds, "none" if not kinds else _fmt_set(kinds)))
    if result.heights_per_electrode:
        out.append(heights_delivered_check(run, result))
    return out


def heights_readback_check(run: TrialRun) -> Check:
    """Firmware v2: the board's per-electrode heights after every sent frame were the driver's."""
    name = "heights_matched_every_sent_frame"
    if run.heights_checked is None:
        return Check(name, None, "no emulator behind the port: the board's heights cannot be read back")
    detail = (
        f"{run.heights_checked} sent frame(s): every electrode's height in the board's pattern buffer "
        f"compared with the driver's, {run.height_mismatches} mismatch(es)"
    )
    first = run.first_height_mismatch
    if first is not None:
        meant, got = first.get("driver_codes"), first.get("board_codes") or []
        diff = (
            [i for i, (a, b) in enumerate(zip(meant, got)) if a != b]
            if meant is not None
            else "driver unknown"
        )
        detail += f"; first at frame {first.get('frame')}, electrodes {diff}"
    return Check(name, run.height_mismatches == 0 and run.heights_checked > 0, detail)


def heights_delivered_check(run: TrialRun, result: StudyRun) -> Check:
    """Firmware v2, timed replay: while a frame was held (after settling), every pulse on an electrode had
    the height the frame's bytes gave that electrode."""
    name = "heights_delivered_each_frame"
    d = run.delivered
    if d is None:
        return Check(name, None, result.timed_note or "timed replay not available")
    table = d["_table"]
    mapping = result.array.channel_mapping()
    hw_to_app = {ch: i for i, ch in enumerate(mapping.app_to_hw)}
    stim = np.isin(table["kind"], (0, 1, 2)) & (table["current_ua"] > 0)
    starts = table["start_us"][stim]
    chans = table["channel"][stim].astype(int)
    cur = table["current_ua"][stim]
    frames = frame_heights(run, result.array)
    end_us = d["window_s"][1] * 1e6
    checked = pulses = 0
    problems: list[str] = []
    for k, (t_us, _levels, heights, _phase) in enumerate(frames):
        nxt = frames[k + 1][0] if k + 1 < len(frames) else end_us
        lo = t_us + SETTLE_S * 1e6
        if nxt <= lo:
            continue
        sel = (starts >= lo) & (starts < nxt)
        checked += 1
        wrong: dict[int, set[float]] = {}
        for ch, ua in zip(chans[sel].tolist(), cur[sel].tolist()):
            pulses += 1
            app = hw_to_app.get(int(ch))
            want = heights[app] if app is not None else 0.0
            if abs(float(ua) - want) > 1e-6:
                wrong.setdefault(-1 if app is None else app, set()).add(round(float(ua), 1))
        if wrong:
            problems.append(
                f"frame at {t_us / 1e6:.3f} s: "
                + ", ".join(
                    f"electrode {e} pulsed at {sorted(v)} µA, meant {heights[e] if e >= 0 else 0:g}"
                    for e, v in sorted(wrong.items())[:3]
                )
            )
    if checked == 0:
        return Check(name, None, "no frame held long enough to be checked")
    detail = f"{checked} frame(s), {pulses} pulse(s) compared with each electrode's height on the wire"
    if problems:
        detail += (
            "; " + "; ".join(problems[:3]) + (f" (+{len(problems) - 3} more)" if len(problems) > 3 else "")
        )
    return Check(name, not problems, detail)


# --- per study -------------------------------------------------------------------------------------------


def _contact_records(run: TrialRun, seg: int | None = None) -> list[tuple[int, Any]]:
    segs = _segment_of(run)
    return [
        (i, r)
        for i, r in enumerate(run.records)
        if r.state in CONTACT_STATES and (seg is None or segs[i] == seg)
    ]


def feature_check(run: TrialRun, expected: str) -> Check:
    seen = [r.feature for _, r in _contact_records(run)]
    if not seen:
        return Check("feature_rendered_matches", False, f"no contact: expected {expected}")
    wrong = [f for f in seen if f != expected]
    return Check(
        "feature_rendered_matches", not wrong, f"expected {expected}; seen in contact: {_fmt_set(seen)}"
    )


def task1_checks(run: TrialRun, result: StudyRun) -> list[Check]:
    ps = result.patterns
    exp = run.trial.segments[0].expect
    feature, orientation = exp["feature"], exp.get("orientation")
    out = [feature_check(run, feature)]
    contact = _contact_records(run)
    if feature == "edge":
        seen = [r.orientation for _, r in contact if r.feature == "edge"]
        wrong = [o for o in seen if o != orientation]
        out.append(
            Check(
                "edge_orientation_matches",
                bool(seen) and not wrong,
                f"expected {orientation}; seen: {_fmt_set(seen)}",
            )
        )
    frames = ps.frames(feature, orientation)
    shown = [r.electrodes for _, r in contact if r.sent and r.state == "approaching"]
    idx = [frames.index(p) if p in frames else -1 for p in shown]
    n = len(frames)
    ok = bool(idx) and -1 not in idx and idx[0] == 0 and len(set(idx)) >= min(2, n)
    if ok:
        ok = all((b - a) % n in (1, n - 1) for a, b in zip(idx, idx[1:]))  # neighbours: one spacing apart
    out.append(
        Check(
            "approach_frames_expand",
            ok,
            f"frames shown while approaching (index into the {n} {feature} frames): "
            f"{['?' if i < 0 else i for i in idx]}",
        )
    )
    held = [r.electrodes for _, r in contact if r.sent and r.state == "interacting"]
    family = {ps.contact(feature, orientation, lv) for lv in range(4)} | {ps.static(feature, orientation)}
    wrong_held = [p for p in held if p not in family]
    out.append(
        Check(
            "contact_pattern_of_feature",
            bool(held) and not wrong_held,
            f"{len(held)} sustained-contact frame(s), {len(wrong_held)} not a {feature} contact pattern",
        )
    )
    return out


def _centroid_x(ps: PatternSet, p: Sequence[int]) -> float | None:
    on = _on(p)
    if not on:
        return None
    rel = ps.array.positions_mm[on, 0] - ps.array.centre_mm[0]
    return round(float(np.mean(rel)), 2)


def task2_checks(run: TrialRun, result: StudyRun) -> list[Check]:
    ps = result.patterns
    exp = run.trial.segments[0].expect
    out = [feature_check(run, "face")]
    level = int(exp["theta_level"])
    if run.trial.contact_mode == "uniform":
        want, what = ps.static("face"), "the uniform (whole-pad) pattern"
    else:
        want, what = ps.contact("face", None, level), f"the θ level {exp['theta_name']} pattern (eq. 4)"
    held = [r.electrodes for _, r in _contact_records(run) if r.sent and r.state == "interacting"]
    levels_seen = []
    for p in held:
        hit = [lv for lv in range(4) if ps.contact("face", None, lv) == p]
        levels_seen.append(hit[0] if hit else ("uniform" if p == ps.static("face") else "other"))
    ok = bool(held) and all(p == want for p in held)
    out.append(
        Check(
            "contact_pattern_matches_theta",
            ok,
            f"expected {what} (centroid x {_centroid_x(ps, want)} mm); held: {levels_seen}, "
            f"centroid x {[_centroid_x(ps, p) for p in held]} mm",
        )
    )
    sliding = [r for r in run.records if r.context == "sliding" and r.sent and any(r.electrodes)]
    out.append(Check("stationary_only", not sliding, f"{len(sliding)} frame(s) sent while sliding"))
    return out


def _stroke_travel(run: TrialRun, recs: list[tuple[int, Any]]) -> tuple[float, float]:
    """Rightward travel (mm) and duration (s) between the first and the last record of ``recs``."""
    a, b = run.record_pose[recs[0][0]], run.record_pose[recs[-1][0]]
    pa, pb = run.poses[a], run.poses[b]
    return float(pb.position_mm[0] - pa.position_mm[0]), float(pb.t_s - pa.t_s)


def task3_checks(run: TrialRun, result: StudyRun) -> list[Check]:
    ps = result.patterns
    d_mm = result.array.pitch_mm
    out: list[Check] = []
    segs = _segment_of(run)
    east = DIRECTIONS.index("E")
    for k, seg in enumerate(run.trial.segments):
        level = int(seg.expect["texture"])
        tag = f"[{seg.plan_object}]"
        recs = [(i, r) for i, r in enumerate(run.records) if segs[i] == k]
        sliding = [(i, r) for i, r in recs if r.state == "interacting" and r.context == "sliding"]
        if not sliding:
            out.append(Check(f"texture_rendered_matches{tag}", False, "no sliding contact on this surface"))
            continue
        seen = [r.texture for _, r in sliding]
        out.append(
            Check(
                f"texture_rendered_matches{tag}",
                all(t == level for t in seen),
                f"expected {TEXTURE_NAMES[level]}; seen while sliding: {_fmt_set(_texture(t) for t in seen)}",
            )
        )
        sent = [r.electrodes for _, r in sliding if r.sent]
        changes = max(0, len(sent) - 1)
        travel, dur = _stroke_travel(run, sliding)
        if level == 0:
            ok = changes == 0 and all(p == ps.static("face") for p in sent)
            detail = f"smooth: {changes} shift(s) over {travel:.1f} mm (expected none, a static pattern)"
        else:
            expected = travel / (d_mm * level)
            tol = max(2.0, 0.1 * expected)
            ok = abs(changes - expected) <= tol
            rate = changes / dur if dur > 0 else math.nan
            v = travel / dur if dur > 0 else math.nan
            detail = (
                f"{changes} shift(s) over {travel:.1f} mm in {dur:.2f} s ({rate:.1f} Hz); eq. 7 expects "
                f"{expected:.1f} ± {tol:.1f} ({v / (d_mm * level):.1f} Hz at {v:.1f} mm/s)"
            )
        out.append(Check(f"texture_shift_count{tag}", ok, detail))
        if level == 0:
            family = {ps.static("face")}
        else:
            family = {ps.sliding("face", None, east, level, ph) for ph in range(ps.mask_period(level))}
        wrong = [p for p in sent if p not in family]
        out.append(
            Check(
                f"sliding_patterns_are_rightward_texture{tag}",
                bool(sent) and not wrong,
                f"{len(sent)} sliding frame(s), {len(wrong)} not a rightward {TEXTURE_NAMES[level]} pattern",
            )
        )
        still = [
            r for _, r in recs if r.state == "interacting" and r.context == "contact" and any(r.electrodes)
        ]
        out.append(
            Check(
                f"silent_while_stationary{tag}",
                not still,
                f"{len(still)} record(s) with electrodes on while in stationary contact",
            )
        )
    return out


def phase2_checks(run: TrialRun, result: StudyRun) -> list[Check]:
    exp = run.trial.segments[0].expect
    scene = run.scene
    out: list[Check] = []
    approach = run.trial.approach
    if approach == "ua":
        sent = [r.electrodes for r in run.records if r.sent]
        mixed = [p for p in sent if any(p) and not all(p)]
        out.append(Check("ua_all_or_nothing", not mixed, f"{len(sent)} sent frame(s), {len(mixed)} partial"))
        wrong = 0
        for i, r in enumerate(run.records):
            pose = run.poses[run.record_pose[i]]
            inside = (
                scene.query(np.asarray(pose.position_mm)).signed_distance_mm <= 0.0
                if scene is not None
                else False
            )
            if bool(all(r.electrodes)) != bool(inside):
                wrong += 1
        out.append(
            Check(
                "ua_on_exactly_inside",
                wrong == 0,
                f"{len(run.records)} record(s) compared with the pad centre's inside test, {wrong} differ",
            )
        )
    elif approach == "cam":
        arr = result.array
        rel = arr.world_offsets()
        pad = np.column_stack((rel, np.zeros(len(rel))))
        wrong = checked = 0
        for i, r in enumerate(run.records):
            if not (r.sent or i % 8 == 0) or scene is None:
                continue
            pose = run.poses[run.record_pose[i]]
            inside_el = np.asarray(scene.contains(pose.to_world(pad)), dtype=bool)
            checked += 1
            if tuple(int(v) for v in inside_el) != tuple(1 if v else 0 for v in r.electrodes):
                wrong += 1
        partial = sum(1 for r in run.records if r.sent and any(r.electrodes) and not all(r.electrodes))
        out.append(
            Check(
                "cam_matches_contact_area",
                checked > 0 and wrong == 0,
                f"{checked} record(s) compared with the electrodes' own inside test, {wrong} differ; "
                f"{partial} partial-contact frame(s) sent",
            )
        )
    else:
        allowed = set(exp.get("features", ("face", "edge", "corner")))
        seen = [r.feature for _, r in _contact_records(run)]
        out.append(
            Check(
                "features_expected",
                bool(seen) and set(seen) <= allowed,
                f"allowed {sorted(allowed)}; seen in contact: {_fmt_set(seen)}",
            )
        )
        want = int(exp.get("texture", 0))
        tex = [r.texture for r in run.records if r.state == "interacting" and r.context == "sliding"]
        ok = bool(tex) and all(t == want for t in tex)
        out.append(
            Check(
                "texture_rendered_matches",
                ok,
                f"expected {TEXTURE_NAMES[want]}; seen while sliding: {_fmt_set(_texture(t) for t in tex)}",
            )
        )
    return out


def tactdeform_pattern_check(run: TrialRun, known: set[Pattern]) -> Check:
    sent = [r.electrodes for r in run.records if r.sent]
    wrong = [p for p in sent if tuple(p) not in known]
    return Check(
        "frames_are_tactdeform_patterns",
        bool(sent) and not wrong,
        f"{len(sent)} sent frame(s), {len(wrong)} not a TactDeform pattern of this array",
    )


_STUDY_CHECKS = {"task1": task1_checks, "task2": task2_checks, "task3": task3_checks, "phase2": phase2_checks}


def check_trial(run: TrialRun, result: StudyRun, known: set[Pattern] | None = None) -> list[Check]:
    """All checks of one trial (also stored on ``run.checks``)."""
    if run.skipped is not None:
        run.checks = []
        return []
    checks = common_checks(run, result)
    checks.extend(_STUDY_CHECKS[result.study.name](run, result))
    if run.trial.approach == "tactdeform":
        checks.append(
            tactdeform_pattern_check(run, known if known is not None else universe(result.patterns))
        )
    run.checks = checks
    return checks


def check_study(result: StudyRun) -> list[Check]:
    """Check every trial; return the study-level checks (the design of the trial list)."""
    known = universe(result.patterns)
    for run in result.trials:
        check_trial(run, result, known)
    return design_checks(result)


def design_checks(result: StudyRun) -> list[Check]:
    study = result.study
    trials = study.trials
    conds = Counter(t.condition for t in trials)
    out: list[Check] = []
    if study.selection is not None:
        out.append(Check("design", None, f"trials {study.selection} only: {len(trials)} trial(s)"))
        return out
    if study.quick:
        out.append(
            Check(
                "design",
                None,
                f"quick run: {len(trials)} trial(s), one per condition "
                f"({_fmt_set(t.condition for t in trials)})",
            )
        )
        return out
    if study.name == "task1":
        feats = Counter(t.segments[0].expect["feature"] for t in trials)
        edges = sorted(n for c, n in conds.items() if c.startswith("edge-"))
        ok = (
            len(trials) == 21
            and feats == Counter({"face": 7, "edge": 7, "corner": 7})
            and edges == [1, 2, 2, 2]
        )
        out.append(
            Check(
                "design",
                ok,
                f"{len(trials)} trials: {_fmt_set(t.segments[0].expect['feature'] for t in trials)}; "
                f"edges {_fmt_set(c for c in (t.condition for t in trials) if c.startswith('edge-'))}",
            )
        )
    elif study.name == "task2":
        ok = len(trials) == 16 and all(n == 1 for n in conds.values())
        out.append(
            Check(
                "design", ok, f"{len(trials)} trials, {len(conds)} distinct (2 modes × 2 bars × 4 θ levels)"
            )
        )
    elif study.name == "task3":
        pairs = Counter(tuple(sorted(lv for _, lv in t.textures)) for t in trials)
        ok = len(trials) == 24 and len(pairs) == 6 and all(n == 4 for n in pairs.values())
        out.append(
            Check(
                "design",
                ok,
                f"{len(trials)} trials over {len(pairs)} level pairs, {sorted(set(pairs.values()))} each",
            )
        )
    else:
        ok = len(trials) == 12 and len(conds) == 12
        out.append(Check("design", ok, f"{len(trials)} trials: 4 objects × UA, CAM, TactDeform"))
    return out
