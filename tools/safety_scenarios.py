"""Whole-session safety scenarios in simulated time: frames → driver → fail-safe → faulty link → scans.

Used by ``tests/test_safety_faults.py``, ``tests/test_safety_pacing.py`` and ``tools/safety_report.py``.
A scenario builds a :class:`~tactdeform_hw.emulator.faults.TimedPort` (timed emulator, seeded faults), an
:class:`~tactdeform_hw.device.EtactileKitDevice` with a participant's guard on it, and a
:class:`~tactdeform_hw.device.safety.failsafe.FailSafe` polled from the simulated clock; it plays a frame
stream shaped like the renderer's (approach rings, a held contact, a sliding line, idle gaps — sent only
when the pattern changes, with a keepalive otherwise), then checks every emulated pulse against what the
host meant.  Everything is deterministic for a given seed.
"""

from __future__ import annotations

import datetime as _dt
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from tactdeform_hw.device import EtactileKitDevice, StimConfig
from tactdeform_hw.device.driver.pacing import PacingPolicy
from tactdeform_hw.device.participant.profiles import ParticipantProfile
from tactdeform_hw.device.safety.failsafe import FailSafe
from tactdeform_hw.device.safety.guard import SafetyGuard
from tactdeform_hw.emulator.faults import Fault, FaultKind, Intent, TimedPort, check_deliveries
from tactdeform_hw.errors import TactDeformError

#: The renderer's highest tracking rate (the frame-rate study covers 30, 72, 90 and 120 Hz).
RENDERER_MAX_RATE_HZ = 120.0

PROFILE = ParticipantProfile(
    participant="SIM01",
    cap_ua=2000,
    regions_ua=(1500, 1400, 1500, 1300, 1200, 1300, 1500, 1400, 1500),
    calibrated_on=_dt.date(2024, 5, 1),
    pulse_width_us=200,
    polarity="anodic",
    contact_mode="orientation",
    ramp_ua_per_frame=500,
)


def grid() -> list[tuple[int, int]]:
    """(row, column) of the 32 TactDeform electrodes in application order."""
    return [(r, c) for r in range(6) for c in range(6) if (r, c) not in {(0, 0), (0, 5), (5, 0), (5, 5)}]


def ring(k: int) -> tuple[int, ...]:
    """Electrodes at Chebyshev distance band ``k`` (0..2) from the array centre: an expanding face ring."""
    return tuple(1 if max(abs(r - 2.5), abs(c - 2.5)) == k + 0.5 else 0 for r, c in grid())


def column(c0: int) -> tuple[int, ...]:
    return tuple(1 if c == c0 else 0 for r, c in grid())


def frame_stream(
    duration_s: float, rate_hz: float = RENDERER_MAX_RATE_HZ, start_s: float = 0.02
) -> list[tuple[float, tuple[int, ...] | None]]:
    """Renderer-shaped frames: every tick either a new pattern or None (unchanged: keepalive).

    A 600 ms cycle: approach (rings 0, 1, 2, 30 ms apart), contact held at ring 2 for 200 ms, a line
    sliding across the pad (one column per 40 ms), then 100 ms idle."""
    out: list[tuple[float, tuple[int, ...] | None]] = []
    last: tuple[int, ...] | None = None
    n = int(duration_s * rate_hz)
    off = (0,) * 32
    for i in range(n):
        t = start_s + i / rate_hz
        ph = (t - start_s) % 0.6
        if ph < 0.09:
            pat = ring(min(2, int(ph / 0.03)))
        elif ph < 0.29:
            pat = ring(2)
        elif ph < 0.5:
            pat = column(min(5, int((ph - 0.29) / 0.04)))
        else:
            pat = off
        out.append((t, pat if pat != last else None))
        last = pat
    return out


@dataclass
class Scenario:
    faults: Sequence[Fault] = ()
    seed: int = 0
    link: str = "usb"
    duration_s: float = 1.2
    rate_hz: float = RENDERER_MAX_RATE_HZ
    watchdog_s: float = 0.1
    probe_s: float | None = 0.02
    refresh_s: float | None = 0.05
    verify_readback: bool = True
    robust_encoding: bool = True
    owner_stops_at_s: float | None = None  # the frame source stops here (no frames, no keepalive)
    tail_s: float = 0.3  # simulated time after the last frame
    profile: ParticipantProfile = PROFILE


