"""Every sequence of up to ``depth`` public ``Device`` calls from a small domain, on the timed emulator,
judged on the pulses it delivered (``safety_campaign.py --exhaustive [--depth N] [--firmware F]``).

Where the random campaign samples, this mode enumerates: no sequence of the domain below, from any start
below, on either firmware, is left out, so a bound proved here holds for every such sequence rather than
for those a seed drew.

The domain (:data:`CALLS`; every parameter from a small set that holds its edges):

* ``configure(N)`` for electrode counts N of 1, 32 and 255, at the session's cap (:data:`CAP_UA`), pulse
  width :data:`WIDTH_US`, at the fastest of 100 Hz and the rate whose biphasic frame of N fits its period;
* ``send_pattern``: the even electrodes on, monophasic; the even electrodes on, biphasic; every electrode
  off (the odd electrodes are meant off in every pattern: a pulse on one is judged);
* ``set_current`` of 0, the cap, and one DAC step above the cap (the guard must refuse it: a pulse above
  the cap is judged);
* ``keepalive``, ``all_off``, ``suspend``, ``probe``, ``resync``, ``reconnect``, ``hardware_reset``, and
  ``close`` followed by a new device on the same port (a program that opens the board again);
* time passing: none (the next call at once), one scan period of the configuration, and the fail-safe's
  default watchdog (:data:`~tactdeform_hw.device.safety.failsafe.DEFAULT_WATCHDOG_S`).

Starts (:data:`STARTS`), one per recovery state (``LinkState``) in which a call can begin without a
fault: ``IN_STEP`` (a fresh open, nothing configured; and a board configured with 32 electrodes and
stimulating the even ones at the cap) and ``SUSPECT`` (that stimulating board after ``mark_unknown``,
what a fail-safe does after a timeout or a wrong readback: the next call begins with the closed-loop
resync).  Every other state (``SYNCING``, ``FLUSHING``, ``SAFE``, ``VERIFYING``, ``DRAINING``,
``RESETTING``, ``BOOTING``) lives inside a call, and ``FAILED`` needs a locked parser, which only a fault
makes.  Each start is checked to be in its state before the sequence runs.

Firmware v1.2 and v2, on the USB link (the UART's own timing is the random campaign's and the seam
sessions'), the guard's cap at :data:`CAP_UA` on both.  Sequence ``i`` is decoded from its index
(firmware, start, length, calls: :func:`decode`), so the sequences split into chunks by index like the
random campaign's sessions and run on ``--jobs`` or ``--cluster`` with the same figures.

The verdict, on the delivered pulses alone: no pulse above the session's limit (the cap, whatever the
guard believes: the judge does not ask the guard), and no stimulation pulse on an electrode the host had
switched off for longer than the settle time (``safety_campaign.SETTLE_S``), and no byte lost in the
device's receive queue (as the random campaign's fault-free verdict: no fault is injected here, so a byte
the queue discarded is one the driver wrote faster than the firmware reads — on v1.2 a loss the host may
never notice).  Hazards the emulated board recorded are counted by kind beside the verdict, with the
defects (the other hazards the random campaign judges: every kind not designed on that firmware, such as
v1.2's torn patterns); those are reported, not judged here.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import campaign_engine as engine  # noqa: E402
import safety_campaign as sc  # noqa: E402

from tactdeform_hw.device import EtactileKitDevice, StimConfig  # noqa: E402
from tactdeform_hw.device.driver.base import LinkState  # noqa: E402
from tactdeform_hw.device.driver.pacing import estimate_scan_us, firmware_period_us  # noqa: E402
from tactdeform_hw.device.safety.failsafe import DEFAULT_WATCHDOG_S  # noqa: E402
from tactdeform_hw.device.safety.guard import SafetyGuard  # noqa: E402
from tactdeform_hw.emulator.faults import TimedPort  # noqa: E402
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator  # noqa: E402
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2  # noqa: E402
from tactdeform_hw.errors import TactDeformError  # noqa: E402
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER  # noqa: E402

#: The session's limit and the guard's cap (µA).
CAP_UA = 1500
#: One DAC step above the cap: a request the guard must refuse.
ABOVE_CAP_UA = CAP_UA + DEFAULT_TRANSFER.step_ua
#: Pulse width of every configuration (µs).
WIDTH_US = 50
#: Electrode counts a configuration takes.
ELECTRODES = (1, 32, 255)
#: Electrodes of the stimulating starts.
START_ELECTRODES = 32
LINK = "usb"
#: Default depth of the enumeration.
DEFAULT_DEPTH = 4


def config(n: int) -> StimConfig:
    """The configuration of ``n`` electrodes: at the cap, at 100 Hz or the fastest rate whose biphasic
    frame fits its period (as the random campaign chooses)."""
    worst = estimate_scan_us(bytes([2]) * n, WIDTH_US, 0, 0)
    rate = max(1, min(100, int(1e6 / (worst * 1.25 + 1500))))
    return StimConfig(electrode_count=n, current_ua=CAP_UA, pulse_width_us=WIDTH_US, rate_hz=rate)


def even_on(n: int, level: int) -> tuple[int, ...]:
    """The even electrodes at ``level`` (1 monophasic, 2 biphasic), the odd ones off."""
    return tuple(level if e % 2 == 0 else 0 for e in range(n))


@dataclass(frozen=True)
class Call:
    """One call of the domain: its name and what it does to a session."""

    name: str
    run: Callable[[ExhaustiveSession], None]


def _configure(n: int) -> Call:
    return Call(f"configure({n})", lambda s: s.configure(n))


def _pattern(name: str, level: int | None) -> Call:
    return Call(f"send_pattern({name})", lambda s: s.pattern(level))


def _current(name: str, ua: int) -> Call:
    return Call(f"set_current({name})", lambda s: s.set_current(ua))


def _plain(name: str) -> Call:
    return Call(name, lambda s: s.plain(name))


#: The domain, in the order the index enumerates it (see the module's docstring).
CALLS: tuple[Call, ...] = (
    *(_configure(n) for n in ELECTRODES),
    _pattern("even mono", 1),
    _pattern("even biphasic", 2),
    _pattern("off", None),
    _current("0", 0),
    _current("cap", CAP_UA),
    _current("cap+step", ABOVE_CAP_UA),
    *(
        _plain(n)
        for n in ("keepalive", "all_off", "suspend", "probe", "resync", "reconnect", "hardware_reset")
    ),
    Call("close+reopen", lambda s: s.reopen()),
    Call("wait(scan)", lambda s: s.wait_scan()),
    Call("wait(watchdog)", lambda s: s.port.advance(DEFAULT_WATCHDOG_S)),
)
#: Starts: name -> the recovery state a call begins in (see the module's docstring).
STARTS: dict[str, LinkState] = {
    "fresh": LinkState.IN_STEP,
    "stimulating": LinkState.IN_STEP,
    "stimulating_suspect": LinkState.SUSPECT,
}
FIRMWARES = sc.FIRMWARES


def make_guard() -> SafetyGuard:
    """The guard of every device of a session: the cap."""
    return SafetyGuard(CAP_UA)


def per_start(depth: int) -> int:
    """Sequences of length 0 .. ``depth`` from one start on one firmware."""
    return sum(len(CALLS) ** k for k in range(depth + 1))


def count(depth: int, firmwares: Sequence[str] = FIRMWARES) -> int:
    """Every sequence the enumeration runs."""
    return len(firmwares) * len(STARTS) * per_start(depth)


def decode(index: int, depth: int, firmwares: Sequence[str] = FIRMWARES) -> tuple[str, str, tuple[int, ...]]:
    """Sequence ``index``: (firmware, start, the indices into :data:`CALLS`), shortest sequences first."""
    if not 0 <= index < count(depth, firmwares):
        raise IndexError(f"sequence {index}: 0 to {count(depth, firmwares) - 1} at depth {depth}")
    per = per_start(depth)
    fw, rest = divmod(index, len(STARTS) * per)
    start, rest = divmod(rest, per)
    length = 0
    while rest >= len(CALLS) ** length:
        rest -= len(CALLS) ** length
        length += 1
    calls = []
    for _ in range(length):
        rest, c = divmod(rest, len(CALLS))
        calls.append(c)
    return firmwares[fw], list(STARTS)[start], tuple(reversed(calls))


class ExhaustiveSession(sc.Session):
    """A session whose configuration and calls are given, not drawn; judged by the random campaign's
    judge (``Session.judge``), against the cap on every electrode."""

    def __init__(  # noqa: PLR0915
        self, index: int, firmware: str, start: str, link: str = LINK, *, robust: bool = False
    ) -> None:
        """``robust``: the devices use the loss-tolerant encoding (the byte-fault mode's ``--encoding
        robust``); the domain's own runs use the plain one, the default of every port."""
        self.firmware = firmware
        self.link = link
        self.robust = robust
        self.cfg = config(START_ELECTRODES)
        self.biphasic = True
        self.regions = False
        self.cap_ua = CAP_UA
        boards = (max(ELECTRODES) + 31) // 32
        emu = (TimedEmulatorV2 if firmware == "v2" else TimedEmulator)("compact", boards, link=link)
        self.port = TimedPort(emu, link=link, faults=[], seed=index, robust_encoding=robust)
        self.notices = []
        self.refused_spans = []
        self.failsafe = None
        self.res = sc.SessionResult(index, index, LINK, robust, START_ELECTRODES, [], CAP_UA, 0)
        self.res.firmware = firmware
        self.res.cap_ua = CAP_UA
        self.dev = self._new_device()
        self.devices = [self.dev]
        self.intents = [(0.0, (0,) * START_ELECTRODES, 0.0)]
        self.sent = None
        self.longest_call_s = 0.0
        self.refused = False
        if start != "fresh":
            self.configure(START_ELECTRODES)
            self.pattern(1)
        if start == "stimulating_suspect":
            self.dev.mark_unknown()
        if self.dev.link_state is not STARTS[start]:
            raise AssertionError(f"start {start}: {self.dev.link_state} rather than {STARTS[start]}")

    def _new_device(self) -> EtactileKitDevice:
        return EtactileKitDevice(self.port, firmware=self.firmware, guard=make_guard())  # type: ignore[arg-type]  # (TimedPort.timeout: a float)

    def electrode_limits_ua(self) -> list[float]:
        """The cap on every channel: the session's limit, not what the guard believes."""
        return [float(CAP_UA)] * 256

    # --- the calls of the domain -------------------------------------------------------------------------

    def configure(self, n: int) -> None:
        cfg = config(n)
        if self._call("configure", lambda: self.dev.configure(cfg), (0,) * n) or not self.refused:
            self.cfg = cfg
            self.res.electrodes = max(self.res.electrodes, n)
            self.sent = None

    def pattern(self, level: int | None) -> None:
        n = self.cfg.electrode_count
        pat = even_on(n, level) if level is not None else (0,) * n
        if self._call("send_pattern", lambda: self.dev.send_pattern(pat), pat) or not self.refused:
            self.sent = pat

    def set_current(self, ua: int) -> None:
        self._call("set_current", lambda: self.dev.set_current(ua))

    def plain(self, name: str) -> None:
        off = (0,) * self.cfg.electrode_count
        intent = {"keepalive": self.sent, "probe": None}.get(name, off)
        if self._call(name, getattr(self.dev, name), intent) and name == "all_off":
            self.sent = None

    def reopen(self) -> None:
        self._call("close", self.dev.close, (0,) * self.cfg.electrode_count)
        self.sent = None
        self.res.calls.append("reopen")
        try:
            self.dev = self._new_device()
        except TactDeformError as exc:
            self.res.errors.append(f"reopen: {exc}"[:160])
            return
        self.devices.append(self.dev)
        self.cfg = config(START_ELECTRODES)  # a new program: nothing configured yet (judged as off)
        if self.failsafe is not None:  # the new program runs its own fail-safe
            self._start_failsafe()

    def wait_scan(self) -> None:
        self.res.calls.append("wait")
        self.port.advance(firmware_period_us(self.cfg.rate_hz) / 1e6)

    def run_calls(self, calls: Sequence[int]) -> None:
        for c in calls:
            CALLS[c].run(self)
        self._call("close", self.dev.close, (0,) * self.cfg.electrode_count)
        self.port.advance(0.03)


