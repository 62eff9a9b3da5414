"""Random sessions of public ``Device`` calls on the timed emulator, judged on the pulses it delivered.

    python tools/safety_campaign.py --sessions 2000 [--firmware v1.2|v2|both] [--faults] [--jobs J] [--seed S]
        [--json] [--cluster dask://HOST:PORT|local:N] [--chunk C]
    python tools/safety_campaign.py --exhaustive [--depth 4] [--firmware v1.2|v2|both] (exhaustive_campaign)
    python tools/safety_campaign.py --exhaustive --depth N --byte-faults               (byte_fault_campaign)
    python tools/safety_campaign.py --seams --sessions 3000                            (seam_sessions)

The sessions run in fixed chunks by index (``tools/campaign_engine.py``) on this process, on ``--jobs``
worker processes or on a Dask cluster's workers (``--cluster``, the ``[cluster]`` extra); the figures are
the same whatever runs them.

Each session is drawn from its own seed (``seed * 1_000_003 + index``), so a run is deterministic for a
seed and any session can be replayed alone (``--only INDEX``).  A session picks a link (USB full speed or
a UART), the loss-tolerant encoding or not, and a configuration (1–255 electrodes, monophasic and
biphasic frames, a sense current or none), then calls the driver's public methods in random order —
``configure``, ``send_pattern``, ``set_current``, ``keepalive``, ``all_off``, ``suspend``, ``probe``,
``measure``, ``resync``, ``reconnect``, ``hardware_reset``, ``close`` followed by a new device on the
same port, and time passing — as an application would.

``--firmware v2`` runs the same sessions on the timed v2 model (:class:`TimedEmulatorV2`, one height per
electrode, the mode global) with a driver that speaks v2: frames are all monophasic or all biphasic (v2
refuses a mix), ``measure`` is called beside ``probe``, and half the sessions guard each electrode with its
own regional limit (a participant's map).  Every pulse is judged against its own electrode's limit: the
largest current the session asked for, lowered to that electrode's regional and charge limit.  ``both``
runs the two firmware versions, one after the other, with the same seeds.

Judged on the scans the emulated board actually ran (``TimedEmulator.reports.pulse_table``):

* **fault-free sessions** — no pulse above the session's own largest allowed current (the largest
  stimulation current and the largest sense current any call of the session asked for; DAC code and
  delivered current both count), no stimulation pulse on an electrode the host had switched off longer
  than the frame settle time, no byte lost in the device's receive queue, no firmware defect hit (every
  hazard the emulated board records but those in :data:`DESIGNED`; torn patterns count), counted per kind;
* **fault sessions** (``--faults``: the fault kinds of :mod:`tactdeform_hw.emulator.faults`, with the
  fail-safe probing and reading back as an application runs it) — every byte the device lost is lost
  while the driver is without proof of the parser's state, or followed within the documented recovery
  bound by something the host noticed (a raised error, a failed proof or probe, a recovery) — or, counted
  apart, by a resync the caller asked for that rewrote the whole state, or by a proof (with the
  fail-safe's readback) that found the firmware as meant (a loss without effect, such as a queue cleared
  by a silent reboot just before the driver wrote everything again); and every wrong delivery (above the
  limit, or on an electrode meant off) starts within that bound of a fault.

Each failed session is printed on stderr with why and the command that replays it alone, and the run
exits 1.
"""

from __future__ import annotations

import argparse
import bisect
import json
import logging
import multiprocessing as mp
import os
import random
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

# the package beside this tool, not an installed one; and the tools beside it (the campaign engine)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import campaign_engine as engine  # noqa: E402

from tactdeform_hw.device import EtactileKitDevice, StimConfig  # noqa: E402
from tactdeform_hw.device.driver.pacing import estimate_scan_us, firmware_period_us  # noqa: E402
from tactdeform_hw.device.safety.guard import SafetyGuard  # noqa: E402
from tactdeform_hw.emulator.faults import FaultKind, TimedPort, random_plan  # noqa: E402
from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind  # noqa: E402
from tactdeform_hw.emulator.firmware.scan import PulseKind  # noqa: E402
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator  # noqa: E402
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2  # noqa: E402
from tactdeform_hw.errors import (  # noqa: E402
    ConfigurationError,
    MissingDependencyError,
    ProtocolMisuseError,
    SafetyError,
    TactDeformError,
)
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER  # noqa: E402

#: A pulse on an electrode switched off earlier than this is a wrong delivery (a frame's own latency:
#: pacing, the USB frame, the parser's tick, the scan in progress).
SETTLE_S = 0.012
_STIM_KINDS = (int(PulseKind.MONO), int(PulseKind.BI_ANODIC), int(PulseKind.BI_CATHODIC))
_USB_FAULTS = (
    FaultKind.CUT,
    FaultKind.CRC_ERROR,
    FaultKind.RESET,
    FaultKind.STOP_READING,
    FaultKind.WATCHDOG_REBOOT,
    FaultKind.DELAY,
)
_UART_FAULTS = tuple(FaultKind)
#: Firmware versions a campaign can run (``both``: each in turn).
FIRMWARES = ("v1.2", "v2")

#: ``--firmware-src``: every session's board runs this firmware tree built on the host (its state map's
#: version must be ``--firmware``); None: the Python timed models.  Worker processes inherit it (fork).
FIRMWARE_SRC: str | None = None
#: Regional limits (µA) of a participant's map, as the v2 driver tests use them.
REGIONS_UA = (400, 800, 1200, 1600, 2000, 2000, 2000, 2000, 2000)
#: Hazards the emulated board records that are the firmware doing what the driver asks of it on purpose,
#: with the reason; every other kind it records — torn patterns included, and any kind the emulator learns
#: later — is a defect the driver must never trigger in a fault-free session.
#: How often a session opens the board again after an open a fault spoiled.
OPEN_ATTEMPTS = 10

DESIGNED: dict[str, str] = {
    "unknown_bytes": "the resync's zeros and the loss-tolerant encoding's padding: bytes the parser skips",
    "hv513_reinit": "0xF5 (the identification on both versions, v1.2's proof of a boundary) re-initialises "
    "the HV513s",
    "sense_current": "the sense current the session configured (v1.2 gives it to the channels off in the "
    "pattern too), judged against the session's sense limit",
    "u16_waiting": "on a UART the second byte of a u16 follows 10.85 µs after the first and the parser may "
    "meet the gap; a lost byte shows up as a loss and as commands out of step",
    "value_byte_like_a_command": "a value byte >= 0xF5 the host meant as a value (electrode count 255)",
}
#: v2 adds one: the driver raises the electrode count in mode 2 at sense height and width 0, so the stale
#: channels v2 keeps are scanned at height 0 until the zero pattern of the new length is read.  A stale
#: height that carried current would still be judged as a pulse (over its electrode's limit, or on an
#: electrode meant off).
DESIGNED_V2: dict[str, str] = {
    **DESIGNED,
    "stale_channels": "raised in mode 2 at sense height 0: the stale heights carry no current",
}
#: Simulated time a v2 fault session keeps the fail-safe running after its last call: its recovery may
#: wait out the firmware's 2 s command timeout.
_FAULT_TAIL_V2_S = 2.6


