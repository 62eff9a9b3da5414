"""The exhaustive campaign's sequences again, each with one fault at each byte the host writes
(``safety_campaign.py --exhaustive --depth N --byte-faults``).

Where ``--faults`` strikes at random times, this mode enumerates the fault's place: for every sequence of
the exhaustive domain (:mod:`exhaustive_campaign`: every sequence of up to ``--depth`` public ``Device``
calls from each start, on each firmware), and for every byte the host writes from the sequence's first
call to the end of its closing ``close`` (the driver's and the fail-safe's bytes alike; the start's own
setup is the same for every sequence of a start and is not struck):

* on a UART (921 600 baud): that byte **lost**, that byte **duplicated**, and that byte **corrupted**
  (XORed with :data:`~tactdeform_hw.emulator.faults.CORRUPT_XOR`, 0xFF: every bit flipped) — three runs
  per byte;
* on USB full speed: the bulk packet that carries that byte **loses its tail** from that byte on (the
  packet's first ``k`` bytes arrive, for every packet and every ``k`` from 0 to its length - 1) — one
  run per byte.

One fault per run (:class:`~tactdeform_hw.emulator.faults.ByteFault`, applied where the host's bytes enter
the emulated link and recorded with the other injected faults).  A sequence's byte counts come from its
fault-free run (a first pass, :func:`count_chunk`): until its byte is written a faulty run is that run,
byte for byte (simulated time, no randomness), so every fault strikes; one that does not is a failure.

Every run keeps the fail-safe running as ``--faults`` sessions do (probes every 20 ms with the readback,
a refresh every 50 ms, a 100 ms watchdog) and is judged by the random campaign's fault verdict
(``safety_campaign.Session._judge_faults``): every wrong delivery — a pulse above the session's limit
(the cap), a stimulation pulse on an electrode meant off (the odd electrodes always, every electrode
after ``all_off``, ``suspend`` or ``close``) — starts within the documented recovery bound of the fault
(the fail-safe's ``recovery_bound_s`` plus the longest call plus the settle time), and every byte lost
— the byte the fault removed, the tail a packet lost, and any byte the receive queue discarded after it
— was reported to the caller within that bound (a raised error, a failed proof, a recovery, or lost
while the driver had no proof of the parser's state), or, counted apart, rewritten by a resync the caller
asked for, or shown by a later proof with the readback to have had no effect.  A run that breaks either
is a failure, printed with the one command that replays it
(``--exhaustive --depth N --firmware F --only SEQUENCE --byte-fault LINK:KIND:BYTE``).

Runs are numbered: sequence by sequence (the exhaustive order), and within a sequence the UART's lost,
duplicated and corrupted bytes, then USB's tails, each by byte; a run is decoded from its number and the
first pass's byte counts, so the runs split into chunks like the other campaigns and give the same
figures on ``--jobs`` and ``--cluster``.
"""

from __future__ import annotations

import bisect
import json
import logging
import random
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from itertools import accumulate
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import campaign_engine as engine  # noqa: E402
import exhaustive_campaign as ex  # noqa: E402
import safety_campaign as sc  # noqa: E402

from tactdeform_hw.device import EtactileKitDevice  # noqa: E402
from tactdeform_hw.emulator.faults import ByteFault, ByteFaultKind  # noqa: E402
from tactdeform_hw.errors import TactDeformError  # noqa: E402

#: The links a sequence runs on, and the faults each byte gets there (in the order runs are numbered).
KINDS: dict[str, tuple[ByteFaultKind, ...]] = {
    "uart": (ByteFaultKind.LOSE, ByteFaultKind.DUPLICATE, ByteFaultKind.CORRUPT),
    "usb": (ByteFaultKind.TAIL_LOSS,),
}
LINKS = tuple(KINDS)
#: Faults that remove bytes (judged as lost bytes: each must be reported).
_LOSING = (ByteFaultKind.LOSE, ByteFaultKind.TAIL_LOSS)
#: Every ``LINK:KIND`` of the enumeration, in its order.
ALL_KINDS = tuple(f"{link}:{kind.value}" for link in LINKS for kind in KINDS[link])
ENCODINGS = ("plain", "robust")
#: The error that fails a run in which a byte lost on a UART under the robust encoding was followed by a
#: pulse above the limit: that encoding promises a lost byte can only lower a value or leave it.
ROBUST_LOSS = "LOST BYTE ABOVE THE LIMIT"


