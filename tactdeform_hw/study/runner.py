"""Run a study's trials through the whole pipeline and keep everything the checks and the report need.

For every trial: the synthetic finger poses of its segments (planned with
:func:`~tactdeform_hw.render.trajectories.make_trajectory`) pass the tracking layer's stream checks
(:class:`~tactdeform_hw.render.tracking.PoseValidator`), the :class:`~tactdeform_hw.render.pipeline.Renderer`
(pattern manager or baseline), the device driver, and the port — by default the emulator behind the
``etactile://`` virtual serial port.  One device session covers the whole study; each trial gets a fresh
renderer, which configures the device (all off) before its first pose, as a new trial block would.

The port is wrapped by a :class:`WireTap` that keeps every write with the session time of the pose being
rendered, so after the run the exact byte stream can be replayed into the timed emulator
(:class:`~tactdeform_hw.emulator.timed.model_v1_2.TimedEmulator`) to see what the firmware's scans delivered:
which
channels were pulsed, at what current and with how much charge.  The replay spaces commands at least
:data:`PACE_S` apart (the driver's pacing rule: one command with a payload per firmware tick), starting
at the moment the renderer produced them.

Session time runs on: trial *k + 1* starts :data:`INTER_TRIAL_S` after trial *k* ended.

Both firmware versions run the same study.  The firmware the device found (v1.2, or v2 where each
electrode's pattern element is its own pulse height) decides how the captured bytes are read, which timed
model replays them (:func:`~tactdeform_hw.emulator.timed.model_v1_2.timed_emulator`), and, on v2, the extra
readback of
every electrode's height after each frame (the level readback alone would not see a wrong height).
"""

from __future__ import annotations

import math
import time
from bisect import bisect_right
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import ConfigurationError, TactDeformError
from ..protocol.constants import Opcode
from ..protocol.firmware import V1_2, V2, OpcodeV2
from ..render.array import ElectrodeArray
from ..render.manager import ManagerConfig
from ..render.patterns import PatternSet
from ..render.pipeline import FrameRecord
from ..render.scene import (
    BUNNY_FILE,
    MESH_DIR_ENV,
    RenderOptions,
    Scene,
    find_mesh_file,
    load_scene,
    mesh_search_dirs,
)
from ..render.tracking import Pose, PoseValidator, slerp
from ..render.trajectories import make_trajectory, scene_for_trajectory
from .scenarios import START_DISTANCE_MM, Segment, Study, Trial

#: Pause between trials (session time), the device holding all-off.
INTER_TRIAL_S = 0.5
#: Spacing of commands in the timed replay: one firmware tick plus margin, the driver's pacing interval.
PACE_S = 0.0012
#: Emulated time after the last write, so the last frame's scans are simulated.
TAIL_S = 0.05
#: Speed of the free-space move between two segments of a trial (e.g. from one surface to the other).
TRANSIT_SPEED_MM_S = 200.0
#: Current used on the emulator when neither --current-ua nor a participant gives one, so the delivered
#: currents and charges are not all zero.
NOMINAL_EMULATOR_UA = 1000

ProgressFn = Callable[[str], None]


# --- the wire tap --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class WireWrite:
    """One write on the port: when (session time of the pose being rendered), in which trial (0 outside
    any), in which phase (``configure`` / ``render`` / ``session``), the bytes, and the firmware whose
    command table reads them (v2 has the sync check 0xF4 and the stimulation mode where v1.2 has the
    pulse height)."""

    t_s: float
    trial: int
    phase: str
    data: bytes
    firmware: str = "v1.2"

    @property
    def opcode(self) -> int | None:
        low = min(OpcodeV2) if self.firmware == V2.name else min(Opcode)
        return self.data[0] if self.data and self.data[0] >= low else None

    @property
    def name(self) -> str:
        op = self.opcode
        if op is None:
            return "ZEROS" if not any(self.data) else "UNKNOWN"
        if self.firmware == V2.name:
            return OpcodeV2(op).name
        return Opcode(op).name

    def command_names(self, electrode_num: int) -> list[str]:
        """The name of every command the firmware reads in this write (a write may carry several: the
        v2 driver's cover writes the mode, the pattern and the mode again at once)."""
        from ..protocol.reader import iter_commands

        spec = V2 if self.firmware == V2.name else V1_2
        names = [
            spec.command(c.opcode).name for c in iter_commands(self.data, electrode_num, spec) if c.opcode
        ]
        return names or [self.name]


