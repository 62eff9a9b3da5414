"""The eTactileKit file formats: electrode-array files and pattern files.

People who already drive the board with the eTactileKit Processing GUI, its Python API or its Unity API
keep their arrays and patterns in two JSON formats.  Reading them here lets those files drive this
package's devices and pictures, and writing them lets a TactDeform sequence be opened and played in the
GUI.  The schema below is what the kit's own readers (the GUI's ``LoadData``/``ETactile``, the Python
API's ``PatternReader``) take from the files.

Electrode-array file (one JSON object)::

    outline            list of {"x", "y"}   board contour, a polygon (often closed: last = first)
    electrodes         list of {"x", "y"}   electrode centres, in application order
    electrode_radius   number               one radius for every electrode
    Mapping_func       list of int          Mapping_func[i] = hardware channel of electrode i
    Electrodes_Number  int                  optional; when present it must equal len(electrodes)
    board              string               optional; "on_board" = the 8 electrodes on the controller
                                            board itself (see :attr:`ArrayFile.pattern_offset`)

Coordinates and the radius are millimetres on the skin side of the array, x to the right and y up (the
GUI draws ``screen_y = 900 - (10·y + 500)``, i.e. 10 px per mm with y flipped onto the screen).  The
coordinates also decide which of a participant's 9 calibrated regions each electrode belongs to
(:meth:`ArrayFile.region_map`): regional limits follow positions, never the order of ``electrodes``.
Electrodes may also carry ``radius`` (used when ``electrode_radius`` is absent) and ``number`` (ignored, as
the GUI ignores it); a non-zero ``z`` marks the 3-D GUI's curved arrays, which the planar renderer cannot use.
The GUI refuses a file without ``outline``, ``electrode_radius`` or ``Mapping_func``; here ``outline`` may
be absent and ``Mapping_func`` defaults to the identity, and the writer always writes all of them.

Pattern file (one JSON object)::

    Execution     bool    the GUI sends the pattern to the board (optional here, default true)
    Simulation    bool    the GUI draws it (optional here, default true)
    Pattern_Data  list of steps; each step is a list holding one object:
        pattern   list of int, one per electrode in application order:
                  0 off, 1 monophasic pulse, 2 biphasic pulse (the firmware's pattern byte values)
        delay     {"ON": ms, "OFF": ms}  hold the pattern ON ms, then every electrode off for OFF ms
                  (no off phase when OFF is 0)
        params    {"frequency": Hz, "stim_mode": 0 | 1}

``stim_mode`` is the stimulation **polarity**, not a pulse shape: the GUI sends it with the polarity
command (0xFD) at every step, 1 anodic and 0 cathodic, and the Python API documents it as "anodic or
cathodic".  The pulse shape is chosen per electrode by the pattern value (2 = biphasic).  A value other
than 0 or 1 is refused, because the firmware would silently clamp it to anodic.

Each step is a list, but the GUI and the Python API only ever read its first object; a step holding more
is read the same way and a note says so.  The GUI plays the steps in a loop; :func:`read_pattern_file`
returns them once.  Unknown top-level keys (some GUI examples carry ``"Frequency"``) are kept and written
back.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ConfigurationError
from ._json import load_text

if TYPE_CHECKING:  # pragma: no cover
    from tactdeform_hw.device.driver.config import Polarity
    from tactdeform_hw.device.participant.mapping import ChannelMapping
    from tactdeform_hw.device.participant.regions import RegionMap

    from ..render.array import ElectrodeArray
    from .frames import Frame

#: Pattern values the firmware knows: 0 off (a sense pulse), 1 monophasic, 2 biphasic.
PATTERN_LEVELS = (0, 1, 2)
#: ``stim_mode`` values: the polarity byte the GUI sends (1 anodic, 0 cathodic).
STIM_MODE_POLARITY: dict[int, Polarity] = {1: "anodic", 0: "cathodic"}
#: Channels the GUI scans when the array is the controller board's own ("board": "on_board").
ON_BOARD_CHANNELS = 32
ON_BOARD_OFFSET = 24


# --- value checks ------------------------------------------------------------------------------------------


def _show(value: Any) -> str:
    try:
        text = json.dumps(value)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _fail(source: str, where: str, expected: str, value: Any) -> ConfigurationError:
    return ConfigurationError(f"{source}: {where}: expected {expected}, got {_show(value)}")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _number(
    source: str, where: str, value: Any, *, minimum: float | None = None, positive: bool = False
) -> float:
    if not _is_number(value) or (positive and value <= 0) or (minimum is not None and value < minimum):
        what = "a positive number" if positive else "a non-negative number" if minimum == 0 else "a number"
        raise _fail(source, where, what, value)
    return float(value)


def _integer(source: str, where: str, value: Any, lo: int, hi: int, what: str | None = None) -> int:
    ok = _is_number(value) and float(value).is_integer() and lo <= value <= hi
    if not ok:
        raise _fail(source, where, what or f"an integer from {lo} to {hi}", value)
    return int(value)


def _get(source: str, obj: dict[str, Any], key: str, where: str) -> Any:
    if key not in obj:
        raise ConfigurationError(f"{source}: {where}: missing (the eTactileKit tools need it)")
    return obj[key]


def _object(source: str, where: str, value: Any) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise _fail(source, where, "an object", value)
    return value


def _list(source: str, where: str, value: Any, *, nonempty: bool = True) -> list[Any]:
    if not isinstance(value, list) or (nonempty and not value):
        raise _fail(source, where, "a non-empty list" if nonempty else "a list", value)
    return value


def _load(path: str | Path) -> tuple[Any, str, list[str]]:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise ConfigurationError(f"{p}: cannot read: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigurationError(f"{p}: not a text file ({exc.reason} at byte {exc.start})") from exc
    data, notes = load_text(text, p.name)
    return data, p.name, notes


def _point(source: str, where: str, value: Any) -> tuple[float, float]:
    obj = _object(source, where, value)
    x = _number(source, f"{where}.x", _get(source, obj, "x", f"{where}.x"))
    y = _number(source, f"{where}.y", _get(source, obj, "y", f"{where}.y"))
    return x, y


# --- electrode-array files --------------------------------------------------------------------------------


@dataclass(frozen=True)
class ArrayFile:
    """An eTactileKit electrode-array file, read.

    ``array`` is the renderer's :class:`~tactdeform_hw.render.array.ElectrodeArray` (positions and radius
    in mm, its ``mapping`` the hardware channel of each electrode).  ``mapping_func`` is the file's own
    ``Mapping_func``; the two differ only for an ``"on_board"`` array, whose electrodes the GUI drives as
    the last 8 of 32 scanned channels (``pattern_offset`` 24, hardware channel ``24 + Mapping_func[i]``).
    ``outline_mm`` is the board contour (``(M, 2)``, possibly empty).
    """

    array: ElectrodeArray
    outline_mm: np.ndarray
    mapping_func: tuple[int, ...]
    board: str | None = None
    source: str = ""
    notes: tuple[str, ...] = ()

    @property
    def electrodes(self) -> int:
        return int(len(self.array.positions_mm))

    @property
    def on_board(self) -> bool:
        return self.board == "on_board"

    @property
    def pattern_offset(self) -> int:
        return ON_BOARD_OFFSET if self.on_board else 0

    @property
    def hw_channels(self) -> int:
        """Channels the firmware must scan so that every mapped channel exists."""
        return int(self.array.hw_channels)

    def channel_mapping(self) -> ChannelMapping:
        """The device layer's mapping: electrode i → hardware channel."""
        return self.array.channel_mapping()

    def region_map(self) -> RegionMap:
        """The calibration region(s) of each electrode, from its coordinates in this file (application
        order, the order of ``electrodes``): what a participant's regional limits follow, whatever order
        the file lists its electrodes in."""
        from tactdeform_hw.device.participant.regions import region_map_from_positions

        return region_map_from_positions(
            [(float(x), float(y)) for x, y in self.array.positions_mm],
            f"array file {self.source or self.array.name}",
        )

    def hardware_regions(self, region_of: Sequence[int]) -> dict[int, tuple[int, int]]:
        """Hardware channel → (electrode, region) for the regions ``region_of`` gives each electrode."""
        return {
            int(ch): (i, int(region_of[i])) for i, ch in enumerate(self.array.channel_mapping().app_to_hw)
        }

    def levels_for(self, pattern: Sequence[int], where: str = "pattern") -> tuple[int, ...]:
        """This array's levels out of one step of a pattern file.

        A pattern as long as the array is used as it is; for an on-board array a 32-value pattern (what
        the GUI sends in that mode) is cut to its last 8.  Any other length is refused."""
        n = self.electrodes
        if len(pattern) == n:
            return tuple(pattern)
        if self.on_board and len(pattern) == ON_BOARD_CHANNELS:
            return tuple(pattern[ON_BOARD_OFFSET : ON_BOARD_OFFSET + n])
        extra = f" (or {ON_BOARD_CHANNELS} for its on-board mode)" if self.on_board else ""
        raise ConfigurationError(
            f"{where} has {len(pattern)} value(s) but the array {self.source or self.array.name!s} has "
            f"{n} electrode(s){extra}"
        )


