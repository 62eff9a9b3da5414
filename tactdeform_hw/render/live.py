"""Live tracking: render poses as they arrive, one sample at a time, and say how late each one was.

A hand tracker (the Unity app on the headset, ``tools/send_tracking.py``, an LSL stream) sends one pose
per sample: the recorded-trajectory columns ``t_s,x_mm,y_mm,z_mm,qw,qx,qy,qz`` (the sender's clock in
seconds, world millimetres, the pad-frame quaternion of :mod:`.tracking`).  Over UDP each datagram is one
sample as UTF-8 text, optionally prefixed by the CSV header line; over Lab Streaming Layer each sample
has those eight channels.

Every sample is judged before the renderer sees it.  A bad one — the wrong number of columns, a cell
that is no number, NaN or infinity, a clock that does not advance, a position that looks like metres
(:data:`METRES_SUSPECT_MM`) — is counted by reason and dropped here: it is never rendered and never feeds
the device's fail-safe watchdog, so a sender that only sends garbage lets stimulation go off.

Safety over time.  The renderer is stepped on arrival (no batching), sends only changed patterns and is
paced by the device.  When no valid sample came for the renderer's ``lost_tracking_s`` of wall time the
loop tells it (:meth:`~.pipeline.Renderer.lose_tracking`): all off at once, before the device's own
watchdog would, and stimulation comes back only after ``resume_after_valid_samples`` valid samples.  A
sender that restarts (its clock starts again below where it was) is the same: its first sample is a
clock going back (bad), the next one starts a new clock — tracking is declared lost and the new clock is
re-based onto the old one's timeline, so the renderer sees time advance and waits for the run of valid
samples before anything is stimulated again.

Latency.  Each valid sample gets the ``time.monotonic()`` it was received, its pattern computed and (if
it changed the pattern) its bytes written (:class:`SampleTiming`); a board served in the same machine
adds when its first scan used the pattern (``tools/live_latency.py`` joins that from the board's own
command reports, on the same monotonic clock).
"""

from __future__ import annotations

import math
import socket
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import KW_ONLY, dataclass, field
from typing import Any, Protocol

from ..errors import ConfigurationError, LimitError, install_command
from .pipeline import FrameRecord, Renderer

#: The columns of a sample, in order (those of a recorded trajectory CSV).
TRACKING_COLUMNS = ("t_s", "x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz")

#: A sample whose position lies this close to the world origin is taken for metres, not millimetres: a
#: tracked hand within 3 m of the origin sent in metres lands here, while the package's scenes put their
#: objects about 300 mm out (the closest pose of any synthetic trajectory is 280 mm from the origin), so
#: in millimetres such a point is far from anything rendered.  A sender in metres never stimulates: every
#: one of its samples is bad.
METRES_SUSPECT_MM = 3.0

#: The reasons a sample is bad, as the summary counts them.
BAD_REASONS = ("columns", "text", "nan", "metres", "time-backwards", "time-repeated")


@dataclass(frozen=True, slots=True)
class LiveSample:
    """One valid sample: the sender's time, world millimetres, the pad quaternion (w, x, y, z), and the
    ``time.monotonic()`` it was received."""

    t_s: float
    position_mm: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    received_s: float


def parse_sample(payload: bytes | str | Sequence[float], received_s: float) -> LiveSample | str:
    """One datagram's text (or an LSL sample's channels) as a sample, or why it is bad (``columns``,
    ``text``, ``nan``, ``metres``).  The clock is judged by :class:`SampleJudge`, which knows the samples
    before."""
    if isinstance(payload, (bytes, bytearray, memoryview)):
        try:
            text = bytes(payload).decode("utf-8")
        except UnicodeDecodeError:
            return "text"
        return _parse_text(text, received_s)
    if isinstance(payload, str):
        return _parse_text(payload, received_s)
    try:
        values = [float(v) for v in payload]
    except (TypeError, ValueError):
        return "text"
    return _sample_of(values, received_s)


def _parse_text(text: str, received_s: float) -> LiveSample | str:
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    if lines and lines[0].replace(" ", "").split(",") == list(TRACKING_COLUMNS):
        lines = lines[1:]  # the optional header line
    if len(lines) != 1:
        return "columns"  # empty, or more than one sample in one datagram
    cells = lines[0].split(",")
    if len(cells) != len(TRACKING_COLUMNS):
        return "columns"
    try:
        values = [float(c) for c in cells]
    except ValueError:
        return "text"
    return _sample_of(values, received_s)


