"""Regional calibration of one participant, as a state machine (the TactDeform paper's procedure).

The paper calibrates pulse amplitude only, over 9 regions (3 × 3) of the 32-electrode array:

1. **centre up** — the centre region (index 4) starts at 0 µA and rises in 10 µA steps until the
   participant reports discomfort (the *accept* key here means "that is uncomfortable");
2. **centre down** — the amplitude is lowered until the sensation is clear and pain-free, then accepted.
   It can never go back above the step below discomfort; that level becomes the participant's cap;
3. **match** — each other region in turn (fingertip row first, left to right) starts at 0 µA and is raised
   or lowered until it feels as intense as the centre, then accepted (``compare`` lets the participant feel
   the centre again at its accepted level);
4. **global** — all regions are shifted together in 10 µA steps, never above the cap or below 0, and the
   result accepted; the profile is then complete.

The machine only decides what to deliver next (a :class:`Stimulus`); the caller puts it on a device
(through the safety guard, like any other current) and feeds keys back.  ``quit`` ends without a profile.
The firmware has one pulse height per scan, so in the global phase the whole array is stimulated at the
lowest regional amplitude — what the device layer would deliver for a frame activating every region.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import Enum

from tactdeform_hw.device.participant.profiles import (
    CENTRE_REGION,
    REGION_COUNT,
    ContactMode,
    ParticipantProfile,
    Polarity,
)
from tactdeform_hw.device.safety.guard import TACTDEFORM_REGION_OF
from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.protocol.constants import CURRENT_STEP_UA, MAX_CURRENT_UA

#: Order in which the other regions are matched to the centre.
MATCH_ORDER: tuple[int, ...] = tuple(r for r in range(REGION_COUNT) if r != CENTRE_REGION)

KEYS: dict[str, str] = {
    "+": "raise",
    "u": "raise",
    "-": "lower",
    "l": "lower",
    ">": "raise10",
    "<": "lower10",
    "a": "accept",
    "!": "accept",
    "\r": "accept",
    "c": "compare",
    "q": "quit",
}


class Phase(str, Enum):
    CENTRE_UP = "centre_up"
    CENTRE_DOWN = "centre_down"
    MATCH = "match"
    GLOBAL = "global"
    DONE = "done"
    ABORTED = "aborted"


@dataclass(frozen=True)
class Stimulus:
    """What to deliver now: ``current_ua`` on the electrodes of ``regions`` (empty: nothing)."""

    regions: tuple[int, ...]
    current_ua: int
    phase: Phase
    prompt: str

    def levels(self, region_of: tuple[int, ...] = TACTDEFORM_REGION_OF) -> list[int]:
        """Application-order pattern: 1 on every electrode of the stimulated regions."""
        on = set(self.regions) if self.current_ua > 0 else set()
        return [1 if r in on else 0 for r in region_of]


@dataclass
class Calibration:
    """The procedure's state.  ``max_ua`` bounds every step (the hardware ceiling by default)."""

    participant: str
    max_ua: int = MAX_CURRENT_UA
    step_ua: int = CURRENT_STEP_UA
    phase: Phase = Phase.CENTRE_UP
    current_ua: int = 0
    discomfort_ua: int | None = None
    regions_ua: list[int] = field(default_factory=lambda: [0] * REGION_COUNT)
    match_index: int = 0
    comparing: bool = False
    history: list[tuple[str, str, int]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if (
            isinstance(self.max_ua, bool)
            or not isinstance(self.max_ua, int)
            or not 0 < self.max_ua <= MAX_CURRENT_UA
        ):
            raise LimitError("max_ua", self.max_ua, f"1 to {MAX_CURRENT_UA} µA")
        if self.max_ua % self.step_ua:
            raise LimitError("max_ua", self.max_ua, f"a multiple of {self.step_ua} µA")

    # --- limits --------------------------------------------------------------------------------------------

    @property
    def cap_ua(self) -> int:
        """The highest level allowed now: below discomfort once it was reported, else the ceiling."""
        if self.discomfort_ua is None:
            return self.max_ua
        return max(0, self.discomfort_ua - self.step_ua)

    @property
    def finished(self) -> bool:
        return self.phase in (Phase.DONE, Phase.ABORTED)

    @property
    def region(self) -> int | None:
        if self.phase in (Phase.CENTRE_UP, Phase.CENTRE_DOWN):
            return CENTRE_REGION
        if self.phase is Phase.MATCH:
            return MATCH_ORDER[self.match_index]
        return None

    # --- the machine ---------------------------------------------------------------------------------------

    def stimulus(self) -> Stimulus:
        p = self.phase
        if p is Phase.CENTRE_UP:
            return Stimulus(
                (CENTRE_REGION,), self.current_ua, p, "centre: raise until uncomfortable, then accept"
            )
        if p is Phase.CENTRE_DOWN:
            return Stimulus(
                (CENTRE_REGION,), self.current_ua, p, "centre: lower until clear and pain-free, then accept"
            )
        if p is Phase.MATCH:
            r = MATCH_ORDER[self.match_index]
            if self.comparing:
                return Stimulus(
                    (CENTRE_REGION,),
                    self.regions_ua[CENTRE_REGION],
                    p,
                    "centre for comparison (c to go back)",
                )
            return Stimulus(
                (r,), self.current_ua, p, f"region {r}: match the centre's intensity, then accept"
            )
        if p is Phase.GLOBAL:
            return Stimulus(
                tuple(range(REGION_COUNT)),
                min(self.regions_ua),
                p,
                "all regions: adjust together, then accept",
            )
        return Stimulus((), 0, p, "finished" if p is Phase.DONE else "aborted")

    def _step(self, value: int, delta: int, hi: int) -> int:
        return max(0, min(hi, value + delta))

    def press(self, key: str) -> Stimulus:
        """Apply one key; unknown keys are refused (a script with a typo must not run on)."""
        action = KEYS.get(key)
        if action is None:
            raise ConfigurationError(
                f"key {key!r} is not a calibration key ({', '.join(sorted(set(KEYS) - {chr(13)}))})"
            )
        if self.finished:
            raise ConfigurationError(f"calibration is {self.phase.value}; key {key!r} has nothing to act on")
        self.history.append((self.phase.value, action, self.current_ua))
        if action == "quit":
            self.phase = Phase.ABORTED
            self.current_ua = 0
            return self.stimulus()
        delta = {"raise": 1, "lower": -1, "raise10": 10, "lower10": -10}.get(action, 0) * self.step_ua
        p = self.phase
        if p is Phase.CENTRE_UP:
            if action == "accept":
                if self.current_ua == 0:
                    raise ConfigurationError("discomfort at 0 µA cannot be: raise the current first")
                self.discomfort_ua = self.current_ua
                self.phase = Phase.CENTRE_DOWN
                self.current_ua = self.cap_ua
            elif action != "compare":
                self.current_ua = self._step(self.current_ua, delta, self.max_ua)
        elif p is Phase.CENTRE_DOWN:
            if action == "accept":
                self.regions_ua[CENTRE_REGION] = self.current_ua
                self.phase = Phase.MATCH
                self.match_index = 0
                self.current_ua = 0
            elif action != "compare":
                self.current_ua = self._step(self.current_ua, delta, self.cap_ua)
        elif p is Phase.MATCH:
            if action == "compare":
                self.comparing = not self.comparing
            elif action == "accept":
                self.comparing = False
                self.regions_ua[MATCH_ORDER[self.match_index]] = self.current_ua
                self.match_index += 1
                self.current_ua = 0
                if self.match_index == len(MATCH_ORDER):
                    self.phase = Phase.GLOBAL
                    self.current_ua = min(self.regions_ua)
            else:
                self.comparing = False
                self.current_ua = self._step(self.current_ua, delta, self.cap_ua)
        elif p is Phase.GLOBAL:
            if action == "accept":
                self.phase = Phase.DONE
                self.current_ua = 0
            elif action != "compare" and delta:
                # shift every region by the same amount, within [0, cap]
                if delta > 0:
                    delta = min(delta, self.cap_ua - max(self.regions_ua))
                else:
                    delta = max(delta, -min(self.regions_ua))
                self.regions_ua = [v + delta for v in self.regions_ua]
                self.current_ua = min(self.regions_ua)
        return self.stimulus()

    def run(self, keys: Iterable[str]) -> Stimulus:
        s = self.stimulus()
        for k in keys:
            s = self.press(k)
            if self.finished:
                break
        return s

    def profile(
        self,
        *,
        pulse_width_us: int = 200,
        polarity: Polarity = "anodic",
        contact_mode: ContactMode = "orientation",
        calibrated_on: _dt.date | None = None,
        ramp_ua_per_frame: int | None = None,
        source: str = "<calibration>",
    ) -> ParticipantProfile:
        if self.phase is not Phase.DONE:
            raise ConfigurationError(f"calibration is {self.phase.value}, not done: no profile to write")
        cap = self.cap_ua
        return ParticipantProfile(
            participant=self.participant,
            cap_ua=cap,
            regions_ua=tuple(self.regions_ua),
            calibrated_on=calibrated_on or _dt.date.today(),
            pulse_width_us=pulse_width_us,
            polarity=polarity,
            contact_mode=contact_mode,
            ramp_ua_per_frame=ramp_ua_per_frame,
            notes=f"discomfort reported at {self.discomfort_ua} µA on the centre region; {len(self.history)} "
            "key(s)",
            source=source,
        )


def parse_key_script(text: str) -> list[str]:
    """Keys from a script: every non-space character is a key; ``#`` starts a comment to the line's end;
    a word ``enter`` is the accept key."""
    keys: list[str] = []
    for line in text.splitlines():
        line = line.split("#", 1)[0]
        for token in line.split():
            if token.lower() in ("enter", "accept"):
                keys.append("a")
            elif token.lower() in ("quit",):
                keys.append("q")
            else:
                keys.extend(token)
    return keys