def _mapping_func(source: str, doc: dict[str, Any], n: int) -> tuple[int, ...]:
    """The array's ``Mapping_func``: one hardware channel (0 to 254) per electrode, none used twice; the
    identity without one."""
    if "Mapping_func" not in doc:
        return tuple(range(n))
    raw = _list(source, "Mapping_func", doc["Mapping_func"])
    if len(raw) != n:
        raise ConfigurationError(
            f"{source}: Mapping_func: has {len(raw)} entr{'y' if len(raw) == 1 else 'ies'} but "
            f"'electrodes' lists {n} position(s); it needs one hardware channel per electrode"
        )
    seen: dict[int, int] = {}
    chans = []
    for i, v in enumerate(raw):
        ch = _integer(source, f"Mapping_func[{i}]", v, 0, 254, "a hardware channel from 0 to 254")
        if ch in seen:
            raise ConfigurationError(
                f"{source}: Mapping_func[{i}]: hardware channel {ch} is already used by electrode {seen[ch]}"
            )
        seen[ch] = i
        chans.append(ch)
    return tuple(chans)


def parse_array(data: Any, source: str = "<array>", name: str | None = None) -> ArrayFile:
    """Check a decoded electrode-array document and build the renderer's array from it."""
    from ..render.array import ElectrodeArray

    doc = _object(source, "top level", data)
    electrodes = _list(source, "electrodes", _get(source, doc, "electrodes", "electrodes"))
    positions = np.empty((len(electrodes), 2), dtype=float)
    radii: list[float] = []
    for i, e in enumerate(electrodes):
        where = f"electrodes[{i}]"
        positions[i] = _point(source, where, e)
        z = e.get("z", 0)
        if not _is_number(z) or z != 0:
            raise ConfigurationError(
                f"{source}: {where}.z: the array is three-dimensional (z={_show(z)}); only planar arrays "
                "(x, y in mm) can be used"
            )
        if "radius" in e:
            radii.append(_number(source, f"{where}.radius", e["radius"], positive=True))

    if "electrode_radius" in doc:
        radius = _number(source, "electrode_radius", doc["electrode_radius"], positive=True)
    elif radii and len(radii) == len(electrodes) and len(set(radii)) == 1:
        radius = radii[0]
    else:
        raise ConfigurationError(f"{source}: electrode_radius: missing (the eTactileKit tools need it)")

    n = len(electrodes)
    if "Electrodes_Number" in doc:
        count = _integer(source, "Electrodes_Number", doc["Electrodes_Number"], 0, 10**6, "an integer")
        if count != n:
            raise ConfigurationError(
                f"{source}: Electrodes_Number: says {count} but 'electrodes' lists {n} position(s)"
            )

    mapping = _mapping_func(source, doc, n)
    outline = np.empty((0, 2), dtype=float)
    if "outline" in doc:
        pts = _list(source, "outline", doc["outline"], nonempty=False)
        outline = np.array(
            [_point(source, f"outline[{i}]", p) for i, p in enumerate(pts)], dtype=float
        ).reshape(-1, 2)
        if 0 < len(outline) < 3:
            raise _fail(source, "outline", "at least 3 points (a polygon)", pts)

    board = doc.get("board")
    if board is not None and not isinstance(board, str):
        raise _fail(source, "board", 'a string such as "on_board"', board)

    if board == "on_board":
        hw = tuple(ON_BOARD_OFFSET + ch for ch in mapping)
        hw_channels = max(ON_BOARD_CHANNELS, max(hw) + 1)
    else:
        hw, hw_channels = mapping, max(mapping) + 1
    try:
        array = ElectrodeArray(positions, radius, hw, name or Path(source).stem, hw_channels=hw_channels)
    except ConfigurationError as exc:
        raise ConfigurationError(f"{source}: {exc}") from exc
    return ArrayFile(array=array, outline_mm=outline, mapping_func=mapping, board=board, source=source)


