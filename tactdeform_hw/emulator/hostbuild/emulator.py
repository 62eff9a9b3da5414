"""The host-built firmware as an emulator: bytes in at a time, virtual time advanced, replies and events out.

Each instance loads its own copy of the built library (copied to a unique temporary path before
``dlopen``), so two emulators never share the firmware's globals; :meth:`HostBuildEmulator.close` (or the
instance being collected) unloads it again, so a long campaign that makes one emulator per run keeps only
the live ones mapped.  Virtual time is integer nanoseconds in
the shim; the Python side speaks microseconds like :class:`..timed.model_v1_2.TimedEmulator`.

What this layer adds to the shim is the eTactileKit board: the stack-sense reading that tells the firmware
how many HV513 chips are stacked, the DAC on the SPI bus (an exchange's outgoing word ``>> 2`` is the DAC
code; it takes effect ``dac_change_at_us`` into the exchange), and the golden traces' event conventions.

The shim records what the firmware did as fixed-size binary records, and decodes the HV513 chain and the DAC
into delivered pulses as it goes (the same decoding as :class:`.delivered.ChainDecoder`, its reference):
Python takes both in one copy per run step, as numpy arrays, and makes objects only of what is asked for.
"""

from __future__ import annotations

import ctypes
import functools
import os
import shutil
import subprocess
import tempfile
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from tactdeform_hw.emulator.hostbuild.build import BuildResult, build
from tactdeform_hw.emulator.hostbuild.delivered import ETACTILEKIT_PINS, DeliveredPulse
from tactdeform_hw.emulator.hostbuild.statemap import StateMap, detect
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.errors import ConfigurationError, FirmwareBuildError, LimitError

STACK_SENSE_PIN = 6
"""The compact board's stack-sense input (``STACK_SENSE`` in the firmware's configuration)."""

USB_PACKET_BYTES = 64
"""A host write reaches the firmware in packets of this size; a packet that does not fit the receive
queue loses its rest (the USB Serial/JTAG receive interrupt's behaviour, protocol.md)."""

STALL_CALLS = 50_000_000
"""Shim calls in a row without virtual time passing after which the firmware is declared stuck."""

_KIND = {
    1: "GPIO",
    2: "SPI",
    3: "ISR_ENTER",
    4: "ISR_RETURN",
    5: "ALARM_ENABLE",
    6: "ALARM_DISABLE",
    7: "TX",
    8: "RX_DROP",
    9: "ALARM_WRITE",
    10: "TIMER_RESTART",
}


_GPIO, _SPI, _ISR_ENTER, _ISR_RETURN, _TX, _RX_DROP = 1, 2, 3, 4, 7, 8

EVENT_DTYPE = np.dtype([("t_ns", "<i8"), ("kind", "<i4"), ("a", "<i4"), ("b", "<i8"), ("c", "<i8")])
"""One shim event record (``hostbuild_runtime.cpp``'s ``Event``)."""

PULSE_DTYPE = np.dtype(
    [("start_ns", "<i8"), ("end_ns", "<i8"), ("code", "<i4"), ("polarity", "<i4"), ("n_outputs", "<i8")]
)
"""One delivered-pulse record (``hostbuild_runtime.cpp``'s ``DeliveredRecord``); its outputs follow in a
separate array of ``int32`` output numbers."""


@dataclass(frozen=True)
class PulseArrays:
    """Delivered pulses as columns (what a comparison reads without making an object per pulse): start
    and end in ns, DAC code, polarity (1 anodic), and each pulse's outputs as
    ``outputs[offsets[i]:offsets[i + 1]]``."""

    start_ns: np.ndarray
    end_ns: np.ndarray
    code: np.ndarray
    polarity: np.ndarray
    offsets: np.ndarray
    outputs: np.ndarray

    def __len__(self) -> int:
        return len(self.start_ns)

    def outputs_of(self, i: int) -> tuple[int, ...]:
        return tuple(self.outputs[self.offsets[i] : self.offsets[i + 1]].tolist())