def run_sequence(index: int, depth: int, firmwares: Sequence[str] = FIRMWARES) -> sc.SessionResult:
    """Run and judge sequence ``index``."""
    firmware, start, calls = decode(index, depth, firmwares)
    wall = time.perf_counter()
    s = ExhaustiveSession(index, firmware, start)
    try:
        s.run_calls(calls)
    except Exception as exc:  # noqa: BLE001 - a crash of the driver is a finding, reported with the sequence
        s.res.errors.append(f"CRASH {type(exc).__name__}: {exc}"[:200])
    res = s.judge()
    res.wall_s = time.perf_counter() - wall
    return res


def describe(index: int, depth: int, firmwares: Sequence[str] = FIRMWARES) -> str:
    firmware, start, calls = decode(index, depth, firmwares)
    return f"{firmware} from {start}: " + (", ".join(CALLS[c].name for c in calls) or "(no call)")


#: Errors that refuse a call before anything is sent (their class names, as a session records them).
_REFUSALS = frozenset(c.__name__ for c in sc.REFUSALS)


def _failed(r: sc.SessionResult) -> bool:
    return bool(r.over_limit or r.meant_off or r.lost_bytes or any(e.startswith("CRASH") for e in r.errors))


@dataclass
class ExhaustiveTally:
    """The enumeration's figures, merged exactly and in any order (the failures of lowest index kept)."""

    depth: int
    firmwares: tuple[str, ...]
    items: int = 0
    failed: int = 0
    pulses: int = 0
    over_limit: int = 0
    meant_off: int = 0
    refusals: int = 0  # calls refused (nothing sent): the guard's cap+step among them
    errors: int = 0
    max_stim_ua: float = 0.0
    hazards: dict[str, int] = field(default_factory=dict)
    lost_bytes: int = 0  # bytes lost in the device's receive queue (a sequence that loses any fails)
    defect_sequences: int = 0  # sequences that hit a hazard not designed on their firmware
    defects: dict[str, int] = field(default_factory=dict)  # records per kind, per firmware
    failures: list[tuple[int, dict[str, Any]]] = field(default_factory=list)

    def add(self, r: sc.SessionResult) -> None:
        self.items += 1
        self.pulses += r.pulses
        self.over_limit += r.over_limit
        self.meant_off += r.meant_off
        self.errors += len(r.errors)
        self.refusals += sum(1 for e in r.errors if e.split(": ")[1:2] and e.split(": ")[1] in _REFUSALS)
        self.max_stim_ua = max(self.max_stim_ua, r.max_stim_ua)
        sc._add_counts(self.hazards, r.hazard_counts)
        self.lost_bytes += r.lost_bytes
        self.defect_sequences += bool(r.defects)
        sc._add_counts(self.defects, {f"{r.firmware} {k}": n for k, n in r.defect_counts.items()})
        if _failed(r):
            self.failed += 1
            why = r.failure() or "; ".join(e for e in r.errors if e.startswith("CRASH"))
            row = {
                "index": r.index,
                "sequence": describe(r.index, self.depth, self.firmwares),
                "why": why,
                "first_violation": r.first_violation,
                "reproduce": reproduce(r.index, self.depth, self.firmwares),
            }
            self.failures = sorted([*self.failures, (r.index, row)], key=lambda f: f[0])[: sc.LISTED_FAILURES]

    def merge(self, o: ExhaustiveTally) -> None:
        for name in ("items", "failed", "pulses", "over_limit", "meant_off", "refusals", "errors"):
            setattr(self, name, getattr(self, name) + getattr(o, name))
        self.lost_bytes += o.lost_bytes
        self.defect_sequences += o.defect_sequences
        self.max_stim_ua = max(self.max_stim_ua, o.max_stim_ua)
        sc._add_counts(self.hazards, o.hazards)
        sc._add_counts(self.defects, o.defects)
        self.failures = sorted(self.failures + o.failures, key=lambda f: f[0])[: sc.LISTED_FAILURES]

    def summary(self) -> dict[str, Any]:
        return {
            "mode": "exhaustive",
            "depth": self.depth,
            "firmware": "+".join(self.firmwares),
            "calls_in_domain": len(CALLS),
            "starts": {k: v.value for k, v in STARTS.items()},
            "sequences": self.items,
            "failed_sequences": self.failed,
            "pulses": self.pulses,
            "over_limit_pulses": self.over_limit,
            "meant_off_pulses": self.meant_off,
            "largest_pulse_ua": round(self.max_stim_ua, 3),
            "limit_ua": CAP_UA,
            "refused_calls": self.refusals,
            "caller_errors": self.errors,
            "hazards_by_kind": dict(sorted(self.hazards.items())),
            "bytes_lost": self.lost_bytes,
            "defect_sequences": self.defect_sequences,
            "defects_by_firmware_and_kind": dict(sorted(self.defects.items())),
            "failures": [row for _, row in self.failures],
        }