def read_array_file(path: str | Path) -> ArrayFile:
    """Read an eTactileKit electrode-array file (errors name the field and its position)."""
    data, source, notes = _load(path)
    af = parse_array(data, source)
    return ArrayFile(af.array, af.outline_mm, af.mapping_func, af.board, af.source, tuple(notes))


def default_outline(array: ElectrodeArray, margin_mm: float | None = None) -> np.ndarray:
    """A closed rectangle around the electrodes, ``margin_mm`` (default two radii) outside their edges."""
    pos = np.asarray(array.positions_mm, dtype=float)
    r = float(array.radius_mm)
    m = 2 * r if margin_mm is None else float(margin_mm)
    (x0, y0), (x1, y1) = pos.min(axis=0) - r - m, pos.max(axis=0) + r + m
    return np.array([[x0, y1], [x1, y1], [x1, y0], [x0, y0], [x0, y1]], dtype=float)


def array_to_dict(
    array: ElectrodeArray, outline_mm: np.ndarray | None = None, board: str | None = None
) -> dict[str, Any]:
    """The eTactileKit array document for ``array`` (outline: the given one, or a rectangle around it)."""
    pos = np.asarray(array.positions_mm, dtype=float)
    outline = default_outline(array) if outline_mm is None or len(outline_mm) == 0 else np.asarray(outline_mm)
    mapping = list(array.mapping if array.mapping is not None else range(len(pos)))
    if board == "on_board":
        mapping = [ch - ON_BOARD_OFFSET for ch in mapping]

    def num(v: float) -> float | int:
        v = round(float(v), 6)
        return int(v) if v.is_integer() else v

    doc: dict[str, Any] = {
        "outline": [{"x": num(x), "y": num(y)} for x, y in outline],
        "electrodes": [{"x": num(x), "y": num(y)} for x, y in pos],
        "Electrodes_Number": len(pos),
        "Mapping_func": [int(c) for c in mapping],
        "electrode_radius": num(array.radius_mm),
    }
    if board is not None:
        doc["board"] = board
    return doc