def _pointer(array: np.ndarray) -> ctypes.c_void_p:
    return ctypes.c_void_p(array.ctypes.data)


class _Sample(ctypes.Structure):
    _fields_ = [("t_ns", ctypes.c_int64), ("slot", ctypes.c_int64), ("value", ctypes.c_double)]


@dataclass(frozen=True)
class IsrSample:
    """A watched register's value at an interrupt's entry, recorded when it differs from the previous
    entry's (see :meth:`HostBuildEmulator.watch_at_isr`)."""

    t_us: float
    register: str
    index: int
    value: int | float


@dataclass(frozen=True)
class ShimEvent:
    """One thing the firmware did, at virtual time ``t_us`` (see ``hostbuild_runtime.cpp``'s Kind)."""

    t_us: float
    kind: str
    a: int
    b: int
    c: int


@dataclass(frozen=True)
class RxDrop:
    """Bytes a full receive queue discarded: when, how many, and the host offset of the first."""

    t_us: float
    count: int
    host_offset: int
    queued: int


def stack_reading_for(hv513_count: int) -> int:
    """The compact board's stack-sense reading that makes the firmware count ``hv513_count`` chips.

    The firmware computes ``stack_count = round(9368.8636 / r - 1.51)`` and ``(stack_count - 1) * 4``
    chips; this inverts it at the centre of the interval (one switching board: 2669, the golden value)."""
    if hv513_count < 0 or hv513_count % 4:
        raise LimitError("hv513_count", hv513_count, "a multiple of 4 >= 0 (4 per compact switching board)")
    stack_count = hv513_count // 4 + 1
    return int(9368.8636 / (stack_count + 1.51))


def _costs(model: TimingModel, rx_buffer_bytes: int | None, stall_calls: int) -> list[int]:
    """The shim's cost table (``hostbuild_runtime.cpp``'s Cost order) from a timing model."""
    apb_ps = int(round(model.timer_tick_us * 1e6 / 40))  # the firmware's timers divide the 80 MHz APB by 40
    return [
        model.spi_ns,
        model.gpio_ns,
        model.isr_entry_ns,
        model.isr_exit_ns,
        model.call_ns,  # Serial.available(): the parser call's overhead
        model.byte_ns,  # one byte read from the receive queue
        model.hv513_detect_ns // 50,  # one analogRead() of the 50 the detection takes
        model.rtos_tick_ns,
        model.tick_phase_ns,
        apb_ps,
        rx_buffer_bytes if rx_buffer_bytes is not None else model.rx_queue_bytes,
        stall_calls,
    ]