class WireTap:
    """A transparent proxy around a pyserial-like port that records every write.

    Attribute reads and writes go to the wrapped port (``emulator``, ``is_open``, ``dtr`` …), so the driver
    and the renderer's verification see the port they expect.  ``firmware`` names the command table the
    writes are read with (set once the device knows the board's version)."""

    def __init__(self, port: Any, firmware: str = "v1.2") -> None:
        object.__setattr__(self, "_port", port)
        object.__setattr__(self, "writes", [])
        object.__setattr__(self, "t_s", 0.0)
        object.__setattr__(self, "trial", 0)
        object.__setattr__(self, "phase", "session")
        object.__setattr__(self, "firmware", firmware)

    def write(self, data: bytes) -> Any:
        n = self._port.write(data)
        self.writes.append(
            WireWrite(float(self.t_s), int(self.trial), str(self.phase), bytes(data), str(self.firmware))
        )
        return n

    def mark(self, *, t_s: float | None = None, trial: int | None = None, phase: str | None = None) -> None:
        if t_s is not None:
            object.__setattr__(self, "t_s", float(t_s))
        if trial is not None:
            object.__setattr__(self, "trial", int(trial))
        if phase is not None:
            object.__setattr__(self, "phase", phase)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._port, name)

    def __setattr__(self, name: str, value: Any) -> None:
        if name in ("t_s", "trial", "phase", "firmware"):
            object.__setattr__(self, name, value)
        else:
            setattr(self._port, name, value)


# --- results -------------------------------------------------------------------------------------------


@dataclass
class TrialRun:
    """Everything one trial produced (session times in seconds)."""

    trial: Trial
    skipped: str | None = None
    scene: Scene | None = None
    t0_s: float = 0.0
    t1_s: float = 0.0
    poses: list[Pose] = field(default_factory=list)
    segment_spans: list[tuple[int, int]] = field(default_factory=list)  # pose index ranges [a, b)
    records: list[FrameRecord] = field(default_factory=list)
    record_pose: list[int] = field(default_factory=list)  # pose index of each record
    summary: dict[str, Any] = field(default_factory=dict)
    tracking_drops: dict[str, int] = field(default_factory=dict)
    verified: bool = False
    hazards: list[dict[str, Any]] = field(default_factory=list)
    end_pattern: list[int] | None = None
    writes: list[WireWrite] = field(default_factory=list)
    replay_us: list[float] = field(default_factory=list)  # replay time of each write (timed model)
    delivered: dict[str, Any] | None = None
    timed_hazards: list[dict[str, Any]] = field(default_factory=list)
    checks: list[Any] = field(default_factory=list)
    wall_s: float = 0.0
    #: Firmware v2: sent frames whose per-electrode heights were read back from the board, how many
    #: differed from the heights the driver put in force, and the first difference (None: not read back).
    heights_checked: int | None = None
    height_mismatches: int = 0
    first_height_mismatch: dict[str, Any] | None = None

    @property
    def passed(self) -> bool | None:
        if self.skipped is not None:
            return None
        return all(c.passed is not False for c in self.checks)


@dataclass
class StudyRun:
    study: Study
    device: str
    current_ua: int
    current_source: str
    rate_hz: float
    array: ElectrodeArray
    patterns: PatternSet
    trials: list[TrialRun]
    limits_ua: list[int]
    participant: str | None = None
    timed: bool = False
    timed_note: str | None = None
    timed_summary: dict[str, Any] | None = None
    notes: list[str] = field(default_factory=list)
    wall_s: float = 0.0
    writes: list[WireWrite] = field(default_factory=list)
    #: What the session sent, from the device's own records (pulse heights written, each electrode's highest,
    #: the guard's clips and refusals): see :mod:`tactdeform_hw.session.delivery`.
    sent: dict[str, Any] | None = None
    #: The firmware the board ran (``v1.2`` or ``v2``), as the device found it.
    firmware: str = "v1.2"

    @property
    def heights_per_electrode(self) -> bool:
        """Whether every electrode had its own pulse height (v2), so the checks read each one back and the
        report lists the heights each was pulsed at."""
        from ..session.delivery import per_electrode_heights

        return per_electrode_heights(self.firmware)


# --- scenes and poses ----------------------------------------------------------------------------------


class _Scenes:
    """Scenes built once per (scene, approach, contact mode, textures) and reused across trials."""

    def __init__(self, mesh_dirs: Sequence[str]) -> None:
        self.mesh_dirs = tuple(mesh_dirs)
        self._cache: dict[tuple[Any, ...], Scene] = {}

    def get(self, trial: Trial, approach: str | None = None) -> Scene:
        approach = approach or trial.approach
        key = (trial.scene, approach, trial.contact_mode, trial.textures)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        base_key = (trial.scene, approach, trial.contact_mode, ())
        scene = self._cache.get(base_key)
        if scene is None:
            scene = load_scene(
                trial.scene,
                options=RenderOptions(contact_mode=trial.contact_mode, approach=approach),
                mesh_dirs=self.mesh_dirs,
            )
            self._cache[base_key] = scene
        for obj, level in trial.textures:
            scene = scene.with_texture_level(level, objects=[obj])
        self._cache[key] = scene
        return scene

    def plan_scene(self, trial: Trial, segment: Segment) -> Scene:
        """Where a segment is planned: the TactDeform version of the trial's scene (faces, edges and
        corners are classified there whatever approach renders it), reduced to the segment's object."""
        scene = self.get(trial, "tactdeform")
        if segment.plan_object is None:
            return scene
        key = ("plan", trial.scene, trial.contact_mode, trial.textures, segment.plan_object)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        specs = [s for s in (scene.specs or ()) if s.name == segment.plan_object]
        if not specs:
            raise ConfigurationError(
                f"scene {trial.scene!r} has no object {segment.plan_object!r} to plan on"
            )
        plan = Scene.from_specs(
            f"{scene.name}:{segment.plan_object}", specs, scene.options, mesh_dirs=self.mesh_dirs
        )
        self._cache[key] = plan
        return plan