@dataclass(frozen=True)
class Mode:
    """What an enumeration runs: the devices' encoding (``plain``, every port's default, or ``robust``,
    the loss-tolerant one) and the faults struck (``LINK:KIND`` of :data:`ALL_KINDS`, in its order).
    Runs are numbered within the mode: a replay names its encoding, not its kinds."""

    encoding: str = "plain"
    kinds: tuple[str, ...] = ALL_KINDS

    @property
    def robust(self) -> bool:
        return self.encoding == "robust"

    def kinds_on(self, link: str) -> tuple[ByteFaultKind, ...]:
        """The faults struck on ``link``, in the enumeration's order."""
        return tuple(k for k in KINDS[link] if f"{link}:{k.value}" in self.kinds)


PLAIN = Mode()


def parse_kinds(text: str) -> tuple[str, ...]:
    """``LINK:KIND[,LINK:KIND...]`` (``uart:lose``), in the enumeration's order; a ``ValueError`` naming
    what is wrong."""
    asked = [k.strip() for k in text.split(",") if k.strip()]
    unknown = [k for k in asked if k not in ALL_KINDS]
    if not asked or unknown:
        raise ValueError(f"--kinds {text!r}: a comma-separated list of {', '.join(ALL_KINDS)}")
    return tuple(k for k in ALL_KINDS if k in asked)


@dataclass(frozen=True)
class Run:
    """One faulty run: the sequence (its exhaustive index), the link, the fault and the byte it strikes
    (counted from the sequence's first byte)."""

    sequence: int
    link: str
    kind: ByteFaultKind
    byte: int

    def spec(self) -> str:
        """``LINK:KIND:BYTE``, as ``--byte-fault`` takes it."""
        return f"{self.link}:{self.kind.value}:{self.byte}"


def parse_runs(text: str) -> tuple[int, int]:
    """``FIRST:END`` (runs ``FIRST`` to ``END - 1``); a ``ValueError`` naming what is wrong."""
    first, sep, end = text.partition(":")
    if not (sep and first.isdigit() and end.isdigit() and int(first) < int(end)):
        raise ValueError(f"--runs {text!r}: FIRST:END with 0 <= FIRST < END, e.g. 0:5000")
    return int(first), int(end)


def parse_spec(text: str) -> tuple[str, ByteFaultKind, int]:
    """``LINK:KIND:BYTE`` (``uart:corrupt:17``); a ``ValueError`` naming what is wrong."""
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"--byte-fault {text!r}: LINK:KIND:BYTE, e.g. uart:corrupt:17")
    link, kind, byte = parts
    if link not in KINDS:
        raise ValueError(f"--byte-fault {text!r}: link {link!r} is one of {', '.join(LINKS)}")
    names = [k.value for k in KINDS[link]]
    if kind not in names:
        raise ValueError(f"--byte-fault {text!r}: on {link} the kind is one of {', '.join(names)}")
    if not byte.isdigit():
        raise ValueError(f"--byte-fault {text!r}: BYTE {byte!r} is an integer >= 0")
    return link, ByteFaultKind(kind), int(byte)


