"""Fuzzing at scale: every input surface of the package fed a fixed budget of generated examples, run
through the campaign engine (chunks by index, ``--jobs``, ``--cluster``) so it distributes and merges
exactly as the safety campaign does.

Why a seeded generator rather than hypothesis here: example ``i`` of a target is drawn from the seed
``(seed, target, i)`` alone, so a chunk gives the same examples whichever process runs it, a run gives
IDENTICAL counts on one core or a cluster, and any failure is replayed from its hex bytes.  Every example
is a byte string that a target reads as its inputs (:class:`Source`: integers, choices, floats, text,
"anything" values; an exhausted string reads as the smallest choice), so one shrinker serves every
target: a failing example is cut down by delta debugging (drop chunks, then lower bytes) while it still
fails with the same exception type, and the minimal bytes are reported with the command that replays them.

The property of every target: it raises nothing but the package's documented errors
(:class:`~tactdeform_hw.errors.TactDeformError` and its subclasses).  Targets add their own:

* ``decoder``: every byte is accounted for, whole or fed in pieces, and the registers its complete
  commands store are the ones the emulated firmware's parser ends with (decoder/parser agreement);
* ``parser_v1_2``, ``parser_v2``: a stream fed in any pieces (with resets) leaves the state fed whole does;
* ``timed_v1_2``, ``timed_v2``: the event-exact models take any stream at any times;
* ``profile``, ``calibration``, ``array_file``: documents built from anything load or are refused;
* ``configure``, ``set_current``, ``send_pattern``, ``interlock``: whatever the call or the raw bytes, the
  emulated firmware never holds a current above the guard's limit for a channel (what its next scan
  delivers), and a refused call sent nothing;
* ``trajectory``, ``tracking``: trajectory parameters and tracking datagrams of any content.

Usage::

    python tools/fuzz_campaign.py --budget-per-target 10000 --jobs 2
    python tools/fuzz_campaign.py --target decoder --replay 0aff12   # one example, with its traceback
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import math
import random
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

TOOLS = Path(__file__).resolve().parent
if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))

import campaign_engine as engine  # noqa: E402

from tactdeform_hw.device.participant.profiles import OPTIONAL_KEYS, REQUIRED_KEYS  # noqa: E402
from tactdeform_hw.errors import ConfigurationError, TactDeformError  # noqa: E402

#: Examples per target unless the command line says otherwise.
DEFAULT_BUDGET = 200
#: Examples per chunk: a chunk of the slowest target (the timed models) takes about a second.
DEFAULT_CHUNK = 100
#: Checks a shrink may make before it reports what it has (a shrink is bounded, whatever the example).
SHRINK_CHECKS = 400
#: Longest example a generator makes (bytes).
MAX_EXAMPLE_BYTES = 600


class PropertyFailure(AssertionError):
    """A target's own property broke (not an exception the code under test raised)."""