def _transit(a: Pose, b: Pose, scene: Scene, rate_hz: float, t0_s: float) -> list[Pose]:
    """Free-space poses from ``a`` to ``b`` (times from ``t0_s``): up to the higher of the two, across,
    then down, so the finger never passes through an object between two surfaces of a trial."""
    pa, pb = np.asarray(a.position_mm, dtype=float), np.asarray(b.position_mm, dtype=float)
    top = max(pa[1], pb[1])
    ways = [pa, np.array((pa[0], top, pa[2])), np.array((pb[0], top, pb[2])), pb]
    lengths = [float(np.linalg.norm(q - p)) for p, q in zip(ways[:-1], ways[1:])]
    total = sum(lengths)
    n = max(2, int(math.ceil(total / TRANSIT_SPEED_MM_S * rate_hz)))
    out: list[Pose] = []
    cum = np.cumsum([0.0, *lengths])
    for i in range(1, n):
        s = total * i / n
        k = min(int(np.searchsorted(cum, s, side="right")) - 1, len(lengths) - 1)
        u = 0.0 if lengths[k] <= 0 else (s - cum[k]) / lengths[k]
        p = ways[k] + u * (ways[k + 1] - ways[k])
        q = slerp(a.orientation, b.orientation, i / n)
        if scene.query(p).signed_distance_mm < 20.0:
            raise ConfigurationError(
                f"the move between two segments passes within 20 mm of a surface at {p.round(1).tolist()}"
            )
        out.append(Pose(t0_s + i / rate_hz, p, q))
    return out


def trial_poses(
    trial: Trial,
    scenes: _Scenes,
    *,
    rate_hz: float,
    seed: int,
    tremor_mm: float = 0.0,
) -> tuple[list[Pose], list[tuple[int, int]]]:
    """The trial's poses from t = 0 (segments joined by free-space moves) and each segment's pose range."""
    poses: list[Pose] = []
    spans: list[tuple[int, int]] = []
    for k, seg in enumerate(trial.segments):
        plan = scene_for_trajectory(seg.trajectory, scenes.plan_scene(trial, seg))
        kw: dict[str, Any] = {
            "rate_hz": rate_hz,
            "seed": seed * 1000 + trial.index * 10 + k,
            "penetration_mm": seg.penetration_mm,
            "start_distance_mm": START_DISTANCE_MM,
            "tremor_mm": tremor_mm,
        }
        if seg.speed_mm_s is not None:
            kw["speed_mm_s"] = seg.speed_mm_s
        part = make_trajectory(seg.trajectory, plan, **kw)
        if poses:
            gap = _transit(poses[-1], part[0], scenes.get(trial), rate_hz, poses[-1].t_s)
            poses.extend(gap)
            t_shift = poses[-1].t_s + 1.0 / rate_hz
        else:
            t_shift = 0.0
        a = len(poses)
        poses.extend(Pose(p.t_s + t_shift, p.position_mm, p.orientation) for p in part)
        spans.append((a, len(poses)))
    return poses, spans


# --- the run -------------------------------------------------------------------------------------------


def _inspectable(device: Any) -> bool:
    """Whether the device's port declares that it can show its board's registers (an emulated board)."""
    return callable(getattr(getattr(device, "port", None), "board_state", None))


@dataclass
class _Live:
    """What every trial of a running study shares: the session, its open device and the tap on its port,
    the simulated clock of an offline run, the renderer's settings, and the session time so far."""

    session: Any
    dev: Any
    tap: WireTap
    sim_clock: Any
    cfg: ManagerConfig
    current_ua: int
    stim: Any
    realtime: bool
    session_t: float = 0.0
    wall_start: float | None = None  # wall clock minus session time, for realtime pacing


def _skip_missing_meshes(study: Study, runs: list[TrialRun], mesh_dirs: Sequence[str]) -> list[str]:
    """A missing mesh skips its trials with a reason instead of failing the study; the study's notes."""
    notes: list[str] = []
    if any(t.scene == "bunny" for t in study.trials):
        try:
            path = find_mesh_file(BUNNY_FILE, mesh_dirs)
            notes.append(f"bunny mesh: {path}")
        except ConfigurationError:
            # the scene's own message names ``--scene``, which a study does not have: say what a study
            # takes (the folders searched, the environment variable)
            where = ", ".join(str(d) for d in mesh_search_dirs(mesh_dirs))
            why = (
                f"mesh {BUNNY_FILE!r} not found (looked in {where}); put it in one of those folders or set "
                f"{MESH_DIR_ENV} to the folder that holds it"
            )
            for r in runs:
                if r.trial.scene == "bunny":
                    r.skipped = f"Stanford bunny not available: {why}"
            notes.append(f"bunny trials skipped: {why}")
    return notes