class ByteFaultSession(ex.ExhaustiveSession):
    """An exhaustive sequence on ``link`` with the fail-safe running, and at most one byte fault."""

    def __init__(self, index: int, firmware: str, start: str, link: str, *, robust: bool = False) -> None:
        super().__init__(index, firmware, start, link, robust=robust)
        self._start_failsafe()
        self.base: int = int(self.port.emulator.host_offset)  # the sequence's first byte

    def _new_device(self) -> EtactileKitDevice:
        """Open the board as a program does: an open a fault spoiled is refused (the program knows), and
        the program opens it again (as the random campaign's sessions)."""
        for attempt in range(1, sc.OPEN_ATTEMPTS + 1):
            began = self.port.now_s
            try:
                return super()._new_device()
            except TactDeformError:
                self.notices.append(self.port.now_s)
                self.refused_spans.append((began, self.port.now_s))
                if attempt == sc.OPEN_ATTEMPTS:
                    raise
                self.port.advance(0.1)
        raise AssertionError("unreachable")

    def strike(self, kind: ByteFaultKind, byte: int) -> None:
        """The sequence's byte ``byte`` (from its first) gets ``kind``."""
        self.port.faulty_link.add_byte_fault(ByteFault(kind, self.base + byte))

    @property
    def bytes_written(self) -> int:
        """Bytes the host wrote since the sequence's first call."""
        return int(self.port.emulator.host_offset) - self.base

    def run_calls(self, calls: Sequence[int]) -> None:
        """The calls, the closing ``close``, then the fail-safe's tail (as a ``--faults`` session)."""
        try:
            for c in calls:
                ex.CALLS[c].run(self)
            self._call("close", self.dev.close, (0,) * self.cfg.electrode_count)
            self.port.advance(sc.fault_tail_s(self.firmware))
        finally:
            self.failsafe.stop()

    def lost_bytes_at(self) -> list[tuple[float, int]]:
        """The receive queue's losses, and the bytes the fault itself removed (when it struck)."""
        struck = [
            (f.t_s, int(f.detail["bytes"])) for f in self.port.faulty_link.injected if f.kind in _LOSING
        ]
        return sorted(super().lost_bytes_at() + struck)


def _session(firmware: str, start: str, sequence: int, link: str, robust: bool) -> ByteFaultSession:
    return ByteFaultSession(sequence, firmware, start, link, robust=robust)


def run_one(run: Run, depth: int, firmwares: Sequence[str], mode: Mode = PLAIN) -> sc.SessionResult:
    """Run and judge one faulty run (a fault that did not strike is recorded as an error: a failure; under
    the robust encoding, so is a byte lost on a UART followed by a pulse above the limit, whatever the
    bound: that encoding promises a lost byte can only lower a value or leave it)."""
    firmware, start, calls = ex.decode(run.sequence, depth, firmwares)
    wall = time.perf_counter()
    s = _session(firmware, start, run.sequence, run.link, mode.robust)
    s.strike(run.kind, run.byte)
    try:
        s.run_calls(calls)
    except Exception as exc:  # noqa: BLE001 - a crash of the driver is a finding, reported with the run
        s.res.errors.append(f"CRASH {type(exc).__name__}: {exc}"[:200])
    res = s.judge()
    if not s.port.faulty_link.injected:
        res.errors.append(f"NOT STRUCK: byte {run.byte} of {s.bytes_written} written")
    if mode.robust and run.kind is ByteFaultKind.LOSE and res.over_limit:
        res.errors.append(
            f"{ROBUST_LOSS}: {res.over_limit} pulses above {ex.CAP_UA} uA under the robust encoding, the "
            f"largest {res.max_stim_ua:.0f} uA"
        )
    res.link = run.link
    res.wall_s = time.perf_counter() - wall
    return res


#: The errors a run records of its own (not the caller's): each fails the run.
_RUN_ERRORS = ("CRASH", "NOT STRUCK", ROBUST_LOSS)


def failed(r: sc.SessionResult) -> bool:
    """The run's verdict: a wrong delivery past the bound, a loss unreported, a crash, a fault that did
    not strike, a lost byte above the limit under the robust encoding."""
    return (not r.faults) or not r.ok or any(e.startswith(_RUN_ERRORS) for e in r.errors)


def why(r: sc.SessionResult) -> str:
    return "; ".join(x for x in (r.failure(), *(e for e in r.errors if e.startswith(_RUN_ERRORS))) if x)


def _add_counts(into: dict[str, int], more: dict[str, int]) -> None:
    for k, n in more.items():
        into[k] = into.get(k, 0) + n


# --- the first pass: each sequence's bytes on each link -----------------------------------------------------


