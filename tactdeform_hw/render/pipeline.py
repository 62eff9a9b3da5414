"""Poses in, device commands out: scene query → pattern manager (or a baseline) → :class:`Device`.

The renderer configures the device once, then sends a pattern only when it differs from the one the
device holds, so a finger resting on an object costs no serial traffic.  It speaks only the
:class:`~tactdeform_hw.device.driver.base.Device` interface — application-order levels — and never bytes.

Every tracking sample yields at least one :class:`FrameRecord`; a sample whose update passed several
expansion or texture frames yields one record per frame (each sent), so the records are exactly the
device's pattern history.

Lost tracking.  A dropped sample (NaN or infinite pose, a time that does not advance, a garbage
quaternion) is recorded but is not a frame: it changes nothing and does *not* feed the device's fail-safe
watchdog, so a tracker that only delivers garbage lets the watchdog switch stimulation off.  A sample's
time is judged against the last sample *received*, dropped ones included, and that time is never
forgotten: a clock that keeps running backwards, or stands still, never yields a valid sample again.

Tracking is lost when no valid sample came for ``lost_tracking_s`` (default :data:`LOST_TRACKING_S`,
80 ms; the time is read from the dropped samples' own clock when it is usable — finite and not behind the
last valid sample — otherwise counted as dropped samples times the tracking period seen so far), or at
once when the clock has stepped back: a sample later than the one before it but not later than the last
one rendered belongs to another clock, and the finger's history cannot be continued.  Then every approach
is reset and all electrodes are switched off, and stimulation resumes only after
``resume_after_valid_samples`` (default :data:`RESUME_AFTER_VALID_SAMPLES`) consecutive valid samples,
each later than the one before: the last of them is the first rendered, by approaches that start afresh.
The samples held back meanwhile are recorded (all off, not sent) and never feed the watchdog.  The run is
asked for only after a loss: a stream's first sample is rendered at once, as before (the device starts
all off and the pattern manager confirms a contact before it stimulates).
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tactdeform_hw.device.driver.base import Device
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.readback import pattern_readback

from ..errors import ConfigurationError, LimitError
from .approach import Approach, make_approach
from .array import ElectrodeArray
from .contexts import TEXTURE_NAMES
from .manager import ManagerConfig, ManagerOutput, check_pose
from .patterns import Pattern, PatternParams

#: Time without a valid tracking sample after which the renderer goes Idle (all off): 80 ms, so that
#: with the next sample (14 ms later at 72 Hz) the all-off is sent before the device's 100 ms no-frame
#: watchdog would switch stimulation off by itself (which it does anyway: dropped samples send nothing).
LOST_TRACKING_S = 0.08

#: Consecutive valid samples, each later than the one before, that a lost stream must deliver before
#: stimulation resumes; the last of them is the first rendered.  Counted in samples, not read from the
#: samples' clock: the clock of a stream that just failed is the thing on trial, and one sample stamped far
#: ahead would satisfy any duration.  6 samples are 69 ms of steady tracking at 72 Hz (83 ms with the sample
#: that ends it), as long as it took to declare the loss; a stream that fails once in every 6 samples or
#: more often never resumes.  At 1 kHz the run is 6 ms: a fast tracker proves itself faster.
RESUME_AFTER_VALID_SAMPLES = 6


@dataclass(slots=True)
class FrameRecord:
    """One pattern the device held (or kept holding) at time ``t_s``."""

    t_s: float
    state: str
    feature: str | None
    texture: int | None
    electrodes: Pattern
    sent: bool
    approach: str = "tactdeform"
    context: str | None = None
    orientation: str | None = None
    interpolated: bool = False
    dropped: str | None = None

    def to_json(self) -> dict[str, Any]:
        """The frames-file line: ``t``, ``state``, ``feature``, ``texture``, ``electrodes``, ``sent``."""
        tex = self.texture
        return {
            "t": self.t_s if math.isfinite(self.t_s) else None,
            "state": self.state,
            "feature": self.feature,
            "texture": None
            if tex is None
            else (TEXTURE_NAMES[tex] if 0 <= tex < len(TEXTURE_NAMES) else tex),
            "electrodes": [1 if v else 0 for v in self.electrodes],
            "sent": self.sent,
        }


#: Called before each frame is sent; returns a current in µA to apply first, or None to keep the
#: present one.  This is where participant safety profiles and calibrated regional levels plug in.
CurrentHook = Callable[[FrameRecord], "int | None"]

#: Told of every frame sent to the device, with the ``time.monotonic()`` just before the device was
#: asked to send it and just after the bytes were written: a live run's latency stages.
DeliverHook = Callable[[FrameRecord, float, float], None]


@dataclass
class RunSummary:
    """What a run did.  ``dropped`` counts invalid samples by reason (``time``, ``time-backwards``,
    ``time-repeated``, ``position``, ``orientation``, ``orientation-norm``, ``query``); ``lost_tracking``
    the times tracking was lost (all off, approaches reset); ``held_resuming`` the valid samples held back
    after a loss before stimulation resumed."""

    poses: int = 0
    records: int = 0
    frames_sent: int = 0
    interpolated: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    teleports: int = 0
    states: dict[str, int] = field(default_factory=dict)
    mismatches: int = 0
    first_mismatch: dict[str, Any] | None = None
    lost_tracking: int = 0
    held_resuming: int = 0
    step_us: list[float] = field(default_factory=list, repr=False)

    def as_dict(self) -> dict[str, Any]:
        us = sorted(self.step_us)
        return {
            "poses": self.poses,
            "records": self.records,
            "frames_sent": self.frames_sent,
            "interpolated": self.interpolated,
            "dropped": dict(self.dropped),
            "teleports": self.teleports,
            "states": dict(self.states),
            "mismatches": self.mismatches,
            "first_mismatch": self.first_mismatch,
            "lost_tracking": self.lost_tracking,
            "held_resuming": self.held_resuming,
            "step_us_median": round(statistics.median(us), 2) if us else None,
            "step_us_p99": round(us[min(len(us) - 1, int(0.99 * len(us)))], 2) if us else None,
        }


def _scene_flag(scene: Any, name: str, default: Any) -> Any:
    needs = getattr(scene, "needs", None)
    if needs is not None and hasattr(needs, name):
        return getattr(needs, name)
    return default


def _scene_config(scene: Any, config: ManagerConfig | None, contact_mode: str | None) -> ManagerConfig:
    """The manager's settings for ``scene``: the contact mode given (else the scene's), and no texture
    machinery on an all-smooth scene."""
    cfg = config or ManagerConfig()
    mode = contact_mode if contact_mode is not None else _scene_option(scene, "contact_mode")
    overrides: dict[str, Any] = {}
    if mode is not None and mode != cfg.contact_mode:
        overrides["contact_mode"] = mode
    if not _scene_flag(scene, "needs_texture", True) and cfg.use_texture:
        overrides["use_texture"] = False
    if overrides:
        from dataclasses import replace

        cfg = replace(cfg, **overrides)
    return cfg


def _scene_option(scene: Any, name: str) -> Any:
    for holder in (getattr(scene, "options", None), getattr(scene, "render", None), scene):
        if holder is not None and hasattr(holder, name):
            return getattr(holder, name)
    return None


def _unsent(out: ManagerOutput, approach: str) -> FrameRecord:
    """The record of an update that sent nothing: what is shown, as the approach decided it."""
    return FrameRecord(
        out.t_s,
        out.state,
        out.feature,
        out.texture,
        out.pattern,
        False,
        approach,
        out.context,
        out.orientation,
        False,
        out.dropped,
    )


class Renderer:
    """Drives one device from a pose stream over one scene.

    ``approach`` is ``"tactdeform"``, ``"ua"`` or ``"cam"`` for the whole run, a mapping from object
    name to one of them (``"*"`` the default) to compare approaches per object, or None to take the
    scene's (its options' approach and any per-object overrides; TactDeform for a bare object).
    ``contact_mode`` (the participant's choice in Task 2) overrides the scene's render option; ``current_ua``
    is the participant's calibrated level, set by ``configure``; ``current_hook`` may change it per frame.
    ``verify`` is a callback returning the pattern the device holds, in application order (for example
    :func:`~tactdeform_hw.device.driver.readback.pattern_readback`); after every sent frame its answer is
    compared with the frame and mismatches are counted.  ``verify=True`` asks the device's port for that
    read-back (a port that declares ``board_state()``, such as the emulator's) and verifies nothing on a
    port that cannot show its pattern.
    ``lost_tracking_s`` and ``resume_after_valid_samples`` are the lost-tracking rules (see the module
    docstring): how long without a valid sample before all is switched off, and how many consecutive valid
    samples a lost stream must then deliver before stimulation resumes.
    """

    def __init__(
        self,
        scene: Any,
        device: Device | None = None,
        *,
        array: ElectrodeArray | None = None,
        approach: str | Mapping[str, str] | None = None,
        config: ManagerConfig | None = None,
        pattern_params: PatternParams | None = None,
        contact_mode: str | None = None,
        current_ua: int = 0,
        stim_config: StimConfig | None = None,
        current_hook: CurrentHook | None = None,
        verify: bool | Callable[[], Sequence[int]] | None = False,
        lost_tracking_s: float = LOST_TRACKING_S,
        resume_after_valid_samples: int = RESUME_AFTER_VALID_SAMPLES,
    ) -> None:
        if not (math.isfinite(lost_tracking_s) and lost_tracking_s > 0.0):
            raise LimitError("lost_tracking_s", lost_tracking_s, "a finite time > 0 s")
        if (
            isinstance(resume_after_valid_samples, bool)
            or not isinstance(resume_after_valid_samples, int)
            or resume_after_valid_samples < 1
        ):
            raise LimitError(
                "resume_after_valid_samples", resume_after_valid_samples, "a whole number of samples ≥ 1"
            )
        self.lost_tracking_s = lost_tracking_s
        self.resume_after_valid_samples = resume_after_valid_samples
        self._last_valid_t: float | None = None
        # The time of the last sample received, dropped ones included; never reset, so a clock that keeps
        # going back or stands still is judged against what it said last, however long ago tracking was lost.
        self._last_received_t: float | None = None
        self._lost = False  # tracking lost: nothing is rendered until the run of valid samples
        self._resume_run = 0
        self._period_s = 1.0 / 72.0
        self._invalid_run = 0
        self.lost_tracking_events = 0
        self.scene = scene
        self.device = device
        self.array = array if array is not None else ElectrodeArray.tactdeform()
        self._scene_approach: Callable[[str], str] | None = None
        self.approach_map: dict[str, str] = self._approaches(scene, approach)
        self.config = cfg = _scene_config(scene, config, contact_mode)
        self.renderers: dict[str, Approach] = {
            a: make_approach(a, self.array, cfg, pattern_params) for a in set(self.approach_map.values())
        }
        self.current_ua = current_ua
        self.stim_config = stim_config
        self.current_hook = current_hook
        self.verify = verify
        self.summary = RunSummary()
        self._device_pattern: Pattern | None = None
        self._mapping = self.array.channel_mapping()
        self._readback: Callable[[], Sequence[int]] | None = None
        self._started = False
        self._dwell_s = 0.0
        #: see :data:`DeliverHook`; None: nothing is timed
        self.deliver_hook: DeliverHook | None = None

    def _approaches(self, scene: Any, approach: str | Mapping[str, str] | None) -> dict[str, str]:
        """The approach of each object (``"*"``: every other): the one given, else the scene's, per object
        (a description's ``approach`` keys) or for the run."""
        if isinstance(approach, str):
            return {"*": approach}
        if approach is not None:
            given = dict(approach)
            given.setdefault("*", "tactdeform")
            return given
        default = getattr(getattr(scene, "options", None), "approach", None) or "tactdeform"
        chosen = {"*": default}
        per_object = getattr(scene, "approach_for", None)
        if callable(per_object):
            self._scene_approach = per_object
            for obj in getattr(scene, "objects", ()):
                chosen[obj.name] = per_object(obj.name)
        return chosen

    # --- device ---------------------------------------------------------------------------------------------

    def start(self) -> None:
        """Configure the device once (electrode count, pulse shape, current) — all channels off."""
        if self._started:
            return
        self._started = True
        dev = self.device
        if dev is None:
            return
        if dev.mapping is not None and dev.mapping != self._mapping:
            raise ConfigurationError(
                f"the device's channel mapping {dev.mapping.app_to_hw} differs from the array's "
                f"{self._mapping.app_to_hw}; open the device with mapping=array.channel_mapping()"
            )
        if dev.mapping is None and self._mapping.app_to_hw != tuple(range(self._mapping.hw_channels)):
            raise ConfigurationError(
                f"array {self.array.name!r} maps electrodes to hardware channels {self._mapping.app_to_hw} "
                "but the device has no mapping; open the device with mapping=array.channel_mapping()"
            )
        cfg = self.stim_config or StimConfig(
            electrode_count=self._mapping.hw_channels, current_ua=self.current_ua
        )
        dev.configure(cfg)
        self._device_pattern = (0,) * self.array.count
        if callable(self.verify):
            self._readback = self.verify
        elif self.verify:
            self._readback = pattern_readback(dev, self._mapping)

    def close(self) -> None:
        if self.device is not None and not self.device.closed:
            self.device.all_off()

    def __enter__(self) -> Renderer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- per sample -----------------------------------------------------------------------------------------

    def approach_for(self, query: Any) -> str:
        name = getattr(query, "object_name", None)
        if name is None:
            return self.approach_map["*"]
        hit = self.approach_map.get(name)
        if hit is None:
            hit = self._scene_approach(name) if self._scene_approach is not None else self.approach_map["*"]
            if hit not in self.renderers:
                raise LimitError(f"approach[{name}]", hit, "'tactdeform', 'ua' or 'cam'")
            self.approach_map[name] = hit
        return hit

    def step(self, pose: Any) -> list[FrameRecord]:
        """Render one tracking sample: ``pose`` has ``t_s``, ``position_mm`` and ``orientation`` (w, x, y, z),
        or is a ``(t_s, position_mm, orientation)`` tuple."""
        if not self._started:
            self.start()
        t0 = time.perf_counter()
        if isinstance(pose, tuple):
            t_s, pos, quat = pose
        else:
            t_s, pos, quat = pose.t_s, pose.position_mm, pose.orientation
        query = self._query(pos)
        active = self.approach_for(query)
        records: list[FrameRecord] = []
        reason = self._judge_time(t_s)
        if reason is None and self._last_valid_t is not None and float(t_s) <= self._last_valid_t:
            # Later than the sample before (which went back), not later than the last one rendered: the
            # clock has stepped back, and the finger's history belongs to another clock.
            records.append(self._lose(float(t_s), active))
        if reason is None and self._lost:
            reason = self._resuming(t_s, pos, quat)
        out: ManagerOutput | None = None
        if reason is None:
            for name, r in self.renderers.items():
                o = r.update(t_s, pos, quat, query, self.scene)
                if name == active:
                    out = o
        elif reason != "resuming":
            # Judged here, never shown to the approaches: after a reset they would take it as a new start.
            for name, r in self.renderers.items():
                o = r.drop(t_s, reason)
                if name == active:
                    out = o
        s = self.summary
        if out is None:
            records.append(
                FrameRecord(
                    float(t_s),
                    "idle",
                    None,
                    None,
                    (0,) * self.array.count,
                    False,
                    approach=active,
                    dropped="resuming",
                )
            )
            s.held_resuming += 1
            state = "idle"
        else:
            if out.dropped:
                records += self._dropped(out, active)
            else:
                self._valid(out.t_s)
                records += self._send(out, active)
            state = out.state
            if out.dropped:
                s.dropped[out.dropped] = s.dropped.get(out.dropped, 0) + 1
        s.step_us.append((time.perf_counter() - t0) * 1e6)
        s.poses += 1
        s.records += len(records)
        s.states[state] = s.states.get(state, 0) + 1
        return records

    def _judge_time(self, t_s: Any) -> str | None:
        """Why the sample's time is unusable (``time``, ``time-backwards``, ``time-repeated``), or None.
        Judged against the last sample received, dropped ones included, whose time is then this one's."""
        try:
            t = float(t_s)
        except (TypeError, ValueError):
            return "time"
        if not math.isfinite(t):
            return "time"
        last = self._last_received_t
        self._last_received_t = t
        if last is None or t > last:
            return None
        return "time-backwards" if t < last else "time-repeated"

    def _resuming(self, t_s: Any, pos: Any, quat: Any) -> str | None:
        """Tracking is lost and the sample's time advances: the reason it is invalid, ``"resuming"`` while
        the run of valid samples is still short, or None for the sample that completes it (rendered, by
        approaches that were reset at the loss)."""
        checked = check_pose(t_s, pos, quat, None, self.config.quat_norm_tolerance)
        if isinstance(checked, str):
            return checked
        self._resume_run += 1
        if self._resume_run < self.resume_after_valid_samples:
            return "resuming"
        self._lost = False
        self._resume_run = 0
        return None

    def _query(self, pos: Any) -> Any:
        try:
            p = np.asarray(pos, dtype=float)
        except (TypeError, ValueError):
            return None
        # three plain floats are checked ~10x faster than a numpy reduction over three elements
        if p.shape != (3,) or not all(map(math.isfinite, p.tolist())):
            return None
        return self.scene.query(p)

    def _valid(self, t: float) -> None:
        last = self._last_valid_t
        if last is not None and t > last:
            # The tracking period, smoothed; bounded so one long pause does not stretch the timeout.
            dt = min(t - last, self.lost_tracking_s)
            self._period_s += 0.1 * (dt - self._period_s)
        self._last_valid_t = t
        self._invalid_run = 0

    def _dropped(self, out: ManagerOutput, approach: str) -> list[FrameRecord]:
        """A dropped sample: recorded, never sent, never a keepalive; tracking is lost once no valid sample
        came for ``lost_tracking_s``, and a lost stream's run of valid samples starts again."""
        rec = _unsent(out, approach)
        if self._lost:
            self._resume_run = 0
            return [rec]
        self._invalid_run += 1
        gone = self._invalid_run * self._period_s
        last = self._last_valid_t
        t = out.t_s
        if last is not None and math.isfinite(t) and t >= last:
            gone = max(gone, t - last)
        if gone < self.lost_tracking_s:
            return [rec]
        return [self._lose(out.t_s, approach)]

    def _lose(self, t_s: float, approach: str) -> FrameRecord:
        """Tracking lost: forget the finger everywhere, switch everything off, and hold stimulation back
        until ``resume_after_valid_samples`` valid samples in a row."""
        self.lost_tracking_events += 1
        self.summary.lost_tracking += 1
        for r in self.renderers.values():
            r.reset()
        self._last_valid_t = None
        self._invalid_run = 0
        self._lost = True
        self._resume_run = 0
        off = (0,) * self.array.count
        rec = FrameRecord(t_s, "idle", None, None, off, True, approach, None, None, False, "lost-tracking")
        if off == self._device_pattern:
            rec.sent = False
        else:
            self._deliver(rec)
        return rec

    def lose_tracking(self) -> FrameRecord | None:
        """The stream has stopped (a live source that heard no valid sample for ``lost_tracking_s``): the
        same as a loss the samples show — every approach reset, all off now, and stimulation back only
        after ``resume_after_valid_samples`` valid samples.  None when tracking is already lost (nothing to
        switch off twice).  The all-off record carries the last time a sample was received."""
        if not self._started:
            self.start()
        if self._lost:
            return None
        t = self._last_received_t if self._last_received_t is not None else 0.0
        return self._lose(t, self.approach_map["*"])

    def _send(self, out: ManagerOutput, approach: str) -> list[FrameRecord]:
        frames = out.frames
        # A change of approach (per-object runs) or a device holding something else: send what is shown.
        if not frames and self._device_pattern is not None and out.pattern != self._device_pattern:
            frames = [(out.t_s, out.pattern)]
        records: list[FrameRecord] = []
        if not frames:
            records.append(_unsent(out, approach))
            if self.device is not None:
                # Nothing changed, but the renderer is alive: feed the device's fail-safe watchdog so a
                # held contact is not switched off, while a dead renderer still is.
                self.device.keepalive()
            return records
        last = len(frames) - 1
        for i, (tf, pat) in enumerate(frames):
            rec = FrameRecord(
                tf,
                out.state,
                out.feature,
                out.texture,
                pat,
                True,
                approach,
                out.context,
                out.orientation,
                i < last,
                out.dropped,
            )
            if pat == self._device_pattern:
                rec.sent = False
            else:
                self._deliver(rec)
            records.append(rec)
        return records

    def _deliver(self, rec: FrameRecord) -> None:
        dev = self.device
        if dev is None:
            self._device_pattern = rec.electrodes
            self.summary.frames_sent += 1
            self.summary.interpolated += int(rec.interpolated)
            return
        if self.current_hook is not None:
            want = self.current_hook(rec)
            if want is not None and want != dev.current_ua:
                dev.set_current(int(want))
        hook = self.deliver_hook
        before = time.monotonic() if hook is not None else 0.0
        dev.send_pattern(rec.electrodes)
        if hook is not None:
            hook(rec, before, time.monotonic())
        if rec.interpolated and self._dwell_s > 0.0:
            time.sleep(self._dwell_s)
        self._device_pattern = rec.electrodes
        self.summary.frames_sent += 1
        self.summary.interpolated += int(rec.interpolated)
        if self._readback is not None:
            got = tuple(self._readback())
            if got != tuple(rec.electrodes):
                self.summary.mismatches += 1
                if self.summary.first_mismatch is None:
                    self.summary.first_mismatch = {
                        "t": rec.t_s,
                        "sent": list(rec.electrodes),
                        "emulator": list(got),
                    }

    # --- whole runs -----------------------------------------------------------------------------------------

    def run(
        self,
        poses: Iterable[Any],
        *,
        on_record: Callable[[FrameRecord], None] | None = None,
        progress: Callable[[int, RunSummary], None] | None = None,
        progress_every: int = 1000,
        realtime: bool = False,
        min_dwell_s: float = 1.0 / 125.0,
    ) -> RunSummary:
        """Render a whole pose stream.

        ``realtime`` paces the stream to the poses' clock and holds every interpolated frame for
        ``min_dwell_s`` (one stimulation period at 125 Hz: a pattern held for less is never scanned out)
        before the next; otherwise the stream runs as fast as it can (CI, offline studies)."""
        self.start()
        self._dwell_s = min_dwell_s if realtime else 0.0
        wall0 = time.perf_counter()
        # An offline run on a device whose pacing clock is simulated follows the trajectory's clock, so
        # the audit log and the fail-safe watchdog see session time, not how fast the host computed.
        clock = getattr(getattr(self.device, "pacer", None), "clock", None)
        session_clock = None if realtime or not callable(getattr(clock, "advance", None)) else clock
        clock0 = session_clock.now() if session_clock is not None else 0.0
        arrival = _Arrival()
        for i, pose in enumerate(poses):
            t = pose[0] if isinstance(pose, tuple) else pose.t_s
            due = arrival.due(t, self._period_s)
            if due is not None and arrival.first:
                wall0 = time.perf_counter()
            if due is not None:
                if realtime:
                    delay = due - (time.perf_counter() - wall0)
                    if delay > 0:
                        time.sleep(delay)
                elif session_clock is not None:
                    ahead = clock0 + due - session_clock.now()
                    if ahead > 0:
                        session_clock.advance(ahead)
            for rec in self.step(pose):
                if on_record is not None:
                    on_record(rec)
            if progress is not None and (i + 1) % progress_every == 0:
                progress(i + 1, self.summary)
        self.summary.teleports = sum(r.stats.teleports for r in self.renderers.values())
        return self.summary


class _Arrival:
    """When each sample of a replayed stream arrives, in seconds after the first sample with a usable time:
    on its own clock while that advances, one tracking period after the sample before when it does not (a
    clock that stands still or runs backwards still delivers at the tracker's rate, and the watchdog must
    see that time pass).  Samples before the first usable time are not paced."""

    def __init__(self) -> None:
        self.first = False
        self._anchor_t: float | None = None
        self._anchor_due = 0.0
        self._due = 0.0
        self._last_t: float | None = None

    def due(self, t_s: Any, period_s: float) -> float | None:
        try:
            t = float(t_s)
        except (TypeError, ValueError):
            t = math.nan
        finite = math.isfinite(t)
        self.first = False
        if self._anchor_t is None or self._last_t is None:
            if not finite:
                return None
            self.first = True
            self._anchor_t = self._last_t = t
            return 0.0
        if finite and t > self._last_t:
            due = self._anchor_due + (t - self._anchor_t)
        else:
            due = self._due + period_s
            if finite:  # its clock goes on from here
                self._anchor_t, self._anchor_due = t, due
        if finite:
            self._last_t = t
        self._due = max(self._due, due)
        return due