def fault_tail_s(firmware: str) -> float:
    """Simulated time a fault session keeps its fail-safe running after its last call, long enough for
    the recovery bound on ``firmware``."""
    return _FAULT_TAIL_V2_S if firmware == "v2" else _FAULT_TAIL_S


def designed(firmware: str) -> dict[str, str]:
    """The hazard kinds that are not defects on ``firmware`` (see :data:`DESIGNED`)."""
    return DESIGNED_V2 if firmware == "v2" else DESIGNED


def dropouts(scans: Iterable[Any]) -> int:
    """Scans without current that replaced stimulation: runs of v2 scans in mode 2 at sense height 0 (the
    cover the driver writes around a pattern, so that no scan uses part of an old and part of a new one)
    next to a scan that delivered stimulation, before or after the run.  The price of the cover, counted so
    that it stays visible; mode-2 scans between scans without current (an electrode count raised behind a
    zero pattern) replace nothing and do not count."""
    out = 0
    run = 0
    stimulated_before = False
    for s in scans:
        if s.stim_mode == 2 and s.sense_pulse_height == 0 and s.electrode_num > 0:
            run += 1
            continue
        stimulates = s.stim_mode in (0, 1) and any(s.codes)
        if run and (stimulated_before or stimulates):
            out += run
        run = 0
        stimulated_before = stimulates
    if run and stimulated_before:
        out += run
    return out


def hazard_name(h: Hazard) -> str:
    """A hazard's kind; a value byte >= 0xF5 that the host meant as a value (electrode count 255) is
    recorded apart from a command byte read as payload, which is a desynchronisation."""
    if h.kind is HazardKind.PAYLOAD_HOLDS_COMMAND_BYTE and h.detail.get("meant_as_command") is False:
        return "value_byte_like_a_command"
    return str(h.kind.value)


#: Errors that refuse a frame (the driver keeps the caller's previous frame) rather than fail to send it.
REFUSALS = (SafetyError, ConfigurationError, ProtocolMisuseError)
#: Transitions the caller asked for (not a fault the driver noticed).
CALLER_REASONS = frozenset({"resync", "reconnect", "hardware_reset"})
#: Simulated time a fault session keeps the fail-safe running after its last call.
_FAULT_TAIL_S = 0.4


@dataclass
class SessionResult:
    index: int
    seed: int
    link: str
    robust: bool
    electrodes: int
    calls: list[str]
    allowed_stim_ua: int
    allowed_sense_ua: int
    biphasic: bool = False
    firmware: str = "v1.2"
    regions: bool = False  # per-electrode (regional) limits guarded
    cap_ua: int | None = None  # a participant's cap guarded (v2 sessions without regions)
    pulses: int = 0
    max_stim_ua: float = 0.0
    over_limit: int = 0
    meant_off: int = 0
    lost_bytes: int = 0
    losses: int = 0
    dropouts: int = 0  # scans the mode-2 cover of a pattern write left without current (v2)
    hazards: list[str] = field(default_factory=list)
    hazard_counts: dict[str, int] = field(default_factory=dict)  # records per kind
    errors: list[str] = field(default_factory=list)
    faults: list[str] = field(default_factory=list)
    faults_survived: int = 0
    wrong_after_fault_s: float = 0.0
    unexplained: int = 0
    unreported_lost_bytes: int = 0
    repaired_lost_bytes: int = 0  # not noticed, but a resync the caller asked for rewrote the state in time
    absorbed_lost_bytes: int = 0  # not noticed: a later proof and readback found the firmware as meant
    recovery_bound_s: float = 0.0
    sim_s: float = 0.0
    wall_s: float = 0.0
    first_violation: dict[str, Any] | None = None
    campaign_seed: int = 0  # with ``index``, what replays the session (``--seed S --only I``)
    fault_session: bool = False

    @property
    def ok(self) -> bool:
        if self.faults:
            return self.unexplained == 0 and self.unreported_lost_bytes == 0
        return self.over_limit == 0 and self.meant_off == 0 and self.lost_bytes == 0 and not self.defects

    @property
    def defects(self) -> list[str]:
        """The kinds of defect the session hit (every hazard kind not designed, a crash of the driver)."""
        ok = designed(self.firmware)
        return [h for h in self.hazards if h not in ok]

    @property
    def defect_counts(self) -> dict[str, int]:
        """Records per kind of defect."""
        return {h: self.hazard_counts.get(h, 1) for h in self.defects}

    def failure(self) -> str:
        """Why the session failed, in one line ("" when it did not)."""
        if self.ok:
            return ""
        why: list[str] = []
        if self.faults:
            if self.unexplained:
                why.append(f"{self.unexplained} wrong deliveries past the recovery bound")
            if self.unreported_lost_bytes:
                why.append(f"{self.unreported_lost_bytes} bytes lost unreported")
        else:
            if self.over_limit:
                why.append(f"{self.over_limit} pulses above the limit")
            if self.meant_off:
                why.append(f"{self.meant_off} pulses on electrodes meant off")
            if self.lost_bytes:
                why.append(f"{self.lost_bytes} bytes lost")
            if self.defects:
                why.append("defects " + ", ".join(f"{k} x{n}" for k, n in self.defect_counts.items()))
        return "; ".join(why)

    def reproduce(self) -> str:
        """The command that replays this session alone."""
        faults = " --faults" if self.fault_session else ""
        return (
            f"python tools/safety_campaign.py --firmware {self.firmware} --seed {self.campaign_seed}"
            f"{faults} --only {self.index}"
        )


def _config(rng: random.Random, robust: bool) -> StimConfig:
    """A configuration whose every frame fits its period (the guard refuses the rest anyway)."""
    n = rng.choice((1, 2, 3, 4, 8, 16, 32, 32, 32, 64, 100, 128, 200, 244 if robust else 255))
    width = rng.choice((20, 50, 100, 200))
    discharge = rng.choice((0, 10, 45))
    sense_ua = rng.choice((0, 0, 0, 40, 120)) if rng.random() < 0.5 else 0
    sense_w = rng.choice((0, 5, 20)) if sense_ua else 0
    worst = estimate_scan_us(bytes([2]) * n, width, discharge, sense_w)
    top = int(1e6 / (worst * 1.25 + 1500))
    rate = max(1, min(top, rng.choice((60, 100, 125, 200, 250))))
    if robust:  # a value whose low byte looks like a command byte is refused under robust encoding
        while rate & 0xFF >= 0xF5 or (rate >> 8) >= 0xF5:
            rate -= 1
    current = rng.choice((0, 400, 800, 1000, 1500, 2000, 2500))
    return StimConfig(
        electrode_count=n,
        current_ua=current,
        pulse_width_us=width,
        discharge_us=discharge,
        rate_hz=rate,
        polarity=rng.choice(("anodic", "anodic", "cathodic")),
        sense_current_ua=sense_ua,
        sense_width_us=sense_w,
    )


