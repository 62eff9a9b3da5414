"""Which calibration region each electrode sits in, from where it sits on the pad.

A participant's profile holds one amplitude per region of a 3 × 3 split of the finger pad (row 0 at the
fingertip, left to right; region 4 is the centre).  Which amplitude limits an electrode therefore depends
on its **position**, never on its place in a list: an array file that lists the same electrodes in another
order must give each of them the same limit.  The split is the bounding box of the electrode centres cut
in thirds along x and y, as the renderer's array does.

An electrode whose centre lies on a third-line (within :data:`BORDER_TOLERANCE_MM`) belongs to every region
that meets there, and an array whose centres all share one x (or one y) spans no width (or height) to cut,
so each of its electrodes belongs to every column (or row).  Such an electrode has one limit only when all
of its candidate regions have the same amplitude; otherwise the guard refuses it, naming the electrode,
its position and the regions (:meth:`RegionMap.resolve`).  Nothing here falls back to a map by index.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from tactdeform_hw.errors import SafetyError

REGION_ROWS = 3
REGION_COLS = 3
#: A centre this close to a third-line (mm) sits on the border between two regions.
BORDER_TOLERANCE_MM = 1e-3

#: The TactDeform finger-pad array: 6 × 6 grid without its corners, 2 mm pitch, rows from the fingertip.
TACTDEFORM_ROWS = 6
TACTDEFORM_COLS = 6
TACTDEFORM_PITCH_MM = 2.0


def _tactdeform_positions() -> tuple[tuple[float, float], ...]:
    corners = {
        (0, 0),
        (0, TACTDEFORM_COLS - 1),
        (TACTDEFORM_ROWS - 1, 0),
        (TACTDEFORM_ROWS - 1, TACTDEFORM_COLS - 1),
    }
    out: list[tuple[float, float]] = []
    for r in range(TACTDEFORM_ROWS):
        y = ((TACTDEFORM_ROWS - 1) / 2.0 - r) * TACTDEFORM_PITCH_MM
        for c in range(TACTDEFORM_COLS):
            if (r, c) not in corners:
                out.append(((c - (TACTDEFORM_COLS - 1) / 2.0) * TACTDEFORM_PITCH_MM, y))
    return tuple(out)


#: Electrode centres (x, y mm) of the 32-electrode TactDeform array in its application order — the same
#: geometry as :meth:`tactdeform_hw.render.array.ElectrodeArray.tactdeform`.
TACTDEFORM_POSITIONS_MM: tuple[tuple[float, float], ...] = _tactdeform_positions()


def _bands(value: float, lo: float, hi: float, count: int) -> tuple[int, ...]:
    """The band(s) of ``count`` equal bands of [lo, hi] that hold ``value`` (two on a border, all when the
    interval is empty)."""
    span = hi - lo
    if span <= BORDER_TOLERANCE_MM:
        return tuple(range(count))
    hits: list[int] = []
    for k in range(count):
        a = lo + span * k / count
        b = lo + span * (k + 1) / count
        if a - BORDER_TOLERANCE_MM <= value <= b + BORDER_TOLERANCE_MM:
            hits.append(k)
    return tuple(hits)


@dataclass(frozen=True)
class RegionMap:
    """The region(s) of each electrode, application order, from the electrode centres.

    ``candidates[i]`` is every region electrode ``i``'s centre lies in: one for an electrode inside a
    region, several for one on a border.  ``source`` names where the positions came from (an array file,
    the TactDeform array), for error messages.
    """

    candidates: tuple[tuple[int, ...], ...]
    positions_mm: tuple[tuple[float, float], ...]
    source: str

    def __post_init__(self) -> None:
        if len(self.candidates) != len(self.positions_mm):
            raise ValueError("one candidate set per electrode position")

    @property
    def electrodes(self) -> int:
        return len(self.candidates)

    @property
    def ambiguous(self) -> tuple[int, ...]:
        """Electrodes on a border between regions."""
        return tuple(i for i, c in enumerate(self.candidates) if len(c) != 1)

    def describe(self, electrode: int) -> str:
        x, y = self.positions_mm[electrode]
        return f"electrode {electrode} at ({x:g}, {y:g}) mm of {self.source}"

    def resolve(self, regions_ua: Sequence[int] | None) -> tuple[int, ...]:
        """One region per electrode.  An electrode on a border takes the candidate with the lowest
        amplitude only when its candidates' amplitudes are all equal (the limit is then the same
        whichever region it is counted in); otherwise :class:`~tactdeform_hw.errors.SafetyError` names it.
        Without amplitudes (no profile) a border electrode is counted in its first candidate: no regional
        limit depends on it."""
        out: list[int] = []
        for i, cand in enumerate(self.candidates):
            if len(cand) == 1 or regions_ua is None:
                out.append(cand[0])
                continue
            limits = {regions_ua[r] for r in cand}
            if len(limits) > 1:
                shown = ", ".join(f"region {r} {regions_ua[r]} µA" for r in cand)
                raise SafetyError(
                    f"{self.describe(i)}: its region cannot be determined — it lies on the border of "
                    f"{len(cand)} regions with different limits ({shown}) (a centre on a third-line of the "
                    "pad, or an array with no width or height to split); move it off the border in the array "
                    "file or calibrate those regions alike; nothing was sent"
                )
            out.append(cand[0])
        return tuple(out)


def region_map_from_positions(
    positions_mm: Sequence[Sequence[float]], source: str = "the array"
) -> RegionMap:
    """The 3 × 3 regions of electrode centres (x to the right, y toward the fingertip, mm).

    A centre that is not two finite numbers is refused with :class:`~tactdeform_hw.errors.SafetyError`
    naming the electrode: without a position there is no region, and no limit."""
    pts: list[tuple[float, float]] = []
    for i, p in enumerate(positions_mm):
        try:
            x, y = (float(v) for v in p)
        except (TypeError, ValueError) as exc:
            raise SafetyError(
                f"electrode {i} of {source} has no position ({p!r}); its region, and so its limit, cannot be "
                "determined; nothing was sent"
            ) from exc
        if not (math.isfinite(x) and math.isfinite(y)):
            raise SafetyError(
                f"electrode {i} of {source} has no finite position ({x!r}, {y!r}); its region, and so its "
                "limit, cannot be determined; nothing was sent"
            )
        pts.append((x, y))
    if not pts:
        raise SafetyError(f"{source} has no electrode positions; nothing was sent")
    xs = [x for x, _ in pts]
    ys = [y for _, y in pts]
    x0, x1, y0, y1 = min(xs), max(xs), min(ys), max(ys)
    cands: list[tuple[int, ...]] = []
    for x, y in pts:
        cols = _bands(x, x0, x1, REGION_COLS)
        rows = tuple(sorted(REGION_ROWS - 1 - b for b in _bands(y, y0, y1, REGION_ROWS)))  # row 0: fingertip
        cands.append(tuple(r * REGION_COLS + c for r in rows for c in cols))
    return RegionMap(tuple(cands), tuple(pts), source)


def tactdeform_region_map() -> RegionMap:
    """The regions of the 32-electrode TactDeform array, from its known positions."""
    return region_map_from_positions(TACTDEFORM_POSITIONS_MM, "the TactDeform 32-electrode array")