class Source:
    """Reads a target's inputs from an example's bytes; past the end every read gives its smallest value,
    so a shorter or lower example is a simpler input (what the shrinker relies on)."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def byte(self) -> int:
        if self.pos >= len(self.data):
            return 0
        b = self.data[self.pos]
        self.pos += 1
        return b

    def int_in(self, lo: int, hi: int) -> int:
        """An integer in ``lo .. hi`` (as many bytes as the span needs)."""
        span = hi - lo
        if span <= 0:
            return lo
        nbytes = (span.bit_length() + 7) // 8
        v = 0
        for _ in range(nbytes):
            v = (v << 8) | self.byte()
        return lo + v % (span + 1)

    def bool(self) -> bool:
        return self.byte() & 1 == 1

    def choice(self, options: Sequence[Any]) -> Any:
        return options[self.int_in(0, len(options) - 1)]

    def stream(self, max_len: int = 300) -> bytes:
        """Wire bytes, biased toward command bytes (>= 0xF4) and small values."""
        n = self.int_in(0, max_len)
        out = bytearray()
        for _ in range(n):
            if self.pos >= len(self.data):
                break
            b = self.byte()
            kind = b >> 6
            low = self.byte()
            out.append(0xF4 + low % 12 if kind == 3 else low % 4 if kind == 2 else low)
        return bytes(out)

    def float(self) -> float:
        return float(self.choice(_FLOATS)) if self.bool() else self.int_in(-20_000, 20_000) / 4.0

    def text(self, max_len: int = 12) -> str:
        n = self.int_in(0, max_len)
        return "".join(self.choice(_CHARS) for _ in range(n))

    def anything(self, depth: int = 0) -> Any:
        """A value of any type a caller might pass by mistake (or by design)."""
        k = self.int_in(0, 9 if depth < 2 else 7)
        if k == 0:
            return None
        if k == 1:
            return self.bool()
        if k == 2:
            return self.int_in(-3, 300)
        if k == 3:
            return self.choice(_BIG_INTS)
        if k == 4:
            return self.float()
        if k == 5:
            return self.text()
        if k == 6:
            return self.data[self.pos : self.pos + self.int_in(0, 4)]
        if k == 7:
            return self.int_in(0, 12_000)
        if k == 8:
            return [self.anything(depth + 1) for _ in range(self.int_in(0, 4))]
        return {self.text(4): self.anything(depth + 1) for _ in range(self.int_in(0, 3))}


_FLOATS = (0.0, -0.0, 1.0, -1.0, 0.5, 1e-300, 1e300, math.inf, -math.inf, math.nan, 2**53 + 1, 1e6, 255.5)
_BIG_INTS = (-(2**70), -1, 0, 2**31, 2**63, 2**70, 65535, 65536, 256, 255)
_CHARS = tuple('abcxyz019 .,-+eE:"[]{}\n\t\\/é') + ("nan", "inf", "true", "null", "0x", "1e999")


def example_bytes(seed: int, target: str, index: int) -> bytes:
    """Example ``index`` of ``target``: a function of the three alone (any process draws the same)."""
    rng = random.Random(f"{seed}/{target}/{index}")
    size = rng.choice((rng.randrange(0, 16), rng.randrange(0, 96), rng.randrange(0, MAX_EXAMPLE_BYTES)))
    return rng.randbytes(size)


# --- the targets ------------------------------------------------------------------------------------------

Target = Callable[[Source], None]
TARGETS: dict[str, Target] = {}


def target(name: str) -> Callable[[Target], Target]:
    def register(fn: Target) -> Target:
        TARGETS[name] = fn
        return fn

    return register


def _expect(ok: bool, what: str) -> None:
    if not ok:
        raise PropertyFailure(what)


@target("decoder")
def fuzz_decoder(src: Source) -> None:
    from tactdeform_hw.emulator import Emulator
    from tactdeform_hw.protocol import decoder
    from tactdeform_hw.protocol.firmware import get_firmware

    fw = get_firmware(src.choice(("v1.2", "v2")))
    data = src.stream()
    cuts = sorted({src.int_in(0, len(data)) for _ in range(src.int_in(0, 6))} | {0, len(data)})
    emu = Emulator(firmware=fw)
    start_num = emu.registers.electrode_num
    whole = decoder.decode(data, start_num, fw)
    _expect(b"".join(c.raw for c in whole) == data, "decode(data) does not account for every byte")
    dec = decoder.StreamDecoder(start_num, fw)
    items = []
    for a, b in zip(cuts, cuts[1:], strict=False):
        items += dec.feed(data[a:b])
    items += dec.finish()
    _expect(b"".join(c.raw for c in items) == data, "the decoder fed in pieces loses or repeats bytes")
    # agreement: what the decoder says each complete command stores is what the parser's registers hold
    emu.feed(data)
    stored: dict[str, int] = {}
    for c in whole:
        if c.status == decoder.OK and c.opcode is not None and c.stored is not None:
            register = fw.by_opcode[c.opcode].register
            if register is not None:
                stored[register] = c.stored
    for register, value in stored.items():
        held = getattr(emu.registers, register, None)
        if isinstance(held, int):
            _expect(held == value, f"decoder stores {register}={value}, the parser holds {held}")


def _fuzz_parser(src: Source, firmware: str) -> None:
    from tactdeform_hw.emulator import Emulator

    data = src.stream()
    cuts = sorted({src.int_in(0, len(data)) for _ in range(src.int_in(0, 8))} | {0, len(data)})
    reset_at = src.int_in(-1, len(cuts))
    pieces = Emulator(firmware=firmware)
    for k, (a, b) in enumerate(zip(cuts, cuts[1:], strict=False)):
        if k == reset_at:
            pieces.reset()
        pieces.feed(data[a:b])
    whole = Emulator(firmware=firmware)
    if 0 <= reset_at < len(cuts) - 1:
        # the reset came before piece ``reset_at``: the firmware then holds what the rest makes of it
        whole.feed(data[cuts[reset_at] :])
    else:
        whole.feed(data)
    _expect(whole.state() == pieces.state(), "a stream fed in pieces leaves another state than fed whole")


@target("parser_v1_2")
def fuzz_parser_v1_2(src: Source) -> None:
    _fuzz_parser(src, "v1.2")


@target("parser_v2")
def fuzz_parser_v2(src: Source) -> None:
    _fuzz_parser(src, "v2")


def _fuzz_timed(src: Source, model: Any) -> None:
    emu = model(link=src.choice(("usb", "uart")))
    t_us = 0.0
    for _ in range(src.int_in(1, 4)):
        data = src.stream(120)
        emu.write(data)
        t_us += src.int_in(0, 3000)
        emu.advance_to(t_us)
    emu.advance_to(t_us + 20_000)
    _expect(emu.now_us >= t_us + 20_000, "the timed model did not reach the time asked")
    for lo in emu.losses:
        _expect(lo.count > 0, "a loss of no byte was recorded")


@target("timed_v1_2")
def fuzz_timed_v1_2(src: Source) -> None:
    from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator

    _fuzz_timed(src, TimedEmulator)


@target("timed_v2")
def fuzz_timed_v2(src: Source) -> None:
    from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2

    _fuzz_timed(src, TimedEmulatorV2)


#: Every key a profile may hold, and one it may not.
_PROFILE_FIELDS = (*REQUIRED_KEYS, *OPTIONAL_KEYS, "extra")


def _profile() -> Any:
    from tactdeform_hw.device.participant.profiles import ParticipantProfile

    return ParticipantProfile(
        "FZ01", 2000, (1500, 1400, 1500, 1300, 1200, 1300, 1500, 1400, 1500), dt.date(2024, 5, 1)
    )


@target("profile")
def fuzz_profile(src: Source) -> None:
    from tactdeform_hw.device.participant.profiles import profile_from_dict

    doc = _profile().to_dict()
    for _ in range(src.int_in(0, 6)):
        key = src.choice(_PROFILE_FIELDS)
        if src.int_in(0, 7) == 0:
            doc.pop(key, None)
        else:
            doc[key] = src.anything()
    prof = profile_from_dict(doc)
    _expect(0 <= prof.cap_ua <= 10_000, f"profile accepted with cap_ua {prof.cap_ua}")
    _expect(all(0 <= r <= prof.cap_ua for r in prof.regions_ua), "a region's limit above the cap")


@target("calibration")
def fuzz_calibration(src: Source) -> None:
    from tactdeform_hw.formats._json import load_text
    from tactdeform_hw.formats.calibration_profile import (
        calibration_from_dict,
        dumps_calibration_profile,
        from_participant,
    )

    doc = json.loads(dumps_calibration_profile(from_participant(_profile(), (0, 1, 2, 3))))
    if src.int_in(0, 5) == 0:  # the text itself, as a file holds it (the lenient reader first)
        text = src.text(80)
        value, _ = load_text(text, "<fuzz>")
        calibration_from_dict(value, "<fuzz>")
        return
    for _ in range(src.int_in(0, 5)):
        where = src.int_in(0, 2)
        if where == 0:
            doc[src.choice((*doc, "extra"))] = src.anything()
        elif where == 1 and isinstance(doc.get("layout"), dict):
            doc["layout"][src.choice(("electrode_count", "name", "slug", "x"))] = src.anything()
        elif isinstance(doc.get("electrodes"), list) and doc["electrodes"]:
            e = doc["electrodes"][src.int_in(0, len(doc["electrodes"]) - 1)]
            if isinstance(e, dict) and e:
                e[src.choice((*e, "x"))] = src.anything()
    prof = calibration_from_dict(doc, "<fuzz>")
    _expect(len(prof.electrodes) == doc["layout"]["electrode_count"], "electrode count not kept")


@target("array_file")
def fuzz_array_file(src: Source) -> None:
    from tactdeform_hw.formats._json import load_text
    from tactdeform_hw.formats.etactilekit import parse_array

    if src.bool():
        value, _ = load_text(src.text(60), "<fuzz>")
    else:
        n = src.int_in(0, 6)
        value = {
            src.choice(("electrodes", "positions", "radius_mm", "name", "mapping", "pitch_mm", "x")): (
                [[src.float(), src.float()] for _ in range(n)] if src.bool() else src.anything()
            )
            for _ in range(src.int_in(0, 5))
        }
    parse_array(value, "<fuzz>")


def _limits() -> list[int]:
    from tactdeform_hw.device.safety.guard import SafetyGuard

    return list(SafetyGuard.from_profile(_profile()).electrode_limits(32))


def _within_limits(emu: Any, limits: list[int]) -> bool:
    """Every channel the firmware's next scan drives gets at most its limit (v1.2: 10 µA per code)."""
    s = emu.state()
    h = s.pulse_height * 10
    n = s.electrode_num
    for ch in range(min(n, 32)):
        level = s.stim_pattern[ch]
        if level in (1, 2) and h > limits[ch]:
            return False
        if level not in (1, 2) and s.sense_pulse_height * 10 > limits[ch]:
            return False
    return not (n > 32 and h > 0 and any(v in (1, 2) for v in s.stim_pattern[32:n]))