def write_array_file(
    array: ElectrodeArray, path: str | Path, outline_mm: np.ndarray | None = None, board: str | None = None
) -> Path:
    """Write ``array`` as an eTactileKit electrode-array file the GUI can open."""
    p = Path(path)
    p.write_text(json.dumps(array_to_dict(array, outline_mm, board), indent=2) + "\n", encoding="utf-8")
    return p


# --- pattern files -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PatternStep:
    """One step: ``levels`` (application order, 0/1/2) held ``on_ms``, then all off for ``off_ms``."""

    levels: tuple[int, ...]
    on_ms: float
    off_ms: float = 0.0
    frequency_hz: int = 125
    stim_mode: int = 1

    @property
    def polarity(self) -> Polarity:
        """``stim_mode`` as the device layer names it ("anodic" or "cathodic")."""
        return STIM_MODE_POLARITY[self.stim_mode]

    @property
    def duration_ms(self) -> float:
        return self.on_ms + self.off_ms

    @property
    def active(self) -> int:
        return sum(1 for v in self.levels if v)


@dataclass(frozen=True)
class PatternSequence:
    """The steps of an eTactileKit pattern file, played once from the first."""

    steps: tuple[PatternStep, ...]
    execution: bool = True
    simulation: bool = True
    extra: dict[str, Any] = field(default_factory=dict)
    source: str = ""
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.steps:
            raise ConfigurationError("a pattern sequence needs at least one step")
        n = len(self.steps[0].levels)
        for i, s in enumerate(self.steps):
            if len(s.levels) != n:
                raise ConfigurationError(
                    f"step {i} has {len(s.levels)} level(s) but step 0 has {n}; every step covers every "
                    "electrode"
                )
            for j, v in enumerate(s.levels):
                if v not in PATTERN_LEVELS or isinstance(v, bool):
                    raise ConfigurationError(f"step {i}: levels[{j}]: expected 0, 1 or 2, got {_show(v)}")
            if s.stim_mode not in STIM_MODE_POLARITY:
                raise ConfigurationError(
                    f"step {i}: stim_mode: expected 0 (cathodic) or 1 (anodic), got {_show(s.stim_mode)}"
                )
            if not (_is_number(s.on_ms) and s.on_ms >= 0 and _is_number(s.off_ms) and s.off_ms >= 0):
                raise ConfigurationError(f"step {i}: on_ms/off_ms must be non-negative numbers")
            if not (isinstance(s.frequency_hz, int) and 1 <= s.frequency_hz <= 0xFFFF):
                raise ConfigurationError(
                    f"step {i}: frequency_hz: expected 1 to 65535 Hz, got {_show(s.frequency_hz)}"
                )

    @property
    def electrodes(self) -> int:
        return len(self.steps[0].levels)

    @property
    def duration_ms(self) -> float:
        return sum(s.duration_ms for s in self.steps)

    @property
    def frequencies_hz(self) -> tuple[int, ...]:
        return tuple(sorted({s.frequency_hz for s in self.steps}))

    @property
    def stim_modes(self) -> tuple[int, ...]:
        return tuple(sorted({s.stim_mode for s in self.steps}))