@dataclass
class CountTally:
    """Per sequence, the bytes its fault-free run writes on each link (merged exactly, in any order)."""

    items: int = 0
    pulses: int = 0
    failed: int = 0
    written: dict[int, tuple[int, ...]] = field(default_factory=dict)

    def merge(self, o: CountTally) -> None:
        self.items += o.items
        self.pulses += o.pulses
        self.failed += o.failed
        self.written.update(o.written)


def count_chunk(depth: int, firmwares: tuple[str, ...], mode: Mode, first: int, count_: int) -> CountTally:
    """The fault-free runs of sequences ``first .. first + count_ - 1`` on each link the mode strikes: their
    byte counts (0 on a link it does not)."""
    logging.disable(logging.WARNING)
    t = CountTally()
    for i in range(first, first + count_):
        firmware, start, calls = ex.decode(i, depth, firmwares)
        row = []
        for link in LINKS:
            if not mode.kinds_on(link):
                row.append(0)
                continue
            s = _session(firmware, start, i, link, mode.robust)
            try:
                s.run_calls(calls)
            except Exception as exc:  # noqa: BLE001 - reported by the faulty runs of the sequence
                s.res.errors.append(f"CRASH {type(exc).__name__}: {exc}"[:200])
            row.append(s.bytes_written)
        t.items += 1
        t.written[i] = tuple(row)
    return t


def runs_per_sequence(written: Sequence[int], mode: Mode = PLAIN) -> int:
    """Faulty runs of a sequence that writes ``written[k]`` bytes on ``LINKS[k]``."""
    return sum(len(mode.kinds_on(link)) * n for link, n in zip(LINKS, written, strict=True))


def decode_run(
    index: int, table: Sequence[Sequence[int]], ends: Sequence[int] | None = None, mode: Mode = PLAIN
) -> Run:
    """Run ``index`` of the enumeration whose sequences write ``table[s]`` bytes on each link; ``ends``:
    the running totals of runs per sequence (computed when not given)."""
    ends = list(accumulate(runs_per_sequence(w, mode) for w in table)) if ends is None else ends
    if not 0 <= index < (ends[-1] if ends else 0):
        raise IndexError(f"run {index}: 0 to {(ends[-1] if ends else 0) - 1}")
    seq = bisect.bisect_right(ends, index)
    rest = index - (ends[seq - 1] if seq else 0)
    for link, n in zip(LINKS, table[seq], strict=True):
        for kind in mode.kinds_on(link):
            if rest < n:
                return Run(seq, link, kind, rest)
            rest -= n
    raise AssertionError("unreachable")


# --- the faulty runs ----------------------------------------------------------------------------------------