def _sample_of(values: list[float], received_s: float) -> LiveSample | str:
    if len(values) != len(TRACKING_COLUMNS):
        return "columns"
    if not all(map(math.isfinite, values)):
        return "nan"
    t, x, y, z, qw, qx, qy, qz = values
    if math.sqrt(x * x + y * y + z * z) < METRES_SUSPECT_MM:
        return "metres"
    return LiveSample(t, (x, y, z), (qw, qx, qy, qz), received_s)


class SampleJudge:
    """The sender's clock, sample by sample: a time that does not advance past the last sample received
    (bad ones with a time included) is bad; a time past it but not past the last *valid* one is a sender
    that restarted, re-based so the renderer's time keeps advancing (:attr:`restarted` tells the loop to
    declare tracking lost)."""

    def __init__(self) -> None:
        self._last_received: float | None = None
        self._last_valid: float | None = None
        self._last_mapped: float | None = None
        self._offset = 0.0
        self.restarts = 0
        self.restarted = False

    def judge(self, sample: LiveSample) -> LiveSample | str:
        """The sample on the renderer's timeline, or ``time-backwards`` / ``time-repeated``."""
        t = sample.t_s
        last = self._last_received
        self._last_received = t
        self.restarted = False
        if last is not None and t <= last:
            return "time-backwards" if t < last else "time-repeated"
        if self._last_valid is not None and t <= self._last_valid and self._last_mapped is not None:
            # a new clock: continue the old timeline from where it stopped
            assert last is not None
            self._offset = self._last_mapped - last
            self.restarts += 1
            self.restarted = True
        self._last_valid = t
        mapped = t + self._offset
        self._last_mapped = mapped
        return LiveSample(mapped, sample.position_mm, sample.orientation, sample.received_s)


class LiveStats:
    """Loss, jitter and rate of a live stream.  Loss is read from the sender's clock: the samples its
    time span should have held at its median period, less those that came valid.  Jitter is the mean
    deviation of the arrival interval from the sender's interval (RFC 3550's estimator, in ms)."""

    def __init__(self) -> None:
        self.received = 0
        self.valid = 0
        self.bad: dict[str, int] = {}
        self.restarts = 0
        self.jitter_ms = 0.0
        self._first_t: float | None = None
        self._prev: LiveSample | None = None
        self._intervals: list[float] = []
        self._span_s = 0.0
        self._window: list[float] = []

    def count_bad(self, reason: str) -> None:
        self.received += 1
        self.bad[reason] = self.bad.get(reason, 0) + 1

    def count_valid(self, sample: LiveSample, restarted: bool = False) -> None:
        self.received += 1
        self.valid += 1
        prev = self._prev
        if prev is not None and not restarted:
            dt = sample.t_s - prev.t_s
            self._span_s += dt
            if len(self._intervals) < 4096:
                self._intervals.append(dt)
            d = (sample.received_s - prev.received_s) - dt
            self.jitter_ms += (abs(d) * 1e3 - self.jitter_ms) / 16.0
        self._prev = sample
        self._window.append(sample.received_s)
        cut = sample.received_s - 1.0
        while self._window and self._window[0] < cut:
            self._window.pop(0)

    @property
    def period_s(self) -> float | None:
        return statistics.median(self._intervals) if self._intervals else None

    def lost(self) -> int:
        """Samples missing from the sender's clock (never negative)."""
        p = self.period_s
        if p is None or p <= 0:
            return 0
        segments = 1 + self.restarts
        expected = round(self._span_s / p) + segments
        return max(0, expected - self.valid)

    def rate_hz(self, now_s: float | None = None) -> float:
        """Valid samples received in the last second."""
        now = time.monotonic() if now_s is None else now_s
        return float(sum(1 for t in self._window if t >= now - 1.0))

    def as_dict(self) -> dict[str, Any]:
        lost = self.lost()
        expected = self.valid + lost
        return {
            "received": self.received,
            "valid": self.valid,
            "bad": dict(self.bad),
            "bad_total": sum(self.bad.values()),
            "lost": lost,
            "loss_pct": round(100.0 * lost / expected, 2) if expected else 0.0,
            "jitter_ms": round(self.jitter_ms, 3),
            "rate_hz": round(1.0 / self.period_s, 2) if self.period_s else None,
            "restarts": self.restarts,
        }

    def line(self, frames_sent: int, now_s: float | None = None) -> str:
        d = self.as_dict()
        bad = ", ".join(f"{k} {v}" for k, v in sorted(self.bad.items())) or "none"
        return (
            f"live: {self.rate_hz(now_s):.0f} Hz, {d['valid']} valid, lost {d['lost']} ({d['loss_pct']} %), "
            f"jitter {d['jitter_ms']:.2f} ms, bad {bad}, {frames_sent} frames sent"
        )