def _study_current(current_ua: int | None, profile: Any, dev: Any) -> tuple[int, str]:
    """The study's current and where it came from: the option, the participant, the nominal emulator
    current (an emulated board, so delivered charges are reported), else none (patterns only)."""
    if current_ua is not None:
        return int(current_ua), "--current-ua"
    if profile is not None:
        return int(profile.stimulation_ua), f"participant {profile.participant}"
    if _inspectable(dev):
        return NOMINAL_EMULATOR_UA, "nominal emulator current"
    return 0, "none given: patterns only"


def _stim_config(session: Any, current_ua: int) -> Any:
    """The study's stimulation on every channel of the array: the participant's pulse, else TactDeform's
    (200 µs, anodic)."""
    from ..device import StimConfig

    profile = session.profile
    return StimConfig(
        electrode_count=session.wiring.mapping.hw_channels,
        current_ua=current_ua,
        pulse_width_us=profile.pulse_width_us if profile is not None else 200,
        polarity=profile.polarity if profile is not None else "anodic",
    )


def _trial_readback(live: _Live, run: TrialRun) -> Callable[[], tuple[int, ...]] | None:
    """What the trial's renderer compares each sent frame with on an offline (instant) port: the levels
    the board holds, and on v2 every electrode's height too (None on a port that cannot show them)."""
    dev = live.dev
    readback = live.session.readback(dev) if live.sim_clock is not None else None
    run.verified = readback is not None
    if readback is None:
        return None
    from tactdeform_hw.device.driver.readback import heights_readback

    heights = heights_readback(dev, live.session.wiring.mapping)
    return readback if heights is None else _with_heights(readback, heights, dev, run)


def _pace(live: _Live, t_s: float) -> None:
    """Bring the session clock to ``t_s``: wait in real time, or advance the simulated clock."""
    if live.realtime:
        if live.wall_start is None:
            live.wall_start = time.perf_counter() - t_s
        wait = t_s - (time.perf_counter() - live.wall_start)
        if wait > 0:
            time.sleep(wait)
    elif live.sim_clock is not None and t_s > live.sim_clock.now():
        live.sim_clock.advance(t_s - live.sim_clock.now())


def _run_trial(
    live: _Live, run: TrialRun, scenes: _Scenes, *, rate_hz: float, seed: int, tremor_mm: float
) -> None:
    """Render one trial's poses on the live session and keep what it produced on ``run``."""
    from ..ports import board_hazards, board_state

    trial, dev, tap = run.trial, live.dev, live.tap
    t_wall = time.perf_counter()
    scene = scenes.get(trial)
    scene.prepare()
    run.scene = scene
    poses, spans = trial_poses(trial, scenes, rate_hz=rate_hz, seed=seed, tremor_mm=tremor_mm)
    offset = live.session_t
    run.poses = [Pose(p.t_s + offset, p.position_mm, p.orientation) for p in poses]
    run.segment_spans = spans
    run.t0_s = offset
    inspectable = _inspectable(dev)
    readback = _trial_readback(live, run)
    hazards_before = len(board_hazards(dev.port) or ())
    renderer = live.session.renderer(
        scene,
        dev,
        approach=trial.approach,
        config=live.cfg,
        contact_mode=trial.contact_mode,
        current_ua=live.current_ua,
        stim_config=live.stim,
        verify=readback,
    )
    tap.mark(t_s=offset, trial=trial.index, phase="configure")
    renderer.start()
    tap.mark(phase="render")
    validator = PoseValidator()
    for i, pose in enumerate(run.poses):
        _pace(live, pose.t_s)
        tap.mark(t_s=pose.t_s)
        checked = validator.check_pose(pose)
        if checked is None:
            continue
        for rec in renderer.step(checked):
            run.records.append(rec)
            run.record_pose.append(i)
    renderer.summary.teleports = sum(r.stats.teleports for r in renderer.renderers.values())
    run.summary = renderer.summary.as_dict()
    run.tracking_drops = dict(validator.drops)
    run.t1_s = run.poses[-1].t_s if run.poses else offset
    if inspectable:
        mapping = live.session.wiring.mapping
        run.hazards = [h.to_dict() for h in (board_hazards(dev.port) or [])[hazards_before:]]
        state = board_state(dev.port)
        assert state is not None  # inspectable: the port declares board_state()
        hw = state.stim_pattern[: mapping.hw_channels]
        run.end_pattern = list(mapping.to_application(hw))
    run.writes = [w for w in tap.writes if w.trial == trial.index]
    run.wall_s = time.perf_counter() - t_wall
    live.session_t = run.t1_s + INTER_TRIAL_S