def parse_pattern(data: Any, source: str = "<pattern>") -> PatternSequence:
    """Check a decoded pattern document; errors name the field and its position."""
    doc = _object(source, "top level", data)
    groups = _list(source, "Pattern_Data", _get(source, doc, "Pattern_Data", "Pattern_Data"))
    flags = {}
    for key in ("Execution", "Simulation"):
        v = doc.get(key, True)
        if not isinstance(v, bool):
            raise _fail(source, key, "true or false", v)
        flags[key] = v
    notes: list[str] = []
    steps: list[PatternStep] = []
    width: int | None = None
    for i, group in enumerate(groups):
        where = f"Pattern_Data[{i}]"
        if isinstance(group, dict):
            raise _fail(
                source, where, "a list holding one object (eTactileKit wraps every step in a list)", group
            )
        group = _list(source, where, group)
        if len(group) > 1:
            notes.append(
                f"{where} holds {len(group)} entries; the eTactileKit GUI and Python API play only the "
                "first, and so does this reader"
            )
        where = f"{where}[0]"
        step = _object(source, where, group[0])
        pattern = _list(source, f"{where}.pattern", _get(source, step, "pattern", f"{where}.pattern"))
        levels = tuple(
            _integer(source, f"{where}.pattern[{j}]", v, 0, 2, "0 (off), 1 (monophasic) or 2 (biphasic)")
            for j, v in enumerate(pattern)
        )
        if width is None:
            width = len(levels)
        elif len(levels) != width:
            raise ConfigurationError(
                f"{source}: {where}.pattern: has {len(levels)} value(s) but Pattern_Data[0][0].pattern has "
                f"{width}; every step must cover the same electrodes"
            )
        delay = _object(source, f"{where}.delay", _get(source, step, "delay", f"{where}.delay"))
        on_ms = _number(
            source, f"{where}.delay.ON", _get(source, delay, "ON", f"{where}.delay.ON"), minimum=0
        )
        off_ms = _number(
            source, f"{where}.delay.OFF", _get(source, delay, "OFF", f"{where}.delay.OFF"), minimum=0
        )
        params = _object(source, f"{where}.params", _get(source, step, "params", f"{where}.params"))
        freq = _integer(
            source,
            f"{where}.params.frequency",
            _get(source, params, "frequency", f"{where}.params.frequency"),
            1,
            0xFFFF,
            "a stimulation frequency in Hz from 1 to 65535",
        )
        mode = _integer(
            source,
            f"{where}.params.stim_mode",
            _get(source, params, "stim_mode", f"{where}.params.stim_mode"),
            0,
            1,
            "0 (cathodic) or 1 (anodic) — stim_mode is the polarity the GUI sends; "
            "choose biphasic pulses with pattern value 2",
        )
        steps.append(PatternStep(levels, on_ms, off_ms, freq, mode))
    extra = {k: v for k, v in doc.items() if k not in ("Pattern_Data", "Execution", "Simulation")}
    return PatternSequence(tuple(steps), flags["Execution"], flags["Simulation"], extra, source, tuple(notes))