@dataclass
class ByteFaultTally:
    """The faulty runs' figures, merged exactly and in any order (the failures of lowest index kept)."""

    depth: int
    firmwares: tuple[str, ...]
    mode: Mode = PLAIN
    items: int = 0
    failed: int = 0
    pulses: int = 0
    runs_by_kind: dict[str, int] = field(default_factory=dict)
    failed_by_kind: dict[str, int] = field(default_factory=dict)
    wrong_deliveries: int = 0  # runs with a pulse above the cap or on an electrode meant off
    over_limit: int = 0
    unexplained: int = 0
    longest_wrong_s: float = 0.0
    recovery_bound_s: float = 0.0
    queue_lost_bytes: int = 0
    unreported: int = 0
    repaired: int = 0
    absorbed: int = 0
    max_stim_ua: float = 0.0
    caller_errors: int = 0
    wrong_by_kind: dict[str, int] = field(default_factory=dict)  # runs with a wrong delivery
    over_limit_by_kind: dict[str, int] = field(default_factory=dict)  # pulses above the cap
    absorbed_by_kind: dict[str, int] = field(default_factory=dict)
    #: The run of the largest pulse above the cap (the lowest index among equals): (current, -index, row).
    worst: tuple[float, int, dict[str, Any]] | None = None
    failures: list[tuple[int, dict[str, Any]]] = field(default_factory=list)
    #: A sample's sum, over its runs, of the faulty runs of the sequence each was drawn from.
    sequence_runs: int = 0

    def add(self, index: int, run: Run, r: sc.SessionResult) -> None:
        key = f"{run.link} {run.kind.value}"
        self.items += 1
        self.pulses += r.pulses
        _add_counts(self.runs_by_kind, {key: 1})
        _add_counts(self.wrong_by_kind, {key: int(r.first_violation is not None)})
        _add_counts(self.over_limit_by_kind, {key: r.over_limit})
        _add_counts(self.absorbed_by_kind, {key: r.absorbed_lost_bytes})
        if r.over_limit:
            row = {
                "index": index,
                "sequence": ex.describe(run.sequence, self.depth, self.firmwares),
                "fault": run.spec(),
                "largest_pulse_ua": round(r.max_stim_ua, 3),
                "over_limit_pulses": r.over_limit,
                "wrong_delivery_after_fault_s": round(r.wrong_after_fault_s, 6),
                "recovery_bound_s": round(r.recovery_bound_s, 6),
                "reproduce": reproduce(run, self.depth, self.firmwares, self.mode),
            }
            self._keep_worst((r.max_stim_ua, -index, row))
        self.over_limit += r.over_limit
        self.unexplained += r.unexplained
        self.wrong_deliveries += r.first_violation is not None
        self.longest_wrong_s = max(self.longest_wrong_s, r.wrong_after_fault_s)
        self.recovery_bound_s = max(self.recovery_bound_s, r.recovery_bound_s)
        self.queue_lost_bytes += r.lost_bytes
        self.unreported += r.unreported_lost_bytes
        self.repaired += r.repaired_lost_bytes
        self.absorbed += r.absorbed_lost_bytes
        self.max_stim_ua = max(self.max_stim_ua, r.max_stim_ua)
        self.caller_errors += sum(1 for e in r.errors if not e.startswith(ROBUST_LOSS))
        if failed(r):
            self.failed += 1
            _add_counts(self.failed_by_kind, {key: 1})
            row = {
                "index": index,
                "sequence": ex.describe(run.sequence, self.depth, self.firmwares),
                "fault": run.spec(),
                "why": why(r),
                "first_violation": r.first_violation,
                "reproduce": reproduce(run, self.depth, self.firmwares, self.mode),
            }
            self.failures = sorted([*self.failures, (index, row)], key=lambda f: f[0])[: sc.LISTED_FAILURES]

    def _keep_worst(self, cand: tuple[float, int, dict[str, Any]] | None) -> None:
        if cand is not None and (self.worst is None or cand[:2] > self.worst[:2]):
            self.worst = cand

    def merge(self, o: ByteFaultTally) -> None:
        self._keep_worst(o.worst)
        for name in ("wrong_by_kind", "over_limit_by_kind", "absorbed_by_kind"):
            _add_counts(getattr(self, name), getattr(o, name))
        for name in ("items", "failed", "pulses", "wrong_deliveries", "over_limit", "unexplained"):
            setattr(self, name, getattr(self, name) + getattr(o, name))
        for name in (
            "queue_lost_bytes",
            "unreported",
            "repaired",
            "absorbed",
            "caller_errors",
            "sequence_runs",
        ):
            setattr(self, name, getattr(self, name) + getattr(o, name))
        for name in ("longest_wrong_s", "recovery_bound_s", "max_stim_ua"):
            setattr(self, name, max(getattr(self, name), getattr(o, name)))
        _add_counts(self.runs_by_kind, o.runs_by_kind)
        _add_counts(self.failed_by_kind, o.failed_by_kind)
        self.failures = sorted(self.failures + o.failures, key=lambda f: f[0])[: sc.LISTED_FAILURES]

    def summary(self) -> dict[str, Any]:
        return {
            "mode": "exhaustive byte faults",
            "depth": self.depth,
            "firmware": "+".join(self.firmwares),
            "encoding": self.mode.encoding,
            "kinds": list(self.mode.kinds),
            "faulty_runs": self.items,
            "runs_by_link_and_kind": dict(sorted(self.runs_by_kind.items())),
            "failed_runs": self.failed,
            "failed_by_link_and_kind": dict(sorted(self.failed_by_kind.items())),
            "pulses": self.pulses,
            "largest_pulse_ua": round(self.max_stim_ua, 3),
            "limit_ua": ex.CAP_UA,
            "runs_with_wrong_deliveries": self.wrong_deliveries,
            "over_limit_pulses": self.over_limit,
            "wrong_deliveries_past_bound": self.unexplained,
            "longest_wrong_delivery_after_fault_s": round(self.longest_wrong_s, 6),
            "recovery_bound_s": round(self.recovery_bound_s, 6),
            "bytes_lost_in_queue": self.queue_lost_bytes,
            "bytes_lost_unreported": self.unreported,
            "bytes_lost_unnoticed_but_repaired": self.repaired,
            "bytes_lost_unnoticed_absorbed": self.absorbed,
            "caller_errors": self.caller_errors,
            "runs_with_wrong_deliveries_by_kind": dict(sorted(self.wrong_by_kind.items())),
            "over_limit_pulses_by_kind": dict(sorted(self.over_limit_by_kind.items())),
            "bytes_lost_unnoticed_absorbed_by_kind": dict(sorted(self.absorbed_by_kind.items())),
            "largest_pulse_run": self.worst[2] if self.worst is not None else None,
            "failures": [row for _, row in self.failures],
        }