def _run_trials(
    live: _Live,
    study: Study,
    runs: list[TrialRun],
    scenes: _Scenes,
    rate_hz: float,
    tremor_mm: float,
    say: ProgressFn,
    on_trial: Callable[[TrialRun], None] | None = None,
) -> None:
    """Every trial in order on the live session, saying how each went (a skipped one says why);
    ``on_trial`` gets each trial as soon as it is done, so an interrupted study keeps what ran."""
    for run in runs:
        trial = run.trial
        head = f"study {study.name}: trial {trial.index}/{len(runs)} {trial.condition}"
        if run.skipped is not None:
            say(f"{head}: skipped ({run.skipped})")
        else:
            _run_trial(live, run, scenes, rate_hz=rate_hz, seed=study.seed, tremor_mm=tremor_mm)
            ok = run.summary.get("mismatches", 0) == 0
            say(
                f"{head}: {len(run.poses)} poses, {run.summary.get('frames_sent', 0)} frames sent"
                f"{'' if ok else ', MISMATCH'} ({run.wall_s:.2f} s)"
            )
        if on_trial is not None:
            on_trial(run)


def _check_rate(rate_hz: Any) -> None:
    """Refuse a tracking rate that is no finite rate above 0 Hz, before any device is opened."""
    if not (isinstance(rate_hz, (int, float)) and math.isfinite(rate_hz) and rate_hz > 0):
        from ..errors import LimitError

        raise LimitError("rate_hz", rate_hz, "a finite rate > 0 Hz")


def _study_session(device: str, timeout: float, firmware: str, guard: Any, audit: Any, profile: Any) -> Any:
    """The session of a study run without one: the TactDeform array on ``device`` under ``guard`` (the
    hardware ceiling without one), writing to ``audit``."""
    from tactdeform_hw.device.safety.guard import SafetyGuard

    from ..session import Session, Wiring

    return Session(
        device=device,
        timeout_s=timeout,
        firmware=firmware,
        wiring=Wiring.tactdeform(),
        guard=guard if guard is not None else SafetyGuard(),
        profile=profile,
        log=audit,
    )


def run_study(
    study: Study,
    *,
    device: str = "emulator",
    timeout: float = 0.5,
    rate_hz: float = 72.0,
    current_ua: int | None = None,
    guard: Any = None,
    audit: Any = None,
    profile: Any = None,
    timed: bool = True,
    tremor_mm: float = 0.0,
    mesh_dirs: Sequence[str] = (),
    progress: ProgressFn | None = None,
    realtime: bool = False,
    firmware: str = "auto",
    session: Any = None,
    on_trial: Callable[[TrialRun], None] | None = None,
    firmware_src: str | None = None,
) -> StudyRun:
    """Run every trial of ``study`` on one device session; return the raw results (:mod:`.checks`).

    ``session`` (a :class:`~tactdeform_hw.session.Session` on the TactDeform array, its delivery log made)
    gives the device, the guard, the participant's profile and the log; without one they come from
    ``device``, ``timeout``, ``firmware``, ``guard`` (the safety guard the device enforces, the hardware
    ceiling without one), ``profile`` and ``audit``.  ``current_ua`` defaults to the participant's
    (``profile.stimulation_ua``), else to :data:`NOMINAL_EMULATOR_UA` on the emulator and 0 (patterns
    only) on a real device.  ``realtime`` paces every pose to the session clock (a real device then shows
    each trial at its real speed); otherwise the run goes as fast as it can, which changes nothing the
    checks look at: the timed replay restores the session's timing (on ``firmware_src``, a tree built on
    this machine, when given).  ``on_trial`` gets each trial done."""
    from ..clock import SimulatedClock

    say = progress or (lambda _msg: None)
    wall0 = time.perf_counter()
    _check_rate(rate_hz)
    if session is None:
        session = _study_session(device, timeout, firmware, guard, audit, profile)
    profile = session.profile
    array = session.wiring.array
    patterns = PatternSet(array)
    scenes = _Scenes(mesh_dirs)
    runs: list[TrialRun] = [TrialRun(t) for t in study.trials]
    notes = _skip_missing_meshes(study, runs, mesh_dirs)
    cfg = ManagerConfig(**study.manager)
    # on a port that answers at once (the in-process emulator) the device's clock (audit log, watchdog) is
    # session time
    dev = session.open_device(offline_clock=None if realtime else SimulatedClock())
    ran = dev.firmware
    tap = WireTap(dev.port, ran)
    dev.port = tap
    try:
        current, source = _study_current(current_ua, profile, dev)
        stim = _stim_config(session, current)
        sim_clock = dev.pacer.clock if isinstance(dev.pacer.clock, SimulatedClock) else None
        live = _Live(session, dev, tap, sim_clock, cfg, current, stim, realtime)
        _run_trials(live, study, runs, scenes, rate_hz, tremor_mm, say, on_trial)
        tap.mark(t_s=live.session_t, trial=0, phase="session")
        if not dev.closed and dev.config is not None:
            dev.all_off()
    finally:
        dev.close()
    result = StudyRun(
        study,
        session.device,
        current,
        source,
        float(rate_hz),
        array,
        patterns,
        runs,
        list(session.guard.electrode_limits(array.count)),
        getattr(profile, "participant", None),
        notes=notes,
        writes=list(tap.writes),
        firmware=ran,
    )
    _replay(result, timed, say, firmware_src)
    result.wall_s = time.perf_counter() - wall0
    return result


