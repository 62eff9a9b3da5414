"""Torn patterns on a host build: scans that ran on part of an old and part of a new pattern.

A built firmware reports no defects; what it does can be seen.  Its stimulation interrupt reads the
pattern array the main loop is writing, so a scan that fires while a pattern command is being stored runs
on the channels stored so far at their new heights and the rest at their old ones (both upstream
versions: v1.2 stores each byte as it reads it, v2 copies its buffer element by element).  This module
finds such scans from two records the host build already keeps:

- the pattern array and the electrode count at each interrupt entry (the values every pulse of that scan
  used; :meth:`~.emulator.HostBuildEmulator.watch_at_isr`);
- the bytes the firmware's queue kept (those a full queue dropped taken out), read as the firmware's
  parser reads them (:func:`~tactdeform_hw.protocol.reader.read_commands`), which gives the pattern in
  force after each pattern command.

A scan is torn when its pattern (on the channels in force) is none of those patterns but is the next one
on its first ``k`` channels and the one before on the rest, ``0 < k < n``: the firmware's own order of
storing.  Only tears that show in the heights can be seen: a scan inside a pattern's storing whose
stored channels all kept their heights, or whose unstored ones already had their new heights, ran on a
whole pattern, and is not one (the Python model, which follows the parser, records those too).  A scan
in a mode that reads no height (v2's mode 2) is never torn, as in the Python model.
Snapshots that match no pattern and no such mix (a queue the main loop stopped reading, a reset in a
command) are counted in :attr:`TornPatternWatch.unexplained`, not reported as torn.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

from tactdeform_hw.protocol.firmware import FirmwareSpec
from tactdeform_hw.protocol.reader import ParserState, read_commands


@dataclass(frozen=True)
class TornScan:
    """A scan that used the first channels of the pattern command at ``command_host_offset`` at their new
    heights and the rest of its ``channels`` at the older ones; ``changed``: ``[channel, old, new]`` where
    the two patterns differ on the channels it took new.

    How many channels the firmware had stored is seen only where the two patterns differ: it is at least
    ``new_channels`` (one past the last changed channel the scan took new) and at most
    ``new_channels_up_to`` (the first changed channel it took old)."""

    t_us: float
    new_channels: int
    new_channels_up_to: int
    channels: int
    command_host_offset: int
    changed: tuple[tuple[int, int, int], ...]


class TornPatternWatch:
    """The patterns one power-up of a host build stored, and the scans that fell inside their storing.

    ``initial``: the pattern array at power-up; ``electrode_num``: the count in force then."""

    def __init__(self, firmware: FirmwareSpec, initial: Sequence[int], electrode_num: int) -> None:
        self.firmware = firmware
        self._state = ParserState(electrode_num)
        self._work = list(initial)  # the array as the parser leaves it, stored element by element
        self._offset = -1  # host offset of the pattern command being stored
        # (pattern in force after a command, host offset of that command); the first is the power-up's
        self._patterns: deque[tuple[tuple[int, ...], int]] = deque([(tuple(initial), -1)])
        self._pending: deque[tuple[float, tuple[int, ...], int, bool]] = deque()
        self.torn: list[TornScan] = []
        self.unexplained = 0

    def read(self, data: bytes, host_offset: int) -> None:
        """The firmware's queue kept ``data``, whose first byte the host wrote at ``host_offset``."""
        reading = read_commands(data, firmware=self.firmware, state=self._state, offset=host_offset)
        self._state = reading.state
        for c in reading.commands:
            if c.levels is None:
                continue
            if not c.resumed:
                self._offset = c.offset
            self._work[c.start : c.start + len(c.levels)] = c.levels
            if c.complete:
                self._patterns.append((tuple(self._work), self._offset))
        self._classify()

    def scan(self, t_us: float, pattern: Sequence[int], channels: int, reads_pattern: bool = True) -> None:
        """A scan began at ``t_us`` on ``pattern`` with ``channels`` electrodes in force (``reads_pattern``:
        the mode uses the pattern's heights).  Judged once the patterns around it are known."""
        self._pending.append((t_us, tuple(pattern[:channels]), channels, reads_pattern))
        self._classify()

    def close(self) -> None:
        """The copy powered down: what is still pending can no longer be told."""
        self.unexplained += len(self._pending)
        self._pending.clear()

    def _match(self, snapshot: tuple[int, ...], n: int) -> int | None:
        for j, (pattern, _off) in enumerate(self._patterns):
            if pattern[:n] == snapshot:
                return j
        return None

    def _tear(self, snapshot: tuple[int, ...], n: int) -> tuple[int, int] | None:
        """(index of the new pattern, k) when ``snapshot`` is one pattern's first ``k`` channels and the
        rest of the pattern before it."""
        pats = self._patterns
        for j in range(1, len(pats)):
            old, new = pats[j - 1][0][:n], pats[j][0][:n]
            k = 0
            while k < n and snapshot[k] == new[k]:
                k += 1
            if 0 < k < n and snapshot[k:] == old[k:]:
                return j, k
        return None

    def _classify(self) -> None:
        pats = self._patterns
        while self._pending:
            t_us, snap, n, reads = self._pending[0]
            j = self._match(snap, n)
            tear = None if j is not None else self._tear(snap, n)
            if j is None and tear is None:
                # a later snapshot already matches a known pattern: this one never will
                if any(self._match(s, m) is not None for _t, s, m, _r in list(self._pending)[1:]):
                    self.unexplained += 1
                    self._pending.popleft()
                    continue
                return  # its pattern command has not been read yet
            self._pending.popleft()
            if tear is not None:
                j, k = tear
                if reads:  # (a scan in a mode that uses no height ran on a whole pulse all the same)
                    old, new = pats[j - 1][0], pats[j][0]
                    changed = tuple((ch, old[ch], new[ch]) for ch in range(k) if old[ch] != new[ch])
                    self.torn.append(TornScan(t_us, changed[-1][0] + 1, k, n, pats[j][1], changed))
                j -= 1  # the pattern being stored is not in force yet
            for _ in range(j or 0):  # the scans have passed these patterns
                pats.popleft()


__all__ = ["TornPatternWatch", "TornScan"]