def read_pattern_file(path: str | Path) -> PatternSequence:
    """Read an eTactileKit pattern file."""
    data, source, notes = _load(path)
    seq = parse_pattern(data, source)
    return PatternSequence(
        seq.steps, seq.execution, seq.simulation, seq.extra, source, tuple(notes) + seq.notes
    )


def _ms(v: float) -> int:
    """The GUI reads delays with ``getInt``: write whole milliseconds."""
    return int(round(v))


def pattern_to_dict(seq: PatternSequence) -> dict[str, Any]:
    """The pattern document, in the key order the kit's Pattern Creator writes."""
    doc: dict[str, Any] = {"Execution": seq.execution, "Simulation": seq.simulation}
    doc.update(seq.extra)
    doc["Pattern_Data"] = [
        [
            {
                "delay": {"OFF": _ms(s.off_ms), "ON": _ms(s.on_ms)},
                "pattern": list(s.levels),
                "params": {"frequency": s.frequency_hz, "stim_mode": s.stim_mode},
            }
        ]
        for s in seq.steps
    ]
    return doc


def dumps_pattern(seq: PatternSequence) -> str:
    """Pattern-file text: indented like the kit's own files, each pattern on one line to stay readable."""
    doc = pattern_to_dict(seq)
    placeholder = {}
    for i, group in enumerate(doc["Pattern_Data"]):
        key = f"@@pattern{i}@@"
        placeholder[key] = json.dumps(group[0]["pattern"], separators=(", ", ": "))
        group[0]["pattern"] = key
    text = json.dumps(doc, indent=2)
    for key, value in placeholder.items():
        text = text.replace(f'"{key}"', value, 1)
    return text + "\n"


def write_pattern_file(seq: PatternSequence, path: str | Path) -> Path:
    """Write ``seq`` as an eTactileKit pattern file (delays rounded to whole ms, as the GUI reads them)."""
    p = Path(path)
    p.write_text(dumps_pattern(seq), encoding="utf-8")
    return p


# --- TactDeform frames → pattern ---------------------------------------------------------------------------


def sequence_from_frames(
    frames: Iterable[Frame],
    *,
    frequency_hz: int = 125,
    stim_mode: int = 1,
    last_ms: float | None = None,
    merge: bool = True,
    sent_only: bool = True,
) -> PatternSequence:
    """Turn a TactDeform frame sequence into pattern steps the GUI can play.

    What the board delivers between two updates is the last pattern it was sent, so by default only
    frames marked ``sent`` become steps, each held until the next one, and an all-off step covers the
    time before the first (see :func:`~tactdeform_hw.formats.frames.delivered_spans`); ``merge`` joins
    runs of identical patterns.  The last step lasts to the end of the record plus one frame interval,
    or ``last_ms``.  Delays are whole milliseconds in the file; they are rounded on the cumulative time
    line, so the total duration keeps its millisecond accuracy however many steps there are.
    """
    from .frames import delivered_spans

    runs: list[tuple[float, tuple[int, ...], float]] = []  # start s, levels, end s
    for f, start_s, dur_ms in delivered_spans(list(frames), sent_only=sent_only, last_ms=last_ms):
        levels = tuple(int(v) for v in f.electrodes)
        end_s = start_s + dur_ms / 1000.0
        if merge and runs and runs[-1][1] == levels:
            runs[-1] = (runs[-1][0], levels, end_s)
        else:
            runs.append((start_s, levels, end_s))
    steps: list[PatternStep] = []
    for t, levels, end in runs:
        on = round(end * 1000.0) - round(t * 1000.0)
        if on > 0 or not steps:  # a pattern replaced within the same millisecond was never felt
            steps.append(PatternStep(levels, float(max(on, 0)), 0.0, frequency_hz, stim_mode))
    return PatternSequence(tuple(steps), extra={}, source="frames")