def reproduce(run: Run, depth: int, firmwares: Sequence[str], mode: Mode = PLAIN) -> str:
    encoding = " --encoding robust" if mode.robust else ""
    return f"{ex.reproduce(run.sequence, depth, firmwares)}{encoding} --byte-fault {run.spec()}"


def tally_chunk(
    depth: int,
    firmwares: tuple[str, ...],
    table: tuple[tuple[int, ...], ...],
    mode: Mode,
    first: int,
    count_: int,
) -> ByteFaultTally:
    """Faulty runs ``first .. first + count_ - 1`` (a chunk of a distributed enumeration)."""
    logging.disable(logging.WARNING)
    ends = list(accumulate(runs_per_sequence(w, mode) for w in table))
    t = ByteFaultTally(depth, firmwares, mode)
    for i in range(first, first + count_):
        run = decode_run(i, table, ends, mode)
        t.add(i, run, run_one(run, depth, firmwares, mode))
    return t


# --- a sample of the runs, at any depth ---------------------------------------------------------------------


def sample_run(
    index: int, seed: int, depth: int, firmwares: tuple[str, ...], mode: Mode = PLAIN
) -> tuple[Run, int]:
    """Sample ``index`` of seed ``seed``: a sequence of the enumeration drawn uniformly, then one of its
    faulty runs drawn uniformly, its bytes counted by its own fault-free run (:func:`count_chunk`), so no
    first pass over every sequence is needed and any depth can be sampled.  Each sample has its own
    generator (seeded by the seed and its index): the same sample on any chunking, worker or engine.
    Returns the run and its sequence's count of faulty runs (their mean over the sample, times the
    sequences, estimates the enumeration's size without counting it)."""
    rng = random.Random(f"byte-fault sample {seed} {index}")
    sequence = rng.randrange(ex.count(depth, firmwares))
    u = rng.random()
    written = count_chunk(depth, firmwares, mode, sequence, 1).written[sequence]
    runs = runs_per_sequence(written, mode)
    if runs == 0:  # nothing written on the struck links: the run at byte 0 fails as not struck
        link = next(name for name in LINKS if mode.kinds_on(name))
        return Run(sequence, link, mode.kinds_on(link)[0], 0), 0
    run = decode_run(int(u * runs), (written,), mode=mode)
    return Run(sequence, run.link, run.kind, run.byte), runs


def sample_chunk(
    depth: int, firmwares: tuple[str, ...], mode: Mode, seed: int, first: int, count_: int
) -> ByteFaultTally:
    """Samples ``first .. first + count_ - 1`` of seed ``seed`` (a chunk of a distributed sample)."""
    logging.disable(logging.WARNING)
    t = ByteFaultTally(depth, firmwares, mode)
    for i in range(first, first + count_):
        run, runs = sample_run(i, seed, depth, firmwares, mode)
        t.sequence_runs += runs
        t.add(i, run, run_one(run, depth, firmwares, mode))
    return t