class _CountingPort:
    """An in-process emulator port that counts the writes (so "nothing was sent" can be checked)."""

    def __new__(cls) -> Any:
        from tactdeform_hw.emulator.serving.in_process import EmulatorPort

        class Counting(EmulatorPort):
            def __init__(self) -> None:
                super().__init__()
                self.writes = 0

            def write(self, data: bytes) -> int:
                self.writes += 1
                return super().write(data)

        return Counting()


def _device(configure: bool = True) -> tuple[Any, Any]:
    from tactdeform_hw.device import EtactileKitDevice, StimConfig
    from tactdeform_hw.device.safety.guard import SafetyGuard

    port = _CountingPort()
    dev = EtactileKitDevice(port, guard=SafetyGuard.from_profile(_profile()))
    if configure:
        dev.configure(StimConfig(current_ua=1500))
    return dev, port


def _refused_quietly(call: Callable[[], Any], port: Any) -> bool:
    """Run ``call``; False when it returned, True when it raised a documented error having sent nothing."""
    before = port.writes
    try:
        call()
    except TactDeformError:
        _expect(port.writes == before, "a refused call wrote to the port")
        return True
    return False


@target("configure")
def fuzz_configure(src: Source) -> None:
    from tactdeform_hw.device import StimConfig

    names = (
        "electrode_count",
        "current_ua",
        "pulse_width_us",
        "discharge_us",
        "rate_hz",
        "polarity",
        "sense_current_ua",
        "sense_width_us",
    )
    fields = {src.choice(names): src.anything() for _ in range(src.int_in(0, 5))}
    dev, port = _device(configure=False)
    try:
        cfg = StimConfig(**fields)
    except TypeError as exc:  # pragma: no cover - the field names above are StimConfig's
        raise PropertyFailure(f"StimConfig rejects its own fields: {exc}") from exc
    except TactDeformError:
        return
    _refused_quietly(lambda: dev.configure(cfg), port)
    _expect(_within_limits(port.emulator, _limits()), "configure left a current above the guard's limit")