class HostBuildEmulator:
    """An eTactileKit firmware's own source, built on the host and run in virtual time.

    ``firmware_src`` is a PlatformIO tree (built and cached on first use).  ``state_map`` names the
    firmware variables :meth:`state` reads (default: the known map whose unit the tree holds).
    ``rx_buffer_bytes`` replaces the receive queue's default size (the timing model's
    ``rx_queue_bytes``) until the firmware sets its own with ``Serial.setRxBufferSize``.
    ``interrupts=False`` never runs the timer interrupt (the parser alone, as the golden vectors
    record it).  ``defines`` replaces the default build defines (:data:`..build.DEFAULT_DEFINES`);
    ``cache`` the build cache folder.  ``stall_calls``: shim calls in a row without virtual time passing
    after which the firmware is declared stuck (a loop polling a call that costs nothing would otherwise
    never return to Python).  ``chain_outputs``: the board's HV513 outputs (default ``8 * hv513_count``),
    for :meth:`delivered_pulses`.  ``pin_events=False`` keeps no pin write or SPI exchange for
    :meth:`events` and :meth:`shim_events` (the delivered pulses are decoded from them all the same): a run
    that only compares pulses, replies and state then carries no per-event record.
    """

    def __init__(
        self,
        firmware_src: str | os.PathLike[str],
        *,
        hv513_count: int = 4,
        timing: TimingModel | None = None,
        state_map: StateMap | None = None,
        stack_reading: int | None = None,
        rx_buffer_bytes: int | None = None,
        interrupts: bool = True,
        defines: dict[str, str] | None = None,
        compiler: str | None = None,
        cache: str | os.PathLike[str] | None = None,
        stall_calls: int = STALL_CALLS,
        chain_outputs: int | None = None,
        pin_events: bool = True,
    ) -> None:
        self.timing = timing if timing is not None else DEFAULT_MODEL
        tree = Path(firmware_src)
        self.state_map = state_map if state_map is not None else detect(tree)
        self.built: BuildResult = build(
            tree, state_map=self.state_map, defines=defines, compiler=compiler, cache=cache
        )
        if rx_buffer_bytes is not None and rx_buffer_bytes < 1:
            raise LimitError("rx_buffer_bytes", rx_buffer_bytes, "an integer >= 1")
        if stall_calls < 1:
            raise LimitError("stall_calls", stall_calls, "an integer >= 1")
        self.stall_calls = stall_calls
        outputs = 8 * hv513_count if chain_outputs is None else chain_outputs
        if outputs < 0:
            raise LimitError("chain_outputs", outputs, ">= 0")
        self._closed = False
        self._lib, handle = _load_private_copy(self.built.library)
        self._bind()
        self._unload = weakref.finalize(self, _unload, handle, self._lib.hb_release)
        costs = _costs(self.timing, rx_buffer_bytes, stall_calls)
        arr = (ctypes.c_int64 * len(costs))(*costs)
        if self._lib.hb_configure(arr, len(costs)) != 0:
            raise FirmwareBuildError(
                "the built library's shim does not match this package (cost table); rebuild"
            )
        reading = stack_reading if stack_reading is not None else stack_reading_for(hv513_count)
        self._lib.hb_set_analog(STACK_SENSE_PIN, reading)
        self._lib.hb_set_interrupts(1 if interrupts else 0)
        self._lib.hb_set_record_pins(1 if pin_events else 0)
        self.pin_events = pin_events
        p = ETACTILEKIT_PINS
        pins = (ctypes.c_int * 5)(p.bl, p.le, p.pol, p.clk, p.din)
        if self._lib.hb_board_configure(outputs, self.timing.dac_at_ns, pins) != 0:
            raise LimitError("chain_outputs", outputs, ">= 0")
        self.now_ns = 0
        self._last_write_ns = 0
        self._host_offset = 0
        self._events: list[np.ndarray] = []  # EVENT_DTYPE chunks, in recording order
        self._tx = bytearray()
        self._tx_log: list[tuple[float, bytes]] = []
        self._drops: list[RxDrop] = []
        self._watched: list[tuple[str, int]] = []  # per watch slot: (register, index)
        self._samples: list[IsrSample] = []
        self._pulse_chunks: list[tuple[np.ndarray, np.ndarray]] = []  # (PULSE_DTYPE records, outputs)
        self._pulse_arrays: PulseArrays | None = None
        self._pulses: list[DeliveredPulse] = []
        self._run(0)  # setup() runs up to its first shim call

    def close(self) -> None:
        """Unload this instance's copy of the firmware (its globals, stack and buffers go with it).  What was
        already read (replies, pulses, events) stays readable; running the firmware again is refused."""
        self._closed = True
        self._unload()

    def __enter__(self) -> HostBuildEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the library --------------------------------------------------------------------------------------

    def _bind(self) -> None:
        lib = self._lib
        i64, i32 = ctypes.c_int64, ctypes.c_int
        sig: dict[str, tuple[Any, list[Any]]] = {
            "hb_configure": (i32, [ctypes.POINTER(i64), i32]),
            "hb_set_analog": (None, [i32, i32]),
            "hb_set_interrupts": (None, [i32]),
            "hb_set_reading": (None, [i32]),
            "hb_run_until": (i32, [i64]),
            "hb_now": (i64, []),
            "hb_rx_push": (None, [ctypes.c_char_p, i64, i64, i64]),
            "hb_rx_queued": (i64, []),
            "hb_rx_in_flight": (i64, []),
            "hb_rx_capacity": (i64, []),
            "hb_rx_dropped": (i64, []),
            "hb_event_count": (i64, []),
            "hb_events_take": (i64, [ctypes.c_void_p, i64]),
            "hb_timer_info": (i32, [i32, ctypes.POINTER(i64)]),
            "hb_pin_levels": (i64, []),
            "hb_watch_add": (i64, [ctypes.c_void_p, i32]),
            "hb_sample_count": (i64, []),
            "hb_samples_take": (i64, [ctypes.POINTER(_Sample), i64]),
            "hb_board_configure": (i32, [i64, i64, ctypes.POINTER(i32)]),
            "hb_delivered_count": (i64, []),
            "hb_delivered_outputs_count": (i64, []),
            "hb_delivered_take": (i64, [ctypes.c_void_p, ctypes.c_void_p]),
            "hb_release": (None, []),
            "hb_set_record_pins": (None, [i32]),
        }
        for name, (res, args) in sig.items():
            fn = getattr(lib, name)
            fn.restype = res
            fn.argtypes = args
        self._getters: dict[str, Any] = {}
        for reg in self.built.registers:
            if reg.local_static:
                self._getters[reg.name] = _local_static_reader(lib, self.built.library, reg.name, reg.expr)
                continue
            if reg.length is None:
                fn = getattr(lib, f"hb_reg_{reg.name}")
                fn.restype = ctypes.c_double
                fn.argtypes = [ctypes.c_int]
            else:  # an array: read whole
                fn = getattr(lib, f"hb_regs_{reg.name}")
                fn.restype = None
                fn.argtypes = [ctypes.c_void_p]
            self._getters[reg.name] = fn

    def _live(self) -> ctypes.CDLL:
        """The loaded library; refused once :meth:`close` unloaded it."""
        if self._closed:
            raise FirmwareBuildError("this host-build emulator was closed: its firmware is unloaded")
        return self._lib

    def _run(self, target_ns: int) -> None:
        self._live()
        status = self._lib.hb_run_until(target_ns)
        if status == 2:
            raise FirmwareBuildError("no memory for the firmware's 1 MiB stack: nothing was run")
        if status != 0:
            raise FirmwareBuildError(
                f"the firmware made {self.stall_calls} shim calls at virtual time "
                f"{self._lib.hb_now() / 1000} us without time passing "
                "(a loop polling a call that costs nothing): it cannot be run further"
            )
        self._drain()

    def _drain(self) -> None:
        """Take the run step's event and pulse records in one copy each; only replies and queue losses
        become Python objects here."""
        lib = self._lib
        n_pulses = lib.hb_delivered_count()
        if n_pulses > 0:
            records = np.empty(n_pulses, PULSE_DTYPE)
            outputs = np.empty(lib.hb_delivered_outputs_count(), np.int32)
            lib.hb_delivered_take(_pointer(records), _pointer(outputs))
            self._pulse_chunks.append((records, outputs))
            self._pulse_arrays = None
        n = lib.hb_event_count()
        if n <= 0:
            return
        buf = np.empty(n, EVENT_DTYPE)
        got = lib.hb_events_take(_pointer(buf), n)
        buf = buf[:got]
        self._events.append(buf)
        kinds = buf["kind"]
        rare = np.flatnonzero((kinds == _TX) | (kinds == _RX_DROP))
        for t_ns, kind, a, b, c in buf[rare].tolist():
            if kind == _RX_DROP:
                self._drops.append(RxDrop(t_ns / 1000.0, a, b, c))
                continue
            self._tx.append(a)
            if self._tx_log and self._tx_log[-1][0] == t_ns / 1000.0:
                self._tx_log[-1] = (self._tx_log[-1][0], self._tx_log[-1][1] + bytes([a]))
            else:
                self._tx_log.append((t_ns / 1000.0, bytes([a])))

    def _all_events(self) -> np.ndarray:
        if len(self._events) > 1:
            self._events[:] = [np.concatenate(self._events)]
        return self._events[0] if self._events else np.empty(0, EVENT_DTYPE)

    # --- the host's side ----------------------------------------------------------------------------------

    @property
    def now_us(self) -> float:
        return self.now_ns / 1000.0

    @property
    def firmware_now_us(self) -> float:
        """Where the firmware's own clock stands: at or past :attr:`now_us` by at most one shim call's cost
        (the firmware is suspended inside the call that crossed the target)."""
        return float(self._live().hb_now()) / 1000.0

    def write(self, data: bytes, at_us: float | None = None) -> int:
        """The host's bytes reach the firmware's receive queue at ``at_us`` (default: now), in packets of
        :data:`USB_PACKET_BYTES`.  Writes come in time order.  Returns the byte count."""
        data = bytes(data)
        t = self.now_ns if at_us is None else int(round(at_us * 1000))
        if t < self.now_ns:
            raise LimitError("at_us", at_us, f">= now ({self.now_us} us)")
        if t < self._last_write_ns:
            raise LimitError("at_us", at_us, f">= the previous write ({self._last_write_ns / 1000} us)")
        self._last_write_ns = t
        lib = self._live()
        for i in range(0, len(data), USB_PACKET_BYTES):
            chunk = data[i : i + USB_PACKET_BYTES]
            lib.hb_rx_push(chunk, len(chunk), t, self._host_offset + i)
        self._host_offset += len(data)
        return len(data)

    def advance_to(self, t_us: float) -> None:
        """Run the firmware until virtual time ``t_us``."""
        target = int(round(t_us * 1000))
        if target < self.now_ns:
            raise LimitError("t_us", t_us, f">= now ({self.now_us} us)")
        self._run(target)
        self.now_ns = target

    def advance(self, dt_us: float) -> None:
        if not dt_us >= 0:
            raise LimitError("dt_us", dt_us, ">= 0")
        self.advance_to(self.now_us + dt_us)

    def read(self, size: int | None = None) -> bytes:
        """Reply bytes the firmware wrote and the host has not read yet (all of them, or ``size``)."""
        n = len(self._tx) if size is None else min(size, len(self._tx))
        out = bytes(self._tx[:n])
        del self._tx[:n]
        return out

    @property
    def tx_log(self) -> list[tuple[float, bytes]]:
        """Every reply write: (firmware time µs, bytes)."""
        return self._tx_log

    @property
    def rx_in_flight(self) -> int:
        """Bytes written that have not reached the receive queue yet (nor been dropped at it)."""
        return int(self._live().hb_rx_in_flight())

    @property
    def rx_drops(self) -> list[RxDrop]:
        """Every loss at the receive queue."""
        return self._drops

    def shim_events(self) -> list[ShimEvent]:
        """Everything recorded so far, in the shim's terms (GPIO, SPI, ISR entry/return, timer ops, TX)."""
        return [
            ShimEvent(t_ns / 1000.0, _KIND.get(kind, str(kind)), a, b, c)
            for t_ns, kind, a, b, c in self._all_events().tolist()
        ]

    def first_event_us(self, kind: str) -> float | None:
        """When the first event of ``kind`` (a :class:`ShimEvent` kind: ``"ALARM_ENABLE"``...) was recorded
        (``None``: never)."""
        code = next((k for k, name in _KIND.items() if name == kind), None)
        if code is None:
            raise LimitError("kind", kind, f"one of {', '.join(_KIND.values())}")
        ev = self._all_events()
        hit = np.flatnonzero(ev["kind"] == code)
        return int(ev["t_ns"][hit[0]]) / 1000.0 if len(hit) else None

    def clear_events(self, before_us: float | None = None) -> None:
        """Forget the recorded events (those before ``before_us``).  Delivered pulses and replies stay."""
        if before_us is None:
            self._events.clear()
        else:
            ev = self._all_events()
            self._events = [ev[ev["t_ns"] >= before_us * 1000.0]]

    def events(self, since_us: float = 0.0) -> list[list[Any]]:
        """GPIO and DAC events in the golden scan traces' conventions: ``[t_us, "GPIO", pin, level]`` when
        the register write completes (one per pin, ascending), ``[t_us, "DAC", "DAC", code]`` at the start
        of the exchange plus ``dac_change_at_us``; sorted by time."""
        if not self.pin_events:
            raise ConfigurationError("events(): this emulator was made with pin_events=False: it kept none")
        ev = self._all_events()
        since_ns = since_us * 1000
        if since_ns > 0:  # a DAC event counts from its exchange's start plus ``dac_at_ns``
            ev = ev[ev["t_ns"] >= since_ns - max(0, self.timing.dac_at_ns)]
        ev = ev[(ev["kind"] == _GPIO) | (ev["kind"] == _SPI)]  # recording order breaks ties in time
        dac = ev["kind"] == _SPI
        t = ev["t_ns"] + np.where(dac, self.timing.dac_at_ns, 0)
        order = np.argsort(t, kind="stable")
        out: list[list[Any]] = []
        for t_ns, is_dac, pin, value in zip(
            t[order].tolist(), dac[order].tolist(), ev["a"][order].tolist(), ev["b"][order].tolist()
        ):
            if t_ns >= since_ns:
                if is_dac:
                    out.append([t_ns / 1000.0, "DAC", "DAC", (value >> 2) & 0xFFF])
                else:
                    out.append([t_ns / 1000.0, "GPIO", pin, value])
        return out

    def delivered_pulses(self) -> list[DeliveredPulse]:
        """Every stretch of current the board delivered so far (a stretch still flowing is not included
        until it ends): what safety is judged on.  See :mod:`.delivered`."""
        arrays = self.delivered_arrays()
        for i in range(len(self._pulses), len(arrays)):
            self._pulses.append(
                DeliveredPulse(
                    int(arrays.start_ns[i]) / 1000.0,
                    int(arrays.end_ns[i]) / 1000.0,
                    int(arrays.code[i]),
                    arrays.outputs_of(i),
                    int(arrays.polarity[i]),
                )
            )
        return list(self._pulses)

    def delivered_arrays(self) -> PulseArrays:
        """:meth:`delivered_pulses` as columns, for comparisons that need no object per pulse."""
        if self._pulse_arrays is None:
            if len(self._pulse_chunks) != 1:
                records = np.concatenate([r for r, _ in self._pulse_chunks] or [np.empty(0, PULSE_DTYPE)])
                outputs = np.concatenate([o for _, o in self._pulse_chunks] or [np.empty(0, np.int32)])
                self._pulse_chunks[:] = [(records, outputs)]
            records, outputs = self._pulse_chunks[0]
            offsets = np.zeros(len(records) + 1, np.int64)
            np.cumsum(records["n_outputs"], out=offsets[1:])
            self._pulse_arrays = PulseArrays(
                records["start_ns"], records["end_ns"], records["code"], records["polarity"], offsets, outputs
            )
        return self._pulse_arrays

    def set_interrupts(self, enabled: bool) -> None:
        """Let the timer interrupt run (or hold it off).  An alarm that fell due while held off fires at the
        firmware's next shim call, as a masked interrupt does when unmasked."""
        self._live().hb_set_interrupts(1 if enabled else 0)

    def set_reading(self, enabled: bool) -> None:
        """Let the firmware read its receive queue (or not: ``available()`` is 0 and a read finds nothing,
        while the host's bytes still arrive, fill the queue and are dropped when it is full)."""
        self._lib.hb_set_reading(1 if enabled else 0)

    def scans(self) -> list[tuple[float, float]]:
        """Every interrupt handler run so far: (entry µs, return µs)."""
        ev = self._all_events()
        ev = ev[(ev["kind"] == _ISR_ENTER) | (ev["kind"] == _ISR_RETURN)]
        out: list[tuple[float, float]] = []
        start: float | None = None
        for t_ns, kind in zip(ev["t_ns"].tolist(), ev["kind"].tolist()):
            if kind == _ISR_ENTER:
                start = t_ns / 1000.0
            elif start is not None:
                out.append((start, t_ns / 1000.0))
                start = None
        return out

    def isr_returns_us(self) -> list[float]:
        ev = self._all_events()
        return [t / 1000.0 for t in ev["t_ns"][ev["kind"] == _ISR_RETURN].tolist()]

    def watch_at_isr(self, register: str) -> None:
        """Read ``register`` (every element of an array) at each timer interrupt's entry from now on.

        A scan is made from the values the main loop left: the loop cannot run again before the handler
        returns, so the reading at entry is what every pulse of that scan used, to the nanosecond, however
        seldom Python looks.  :meth:`isr_samples` gives the readings that changed."""
        reg = next((r for r in self.built.registers if r.name == register), None)
        if reg is None:
            raise ConfigurationError(
                f"watch_at_isr: register {register!r} is not in the state map "
                f"({', '.join(r.name for r in self.built.registers) or 'no registers'})"
            )
        if reg.local_static:
            raise ConfigurationError(
                f"watch_at_isr: register {register!r} is a function-local static ({reg.expr}), read through "
                "the symbol table only: the interrupt's entry needs a getter the build generates"
            )
        # the per-element getter, ``double hb_reg_NAME(int i)``, the signature the runtime calls at entry
        element = getattr(self._lib, f"hb_reg_{register}")
        address = ctypes.cast(element, ctypes.c_void_p).value
        for i in range(1 if reg.length is None else reg.length):
            self._lib.hb_watch_add(address, i)
            self._watched.append((register, i))

    def isr_samples(self) -> list[IsrSample]:
        """Every watched value at the interrupt entries so far, when it differed from the entry before
        (the first entry records them all), in time order."""
        n = self._lib.hb_sample_count()
        if n > 0:
            buf = (_Sample * n)()
            got = self._lib.hb_samples_take(buf, n)
            for smp in buf[:got]:
                name, index = self._watched[smp.slot]
                self._samples.append(IsrSample(smp.t_ns / 1000.0, name, index, _num(smp.value)))
        return self._samples

    def timer(self, num: int) -> dict[str, Any] | None:
        """A hardware timer's state (``None``: the firmware never began it)."""
        out = (ctypes.c_int64 * 7)()
        if not self._live().hb_timer_info(num, out):
            return None
        return {
            "alarm_ticks": out[0],
            "autoreload": bool(out[1]),
            "alarm_enabled": bool(out[2]),
            "has_interrupt": bool(out[3]),
            "tick_ps": out[4],
            "counter": out[5],
            "next_alarm_us": None if out[6] < 0 else out[6] / 1000.0,
        }

    def state(self) -> dict[str, Any]:
        """The mapped firmware variables, the stimulation timer's alarm and the receive queue."""
        snap: dict[str, Any] = {}
        self._live()
        for reg in self.built.registers:
            fn = self._getters[reg.name]
            if reg.length is None:
                snap[reg.name] = _num(fn(0))
            else:
                values = np.empty(reg.length, np.float64)
                fn(_pointer(values))
                snap[reg.name] = [_num(v) for v in values.tolist()]
        for num in range(4):
            info = self.timer(num)
            if info is not None and info["has_interrupt"]:
                snap["timer_alarm_ticks"] = info["alarm_ticks"]
        snap["rx_pending"] = self._lib.hb_rx_queued()
        snap["rx_in_flight"] = self._lib.hb_rx_in_flight()
        snap["rx_capacity"] = self._lib.hb_rx_capacity()
        snap["rx_dropped"] = self._lib.hb_rx_dropped()
        return snap


