"""TactDeform's base patterns on any electrode array, precomputed once per array.

A pattern is a tuple of levels in application order (0 off, ``on_level`` on), the exact value
:meth:`Device.send_pattern` takes, so the per-frame work of the renderer is a dictionary lookup and a
tuple comparison.  Everything is derived from electrode positions in millimetres, so the same definitions
hold on the 32-electrode pad, a 64-electrode board or an eTactileKit array file.

Geometry used throughout:

* ``rho`` — an electrode's distance from the array centre minus the smallest such distance, so the
  innermost electrodes (the centre 2 × 2 on an even grid, the centre electrode on an odd one) sit at 0.
* ``ring`` — ``round(rho / step)``: how many electrode spacings an electrode is beyond the innermost
  ones.  On the 6 × 6 array this reproduces the square rings (4, 12 and 16 electrodes).
* Expansion frame ``n`` of a pattern is "one electrode spacing further along" than frame ``n - 1``,
  and every feature is recognisable from its first frame: the face shows ring ``n`` (a ring diverging
  from the centre 2 × 2), the edge shows the pair of lines ``n`` spacings either side of its centre line
  (frame 0 is the whole line, then it splits and diverges across the pad), the corner shows everything
  within its falloff plus ``n`` spacings of the centre (a concentrated blob, already wider than the face's
  first ring, that spreads).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigurationError, LimitError
from .array import ElectrodeArray

Pattern = tuple[int, ...]

FEATURES: tuple[str, ...] = ("face", "edge", "corner")

#: Edge orientations in the finger-pad frame: horizontal (along x), the diagonal rising to the right
#: (``/``, toward the fingertip on the right), vertical (along y, toward the fingertip), the other
#: diagonal (``\``).  Angles are measured from +x toward +y, modulo 180°.
EDGE_ORIENTATIONS: tuple[str, ...] = ("h", "d1", "v", "d2")
EDGE_ANGLE_DEG: dict[str, float] = {"h": 0.0, "d1": 45.0, "v": 90.0, "d2": 135.0}

#: The eight sliding directions in the pad frame, 45° apart from +x (right) toward +y (fingertip):
#: E = right, N = toward the fingertip, W = left, S = toward the palm.
DIRECTIONS: tuple[str, ...] = ("E", "NE", "N", "NW", "W", "SW", "S", "SE")
#: Each direction as a step on the grid (dx, dy in {-1, 0, 1}); texture stripes run across it.
DIRECTION_STEPS: tuple[tuple[int, int], ...] = (
    (1, 0),
    (1, 1),
    (0, 1),
    (-1, 1),
    (-1, 0),
    (-1, -1),
    (0, -1),
    (1, -1),
)

#: Contact-orientation levels (eq. 4), left to right on the pad.
THETA_LEVELS: tuple[str, ...] = ("steep-left", "shallow-left", "shallow-right", "steep-right")

_TOL = 1e-6


@dataclass(frozen=True)
class PatternParams:
    """Shapes the paper leaves open.  ``None`` derives a value from the array's pitch.

    * ``step_mm`` — one expansion frame; the paper: one electrode spacing.
    * ``edge_half_width_mm`` — electrodes within this distance of the edge line (through the array
      centre) form the line.  *Interpretation*: pitch/√2, which gives the horizontal and vertical lines
      their two central rows/columns (an even grid has no centre row) and the diagonals their central
      diagonal plus both neighbours — 12 and 14 electrodes, lines of comparable weight.
    * ``corner_falloff_mm`` — *interpretation of the "parametric falloff"*: the corner's stimulation
      falls from the innermost electrodes to nothing over this distance (``rho`` ≤ falloff); the default
      of one spacing gives the centre 2 × 2 plus its 8 edge neighbours.  Larger values spread the
      corner toward a face, smaller ones concentrate it on the centre.
    * ``contact_half_width_mm`` — only places the default shifts: the outermost shift puts a band of this
      half-width about the pattern's centre against the array's side (default half a pitch).
    * ``contact_centres_mm`` — where the four θ levels (left to right) move the pattern's centre; eq. 4
      is P_contact(x, y) = P_base(x − c, y): the feature's whole base pattern is shifted, never cut to a
      window, so its shape survives (what is pushed past the array's side is lost, zeros come in from
      the other side).  ``None``: the outermost shift puts the central band against the array's side and
      the inner ones sit half way, snapped to whole spacings (−4, −2, +2, +4 mm on the 6 × 6 array: the
      leftmost, left-centre, right-centre, rightmost regions).
    * ``mask_period_factor`` — the texture mask's spatial period in units of k spacings.  *Interpretation*:
      3 — stripes k spacings wide with 2k off between them.  The mask moves k spacings per shift, so a
      period of exactly 2k would only toggle two complementary states (no direction); with 3k every
      shift moves the stripes one third of a period against the finger, and β = +1 and β = −1 give the
      same states in opposite orders.  Must be ≥ 3.
    * ``on_level`` — the level of an active electrode: 1 (monophasic, the paper's setting) or 2.
    """

    step_mm: float | None = None
    edge_half_width_mm: float | None = None
    corner_falloff_mm: float | None = None
    contact_half_width_mm: float | None = None
    contact_centres_mm: tuple[float, float, float, float] | None = None
    mask_period_factor: int = 3
    on_level: int = 1

    def __post_init__(self) -> None:
        for name in ("step_mm", "edge_half_width_mm", "corner_falloff_mm", "contact_half_width_mm"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v >= 0.0):
                raise LimitError(name, v, "a finite length ≥ 0 mm (or None for the pitch-derived default)")
        if self.step_mm is not None and self.step_mm <= 0:
            raise LimitError("step_mm", self.step_mm, "> 0 mm")
        if self.contact_centres_mm is not None:
            c = tuple(float(v) for v in self.contact_centres_mm)
            if len(c) != 4 or not all(math.isfinite(v) for v in c):
                raise LimitError(
                    "contact_centres_mm", self.contact_centres_mm, "four finite x positions in mm"
                )
        if (
            isinstance(self.mask_period_factor, bool)
            or not isinstance(self.mask_period_factor, int)
            or self.mask_period_factor < 3
        ):
            raise LimitError(
                "mask_period_factor",
                self.mask_period_factor,
                "an integer ≥ 3 (a period of 2 steps only toggles two states: the texture would have no "
                "direction)",
            )
        if self.on_level not in (1, 2):
            raise LimitError("on_level", self.on_level, "1 (monophasic) or 2 (biphasic)")


class PatternSet:
    """Every base pattern of one array: expansion frames, static patterns, contact shifts and texture
    masks for k = 1 and 2.  Built once (under 10 ms for 32 electrodes); the renderer only looks patterns
    up.  Other texture levels are built on first use and kept."""

    def __init__(self, array: ElectrodeArray, params: PatternParams | None = None) -> None:
        self.array = array
        self.params = params or PatternParams()
        p = self.params
        pitch = array.pitch_mm
        self.step_mm = p.step_mm if p.step_mm is not None else pitch
        rel = array.positions_mm - array.centre_mm
        self._rel = rel
        r = np.hypot(rel[:, 0], rel[:, 1])
        self.rho_mm = r - float(r.min())
        self.ring = np.rint(self.rho_mm / self.step_mm + _TOL).astype(int)
        n = array.count
        self.off: Pattern = (0,) * n
        self.on_level = p.on_level

        everything = np.ones(n, dtype=bool)
        # Face: the whole pad is in contact; frames are its rings, innermost first.
        self._static: dict[tuple[str, str | None], np.ndarray] = {("face", None): everything}
        self._frames: dict[tuple[str, str | None], tuple[Pattern, ...]] = {
            ("face", None): tuple(self._pat(self.ring == k) for k in np.unique(self.ring))
        }
        half = p.edge_half_width_mm if p.edge_half_width_mm is not None else pitch / math.sqrt(2.0)
        for o in EDGE_ORIENTATIONS:
            a = math.radians(EDGE_ANGLE_DEG[o])
            perp = np.abs(-rel[:, 0] * math.sin(a) + rel[:, 1] * math.cos(a))
            band = perp <= half + _TOL
            if not band.any():
                raise ConfigurationError(
                    f"edge_half_width_mm={half:g} leaves the {o!r} edge line without electrodes on "
                    f"{array.name}"
                )
            self._static[("edge", o)] = band
            # Diverging lines: line index 0 is the band itself, index m the electrodes m spacings beyond it.
            line = np.where(band, 0, np.ceil((perp - half) / self.step_mm - _TOL)).astype(int)
            self._frames[("edge", o)] = tuple(self._pat(line == m) for m in np.unique(line))
        falloff = p.corner_falloff_mm if p.corner_falloff_mm is not None else pitch
        blob = self.rho_mm <= falloff + _TOL
        self._static[("corner", None)] = blob
        # Concentrated at the centre with the falloff's extent, spreading one spacing per frame.
        reach = np.where(blob, 0, np.ceil((self.rho_mm - falloff) / self.step_mm - _TOL)).astype(int)
        self._frames[("corner", None)] = tuple(self._pat(reach <= m) for m in np.unique(reach))

        self._contact_shifts(rel)

        # Texture masks: coordinate across each direction in electrode spacings, starting at 0.
        self._mask_coord: list[np.ndarray] = []
        for dx, dy in DIRECTION_STEPS:
            q = (rel[:, 0] * dx + rel[:, 1] * dy) / pitch
            self._mask_coord.append(q - q.min())
        self._contact_cache: dict[tuple[str, str | None, int], Pattern] = {}
        self._static_cache: dict[tuple[str, str | None], Pattern] = {
            key: self._pat(v) for key, v in self._static.items()
        }
        self._slide_cache: dict[tuple[str, str | None, int, int, int], Pattern] = {}
        self.all_on: Pattern = self._pat(everything)
        self._prebuild()

    # --- building -------------------------------------------------------------------------------------------

    def _contact_shifts(self, rel: np.ndarray) -> None:
        """Eq. 4's shifted contact patterns: for each θ level's centre, which electrode's base value each
        electrode shows."""
        p, array, pitch = self.params, self.array, self.array.pitch_mm
        # Contact (eq. 4): P_contact(x, y) = P_base(x + Δx(θ), y) with Δx = -centre(θ level).
        chw = p.contact_half_width_mm if p.contact_half_width_mm is not None else pitch / 2.0
        self.contact_half_width_mm = chw
        if p.contact_centres_mm is not None:
            centres = tuple(float(c) for c in p.contact_centres_mm)
        else:
            half_span = float(rel[:, 0].max() - rel[:, 0].min()) / 2.0
            outer = max(0.0, half_span - chw)
            outer = _snap(outer, pitch)
            inner = _snap(outer / 2.0, pitch)
            centres = (-outer, -inner, inner, outer)
        self.contact_centres_mm = centres
        self._shift_index: list[np.ndarray] = []
        for c in centres:
            # src[i]: the electrode whose base value electrode i shows, or -1 (nothing there).
            src = np.array(
                [
                    array.index_at(float(x) + array.centre_mm[0] - c, float(y) + array.centre_mm[1])
                    for x, y in rel
                ]
            )
            self._shift_index.append(src)

    def _prebuild(self) -> None:
        """Every pattern the paper's settings can show, built now (a few ms) so no frame pays for it."""
        for feature, orientation in self._static:
            for level in range(len(THETA_LEVELS)):
                self.contact(feature, orientation, level)
            for k in (1, 2):
                for direction in range(len(DIRECTIONS)):
                    for phase in range(self.mask_period(k)):
                        self.sliding(feature, orientation, direction, k, phase)

    def _pat(self, mask: np.ndarray) -> Pattern:
        lvl = self.on_level
        return tuple(lvl if bool(m) else 0 for m in mask)

    @staticmethod
    def _key(feature: str, orientation: str | None) -> tuple[str, str | None]:
        if feature == "edge":
            if orientation not in EDGE_ANGLE_DEG:
                raise LimitError("orientation", orientation, f"one of {', '.join(EDGE_ORIENTATIONS)}")
            return ("edge", orientation)
        if feature not in ("face", "corner"):
            raise LimitError("feature", feature, f"one of {', '.join(FEATURES)}")
        return (feature, None)

    # --- lookups --------------------------------------------------------------------------------------------

    def frames(self, feature: str, orientation: str | None = None) -> tuple[Pattern, ...]:
        """The expansion frames of a feature's base pattern, frame 0 first."""
        return self._frames[self._key(feature, orientation)]

    def frame_count(self, feature: str, orientation: str | None = None) -> int:
        return len(self._frames[self._key(feature, orientation)])

    def static(self, feature: str, orientation: str | None = None) -> Pattern:
        """The feature's whole base pattern (every frame's electrodes): what sustained contact shows."""
        return self._static_cache[self._key(feature, orientation)]

    def contact(self, feature: str, orientation: str | None, level: int) -> Pattern:
        """Eq. 4: the feature's whole static pattern shifted to θ level ``level`` (0–3), shape intact."""
        key = self._key(feature, orientation)
        ck = (key[0], key[1], level)
        hit = self._contact_cache.get(ck)
        if hit is not None:
            return hit
        if not 0 <= level < len(THETA_LEVELS):
            raise LimitError("theta level", level, "0 (steep left) to 3 (steep right)")
        base = self._static[key]
        src = self._shift_index[level]
        shifted = np.where(src >= 0, base[np.maximum(src, 0)], False)
        pat = self._pat(shifted)
        self._contact_cache[ck] = pat
        return pat

    def mask(self, direction: int, k: int, phase: int) -> np.ndarray:
        """The texture mask (eq. 7 interpretation): stripes across ``direction``, ``k`` spacings on and
        ``(period_factor - 1)·k`` off, read ``phase`` spacings further along ``direction`` — so a growing
        phase moves the stripes against ``direction``.  ``k = 0`` is the all-ones mask."""
        n = self.array.count
        if k == 0:
            return np.ones(n, dtype=bool)
        if not 0 <= direction < len(DIRECTIONS):
            raise LimitError("direction", direction, "0 to 7")
        if k < 0:
            raise LimitError("k_texture", k, "0, 1 or 2 (≥ 0)")
        s = self._mask_coord[direction] + phase
        stripe = np.floor(s / k + _TOL).astype(int)
        mask: np.ndarray = (stripe % self.params.mask_period_factor) == 0
        return mask

    def mask_period(self, k: int) -> int:
        """Spatial period of the texture mask in spacings (0 for a smooth surface)."""
        return self.params.mask_period_factor * k

    def sliding(self, feature: str, orientation: str | None, direction: int, k: int, phase: int) -> Pattern:
        """Eq. 5–7 interpretation: the static pattern multiplied by the texture mask."""
        key = self._key(feature, orientation)
        if k == 0:
            return self._static_cache[key]
        phase %= self.mask_period(k)
        sk = (key[0], key[1], direction, k, phase)
        hit = self._slide_cache.get(sk)
        if hit is not None:
            return hit
        pat = self._pat(self._static[key] & self.mask(direction, k, phase))
        self._slide_cache[sk] = pat
        return pat

    def describe(self) -> dict[str, object]:
        """Electrode counts per frame and pattern (for reports and tests)."""
        out: dict[str, object] = {}
        for (f, o), frames in self._frames.items():
            name = f if o is None else f"{f}-{o}"
            out[name] = {
                "frames": [sum(1 for v in fr if v) for fr in frames],
                "static": int(self._static[(f, o)].sum()),
            }
        out["contact_centres_mm"] = list(self.contact_centres_mm)
        return out


def _snap(value_mm: float, pitch_mm: float) -> float:
    """Round to whole electrode spacings (half away from zero) so shifted patterns land on electrodes."""
    return math.floor(value_mm / pitch_mm + 0.5 + _TOL) * pitch_mm


def active(pattern: Sequence[int]) -> int:
    """Number of active electrodes in a pattern."""
    return sum(1 for v in pattern if v)


def render_ascii(array: ElectrodeArray, pattern: Sequence[int]) -> str:
    """A text picture of a pattern on a grid-like array (rows from the fingertip), for messages and
    docs: ``#`` on, ``.`` off, blank where the grid has no electrode."""
    pos = array.positions_mm
    pitch = array.pitch_mm
    xs = np.rint((pos[:, 0] - pos[:, 0].min()) / pitch).astype(int)
    ys = np.rint((pos[:, 1].max() - pos[:, 1]) / pitch).astype(int)
    grid = [[" "] * (int(xs.max()) + 1) for _ in range(int(ys.max()) + 1)]
    for i, v in enumerate(pattern):
        grid[ys[i]][xs[i]] = "#" if v else "."
    return "\n".join("".join(row).rstrip() for row in grid)