@target("set_current")
def fuzz_set_current(src: Source) -> None:
    dev, port = _device()
    dev.send_pattern([1 if r in (0, 4) else 0 for r in range(32)])
    value = src.anything()
    if not _refused_quietly(lambda: dev.set_current(value), port):
        _expect(
            isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value),
            f"set_current accepted {value!r}",
        )
    _expect(_within_limits(port.emulator, _limits()), "set_current left a current above the guard's limit")


@target("send_pattern")
def fuzz_send_pattern(src: Source) -> None:
    dev, port = _device()
    if src.bool():
        levels: Any = [src.int_in(-2, 4) for _ in range(src.int_in(28, 34))]
    else:
        levels = [src.anything() for _ in range(src.int_in(0, 40))] if src.bool() else src.anything()
    if not _refused_quietly(lambda: dev.send_pattern(levels), port):
        got = list(port.emulator.state().stim_pattern[:32])
        _expect(got == list(levels), "the pattern the firmware holds is not the one sent")
    _expect(_within_limits(port.emulator, _limits()), "send_pattern left a current above the guard's limit")


@target("interlock")
def fuzz_interlock(src: Source) -> None:
    """Raw writes judged by the wire interlock alone: what it lets through keeps the firmware (fed exactly
    the accepted bytes, from power-on) within every limit."""
    from tactdeform_hw.device.safety.guard import SafetyGuard
    from tactdeform_hw.device.safety.interlock import WireInterlock
    from tactdeform_hw.emulator import Emulator

    lock = WireInterlock(SafetyGuard.from_profile(_profile()))
    emu = Emulator()
    limits = _limits()
    for _ in range(src.int_in(1, 6)):
        data = src.stream(80)
        try:
            state = lock.check_wire(data)
        except TactDeformError:
            continue
        lock.commit(state)
        emu.feed(data)
        _expect(_within_limits(emu, limits), f"the interlock let {data.hex()} break a limit")