def upper_bound_95(failed: int, runs: int) -> float | None:
    """The share of failing runs that ``runs`` samples with ``failed`` failures rule out at 95 % (one-sided,
    exact for 0 failures: ``1 - 0.05 ** (1 / runs)``); None where a run failed (the failures are the
    finding, listed with their replays)."""
    if failed or runs == 0:
        return None
    return 1.0 - 0.05 ** (1.0 / runs)


def start_ranges(
    table: Sequence[Sequence[int]], depth: int, firmwares: Sequence[str], mode: Mode = PLAIN
) -> list[str]:
    """Per firmware and start, its runs as ``FIRST:END`` (a ``--runs`` slice of whole sequences)."""
    out = []
    ends = list(accumulate(runs_per_sequence(w, mode) for w in table))
    per = ex.per_start(depth)
    for k in range(len(table) // per):
        firmware, start, _ = ex.decode(k * per, depth, firmwares)
        first = ends[k * per - 1] if k else 0
        out.append(f"{firmware} {start}: runs {first}:{ends[(k + 1) * per - 1]}")
    return out


def byte_table(
    depth: int, firmwares: tuple[str, ...], a: Any, mode: Mode = PLAIN
) -> tuple[tuple[int, ...], ...]:
    """The first pass: every sequence's fault-free bytes on each link, on the run's engine."""
    job = engine.Job(
        "byte_fault_campaign",
        "count_chunk",
        (depth, firmwares, mode),
        ex.count(depth, firmwares),
        chunk=a.chunk,
        fingerprint=engine.fingerprint(),
        unit="sequences",
    )
    t = engine.run(job, jobs=a.jobs, cluster=a.cluster, progress=True)
    return tuple(t.written[i] for i in range(ex.count(depth, firmwares)))


def job(
    depth: int,
    firmwares: tuple[str, ...],
    table: tuple[tuple[int, ...], ...],
    chunk: int = engine.DEFAULT_CHUNK,
    runs: tuple[int, int] | None = None,
    mode: Mode = PLAIN,
) -> engine.Job:
    """The faulty runs (``runs``: only ``first`` to ``end - 1``) as chunks for :func:`campaign_engine.run`."""
    total = sum(runs_per_sequence(w, mode) for w in table)
    first, end = runs if runs is not None else (0, total)
    return engine.Job(
        "byte_fault_campaign",
        "tally_chunk",
        (depth, firmwares, table, mode),
        end - first,
        first=first,
        chunk=chunk,
        fingerprint=engine.fingerprint(),
        unit="runs",
    )


def main(a: Any) -> int:
    """``safety_campaign.py --exhaustive --byte-faults`` (or ``--only SEQUENCE --byte-fault SPEC``)."""
    firmwares = ex.FIRMWARES if a.firmware in (None, "both") else (a.firmware,)
    kinds = parse_kinds(a.kinds) if getattr(a, "kinds", None) else ALL_KINDS
    mode = Mode(getattr(a, "encoding", None) or "plain", kinds)
    if a.only is not None:
        link, kind, byte = parse_spec(a.byte_fault)
        run = Run(a.only, link, kind, byte)
        r = run_one(run, a.depth, firmwares, mode)
        row = {
            "sequence": ex.describe(a.only, a.depth, firmwares),
            "fault": run.spec(),
            "encoding": mode.encoding,
            **asdict(r),
        }
        print(json.dumps({**row, "ok": not failed(r)}, indent=1, default=str))
        if failed(r):
            print(f"FAILED sequence {a.only} with {run.spec()}: {why(r)}", file=sys.stderr)
        return 1 if failed(r) else 0
    t0 = time.perf_counter()
    sequences = ex.count(a.depth, firmwares)
    if getattr(a, "sample", None) is not None:
        return _sampled(a, firmwares, mode, sequences, t0)
    print(
        f"exhaustive byte faults: counting the bytes of {sequences} sequences of up to {a.depth} calls on "
        f"{' and '.join(link for link in LINKS if mode.kinds_on(link))} ({' and '.join(firmwares)}), "
        f"{mode.encoding} encoding",
        file=sys.stderr,
    )
    table = byte_table(a.depth, firmwares, a, mode)
    uart = sum(w[0] for w in table)
    usb = sum(w[1] for w in table)
    total = sum(runs_per_sequence(w, mode) for w in table)
    made = (
        f"3 x {uart} UART bytes (lost, duplicated, corrupted) + {usb} USB bytes (packet tail lost from each)"
        if mode.kinds == ALL_KINDS
        else f"{', '.join(mode.kinds)} over {uart} UART bytes and {usb} USB bytes"
    )
    print(
        f"exhaustive byte faults: {total} faulty runs = {made}; "
        + "; ".join(start_ranges(table, a.depth, firmwares, mode)),
        file=sys.stderr,
    )
    runs = None
    if a.runs is not None:
        runs = parse_runs(a.runs)
        if runs[1] > total:
            print(f"safety_campaign: --runs {a.runs}: the last run is {total - 1}", file=sys.stderr)
            return 1
        print(f"exhaustive byte faults: runs {runs[0]} to {runs[1] - 1} only (--runs)", file=sys.stderr)
    j = job(a.depth, firmwares, table, a.chunk, runs, mode)
    tally = engine.run(j, jobs=a.jobs, cluster=a.cluster, progress=True)
    summary = tally.summary()
    where = {"jobs": a.jobs} if a.cluster is None else {"cluster": a.cluster}
    summary.update(
        {"sequences": sequences, "uart_bytes": uart, "usb_bytes": usb, "runs_in_enumeration": total, **where},
    )
    summary["wall_s"] = round(time.perf_counter() - t0, 3)
    return _report(a, summary)


def _sampled(a: Any, firmwares: tuple[str, ...], mode: Mode, sequences: int, t0: float) -> int:
    """``--sample N``: N runs drawn from the enumeration (:func:`sample_run`), with no first pass."""
    print(
        f"exhaustive byte faults: {a.sample} runs sampled (seed {a.seed}) from the {sequences} sequences of "
        f"up to {a.depth} calls ({' and '.join(firmwares)}), {mode.encoding} encoding; each a sequence "
        "drawn uniformly, then one of its faulty runs",
        file=sys.stderr,
    )
    j = engine.Job(
        "byte_fault_campaign",
        "sample_chunk",
        (a.depth, firmwares, mode, a.seed),
        a.sample,
        chunk=a.chunk,
        fingerprint=engine.fingerprint(),
        unit="runs",
    )
    tally = engine.run(j, jobs=a.jobs, cluster=a.cluster, progress=True)
    summary = tally.summary()
    where = {"jobs": a.jobs} if a.cluster is None else {"cluster": a.cluster}
    bound = upper_bound_95(tally.failed, tally.items)
    summary.update(
        {
            "mode": "sampled byte faults",
            "sequences": sequences,
            "sampled_runs": tally.items,
            "seed": a.seed,
            "failing_share_below_95": None if bound is None else float(f"{bound:.3g}"),
            "runs_in_enumeration_estimated": round(tally.sequence_runs / max(1, tally.items) * sequences),
            **where,
        }
    )
    summary["wall_s"] = round(time.perf_counter() - t0, 3)
    return _report(a, summary)


def _report(a: Any, summary: dict[str, Any]) -> int:
    """Print the summary (a table, or JSON with ``--json``) and each failure with its replay."""
    if a.json:
        print(json.dumps(summary, indent=1))
    else:
        width = max(map(len, summary))
        print("\n".join(f"{k:<{width}}  {v}" for k, v in summary.items() if k != "failures"))
    for f in summary["failures"]:
        print(
            f"FAILED run {f['index']} ({f['sequence']}; {f['fault']}): {f['why']} "
            f"-- reproduce: {f['reproduce']}",
            file=sys.stderr,
        )
    if summary["failed_runs"] > len(summary["failures"]):
        print(f"... and {summary['failed_runs'] - len(summary['failures'])} more", file=sys.stderr)
    return 0 if summary["failed_runs"] == 0 else 1