@dataclass(slots=True)
class SampleTiming:
    """One valid sample's way through: ``time.monotonic()`` seconds when it was received, its pattern
    computed (the first frame handed to the device, or the step's end when nothing was sent) and its last
    frame's bytes written (None: the pattern did not change).  ``patterns`` are the frames sent, in
    application order."""

    seq: int
    t_s: float
    received_s: float
    computed_s: float
    written_s: float | None
    state: str
    patterns: list[list[int]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {
            "seq": self.seq,
            "t_s": self.t_s,
            "received_s": self.received_s,
            "computed_s": self.computed_s,
            "written_s": self.written_s,
            "compute_ms": round((self.computed_s - self.received_s) * 1e3, 4),
            "write_ms": None
            if self.written_s is None
            else round((self.written_s - self.received_s) * 1e3, 4),
            "state": self.state,
            "patterns": self.patterns,
        }


def stage_stats(values_ms: Sequence[float]) -> dict[str, float | int | None]:
    """Median, p99 and max of one latency stage (ms); ``n`` the samples it covers."""
    v = sorted(values_ms)
    if not v:
        return {"n": 0, "median_ms": None, "p99_ms": None, "max_ms": None}
    return {
        "n": len(v),
        "median_ms": round(statistics.median(v), 3),
        "p99_ms": round(v[min(len(v) - 1, math.ceil(0.99 * len(v)) - 1)], 3),
        "max_ms": round(v[-1], 3),
    }


# --- sources --------------------------------------------------------------------------------------------


class TrackingSource(Protocol):
    """Where samples come from: ``receive(timeout_s)`` returns one sample's payload and the
    ``time.monotonic()`` it arrived, or None when nothing came within ``timeout_s``."""

    name: str

    def receive(self, timeout_s: float) -> tuple[bytes | Sequence[float], float] | None: ...

    def close(self) -> None: ...


class UdpTrackingSource:
    """One sample per UDP datagram on ``host:port`` (port 0: a free one, see :attr:`address`)."""

    def __init__(self, host: str, port: int) -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind((host, port))
        except OSError as exc:
            self._sock.close()
            raise ConfigurationError(f"--tracking udp://{host}:{port}: cannot listen there: {exc}") from exc
        self.address: tuple[str, int] = self._sock.getsockname()[:2]
        self.name = f"udp://{self.address[0]}:{self.address[1]}"

    def receive(self, timeout_s: float) -> tuple[bytes, float] | None:
        self._sock.settimeout(max(0.0005, timeout_s))
        try:
            data = self._sock.recv(65536)
        except TimeoutError:
            return None
        return data, time.monotonic()

    def close(self) -> None:
        self._sock.close()


class LslTrackingSource:
    """An LSL stream of eight channels (:data:`TRACKING_COLUMNS`), resolved by name.  ``inlet`` is any
    object with ``pull_sample(timeout=…)`` (a ``pylsl.StreamInlet``; tests give a fake)."""

    def __init__(self, stream_name: str, inlet: Any = None, *, resolve_timeout_s: float = 5.0) -> None:
        self.name = f"lsl://{stream_name}"
        if inlet is None:
            pylsl = import_pylsl("--tracking lsl://")
            found = pylsl.resolve_byprop("name", stream_name, timeout=resolve_timeout_s)
            if not found:
                raise ConfigurationError(
                    f"--tracking lsl://{stream_name}: no LSL stream of that name found within "
                    f"{resolve_timeout_s:g} s"
                )
            inlet = pylsl.StreamInlet(found[0])
            # connected now, not at the first pull: the samples sent from here on are all received
            inlet.open_stream(timeout=resolve_timeout_s)
        self._inlet = inlet

    def receive(self, timeout_s: float) -> tuple[Sequence[float], float] | None:
        sample, _stamp = self._inlet.pull_sample(timeout=max(0.0, timeout_s))
        if sample is None:
            return None
        return sample, time.monotonic()

    def close(self) -> None:
        close = getattr(self._inlet, "close_stream", None)
        if callable(close):
            close()


def import_pylsl(what: str) -> Any:
    """pylsl, or an error naming the extra that installs it."""
    try:
        import pylsl  # type: ignore[import-not-found,unused-ignore]
    except ImportError as exc:
        raise ConfigurationError(f"{what} needs pylsl: {install_command('lsl')} (the lsl extra)") from exc
    return pylsl


def open_tracking(url: str) -> TrackingSource:
    """``udp://HOST:PORT`` or ``lsl://STREAM_NAME``."""
    if url.startswith("udp://"):
        host, sep, port = url[len("udp://") :].rpartition(":")
        if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
            raise LimitError("--tracking", url, "udp://HOST:PORT with a port 0–65535")
        return UdpTrackingSource(host or "0.0.0.0", int(port))
    if url.startswith("lsl://") and len(url) > len("lsl://"):
        return LslTrackingSource(url[len("lsl://") :])
    raise LimitError("--tracking", url, "udp://HOST:PORT or lsl://STREAM_NAME")


# --- the LSL outlet -------------------------------------------------------------------------------------


class LslPatternOutlet:
    """Each pattern put in force as one LSL sample: ``t_s`` (the sample's time), the state and feature as
    codes (:attr:`states`, :attr:`features`: their index + 1, 0 none) and each electrode's current in µA.
    ``outlet`` is any object with ``push_sample(values)`` (a ``pylsl.StreamOutlet``; tests give a fake)."""

    states = ("idle", "approaching", "interacting")
    features = ("face", "edge", "corner")

    def __init__(self, name: str, electrodes: int, outlet: Any = None) -> None:
        self.channels = ["t_s", "state", "feature"] + [f"e{i + 1}_ua" for i in range(electrodes)]
        if outlet is None:
            pylsl = import_pylsl("--lsl-out")
            info = pylsl.StreamInfo(
                name, "TactilePattern", len(self.channels), 0, "float32", f"tactdeform-{name}"
            )
            chans = info.desc().append_child("channels")
            for ch in self.channels:
                chans.append_child("channel").append_child_value("label", ch)
            outlet = pylsl.StreamOutlet(info)
        self._outlet = outlet
        self.pushed = 0

    def push(self, rec: FrameRecord, current_ua: int) -> None:
        state = self.states.index(rec.state) + 1 if rec.state in self.states else 0
        feature = self.features.index(rec.feature) + 1 if rec.feature in self.features else 0
        self._outlet.push_sample(
            [float(rec.t_s), float(state), float(feature)] + [float(v) * current_ua for v in rec.electrodes]
        )
        self.pushed += 1


# --- the loop ---------------------------------------------------------------------------------------------


@dataclass
class LiveResult:
    """What a live run did: the stream's figures, the samples' timings, and whether it was stopped."""

    stats: LiveStats
    timings: list[SampleTiming]
    stream_stops: int = 0

    def latency(self) -> dict[str, Any]:
        """Median, p99 and max of received → computed and received → written (ms)."""
        compute = [(s.computed_s - s.received_s) * 1e3 for s in self.timings]
        write = [(s.written_s - s.received_s) * 1e3 for s in self.timings if s.written_s is not None]
        return {"received_to_computed": stage_stats(compute), "received_to_written": stage_stats(write)}


@dataclass(eq=False, repr=False)
class LiveRun:
    """Render a live source through ``renderer`` until :meth:`stop` (another thread, a signal handler) or
    the source has said nothing for ``idle_exit_s`` (None: run until stopped).

    ``on_record`` sees every frame record, ``on_status`` a status line once every ``status_every_s``,
    ``on_timing`` every valid sample's :class:`SampleTiming` as it completes; ``outlet`` gets every frame
    sent (see :class:`LslPatternOutlet`)."""

    renderer: Renderer
    source: TrackingSource
    _: KW_ONLY
    on_record: Callable[[FrameRecord], None] | None = None
    on_status: Callable[[str], None] | None = None
    on_timing: Callable[[SampleTiming], None] | None = None
    outlet: LslPatternOutlet | None = None
    status_every_s: float = 1.0
    keep_timings: bool = True
    result: LiveResult = field(init=False, default_factory=lambda: LiveResult(LiveStats(), []))
    _stop: bool = field(init=False, default=False)
    _sent: list[tuple[FrameRecord, float, float]] = field(init=False, default_factory=list)

    def stop(self) -> None:
        self._stop = True

    def _delivered(self, rec: FrameRecord, before_s: float, after_s: float) -> None:
        self._sent.append((rec, before_s, after_s))
        if self.outlet is not None:
            dev = self.renderer.device
            self.outlet.push(rec, dev.current_ua if dev is not None else self.renderer.current_ua)

    def run(self, idle_exit_s: float | None = None) -> LiveResult:
        r = self.renderer
        r.start()
        r.deliver_hook = self._delivered
        stats, judge, res = self.result.stats, SampleJudge(), self.result
        lost_s = r.lost_tracking_s
        last_valid: float | None = None
        last_any = time.monotonic()
        next_status = last_any + self.status_every_s
        seq = 0
        try:
            while not self._stop:
                now = time.monotonic()
                wait = min(0.05, max(0.0, next_status - now))
                if last_valid is not None:
                    wait = min(wait, max(0.0, last_valid + lost_s - now))
                got = self.source.receive(wait)
                now = time.monotonic()
                if last_valid is not None and now - last_valid >= lost_s:
                    self._stream_stopped()
                    last_valid = None
                if now >= next_status:
                    next_status = now + self.status_every_s
                    if self.on_status is not None:
                        self.on_status(stats.line(r.summary.frames_sent, now))
                if got is None:
                    if idle_exit_s is not None and now - last_any >= idle_exit_s:
                        break
                    continue
                payload, received_s = got
                last_any = received_s
                sample = parse_sample(payload, received_s)
                if not isinstance(sample, str):
                    sample = judge.judge(sample)
                if isinstance(sample, str):
                    stats.count_bad(sample)  # never rendered, never a keepalive
                    continue
                if judge.restarted:
                    stats.restarts += 1
                    self._stream_stopped()
                stats.count_valid(sample, judge.restarted)
                seq += 1
                self._step(seq, sample)
                last_valid = received_s
        finally:
            r.deliver_hook = None
            r.summary.teleports = sum(a.stats.teleports for a in r.renderers.values())
        return res

    def _stream_stopped(self) -> None:
        rec = self.renderer.lose_tracking()
        if rec is None:
            return
        self.result.stream_stops += 1
        if self.on_record is not None:
            self.on_record(rec)

    def _step(self, seq: int, sample: LiveSample) -> None:
        self._sent.clear()
        records = self.renderer.step((sample.t_s, sample.position_mm, sample.orientation))
        end = time.monotonic()
        if self.on_record is not None:
            for rec in records:
                self.on_record(rec)
        sent = self._sent
        timing = SampleTiming(
            seq,
            sample.t_s,
            sample.received_s,
            sent[0][1] if sent else end,
            sent[-1][2] if sent else None,
            records[-1].state if records else "idle",
            [list(rec.electrodes) for rec, _, _ in sent],
        )
        if self.keep_timings:
            self.result.timings.append(timing)
        if self.on_timing is not None:
            self.on_timing(timing)


# --- sending ----------------------------------------------------------------------------------------------


def sample_line(t_s: float, position_mm: Sequence[float], orientation: Sequence[float]) -> str:
    """One sample's datagram text (``repr`` floats: nothing lost on the way)."""
    return ",".join(repr(float(v)) for v in (t_s, *position_mm, *orientation))


def send_samples(
    poses: Sequence[Any],
    address: tuple[str, int],
    *,
    drop: float = 0.0,
    seed: int = 0,
    header: bool = False,
    speed: float = 1.0,
) -> tuple[int, int]:
    """Send poses (with ``t_s``, ``position_mm``, ``orientation``) over UDP at their own clock (``speed``
    times as fast), one datagram each, leaving out a fraction ``drop`` of them (seeded); returns how many
    were sent and left out.  What ``tools/send_tracking.py`` and ``tools/live_latency.py`` use."""
    import random

    if not 0.0 <= drop < 1.0:
        raise LimitError("drop", drop, "a fraction in [0, 1)")
    if not (math.isfinite(speed) and speed > 0):
        raise LimitError("speed", speed, "a finite factor > 0")
    rng = random.Random(seed)
    head = ",".join(TRACKING_COLUMNS) + "\n" if header else ""
    sent = left_out = 0
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        start = time.monotonic()
        t_first = float(poses[0].t_s) if len(poses) else 0.0
        for p in poses:
            delay = start + (float(p.t_s) - t_first) / speed - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if drop and rng.random() < drop:
                left_out += 1
                continue
            sock.sendto((head + sample_line(p.t_s, p.position_mm, p.orientation)).encode(), address)
            sent += 1
    return sent, left_out