def reproduce(index: int, depth: int, firmwares: Sequence[str]) -> str:
    fw = firmwares[0] if len(firmwares) == 1 else "both"
    return f"python tools/safety_campaign.py --exhaustive --depth {depth} --firmware {fw} --only {index}"


def tally_chunk(depth: int, firmwares: tuple[str, ...], first: int, count_: int) -> ExhaustiveTally:
    """Sequences ``first .. first + count_ - 1`` (a chunk of a distributed enumeration)."""
    logging.disable(logging.WARNING)  # the guard logs each refusal; the tally counts them
    t = ExhaustiveTally(depth, firmwares)
    for i in range(first, first + count_):
        t.add(run_sequence(i, depth, firmwares))
    return t


def job(
    depth: int,
    firmwares: tuple[str, ...],
    chunk: int = engine.DEFAULT_CHUNK,
    first: int = 0,
    total: int = 0,
) -> engine.Job:
    """The sequences ``first ..`` (``total`` of them; 0: to the last) as chunks for
    :func:`campaign_engine.run`."""
    return engine.Job(
        "exhaustive_campaign",
        "tally_chunk",
        (depth, firmwares),
        total or count(depth, firmwares) - first,
        first=first,
        chunk=chunk,
        fingerprint=engine.fingerprint(),
        unit="sequences",
    )