def _replay(result: StudyRun, timed: bool, say: ProgressFn, firmware_src: str | None = None) -> None:
    """The timed replay of the study's writes (into ``firmware_src`` built on this machine, when given),
    or the report's note on why there is none."""
    if not timed:
        result.timed_note = "timed replay not run (--no-timed)"
        return
    try:
        say(f"study {result.study.name}: replaying {len(result.writes)} writes into the timed emulator")
        replay_timed(result, firmware_src=firmware_src)
    except TactDeformError as exc:  # the report says why there are no delivered currents
        result.timed_note = f"timed replay failed: {exc}"


def _with_heights(
    levels: Callable[[], tuple[int, ...]], heights: Callable[[], tuple[int, ...]], dev: Any, run: TrialRun
) -> Callable[[], tuple[int, ...]]:
    """The renderer's readback on a v2 board: the levels it compares, and beside them every electrode's
    height on the board against the height the driver put in force (counted on ``run``)."""
    run.heights_checked = 0

    def read() -> tuple[int, ...]:
        got = heights()
        meant = dev.heights_in_force
        assert run.heights_checked is not None
        run.heights_checked += 1
        if meant is None or tuple(meant) != got:
            run.height_mismatches += 1
            if run.first_height_mismatch is None:
                run.first_height_mismatch = {
                    "frame": run.heights_checked,
                    "driver_codes": None if meant is None else list(meant),
                    "board_codes": list(got),
                }
        return levels()

    return read


# --- what the scans delivered --------------------------------------------------------------------------

_STIM_KINDS = (0, 1, 2)  # PulseKind.MONO, BI_ANODIC, BI_CATHODIC
_PULSE_COLUMNS = ("start_us", "channel", "kind", "current_ua", "charge_nc")


def _replay_writes(emu: Any, writes: list[WireWrite]) -> dict[int, float]:
    """Feed the writes to the timed model, each at its session time but at least :data:`PACE_S` after the
    one before, then :data:`TAIL_S` more; the replay time (µs) of each write by its id."""
    at: dict[int, float] = {}
    last = -math.inf
    for w in writes:
        t_us = max(w.t_s * 1e6, last + PACE_S * 1e6)
        last = t_us
        at[id(w)] = t_us
        emu.advance_to(max(emu.now_us, t_us))
        emu.write(w.data, at_us=t_us)
    emu.advance_to(last + TAIL_S * 1e6)
    return at


@dataclass
class _TimedAccount:
    """What the timed model recorded over the session: the pulse table of a time window, the scan starts
    of torn patterns (per run of scans), the losses and the other hazards."""

    pulse_table: Callable[[float, float], dict[str, np.ndarray]]
    torn_runs: list[Any]
    losses: list[Any]
    hazards: list[Any]


def _account_v2(emu: Any, result: StudyRun) -> _TimedAccount:
    """v2 records every scan (a torn pattern is one hazard per scan it tore, with its time): the hazard
    list and the model's loss reports are the whole account."""
    return _account_of_pulses(emu, result, {"firmware": V2.name, "scans": int(emu.scan_count)})


def _account_of_pulses(emu: Any, result: StudyRun, summary: dict[str, Any]) -> _TimedAccount:
    """The account of a model whose pulse table, hazard list and loss reports say it all (``summary``:
    the report's first fields)."""
    pulses = emu.reports.pulse_table()  # once; each trial takes its window of it
    hazards = list(emu.hazards)
    result.timed = True
    result.timed_summary = {
        **summary,
        "pulses": int(pulses["channel"].size),
        "hazards": dict(sorted(Counter(h.kind.value for h in hazards).items())),
    }

    def pulse_table(lo_us: float, hi_us: float) -> dict[str, np.ndarray]:
        sel = (pulses["start_us"] >= lo_us) & (pulses["start_us"] < hi_us)
        return {k: v[sel] for k, v in pulses.items()}

    return _TimedAccount(pulse_table, [], list(emu.losses), hazards)


def _host_build(firmware_src: str, ran: str, link: str) -> Any:
    """The firmware tree built on this machine, as the replay's timed model: it must speak the version
    the session ran."""
    from tactdeform_hw.emulator.hostbuild.timed import HostBuildTimedModel

    emu = HostBuildTimedModel(firmware_src, link=link)
    declared = emu.firmware.name if emu.firmware is not None else None
    if declared != ran:
        raise ConfigurationError(
            f"--firmware-src {firmware_src}: its state map declares firmware {declared or 'none'}, "
            f"the session ran {ran}"
        )
    return emu


def _account_host_build(emu: Any, result: StudyRun) -> _TimedAccount:
    """A host build records the pulses its firmware delivered and the receive queue's losses; firmware
    defects (torn patterns, overruns) are the Python models' reading of the code and are not recorded."""
    source = {"firmware": result.firmware, "firmware_src": str(emu.firmware_src)}
    return _account_of_pulses(emu, result, source)