@functools.lru_cache(maxsize=64)
def _symbols(library: Path) -> dict[str, tuple[int, int]]:
    """Demangled name -> (value, size) of the library's defined symbols, from binutils' ``nm``: the one way
    to a function-local static, which the dynamic table does not export."""
    nm = shutil.which("nm")
    if nm is None:
        raise FirmwareBuildError(
            "reading a function-local static needs binutils' nm (apt install binutils); nm is not on PATH"
        )
    out = subprocess.run(
        [nm, "-C", "-S", "--defined-only", str(library)], capture_output=True, text=True, check=False
    )
    if out.returncode != 0:
        raise FirmwareBuildError(f"nm could not read {library}: {out.stderr.strip()}")
    table: dict[str, tuple[int, int]] = {}
    for line in out.stdout.splitlines():
        parts = line.split(maxsplit=3)
        if len(parts) == 4:  # value size type name
            table[parts[3]] = (int(parts[0], 16), int(parts[1], 16))
    return table


def _local_static_reader(lib: ctypes.CDLL, library: Path, register: str, expr: str) -> Callable[[int], float]:
    """A getter for the function-local static ``expr`` (``function()::variable``) in this instance's copy:
    its offset and size from the symbol table, its address from that of an exported function of the same
    library (``hb_now``)."""
    table = _symbols(library)
    if expr not in table:
        raise ConfigurationError(
            f"state map register {register!r}: no function-local static {expr!r} in the built firmware "
            "(nm names it function()::variable)"
        )
    offset, size = table[expr]
    if size not in (1, 2, 4, 8):
        raise ConfigurationError(f"state map register {register!r}: {expr!r} is {size} bytes, not an integer")
    anchor = table.get("hb_now")
    if anchor is None:  # (the shim defines it in every build)
        raise FirmwareBuildError(f"{library}: no hb_now in its symbol table, so no load address to read from")
    base = int(ctypes.cast(lib.hb_now, ctypes.c_void_p).value or 0) - anchor[0]
    address = base + offset

    def read(_index: int) -> float:
        return float(int.from_bytes(ctypes.string_at(address, size), "little"))

    return read