def main(a: Any) -> int:
    """``safety_campaign.py --exhaustive``: the parsed arguments of the campaign's command line."""
    firmwares = FIRMWARES if a.firmware in (None, "both") else (a.firmware,)
    if a.only is not None:
        r = run_sequence(a.only, a.depth, firmwares)
        row = {"sequence": describe(a.only, a.depth, firmwares), **asdict(r), "ok": not _failed(r)}
        print(json.dumps(row, indent=1, default=str))
        if _failed(r):
            print(f"FAILED sequence {a.only}: {r.failure()}", file=sys.stderr)
        return 1 if _failed(r) else 0
    t0 = time.perf_counter()
    total = count(a.depth, firmwares)
    print(
        f"exhaustive: {total} sequences of up to {a.depth} calls ({len(CALLS)} in the domain) from "
        f"{len(STARTS)} starts on {' and '.join(firmwares)}",
        file=sys.stderr,
    )
    tally = engine.run(job(a.depth, firmwares, a.chunk), jobs=a.jobs, cluster=a.cluster, progress=True)
    summary = tally.summary()
    where = {"jobs": a.jobs} if a.cluster is None else {"cluster": a.cluster}
    summary.update({**where, "wall_s": round(time.perf_counter() - t0, 3)})
    if a.json:
        print(json.dumps(summary, indent=1))
    else:
        width = max(map(len, summary))
        print("\n".join(f"{k:<{width}}  {v}" for k, v in summary.items() if k != "failures"))
    for f in summary["failures"]:
        print(
            f"FAILED sequence {f['index']} ({f['sequence']}): {f['why']} -- reproduce: {f['reproduce']}",
            file=sys.stderr,
        )
    if summary["failed_sequences"] > len(summary["failures"]):
        print(f"... and {summary['failed_sequences'] - len(summary['failures'])} more", file=sys.stderr)
    return 0 if summary["failed_sequences"] == 0 else 1