def random_pattern(rng: random.Random, n: int, biphasic: bool, mixed: bool = True) -> tuple[int, ...]:
    """Levels of one frame; ``mixed`` False: a biphasic frame has every active electrode biphasic (v2's
    mode is global: its driver refuses a mix)."""
    dens = rng.choice((0.0, 0.1, 0.3, 0.6, 1.0))
    levels = [1 if rng.random() < dens else 0 for _ in range(n)]
    if biphasic:
        levels = [2 if v and (not mixed or rng.random() < 0.7) else v for v in levels]
    return tuple(levels)


class Session:
    """One session: the port, the device, the calls, and what the host meant at every moment."""

    def __init__(self, index: int, seed: int, faults: bool, firmware: str = "v1.2") -> None:
        if firmware not in FIRMWARES:
            raise ValueError(f"firmware {firmware!r}: one of {', '.join(FIRMWARES)}")
        self.firmware = firmware
        self.rng = random.Random(seed)
        rng = self.rng
        self.link = rng.choice(("usb", "uart"))
        self.robust = rng.random() < 0.5
        self.cfg = _config(rng, self.robust)
        self.biphasic = rng.random() < 0.5
        # v2: a participant's guard — regional limits on the 32-electrode array (the regions of other
        # counts need an array file's positions), else a lower cap in half the sessions
        self.regions = False
        self.cap_ua: int | None = None
        if firmware == "v2":
            draw = rng.random()
            self.regions = self.cfg.electrode_count == 32 and draw < 0.8
            if not self.regions and draw < 0.5:
                self.cap_ua = rng.choice((800, 1500))
                # the participant's cap is the configuration's ceiling (set_current may still ask more)
                self.cfg = StimConfig(
                    **{**asdict(self.cfg), "current_ua": min(self.cfg.current_ua, self.cap_ua)}
                )
        plan = []
        self.n_calls = rng.randint(4, 14)
        if faults:
            kinds = _USB_FAULTS if self.link == "usb" else _UART_FAULTS
            plan = random_plan(seed, kinds, rng.randint(1, 3), 0.02, 0.25)
        boards = (self.cfg.electrode_count + 31) // 32  # 4 HV513 (32 outputs) per switching board
        emu: TimedEmulator | TimedEmulatorV2
        if FIRMWARE_SRC is not None:  # --firmware-src: the firmware's own code, built on this machine
            from tactdeform_hw.emulator.hostbuild.timed import HostBuildTimedModel

            emu = HostBuildTimedModel(FIRMWARE_SRC, "compact", boards, link=self.link)  # type: ignore[assignment]
        elif firmware == "v2":
            emu = TimedEmulatorV2("compact", boards, link=self.link)
        else:
            emu = TimedEmulator("compact", boards, link=self.link)
        self.port = TimedPort(emu, link=self.link, faults=plan, seed=seed, robust_encoding=self.robust)
        self.notices: list[float] = []  # when the host noticed something (a raised error, a refused open)
        self.refused_spans: list[tuple[float, float]] = []  # opens refused, from their first byte
        self.dev = self._new_device()
        self.devices = [self.dev]  # every device opened on the port in this session
        self.failsafe: Any = None
        if faults:
            self._start_failsafe()
        self.res = SessionResult(
            index,
            seed,
            self.link,
            self.robust,
            self.cfg.electrode_count,
            [],
            0,
            0,
            biphasic=self.biphasic,
            firmware=firmware,
            regions=self.regions,
            cap_ua=self.cap_ua,
        )
        # (call time, the electrodes the host means from then on, when an "off" is surely in force)
        self.intents: list[tuple[float, tuple[int, ...], float]] = [
            (0.0, (0,) * self.cfg.electrode_count, 0.0)
        ]
        self.sent: tuple[int, ...] | None = None  # the caller's frame a keepalive brings back
        self.longest_call_s = 0.0  # the fail-safe cannot act while one of the owner's calls runs
        self.refused = False  # the last call was refused before anything was sent

    def _guard(self) -> SafetyGuard | None:
        """v2: a participant's map guards each electrode with its own limit, or a participant's cap."""
        if self.regions:
            return SafetyGuard(regions_ua=REGIONS_UA)
        return SafetyGuard(self.cap_ua) if self.cap_ua is not None else None

    def _new_device(self) -> EtactileKitDevice:
        """Open the board as a program does: identified first; an open that a fault spoils (the link cut
        or the board reset during the identification) is refused, and the program opens it again."""
        for attempt in range(1, OPEN_ATTEMPTS + 1):
            began = self.port.now_s
            try:
                if self.firmware == "v2":
                    return EtactileKitDevice(self.port, firmware="v2", guard=self._guard())
                return EtactileKitDevice(self.port, firmware="v1.2")
            except TactDeformError:
                # the open was refused: the program knows, and it never had a proof while it wrote
                self.notices.append(self.port.now_s)
                self.refused_spans.append((began, self.port.now_s))
                if attempt == OPEN_ATTEMPTS:
                    raise
                self.port.advance(0.1)
        raise AssertionError("unreachable")

    def electrode_limits_ua(self) -> list[float]:
        """Each hardware channel's own stimulation limit (no mapping: channel = electrode): on v2 what
        the session asked for, lowered to the guard's limit for that electrode (region, cap, charge);
        on v1.2 the frame's height is global, so every channel gets the session's largest request."""
        top = float(self.res.allowed_stim_ua)
        if self.firmware != "v2":
            return [top] * 256
        guard = self.dev.guard
        base = guard.base_limit_ua(self.cfg.pulse_width_us)
        own = guard.electrode_limits(self.cfg.electrode_count)
        return [min(top, base, own[ch]) if ch < len(own) else 0.0 for ch in range(256)]

    def _start_failsafe(self) -> None:
        from tactdeform_hw.device.safety.failsafe import FailSafe

        fs = FailSafe(
            self.dev,
            watchdog_s=0.1,
            probe_interval_s=0.02,
            refresh_interval_s=0.05,
            verify_readback=True,
            thread=False,
            signals=False,
            at_exit=False,
        )
        last = [-1.0]

        def hook(t: float) -> None:
            if t - last[0] >= fs.poll_s:
                last[0] = t
                try:
                    fs.poll(t)
                except TactDeformError:
                    pass

        if self.failsafe is not None:
            self.failsafe.stop()
            self.port.hooks.clear()
        self.port.hooks.append(hook)
        self.failsafe = fs.start()  # (no thread: the port's clock drives it)

    # --- the host's intent ------------------------------------------------------------------------------

    def _effective_s(self) -> float:
        """When what was just written is surely in force: the driver's own worst case for the device to
        have read it, plus a whole scan (biphasic) that had started before."""
        dev, cfg = self.dev, self.cfg
        period = firmware_period_us(cfg.rate_hz) / 1e6
        scan = (
            estimate_scan_us(
                bytes([2]) * cfg.electrode_count, cfg.pulse_width_us, cfg.discharge_us, cfg.sense_width_us
            )
            / 1e6
        )
        return max(self.port.now_s, dev.pacer.drained_by()) + min(scan, period)

    # --- calls ------------------------------------------------------------------------------------------

    def _call(self, name: str, fn: Callable[[], Any], intent: tuple[int, ...] | None = None) -> bool:
        """Call ``fn``; ``intent``: the electrodes the host means from this call on (None: unchanged)."""
        self.res.calls.append(name)
        self.refused = False
        t0 = self.port.now_s
        fs = self.failsafe
        waited = fs.owner_wait_s if fs is not None else 0.0
        try:
            try:
                fn()
            finally:
                # the owner's own time: a probe the fail-safe ran first is the fail-safe's, in the bound
                if fs is not None:
                    waited = fs.owner_wait_s - waited
                self.longest_call_s = max(self.longest_call_s, self.port.now_s - t0 - waited)
        except TactDeformError as exc:
            self.notices.append(self.port.now_s)
            self.res.errors.append(f"{name}: {type(exc).__name__}: {exc}"[:160])
            # what a failed call asked for may be in force in part: still the host's intent; a refusal sent
            # nothing, so the frame before it is still the one the host means (and the board runs)
            self.refused = isinstance(exc, REFUSALS)
            if intent is not None and not self.refused:
                self.intents.append((t0, intent, self.port.now_s))
            return False
        if intent is not None:
            self.intents.append((t0, intent, self._effective_s()))
        return True

    def run(self) -> None:
        rng, dev, cfg = self.rng, self.dev, self.cfg
        res = self.res
        res.allowed_stim_ua = cfg.current_ua
        res.allowed_sense_ua = cfg.sense_current_ua
        off = (0,) * cfg.electrode_count
        if rng.random() < 0.2:  # a session that starts with a resync on a board of unknown state
            self._call("resync", dev.resync, off)
        self._call("configure", lambda: dev.configure(cfg), off)
        self.sent = None
        for _ in range(self.n_calls):
            self.step()
        self._call("close", self.dev.close, off)
        self.port.advance(0.03 if self.failsafe is None else fault_tail_s(self.firmware))
        if self.failsafe is not None:
            self.failsafe.stop()

    def step(self) -> None:
        rng, dev, cfg = self.rng, self.dev, self.cfg
        n = cfg.electrode_count
        off = (0,) * n
        r = rng.random()
        if r < 0.30:
            pat = random_pattern(rng, n, self.biphasic, mixed=self.firmware != "v2")
            if self._call("send_pattern", lambda: dev.send_pattern(pat), pat) or not self.refused:
                # the caller's frame, even when the link failed under it: keepalive resumes it
                self.sent = pat
        elif r < 0.40:
            ua = rng.choice((0, 200, 600, 1000, 1800, 3000))
            self.res.allowed_stim_ua = max(self.res.allowed_stim_ua, ua)
            self._call("set_current", lambda: dev.set_current(ua))
        elif r < 0.48:
            self._call("keepalive", dev.keepalive, self.sent)
        elif r < 0.52:
            if self._call("all_off", dev.all_off, off):
                self.sent = None
        elif r < 0.55:
            self._call("suspend", dev.suspend, off)
        elif r < 0.60:
            if self.firmware == "v2" and rng.random() < 0.5:
                self._call("measure", dev.measure)
            else:
                self._call("probe", dev.probe)
        elif r < 0.64:
            self._call("resync", dev.resync, off)
        elif r < 0.68:
            self._call("reconnect", dev.reconnect, off)
        elif r < 0.72:
            self._call("hardware_reset", dev.hardware_reset, off)
        elif r < 0.75:
            self._call("close", dev.close, off)
            self.sent = None
            self.res.calls.append("reopen")
            try:
                self.dev = self._new_device()
                self.devices.append(self.dev)
            except TactDeformError as exc:
                self.res.errors.append(f"reopen: {exc}"[:160])
                return
            if self.failsafe is not None:
                self._start_failsafe()
            if rng.random() < 0.5:
                self._call("resync", self.dev.resync, off)
            self._call("configure", lambda: self.dev.configure(cfg), off)
        elif r < 0.78:
            new = StimConfig(**{**asdict(cfg), "current_ua": rng.choice((0, 500, 1200))})
            self.res.allowed_stim_ua = max(self.res.allowed_stim_ua, new.current_ua)
            # a configuration the driver wrote ends the caller's frame; a refusal does not
            if self._call("configure", lambda: dev.configure(new), off) or not self.refused:
                self.sent = None
        else:
            dt = rng.choice((0.0005, 0.002, 0.008, 0.02, 0.05))
            self.res.calls.append(f"wait {dt * 1e3:g} ms")
            self.port.advance(dt)

    # --- the verdict ------------------------------------------------------------------------------------

    def judge(self) -> SessionResult:
        res = self.res
        emu = self.port.emulator
        res.sim_s = self.port.now_s
        table = emu.reports.pulse_table()
        code = table["code"]
        kind = table["kind"]
        cur = np.maximum(table["current_ua"], code * DEFAULT_TRANSFER.step_ua) if code.size else code
        live = np.nonzero(cur > 0)[0]
        res.pulses = int(live.size)
        stim = np.isin(kind, _STIM_KINDS)
        wrong: list[dict[str, Any]] = []
        if live.size:
            res.max_stim_ua = float(cur[live][stim[live]].max()) if stim[live].any() else 0.0
            own = np.asarray(self.electrode_limits_ua())[table["channel"]]
            limit = np.where(stim, own, res.allowed_sense_ua)
            over = live[cur[live] > limit[live] + 1e-6]
            res.over_limit = int(over.size)
            for k in over[:1]:
                wrong.append(self._pulse(table, int(k), cur, "over_limit"))
            wrong += self._meant_off(table, live[stim[live]], cur)
            if self.failsafe is None:
                res.meant_off = sum(1 for w in wrong if w["why"] == "meant_off")
            else:
                for k in over:
                    wrong.append(self._pulse(table, int(k), cur, "over_limit"))
        if isinstance(emu, TimedEmulatorV2):  # (v1.2 writes no cover: a scan at height 0 still reads it)
            res.dropouts = dropouts(emu.scans)
        res.losses = len(emu.losses)
        res.lost_bytes = sum(lo.count for lo in emu.losses)
        counts: dict[str, int] = {}
        for h in emu.hazards:
            name = hazard_name(h)
            counts[name] = counts.get(name, 0) + 1
        out_of_step = sum(1 for c in emu.commands if not c.in_sync)
        if out_of_step:
            counts["commands_out_of_step"] = out_of_step
        res.hazard_counts = dict(sorted(counts.items()))
        res.hazards = sorted(counts)
        if wrong and res.first_violation is None:
            res.first_violation = min(wrong, key=lambda w: w["t_s"])
        if self.failsafe is not None:
            self._judge_faults(wrong)
        return res

    def _pulse(self, table: dict[str, np.ndarray], k: int, cur: np.ndarray, why: str) -> dict[str, Any]:
        return {
            "t_s": float(table["start_us"][k]) / 1e6,
            "channel": int(table["channel"][k]),
            "kind": int(table["kind"][k]),
            "code": int(table["code"][k]),
            "current_ua": float(cur[k]),
            "why": why,
        }

    def _meant_off(
        self, table: dict[str, np.ndarray], idx: Iterable[int], cur: np.ndarray
    ) -> list[dict[str, Any]]:
        """Stimulation pulses on an electrode the host had switched off, later than ``SETTLE_S`` after the
        driver's own worst case for the switch-off to be in force."""
        times = [t for t, _, _ in self.intents]
        since: list[list[float | None]] = []  # per intent, per electrode: off since (None: meant on)
        prev: list[float | None] = [0.0] * 256
        for _, lv, eff in self.intents:
            row = [eff if p is None else p for p in prev]
            for e in range(min(len(lv), 256)):
                if lv[e] in (1, 2):
                    row[e] = None
            since.append(row)
            prev = row
        out = []
        ks = np.asarray(idx, dtype=np.intp)
        for k, start_us, ch in zip(
            ks.tolist(), table["start_us"][ks].tolist(), table["channel"][ks].tolist(), strict=True
        ):
            t = float(start_us) / 1e6
            i = bisect.bisect_right(times, t) - 1
            off = since[i][ch] if i >= 0 else 0.0
            if off is not None and t - off > SETTLE_S:
                out.append(self._pulse(table, int(k), cur, "meant_off"))
        return out

    def _judge_faults(self, wrong: list[dict[str, Any]]) -> None:
        res = self.res
        fs = self.failsafe
        injected = self.port.all_injected
        res.faults = [f.kind.value for f in injected]
        bound = self.recovery_bound_s()
        res.recovery_bound_s = bound
        notices = list(self.notices)
        notices += [
            e.t for e in fs.events if e.kind in ("error", "recover", "recover_step_failed", "watchdog")
        ]
        # the driver's own notices: a proof that failed (not a resync the caller asked for)
        notices += [
            t
            for d in self.devices
            for t, _, new, why in d.transitions
            if new in ("suspect", "failed") and why not in CALLER_REASONS
        ]
        bad_faults: set[int] = set()
        for w in wrong:
            before = [i for i, f in enumerate(injected) if f.t_s <= w["t_s"] + 1e-6]
            if not before:
                res.unexplained += 1
                continue
            dt = w["t_s"] - injected[before[-1]].t_s
            res.wrong_after_fault_s = max(res.wrong_after_fault_s, dt)
            if dt > bound:
                res.unexplained += 1
                bad_faults.add(before[-1])
        # a loss while the driver had no proof that the parser was in step is one the host knew of
        spans = [
            (a, b if b is not None else float("inf")) for d in self.devices for a, b in d.unproved_spans()
        ] + self.refused_spans
        # a resync completed after the loss rewrote everything it could have changed (the caller's own)
        repairs = [
            t
            for d in self.devices
            for t, old, new, _ in d.transitions
            if new == "in_step" and old in ("verifying", "safe")
        ]
        # a proof after the loss (a reply of the right length; the fail-safe's also reads back the voltages)
        # found the firmware in step: the loss had no effect the host could see
        proofs = [t for d in self.devices for t in d.proofs]
        for t, lost in self.lost_bytes_at():
            if any(t - bound <= nt <= t + bound for nt in notices) or any(a <= t <= b for a, b in spans):
                continue
            if any(t <= rt <= t + bound for rt in repairs):
                res.repaired_lost_bytes += lost
            elif any(t < pt <= t + bound for pt in proofs):
                res.absorbed_lost_bytes += lost
            else:
                res.unreported_lost_bytes += lost
                before = [i for i, f in enumerate(injected) if f.t_s <= t + 1e-6]
                if before:
                    bad_faults.add(before[-1])
        res.faults_survived = (
            len(injected) - len(bad_faults) if not (res.unexplained or res.unreported_lost_bytes) else 0
        )

    def lost_bytes_at(self) -> list[tuple[float, int]]:
        """The bytes that never reached the parser, as (when in seconds, how many): the receive queue's
        losses the emulated board recorded."""
        return [(lo.time_us / 1e6, lo.count) for lo in self.port.emulator.losses]

    def recovery_bound_s(self) -> float:
        period = firmware_period_us(self.cfg.rate_hz) / 1e6
        resync = max(d.resync_bound_s() for d in self.devices)
        probe = max(d.probe_bound_s() for d in self.devices)
        bound = float(self.failsafe.recovery_bound_s(scan_period_s=period, resync_s=resync, probe_s=probe))
        return bound + self.longest_call_s + SETTLE_S