@target("trajectory")
def fuzz_trajectory(src: Source) -> None:
    from tactdeform_hw import load_scene
    from tactdeform_hw.render.trajectories import TRAJECTORIES, make_trajectory

    name = src.choice((*TRAJECTORIES, "", "nope"))
    # numbers only: the parameters are typed floats (the command line parses them as such)
    kw: dict[str, Any] = {
        src.choice(
            ("speed_mm_s", "rate_hz", "tremor_mm", "noise_mm", "dwell_s", "penetration_mm")
        ): src.float()
        for _ in range(src.int_in(0, 3))
    }
    if "rate_hz" not in kw:
        kw["rate_hz"] = 20.0  # a short timeline keeps an example fast
    poses = make_trajectory(name, _scene(load_scene), **kw)
    _expect(isinstance(poses, list), "make_trajectory returned no list")


_SCENES: dict[str, Any] = {}


def _scene(load: Callable[[str], Any]) -> Any:
    if "cube" not in _SCENES:
        _SCENES["cube"] = load("cube")
    return _SCENES["cube"]


@target("tracking")
def fuzz_tracking(src: Source) -> None:
    from tactdeform_hw.render.live import LiveSample, SampleJudge, parse_sample

    judge = SampleJudge()
    for _ in range(src.int_in(1, 5)):
        kind = src.int_in(0, 2)
        if kind == 0:
            payload: Any = src.data[src.pos : src.pos + src.int_in(0, 60)]
            src.pos += len(payload)
        elif kind == 1:
            payload = ",".join(
                str(src.float()) if src.bool() else src.text(5) for _ in range(src.int_in(0, 9))
            )
        else:
            payload = [src.float() for _ in range(src.int_in(0, 9))]
        sample = parse_sample(payload, src.int_in(0, 10_000) / 100)
        if isinstance(sample, LiveSample):
            _expect(all(map(math.isfinite, sample.position_mm)), "a sample with a non-finite position")
            judge.judge(sample)
        else:
            _expect(sample in ("columns", "text", "nan", "metres"), f"unknown rejection {sample!r}")