def _num(v: float) -> int | float:
    return int(v) if v.is_integer() else v


@functools.lru_cache(maxsize=1)
def _dl() -> ctypes.CDLL:
    """The process's own ``dlopen``/``dlclose``/``dlerror`` (libc's, or libdl's on older systems)."""
    libc = ctypes.CDLL(None)
    libc.dlopen.restype = ctypes.c_void_p
    libc.dlopen.argtypes = [ctypes.c_char_p, ctypes.c_int]
    libc.dlclose.argtypes = [ctypes.c_void_p]
    libc.dlerror.restype = ctypes.c_char_p
    return libc


def _unload(handle: int, release: Callable[[], None]) -> None:
    """Free the firmware run's memory, then unload the library."""
    release()
    _dl().dlclose(handle)


def _load_private_copy(library: Path) -> tuple[ctypes.CDLL, int]:
    """dlopen a private copy, so this instance's firmware globals are its own; returns the library and its
    handle (for ``dlclose``)."""
    fd, path = tempfile.mkstemp(prefix="tactdeform-fw-", suffix=".so")
    os.close(fd)
    try:
        shutil.copyfile(library, path)
        dl = _dl()
        handle = dl.dlopen(os.fsencode(path), os.RTLD_NOW | os.RTLD_LOCAL)
        if not handle:
            why = dl.dlerror()
            raise FirmwareBuildError(
                f"the built library {library} does not load: {why.decode(errors='replace') if why else '?'}"
            )
        return ctypes.CDLL(path, handle=handle), handle
    finally:
        os.unlink(path)  # the mapping stays; nothing is left on disk