def _account_v1_2(emu: Any, result: StudyRun) -> _TimedAccount:
    """Overruns, queue overflows and watchdog resets are in the hazard list; torn scans and lost bytes
    are taken from the scan runs and the loss reports (per-cycle reports would be tens of thousands): a
    torn_pattern record covers a stretch of cycles, each trial gets the torn scans inside its window."""
    from tactdeform_hw.emulator.firmware.hazards import HazardKind

    reports = emu.reports
    torn_runs = [r.starts_ns() / 1000.0 for r in reports.runs if r.torn is not None]
    losses = list(emu.losses)
    hazards = [h for h in emu.hazards if h.kind is not HazardKind.TORN_PATTERN]
    result.timed = True
    summary = reports.summary()
    # The model's assumptions are the timing command's business; a pattern's "latency" to its first
    # pulse is unbounded for an all-off frame, so the maximum says nothing about the session here.
    for key in ("model_assumptions", "latency_us_max", "now_us"):
        summary.pop(key, None)
    result.timed_summary = summary
    return _TimedAccount(reports.pulse_table, torn_runs, losses, hazards)


def _delivered(
    sel: dict[str, np.ndarray], hw_to_app: dict[int, int], count: int, v2: bool, lo_us: float, hi_us: float
) -> dict[str, Any]:
    """One trial's ``delivered`` block from the pulses of its window: per electrode the pulses, the
    charge and the largest current (on v2 the heights too), and the session's maxima."""
    stim = np.isin(sel["kind"], _STIM_KINDS)
    live = stim & (sel["current_ua"] > 0)
    per_charge = [0.0] * count
    per_pulses = [0] * count
    per_max = [0.0] * count
    per_heights: list[set[float]] = [set() for _ in range(count)]
    unmapped = 0
    for ch, ua, q in zip(
        sel["channel"][stim].tolist(), sel["current_ua"][stim].tolist(), sel["charge_nc"][stim].tolist()
    ):
        app = hw_to_app.get(int(ch))
        if app is None:
            unmapped += 1
            continue
        per_pulses[app] += 1
        per_charge[app] += float(q)
        per_max[app] = max(per_max[app], float(ua))
        if v2 and ua > 0:
            per_heights[app].add(round(float(ua), 1))
    sense_live = int(np.sum(~stim & (sel["current_ua"] > 0)))
    per_electrode: dict[str, Any] = {
        "pulses": per_pulses,
        "charge_nc": [round(v, 1) for v in per_charge],
        "max_current_ua": [round(v, 1) for v in per_max],
    }
    if v2:
        # each electrode's own pulse heights: on v2 every pattern element is a height
        per_electrode["heights_ua"] = [sorted(h) for h in per_heights]
    return {
        "window_s": [round(lo_us / 1e6, 6), round(hi_us / 1e6, 6)],
        "stimulation_pulses": int(stim.sum()),
        "pulses_with_current": int(live.sum()),
        "sense_pulses_with_current": sense_live,
        "pulses_on_unmapped_channels": unmapped,
        "max_current_ua": round(float(sel["current_ua"][stim].max()), 1) if stim.any() else 0.0,
        "max_charge_per_pulse_nc": round(float(sel["charge_nc"][stim].max()), 3) if stim.any() else 0.0,
        "total_charge_nc": round(float(sel["charge_nc"][stim].sum()), 1),
        "per_electrode": per_electrode,
        "_table": sel,
    }


def _hazards_in(
    account: _TimedAccount,
    writes: list[WireWrite],
    offsets: list[int],
    trial: int,
    lo_us: float,
    hi_us: float,
) -> list[dict[str, Any]]:
    """The timing hazards of one trial's window: torn scans, losses, and the model's hazards (a parser
    hazard belongs to the trial whose write holds its byte)."""
    found: list[dict[str, Any]] = []
    for scan_starts in account.torn_runs:
        for s_us in scan_starts[(scan_starts >= lo_us) & (scan_starts < hi_us)].tolist():
            found.append({"kind": "torn_pattern", "time_us": s_us})
    for lo in account.losses:
        if lo_us <= lo.time_us < hi_us:
            found.append({"kind": "loss", "time_us": lo.time_us, "count": lo.count, "reason": lo.reason})
    for h in account.hazards:
        if h.time_us is not None:
            mine = lo_us <= h.time_us < hi_us
        else:  # a parser hazard: the write that holds its byte says which trial caused it
            k = bisect_right(offsets, h.offset) - 1
            mine = 0 <= k < len(writes) and writes[k].trial == trial
        if mine:
            found.append(h.to_dict())
    return found