def run_session(index: int, seed: int = 0, faults: bool = False, firmware: str = "v1.2") -> SessionResult:
    """Run one session and judge it."""
    wall = time.perf_counter()
    s = Session(index, seed * 1_000_003 + index, faults, firmware)
    try:
        s.run()
    except Exception as exc:  # noqa: BLE001 - a crash of the driver is a finding, reported with the session
        s.res.errors.append(f"CRASH {type(exc).__name__}: {exc}"[:200])
        s.res.hazards.append("driver_crash")
    res = s.judge()
    if any(e.startswith("CRASH") for e in res.errors) and "driver_crash" not in res.hazards:
        res.hazards.append("driver_crash")
        res.hazard_counts["driver_crash"] = 1
    res.campaign_seed = seed
    res.fault_session = faults
    res.wall_s = time.perf_counter() - wall
    return res


def _worker(args: tuple[int, int, bool, str]) -> SessionResult:
    return run_session(*args)


def run_campaign(
    sessions: int,
    *,
    seed: int = 0,
    faults: bool = False,
    jobs: int = 1,
    progress: bool = False,
    first: int = 0,
    firmware: str = "v1.2",
) -> list[SessionResult]:
    """Sessions ``first .. first + sessions - 1``; the same list for the same arguments, whatever ``jobs``."""
    if firmware not in FIRMWARES:
        raise ValueError(f"firmware {firmware!r}: one of {', '.join(FIRMWARES)}")
    tasks = [(first + i, seed, faults, firmware) for i in range(sessions)]
    out: list[SessionResult] = []
    t0 = time.perf_counter()

    def tick(done: int) -> None:
        if progress and (done % max(1, sessions // 50) == 0 or done == sessions):
            rate = done / max(1e-9, time.perf_counter() - t0)
            print(f"\r{done}/{sessions} sessions ({rate:.0f}/s)", end="", file=sys.stderr, flush=True)

    if jobs <= 1:
        for t in tasks:
            out.append(_worker(t))
            tick(len(out))
    else:
        with mp.get_context("fork" if sys.platform != "win32" else "spawn").Pool(jobs) as pool:
            for r in pool.imap(_worker, tasks, chunksize=max(1, min(64, sessions // (jobs * 8) or 1))):
                out.append(r)
                tick(len(out))
    if progress:
        print(file=sys.stderr)
    return out


#: Failed sessions a summary lists (those of lowest index), with the command that replays each.
LISTED_FAILURES = 20


@dataclass
class CampaignTally:
    """Everything :func:`summarize` reports, of any set of sessions, merged exactly and in any order:
    counts are integers, sums of seconds are exact (fractions, rounded once at the end), and the failures
    listed are those of lowest index.  So a campaign cut into chunks — run on one core, on ``--jobs``
    processes or on a cluster's workers, completing in any order — gives the figures of one run."""

    faults: bool = False
    items: int = 0  # sessions
    failed: int = 0
    failures: list[tuple[int, dict[str, Any]]] = field(default_factory=list)  # (index, row), lowest first
    firmwares: set[str] = field(default_factory=set)
    links: dict[str, int] = field(default_factory=lambda: {"usb": 0, "uart": 0})
    robust: int = 0
    biphasic: int = 0
    regions: int = 0
    cap: int = 0
    sense: int = 0
    electrodes_min: int | None = None
    electrodes_max: int | None = None
    calls: dict[str, int] = field(default_factory=dict)
    pulses: int = 0
    dropouts: int = 0
    over_limit: int = 0
    meant_off: int = 0
    lost_bytes: int = 0
    defects_hit: set[str] = field(default_factory=set)
    defects_by_kind: dict[str, int] = field(default_factory=dict)
    defect_sessions: int = 0
    hazards: set[str] = field(default_factory=set)
    caller_errors: int = 0
    sim_s: Fraction = Fraction(0)
    wall_s: Fraction = Fraction(0)
    injected: int = 0
    survived: int = 0
    fault_kinds: set[str] = field(default_factory=set)
    longest_wrong_s: float = 0.0
    recovery_bound_s: float = 0.0
    unexplained: int = 0
    unreported: int = 0
    repaired: int = 0
    absorbed: int = 0

    def add(self, r: SessionResult) -> None:
        """Count one session."""
        self.items += 1
        if not r.ok:
            self.failed += 1
            row = {"index": r.index, "seed": r.campaign_seed, "why": r.failure(), "reproduce": r.reproduce()}
            self._keep_failures([(r.index, row)])
        self.firmwares.add(r.firmware)
        self.links[r.link] = self.links.get(r.link, 0) + 1
        self.robust += r.robust
        self.biphasic += r.biphasic
        self.regions += r.regions
        self.cap += r.cap_ua is not None
        self.sense += bool(r.allowed_sense_ua)
        lo, hi = self.electrodes_min, self.electrodes_max
        self.electrodes_min = r.electrodes if lo is None else min(lo, r.electrodes)
        self.electrodes_max = r.electrodes if hi is None else max(hi, r.electrodes)
        for c in r.calls:
            key = "wait" if c.startswith("wait") else c
            self.calls[key] = self.calls.get(key, 0) + 1
        self.pulses += r.pulses
        self.dropouts += r.dropouts
        self.over_limit += r.over_limit
        self.meant_off += r.meant_off
        self.lost_bytes += r.lost_bytes
        self.defects_hit.update(r.defects)
        _add_counts(self.defects_by_kind, r.defect_counts)
        self.defect_sessions += bool(r.defects)
        self.hazards.update(r.hazards)
        self.caller_errors += len(r.errors)
        self.sim_s += Fraction(r.sim_s)
        self.wall_s += Fraction(r.wall_s)
        self.injected += len(r.faults)
        self.survived += r.faults_survived
        self.fault_kinds.update(r.faults)
        self.longest_wrong_s = max(self.longest_wrong_s, r.wrong_after_fault_s)
        self.recovery_bound_s = max(self.recovery_bound_s, r.recovery_bound_s)
        self.unexplained += r.unexplained
        self.unreported += r.unreported_lost_bytes
        self.repaired += r.repaired_lost_bytes
        self.absorbed += r.absorbed_lost_bytes

    def _keep_failures(self, rows: list[tuple[int, dict[str, Any]]]) -> None:
        self.failures = sorted(self.failures + rows, key=lambda f: f[0])[:LISTED_FAILURES]

    def merge(self, o: CampaignTally) -> None:
        """Add another tally (of other sessions) to this one."""
        self.faults = self.faults or o.faults
        self.items += o.items
        self.failed += o.failed
        self._keep_failures(o.failures)
        self.firmwares |= o.firmwares
        _add_counts(self.links, o.links)
        for name in ("robust", "biphasic", "regions", "cap", "sense", "pulses", "dropouts", "over_limit"):
            setattr(self, name, getattr(self, name) + getattr(o, name))
        for name in ("meant_off", "lost_bytes", "defect_sessions", "caller_errors", "injected", "survived"):
            setattr(self, name, getattr(self, name) + getattr(o, name))
        for name in ("unexplained", "unreported", "repaired", "absorbed", "sim_s", "wall_s"):
            setattr(self, name, getattr(self, name) + getattr(o, name))
        if o.electrodes_min is not None:
            lo, hi = self.electrodes_min, self.electrodes_max
            self.electrodes_min = o.electrodes_min if lo is None else min(lo, o.electrodes_min)
            self.electrodes_max = o.electrodes_max if hi is None else max(hi or 0, o.electrodes_max or 0)
        _add_counts(self.calls, o.calls)
        self.defects_hit |= o.defects_hit
        _add_counts(self.defects_by_kind, o.defects_by_kind)
        self.hazards |= o.hazards
        self.fault_kinds |= o.fault_kinds
        self.longest_wrong_s = max(self.longest_wrong_s, o.longest_wrong_s)
        self.recovery_bound_s = max(self.recovery_bound_s, o.recovery_bound_s)

    def summary(self) -> dict[str, Any]:
        """The campaign's figures (the fields of ``--json``)."""
        wall = float(self.wall_s)
        summary: dict[str, Any] = {
            "firmware": "+".join(sorted(self.firmwares)) or "none",
            "sessions": self.items,
            "faults": self.faults,
            "failed_sessions": self.failed,
            "failed_indices": [i for i, _ in self.failures],
            "links": {k: self.links.get(k, 0) for k in ("usb", "uart")},
            "robust_encoding": self.robust,
            "biphasic": self.biphasic,
            "regional_limits": self.regions,
            "participant_cap": self.cap,
            "sense_current": self.sense,
            "electrodes_min_max": [self.electrodes_min or 0, self.electrodes_max or 0],
            "calls": dict(sorted(self.calls.items())),
            "pulses": self.pulses,
            "dropouts": self.dropouts,
            "over_limit_pulses": self.over_limit,
            "meant_off_pulses": self.meant_off,
            "bytes_lost": self.lost_bytes,
            "defects_hit": sorted(self.defects_hit),
            "defects_by_kind": dict(sorted(self.defects_by_kind.items())),
            "defect_sessions": self.defect_sessions,
            "hazards": sorted(self.hazards),
            "caller_errors": self.caller_errors,
            "simulated_s": round(float(self.sim_s), 3),
            "session_s": round(wall, 3),  # the sessions' own run times, summed over workers
            "ms_per_session": round(1e3 * wall / max(1, self.items), 3),
        }
        summary["failures"] = [row for _, row in self.failures]
        if self.faults:
            summary.update(
                {
                    "faults_injected": self.injected,
                    "faults_survived": self.survived,
                    "fault_kinds": sorted(self.fault_kinds),
                    "longest_wrong_delivery_s": round(self.longest_wrong_s, 6),
                    "recovery_bound_s": round(self.recovery_bound_s, 6),
                    "unexplained_wrong_deliveries": self.unexplained,
                    "bytes_lost_unreported": self.unreported,
                    "bytes_lost_unnoticed_but_repaired": self.repaired,
                    "bytes_lost_unnoticed_absorbed": self.absorbed,
                }
            )
        return summary


def _add_counts(into: dict[str, int], more: dict[str, int]) -> None:
    for k, n in more.items():
        into[k] = into.get(k, 0) + n


def tally(results: Iterable[SessionResult], *, faults: bool) -> CampaignTally:
    """The tally of ``results``."""
    out = CampaignTally(faults=faults)
    for r in results:
        out.add(r)
    return out


def tally_chunk(
    seed: int, faults: bool, firmware: str, firmware_src: str | None, first: int, count: int
) -> CampaignTally:
    """Run sessions ``first .. first + count - 1`` and tally them (a chunk of a distributed campaign);
    ``firmware_src``: the boards run that firmware tree built on the host (set in the worker itself, so a
    cluster's workers run it too)."""
    global FIRMWARE_SRC
    FIRMWARE_SRC = firmware_src
    logging.disable(logging.WARNING)  # the guard logs each refusal; the summary counts them
    return tally((run_session(i, seed, faults, firmware) for i in range(first, first + count)), faults=faults)


def summarize(results: list[SessionResult], *, faults: bool) -> dict[str, Any]:
    """The campaign's figures for ``results``."""
    return tally(results, faults=faults).summary()


def _table(summary: dict[str, Any]) -> str:
    rows = [(k, v) for k, v in summary.items() if k not in ("calls", "failed_indices", "failures")]
    rows.append(("calls", ", ".join(f"{k} {v}" for k, v in summary["calls"].items())))
    if summary["failed_indices"]:
        rows.append(("first failed sessions", " ".join(map(str, summary["failed_indices"]))))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def _report_failures(failures: list[dict[str, Any]], total: int | None = None, firmware: str = "") -> None:
    """Each failed session on stderr, one line each: why, and the command that replays it alone."""
    for f in failures:
        print(f"FAILED session {f['index']}: {f['why']} -- reproduce: {f['reproduce']}", file=sys.stderr)
    shown = len(failures)
    if total is not None and total > shown:
        print(f"... and {total - shown} more failed {firmware} sessions", file=sys.stderr)


def campaign_job(
    sessions: int,
    *,
    seed: int = 0,
    faults: bool = False,
    first: int = 0,
    firmware: str = "v1.2",
    chunk: int = engine.DEFAULT_CHUNK,
    firmware_src: str | None = None,
) -> engine.Job:
    """Sessions ``first .. first + sessions - 1`` as chunks for :func:`campaign_engine.run`."""
    if firmware not in FIRMWARES:
        raise ValueError(f"firmware {firmware!r}: one of {', '.join(FIRMWARES)}")
    return engine.Job(
        "safety_campaign",
        "tally_chunk",
        (seed, faults, firmware, firmware_src),
        sessions,
        first=first,
        chunk=chunk,
        fingerprint=engine.fingerprint(),
    )


def _use_firmware_src(ap: argparse.ArgumentParser, src: str, firmware: str) -> None:
    """Check the tree declares ``firmware`` and make every session run it."""
    global FIRMWARE_SRC
    from tactdeform_hw.emulator.hostbuild.statemap import detect

    smap = detect(Path(src))
    declared = smap.firmware if smap is not None else ""
    if declared != firmware:
        ap.error(
            f"--firmware-src {src}: its state map declares firmware {declared or 'none'!r}, "
            f"--firmware is {firmware!r}"
        )
    FIRMWARE_SRC = src


def main(argv: list[str] | None = None) -> int:
    """The command line; a missing engine or an unreachable cluster is one line on stderr and exit 1."""
    try:
        return _main(argv)
    except (engine.EngineError, MissingDependencyError) as exc:
        print(f"safety_campaign: {exc}", file=sys.stderr)
        return 1


def _main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--sessions", type=int, default=1000, help="number of sessions (default 1000)")
    ap.add_argument("--faults", action="store_true", help="inject the emulator's faults into every session")
    ap.add_argument(
        "--firmware",
        choices=(*FIRMWARES, "both"),
        default=None,
        help="firmware the emulated board runs and the driver speaks (default v1.2, --exhaustive both; "
        "both: each in turn)",
    )
    ap.add_argument(
        "--jobs", type=int, default=os.cpu_count() or 1, help="worker processes (default: every core)"
    )
    ap.add_argument(
        "--cluster",
        default=None,
        metavar="dask://HOST:PORT|local:N",
        help="run the chunks on a Dask cluster's workers, or on a local one of N worker processes "
        "(pip install 'tactdeform_hw[cluster]'); the figures are those of one core",
    )
    ap.add_argument(
        "--chunk",
        type=int,
        default=engine.DEFAULT_CHUNK,
        help=f"sessions per chunk handed to a worker (default {engine.DEFAULT_CHUNK}; the figures do not "
        "depend on it)",
    )
    ap.add_argument("--seed", type=int, default=0, help="campaign seed (default 0)")
    ap.add_argument("--first", type=int, default=0, help="index of the first session")
    ap.add_argument("--only", type=int, default=None, help="run one session and print it whole")
    ap.add_argument("--json", action="store_true", help="print the summary as JSON")
    ap.add_argument(
        "--seams",
        action="store_true",
        help="sessions at the seams between programs, firmware versions, links and calibration files "
        "(tools/seam_sessions.py); --firmware and --faults do not apply",
    )
    ap.add_argument(
        "--exhaustive",
        action="store_true",
        help="every sequence of up to --depth calls from a small domain, from every start state, on the "
        "firmware(s) (tools/exhaustive_campaign.py); --sessions and --faults do not apply",
    )
    ap.add_argument(
        "--depth", type=int, default=4, help="--exhaustive: the longest sequence of calls (default 4)"
    )
    ap.add_argument(
        "--byte-faults",
        action="store_true",
        help="--exhaustive: every sequence again once per fault at each byte the host writes from its "
        "first call on, the fail-safe running (tools/byte_fault_campaign.py): on a UART each byte lost, "
        "duplicated and corrupted (XOR 0xFF), on USB each packet's tail lost from each byte on; "
        "3 x (UART bytes) + (USB bytes) runs, counted by a fault-free pass and printed before they start "
        "(135 280 at depth 1, both firmwares), judged by the --faults verdict",
    )
    ap.add_argument(
        "--runs",
        metavar="FIRST:END",
        default=None,
        help="--byte-faults: only runs FIRST to END - 1 of the enumeration (the count printed gives each "
        "start's range), to split a long enumeration across runs or machines",
    )
    ap.add_argument(
        "--sample",
        metavar="N",
        type=int,
        default=None,
        help="--byte-faults: run N runs drawn from the enumeration instead of all of them (each a sequence "
        "drawn uniformly, then one of its faulty runs; --seed picks them), with no first pass, so any "
        "--depth can be sampled; prints the share of failing runs the sample rules out at 95 %%",
    )
    ap.add_argument(
        "--byte-fault",
        metavar="LINK:KIND:BYTE",
        default=None,
        help="--exhaustive --only SEQUENCE: replay that sequence with one byte fault "
        "(uart:lose|duplicate|corrupt:BYTE or usb:tail_loss:BYTE), as a failed run prints it",
    )
    ap.add_argument(
        "--encoding",
        choices=("plain", "robust"),
        default=None,
        help="--byte-faults / --byte-fault: the devices' encoding (default plain, every port's default); "
        "robust, the loss-tolerant one, fails a run whose byte lost on a UART is followed by a pulse "
        "above the limit",
    )
    ap.add_argument(
        "--kinds",
        metavar="LINK:KIND,...",
        default=None,
        help="--byte-faults: strike only these faults (uart:lose, uart:duplicate, uart:corrupt, "
        "usb:tail_loss; default all), numbering the runs among them",
    )
    ap.add_argument(
        "--firmware-src",
        metavar="DIR",
        default=None,
        help="run every session's board on this firmware tree built on the host "
        "(docs/firmware-host-build.md); "
        "its state map's version must be --firmware",
    )
    a = ap.parse_args(argv)
    if a.firmware_src is not None:
        if a.seams or a.exhaustive:
            ap.error("--firmware-src runs the random sessions only (not --seams or --exhaustive)")
        a.firmware = a.firmware or "v1.2"
        _use_firmware_src(ap, a.firmware_src, a.firmware)
    logging.disable(logging.WARNING)  # the guard logs each refusal; the summary counts them
    if a.sessions < 1:
        ap.error(f"--sessions must be at least 1 (got {a.sessions})")
    if a.jobs < 1:
        ap.error(f"--jobs must be at least 1 (got {a.jobs})")
    if a.chunk < 1:
        ap.error(f"--chunk must be at least 1 (got {a.chunk})")
    if a.cluster is not None:
        try:
            engine.parse_cluster(a.cluster)
        except ConfigurationError as exc:
            ap.error(str(exc))
    if (a.byte_faults or a.byte_fault is not None) and not a.exhaustive:
        ap.error("--byte-faults and --byte-fault apply to --exhaustive")
    if a.encoding is not None and not (a.byte_faults or a.byte_fault is not None):
        ap.error("--encoding applies to --exhaustive --byte-faults and --byte-fault")
    if a.kinds is not None:
        if not a.byte_faults:
            ap.error("--kinds applies to --exhaustive --byte-faults")
        import byte_fault_campaign

        try:
            byte_fault_campaign.parse_kinds(a.kinds)
        except ValueError as exc:
            ap.error(str(exc))
    if a.runs is not None:
        if not a.byte_faults:
            ap.error("--runs applies to --exhaustive --byte-faults")
        import byte_fault_campaign

        try:
            byte_fault_campaign.parse_runs(a.runs)
        except ValueError as exc:
            ap.error(str(exc))
    if a.sample is not None:
        if not a.byte_faults:
            ap.error("--sample applies to --exhaustive --byte-faults")
        if a.runs is not None:
            ap.error("--sample draws from the whole enumeration: give it or --runs, not both")
        if a.sample < 1:
            ap.error(f"--sample must be at least 1 (got {a.sample})")
    if a.seams:
        import seam_sessions

        return seam_sessions.main(a)
    if a.exhaustive:
        if a.depth < 0:
            ap.error(f"--depth must be at least 0 (got {a.depth})")
        if a.byte_fault is not None:
            if a.only is None:
                ap.error("--byte-fault replays one run: give the sequence with --only")
            import byte_fault_campaign

            try:
                byte_fault_campaign.parse_spec(a.byte_fault)
            except ValueError as exc:
                ap.error(str(exc))
            return byte_fault_campaign.main(a)
        if a.byte_faults:
            import byte_fault_campaign

            return byte_fault_campaign.main(a)
        import exhaustive_campaign

        return exhaustive_campaign.main(a)
    a.firmware = a.firmware or "v1.2"
    firmwares = FIRMWARES if a.firmware == "both" else (a.firmware,)
    if a.only is not None:
        rows = [run_session(a.only, a.seed, a.faults, fw) for fw in firmwares]
        out = [{**asdict(r), "ok": r.ok, "defect_counts": r.defect_counts} for r in rows]
        print(json.dumps(out[0] if len(out) == 1 else out, indent=1, default=str))
        _report_failures(
            [{"index": r.index, "why": r.failure(), "reproduce": r.reproduce()} for r in rows if not r.ok]
        )
        return 0 if all(r.ok for r in rows) else 1
    summaries: list[dict[str, Any]] = []
    for fw in firmwares:
        t0 = time.perf_counter()
        job = campaign_job(
            a.sessions,
            seed=a.seed,
            faults=a.faults,
            first=a.first,
            firmware=fw,
            chunk=a.chunk,
            firmware_src=a.firmware_src,
        )
        summary = engine.run(job, jobs=a.jobs, cluster=a.cluster, progress=True).summary()
        where = {"jobs": a.jobs} if a.cluster is None else {"cluster": a.cluster}
        summary.update({"seed": a.seed, **where, "wall_s": round(time.perf_counter() - t0, 3)})
        summaries.append(summary)
    if a.json:
        print(json.dumps(summaries[0] if len(summaries) == 1 else summaries, indent=1))
    else:
        print("\n\n".join(_table(s) for s in summaries))
    for s in summaries:
        _report_failures(s["failures"], s["failed_sessions"], s["firmware"])
    return 0 if all(s["failed_sessions"] == 0 for s in summaries) else 1


if __name__ == "__main__":
    raise SystemExit(main())