# --- running, judging, shrinking --------------------------------------------------------------------------


def failure_of(name: str, data: bytes) -> tuple[str, str] | None:
    """Run one example: None when it passes, else (exception type, one-line description)."""
    try:
        TARGETS[name](Source(data))
    except TactDeformError:
        return None
    except Exception as exc:  # noqa: BLE001 - any other exception is the finding
        tb = traceback.extract_tb(exc.__traceback__)
        where = f"{Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else "?"
        return type(exc).__name__, f"{type(exc).__name__} at {where}: {exc}"[:300]
    return None


def shrink(name: str, data: bytes, kind: str, budget: int = SHRINK_CHECKS) -> tuple[bytes, str]:
    """The smallest example found that still fails with an exception of type ``kind`` (delta debugging:
    drop ever smaller chunks, then lower each byte), and its description."""
    best = data
    found = failure_of(name, data)
    desc = found[1] if found else ""
    checks = 0

    def fails(candidate: bytes) -> bool:
        nonlocal checks, desc
        checks += 1
        f = failure_of(name, candidate)
        if f is not None and f[0] == kind:
            desc = f[1]
            return True
        return False

    improved = True
    while improved and checks < budget:
        improved = False
        size = max(1, len(best) // 2)
        while size >= 1 and checks < budget:
            i = 0
            while i < len(best) and checks < budget:
                candidate = best[:i] + best[i + size :]
                if fails(candidate):
                    best, improved = candidate, True
                else:
                    i += size
            size //= 2
        for i in range(len(best)):
            for lower in (0, best[i] // 2, best[i] - 1):
                if checks >= budget or lower >= best[i] or lower < 0:
                    continue
                candidate = best[:i] + bytes([lower]) + best[i + 1 :]
                if fails(candidate):
                    best, improved = candidate, True
                    break
    return best, desc


@dataclass
class Finding:
    """A target's first failing example (lowest index), and its shrunk form."""

    target: str
    index: int
    description: str
    example_hex: str
    minimal_hex: str


@dataclass
class FuzzTally:
    """Examples and failures per target, the first finding of each; merges exactly in any order."""

    items: int = 0
    failed: int = 0
    examples: dict[str, int] = field(default_factory=dict)
    failures: dict[str, int] = field(default_factory=dict)
    findings: dict[str, Finding] = field(default_factory=dict)

    @property
    def pulses(self) -> int:  # the engine's progress line counts pulses; a fuzz run counts examples
        return self.items

    def merge(self, other: FuzzTally) -> None:
        self.items += other.items
        self.failed += other.failed
        for k, v in other.examples.items():
            self.examples[k] = self.examples.get(k, 0) + v
        for k, v in other.failures.items():
            self.failures[k] = self.failures.get(k, 0) + v
        for k, f in other.findings.items():
            mine = self.findings.get(k)
            if mine is None or f.index < mine.index:
                self.findings[k] = f


def tally_chunk(seed: int, targets: tuple[str, ...], budget: int, first: int, count: int) -> FuzzTally:
    """Items ``first .. first + count - 1``: item ``i`` is example ``i % budget`` of target
    ``targets[i // budget]``."""
    t = FuzzTally()
    for i in range(first, first + count):
        name, index = targets[i // budget], i % budget
        data = example_bytes(seed, name, index)
        t.items += 1
        t.examples[name] = t.examples.get(name, 0) + 1
        found = failure_of(name, data)
        if found is None:
            continue
        t.failed += 1
        t.failures[name] = t.failures.get(name, 0) + 1
        if name not in t.findings:  # the lowest index of this chunk: the only one shrunk here
            minimal, desc = shrink(name, data, found[0])
            t.findings[name] = Finding(name, index, desc, data.hex(), minimal.hex())
    return t


def job(seed: int, targets: tuple[str, ...], budget: int, chunk: int = DEFAULT_CHUNK) -> engine.Job:
    """The campaign as an engine job (the same chunks on one core, ``--jobs`` or a cluster)."""
    return engine.Job(
        "fuzz_campaign",
        "tally_chunk",
        (seed, targets, budget),
        total=budget * len(targets),
        chunk=chunk,
        fingerprint=engine.fingerprint(),
        unit="examples",
    )


def summary(tally: FuzzTally, seed: int, budget: int, targets: tuple[str, ...]) -> dict[str, Any]:
    return {
        "seed": seed,
        "budget_per_target": budget,
        "examples": tally.items,
        "failed": tally.failed,
        "targets": {
            name: {
                "examples": tally.examples.get(name, 0),
                "failures": tally.failures.get(name, 0),
                **(
                    {
                        "first_failure": tally.findings[name].index,
                        "description": tally.findings[name].description,
                        "minimal_hex": tally.findings[name].minimal_hex,
                        "replay": f"python tools/fuzz_campaign.py --target {name} --replay "
                        + (tally.findings[name].minimal_hex or '""'),
                    }
                    if name in tally.findings
                    else {}
                ),
            }
            for name in targets
        },
    }


def _targets(spec: str | None) -> tuple[str, ...]:
    if spec is None:
        return tuple(TARGETS)
    names = tuple(s.strip() for s in spec.split(",") if s.strip())
    unknown = [n for n in names if n not in TARGETS]
    if unknown or not names:
        raise ConfigurationError(f"--target {spec!r}: unknown {unknown}; choose from {', '.join(TARGETS)}")
    return names


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("--budget-per-target", type=int, default=DEFAULT_BUDGET, help="examples per target")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--target", help="comma-separated targets (default: all)")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--cluster", help="dask://HOST:PORT or local:N")
    ap.add_argument("--chunk", type=int, default=DEFAULT_CHUNK, help="examples per chunk")
    ap.add_argument("--replay", help="run one example (hex bytes) of --target and show its traceback")
    ap.add_argument("--list", action="store_true", help="list the targets")
    ap.add_argument("--json", action="store_true", help="print the summary as JSON")
    a = ap.parse_args(argv)
    # a refusal is an expected outcome of most examples: its log line would drown the report
    logging.getLogger("tactdeform_hw.safety").setLevel(logging.CRITICAL)
    try:
        targets = _targets(a.target)
        if a.list:
            print("\n".join(TARGETS))
            return 0
        if a.replay is not None:
            return _replay(targets, a.replay)
        if a.budget_per_target < 1:
            raise ConfigurationError(f"--budget-per-target {a.budget_per_target}: at least 1")
        if a.chunk < 1:
            raise ConfigurationError(f"--chunk {a.chunk}: at least 1")
        t0 = time.perf_counter()
        tally = engine.run(
            job(a.seed, targets, a.budget_per_target, a.chunk), jobs=a.jobs, cluster=a.cluster, progress=True
        )
    except TactDeformError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = summary(tally, a.seed, a.budget_per_target, targets)
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    if a.json:
        print(json.dumps(out, indent=1))
    else:
        for name, row in out["targets"].items():
            line = f"{name:<14} {row['examples']:>7} examples, {row['failures']} failed"
            if "description" in row:
                line += f"\n    first at {row['first_failure']}: {row['description']}\n    {row['replay']}"
            print(line)
        print(f"{out['examples']} examples, {out['failed']} failed, {out['wall_s']} s")
    return 1 if tally.failed else 0


def _replay(targets: tuple[str, ...], hex_bytes: str) -> int:
    if len(targets) != 1:
        raise ConfigurationError("--replay needs exactly one --target")
    try:
        data = bytes.fromhex(hex_bytes)
    except ValueError as exc:
        raise ConfigurationError(f"--replay {hex_bytes!r}: not hex bytes ({exc})") from exc
    try:
        TARGETS[targets[0]](Source(data))
    except TactDeformError as exc:
        print(f"passes: refused with {type(exc).__name__}: {exc}")
        return 0
    except Exception:  # noqa: BLE001 - the finding, shown whole
        traceback.print_exc()
        return 1
    print("passes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