@dataclass
class ScenarioResult:
    scenario: Scenario
    injected: list[dict[str, Any]]
    events: list[dict[str, Any]]
    caller_errors: list[dict[str, Any]]
    violations: list[dict[str, Any]]
    unexplained: list[dict[str, Any]]
    losses: list[dict[str, Any]]
    unreported_losses: list[dict[str, Any]]
    noticed: list[bool]
    effect: list[bool]
    max_current_ua: float
    limit_cap_ua: int
    recovery_bound_s: float
    owner_stop_on_s: float | None
    longest_after_fault_s: float
    frames_sent: int
    commands_out_of_step: int
    sim_s: float
    wall_s: float
    #: the board's registers at the end, by the firmware's names (``BoardState.as_dict``: JSON)
    final_state: dict[str, Any] = field(default_factory=dict)

    @property
    def survived(self) -> bool:
        return (
            not self.unexplained
            and not self.unreported_losses
            and self.max_current_ua <= self.limit_cap_ua + 1e-6
        )

    def summary(self) -> dict[str, Any]:
        return {
            "faults": [i["kind"] for i in self.injected],
            "noticed": sum(self.noticed),
            "with_effect": sum(self.effect),
            "violations": len(self.violations),
            "unexplained": len(self.unexplained),
            "lost_bytes": sum(lo["count"] for lo in self.losses),
            "unreported_lost_bytes": sum(lo["count"] for lo in self.unreported_losses),
            "max_current_ua": round(self.max_current_ua, 1),
            "recovery_bound_s": round(self.recovery_bound_s, 4),
            "longest_after_fault_s": round(self.longest_after_fault_s, 4),
            "owner_stop_on_s": None if self.owner_stop_on_s is None else round(self.owner_stop_on_s, 4),
            "survived": self.survived,
        }


def build_session(sc: Scenario) -> tuple[TimedPort, EtactileKitDevice, FailSafe]:
    port = TimedPort(link=sc.link, faults=sc.faults, seed=sc.seed, robust_encoding=sc.robust_encoding)
    guard = SafetyGuard.from_profile(sc.profile)
    dev = EtactileKitDevice(port, guard=guard)
    fs = FailSafe(
        dev,
        watchdog_s=sc.watchdog_s,
        probe_interval_s=sc.probe_s,
        refresh_interval_s=sc.refresh_s,
        verify_readback=sc.verify_readback,
        thread=False,
        signals=False,
        at_exit=False,
    ).start()  # (no thread: the port's clock drives it)
    last_poll = [-1.0]

    def hook(t: float) -> None:
        if t - last_poll[0] >= fs.poll_s:
            last_poll[0] = t
            try:
                fs.poll(t)
            except TactDeformError:
                pass  # an unrecoverable device: recorded as an event; the scenario's check shows the rest

    port.hooks.append(hook)
    return port, dev, fs


SCAN_RATE_HZ = 125  # the stimulation rate the sessions configure (StimConfig's default)


def frame_settle_s(sc: Scenario) -> float:
    """The longest a frame legitimately takes to reach the scans: its height and pattern commands paced a
    command interval apart (two copies of each under robust encoding), the USB frame, the parser's tick,
    and the whole scan in progress when the pattern arrives just after it started."""
    copies = 2 if sc.robust_encoding else 1
    return 2 * copies * PacingPolicy().command_interval_s + 0.001 + 0.001 + 1.0 / SCAN_RATE_HZ