def replay_timed(result: StudyRun, *, link: str = "usb", firmware_src: str | None = None) -> None:
    """Replay the session's writes into the timed model of the firmware that ran (``firmware_src``: into
    that firmware tree built on this machine, which must declare the version that ran) and attach, per
    trial, the pulses delivered (per electrode: pulses, largest current, charge; on v2 also the heights
    each electrode was pulsed at), the timing hazards in the trial's window and the replay time of each
    write."""
    from tactdeform_hw.emulator.firmware.models import model_entry

    writes = result.writes
    if not writes:
        result.timed_note = "nothing was written"
        return
    v2 = result.firmware == V2.name
    if firmware_src is not None:
        emu: Any = _host_build(firmware_src, result.firmware, link)
    else:
        emu = model_entry(result.firmware).timed(link=link)
    at = _replay_writes(emu, writes)
    offsets = [0]
    for w in writes[:-1]:
        offsets.append(offsets[-1] + len(w.data))
    mapping = result.array.channel_mapping()
    hw_to_app = {ch: i for i, ch in enumerate(mapping.app_to_hw)}
    if firmware_src is not None:
        account = _account_host_build(emu, result)
    else:
        account = _account_v2(emu, result) if v2 else _account_v1_2(emu, result)
    for run in result.trials:
        if run.skipped is not None or not run.writes:
            continue
        run.replay_us = [at[id(w)] for w in run.writes]
        lo_us = run.replay_us[0]
        hi_us = max(run.t1_s * 1e6, run.replay_us[-1]) + 20_000.0
        # One window per trial, and only the columns the checks use: a study is millions of pulses.
        window = account.pulse_table(lo_us, hi_us)
        sel = {k: window[k] for k in _PULSE_COLUMNS}
        del window
        run.delivered = _delivered(sel, hw_to_app, result.array.count, v2, lo_us, hi_us)
        run.timed_hazards = _hazards_in(account, writes, offsets, run.trial.index, lo_us, hi_us)


def frame_heights(
    run: TrialRun, array: ElectrodeArray
) -> list[tuple[float, tuple[int, ...], tuple[float, ...], str]]:
    """Firmware v2: the frames the host put on the wire during a trial, decoded from the captured writes
    with the v2 table — replay time (µs), levels (0 off, else the waveform of the mode the frame runs in: 1
    monophasic, 2 biphasic), each electrode's height in µA, phase — in application order.  A pattern
    written under the driver's cover (mode 2 before it, the frame's mode right after it in the same write)
    runs in the mode that follows it; an all-zero pattern written just before a change of mode is part of
    that change, not a frame."""
    from ..protocol.reader import iter_commands
    from ..protocol.units import DEFAULT_TRANSFER

    mapping = array.channel_mapping()
    times = run.replay_us or [w.t_s * 1e6 for w in run.writes]
    n = mapping.hw_channels
    reads = [
        [c for c in iter_commands(w.data, n, V2) if c.opcode is not None] for w in run.writes
    ]  # every command of every write, as the firmware reads them
    mode = 0
    out: list[tuple[float, tuple[int, ...], tuple[float, ...], str]] = []
    for k, (w, t_us, cmds) in enumerate(zip(run.writes, times, reads)):
        for i, c in enumerate(cmds):
            if c.opcode == OpcodeV2.STIM_MODE and c.value is not None:
                mode = c.value
                continue
            if c.opcode != OpcodeV2.PATTERN or c.levels is None or len(c.levels) < n:
                continue
            frame_mode = mode
            if i + 1 < len(cmds):  # under the cover: the frame runs in the mode written right after it
                nxt = cmds[i + 1]
                if nxt.opcode == OpcodeV2.STIM_MODE and nxt.value is not None:
                    frame_mode = nxt.value
            elif not any(c.levels) and k + 1 < len(reads) and reads[k + 1]:
                if reads[k + 1][0].opcode == OpcodeV2.STIM_MODE:
                    continue  # the zero pattern before a change of mode, in a write of its own
            codes = mapping.to_application(list(c.levels[:n]))
            on = 2 if frame_mode == 1 else 1
            levels = tuple(on if code else 0 for code in codes)
            top = V2.dac_max_code
            heights = tuple(float(DEFAULT_TRANSFER.to_ua(min(int(code), top))) for code in codes)
            out.append((t_us, levels, heights, w.phase))
    return out


def frame_intents(run: TrialRun, array: ElectrodeArray) -> list[tuple[float, tuple[int, ...], str]]:
    """The patterns the host put on the wire during a trial, in application order, with their replay
    time (µs) and phase, decoded from the captured writes (with the table of the firmware that ran)."""
    if run.writes and run.writes[0].firmware == V2.name:
        return [(t, levels, phase) for t, levels, _h, phase in frame_heights(run, array)]
    mapping = array.channel_mapping()
    out = []
    for w, t_us in zip(run.writes, run.replay_us or [w.t_s * 1e6 for w in run.writes]):
        if w.opcode == Opcode.PATTERN:
            hw = w.data[1 : 1 + mapping.hw_channels]
            if len(hw) == mapping.hw_channels:
                out.append((t_us, tuple(mapping.to_application(hw)), w.phase))
    return out


__all__ = [
    "INTER_TRIAL_S",
    "NOMINAL_EMULATOR_UA",
    "PACE_S",
    "StudyRun",
    "TrialRun",
    "WireTap",
    "WireWrite",
    "frame_heights",
    "frame_intents",
    "replay_timed",
    "run_study",
    "trial_poses",
]