def run(sc: Scenario) -> ScenarioResult:
    wall0 = time.perf_counter()
    port, dev, fs = build_session(sc)
    prof = sc.profile
    limits = SafetyGuard.from_profile(prof).electrode_limits(32)
    intents: list[Intent] = [Intent(0.0, (0,) * 32)]
    errors: list[dict[str, Any]] = []

    def attempt(t: float, fn: Any) -> None:
        try:
            fn()
        except TactDeformError as exc:  # the renderer reports the error and goes on with the next frame
            errors.append({"t_s": port.now_s, "error": f"{type(exc).__name__}: {exc}"})

    attempt(
        0.0,
        lambda: dev.configure(
            StimConfig(
                current_ua=prof.stimulation_ua, pulse_width_us=prof.pulse_width_us, polarity=prof.polarity
            )
        ),
    )
    frames = frame_stream(sc.duration_s, sc.rate_hz)
    for t, pat in frames:
        if sc.owner_stops_at_s is not None and t >= sc.owner_stops_at_s:
            break
        port.advance_to(t)
        if pat is None:
            attempt(t, dev.keepalive)
        else:
            intents.append(Intent(port.now_s, pat))
            attempt(t, lambda pat=pat: dev.send_pattern(pat))
    stop_t = port.now_s
    end = max(stop_t, frames[-1][0] if frames else 0.0) + sc.tail_s
    while port.now_s < end:
        port.advance(min(fs.poll_s, end - port.now_s))
    fs.stop()
    emu = port.emulator
    mapping = {ch: ch for ch in range(32)}
    chk = check_deliveries(emu, intents, limits, mapping)
    # + the frame's own settle time; the resync's own proofs wait as long as the driver says they may
    bound = fs.recovery_bound_s(scan_period_s=1.0 / 125, resync_s=dev.resync_bound_s()) + 0.012
    injected = port.all_injected
    events = [{"kind": e.kind, "t_s": e.t, **e.detail} for e in fs.events]
    notice_times = [e["t_s"] for e in events if e["kind"] in ("error", "recover", "recover_step_failed")]
    notice_times += [e["t_s"] for e in errors]
    unexplained = []
    longest = 0.0
    for v in chk.violations:
        before = [f.t_s for f in injected if f.t_s <= v["t_s"] + 1e-6]
        if not before:
            unexplained.append(v)
            continue
        dt = v["t_s"] - max(before)
        longest = max(longest, dt)
        if dt > bound:
            unexplained.append({**v, "after_fault_s": round(dt, 6)})
    noticed = [any(f.t_s - 1e-6 <= nt <= f.t_s + bound for nt in notice_times) for f in injected]
    effect = [any(f.t_s - 1e-6 <= v["t_s"] <= f.t_s + bound for v in chk.violations) for f in injected]
    losses = [
        {"t_s": lo.time_us / 1e6, "count": lo.count, "reason": lo.reason, "parser": lo.parser_state}
        for lo in emu.losses
    ]
    # a loss while the driver itself had no proof of the parser's state is one it knew of
    spans = [(a, b if b is not None else float("inf")) for a, b in dev.unproved_spans()]
    unreported = [
        lo
        for lo in losses
        if not any(lo["t_s"] - bound <= nt <= lo["t_s"] + bound for nt in notice_times)
        and not any(a <= lo["t_s"] <= b for a, b in spans)
    ]
    owner_on = None
    if sc.owner_stops_at_s is not None:
        table = emu.reports.pulse_table(stop_t * 1e6, None)
        live = table["current_ua"] > 0
        if live.any():
            ends = (table["start_us"][live] + table["width_us"][live]) / 1e6
            owner_on = float(ends.max()) - stop_t
        else:
            owner_on = 0.0
    out_of_step = sum(1 for c in emu.commands if not c.in_sync)
    try:
        dev.close()
    except TactDeformError:
        pass
    port.advance(0.05)  # let the firmware read the all-off of close
    return ScenarioResult(
        scenario=sc,
        injected=[f.to_dict() for f in injected],
        events=events,
        caller_errors=errors,
        violations=chk.violations,
        unexplained=unexplained,
        losses=losses,
        unreported_losses=unreported,
        noticed=noticed,
        effect=effect,
        max_current_ua=chk.max_current_ua,
        limit_cap_ua=prof.cap_ua,
        recovery_bound_s=bound,
        owner_stop_on_s=owner_on,
        longest_after_fault_s=longest,
        frames_sent=dev.frames_sent,
        commands_out_of_step=out_of_step,
        sim_s=port.now_s,
        wall_s=time.perf_counter() - wall0,
        final_state=emu.state().as_dict(),
    )


def single_fault(kind: FaultKind | str, seed: int, at_s: float = 0.35, **kw: Any) -> Scenario:
    return Scenario(faults=[Fault(FaultKind(kind), at_s, **kw)], seed=seed)
