"""The trial lists of the TactDeform studies, as data.

Each study is a list of :class:`Trial` values; a trial names the scene, the rendering approach, the
texture levels its surfaces carry and one or more :class:`Segment` (a synthetic trajectory planned on one
object) together with what the renderer is expected to deliver.  The runner executes them; nothing here
renders or talks to a device, so the lists can be printed, filtered and tested on their own.

==========  ==============================================================================================
``task1``   21 approaches to the 5 cm cube 45 cm ahead and 20 cm below the eye: 7 faces, 7 edges, 7
            corners.  The edges are shown in four orientations on the pad (h, v, d1, d2), three of them
            twice and one once; *which* one is shown once is drawn from the seed.  Every approach starts
            and ends 10 cm from the surface (the study withdrew beyond 8 cm between approaches).
``task2``   Stationary presses on the two 20 × 5 × 5 cm bars (left and right) at the centre of each θ
            level of eq. 4, in an orientation-specific block and a uniform block (the comparison of the
            task): 2 blocks × 2 bars × 4 levels = 16 trials; stimulation only while the pad is still.
``task3``   24 trials over the texture-level pairs of the two stacked surfaces: each unordered pair
            {a, b} of smooth / rough / rougher (6 pairs, the same level twice included) four times, twice
            with a on the upper surface and twice with a on the lower; one rightward stroke per surface.
            *Interpretation*: the paper gives "24 trials over all level pairs" without the design; this
            is the balanced design with that count.
``phase2``  Free exploration of the sphere, the cube, the Utah teapot and the Stanford bunny (the textured
            object), each under UA, CAM and TactDeform: 12 trials.  The order of the approaches is drawn
            from the seed per object (counterbalancing); the objects keep the paper's order.
==========  ==============================================================================================

``quick`` keeps one trial per condition (task 1: one per feature and edge orientation, 6; task 2: both
blocks, each level once on alternating bars, 8; task 3: each pair once, 6; phase 2: all 12 with faster
strokes) so a setup check takes seconds; the full lists are the studies as run.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from typing import Any

from ..errors import ConfigurationError
from ..render.geometry import TEXTURE_NAMES
from ..render.trajectories import APPROACH_EDGE_ANGLES_DEG, CONTACT_THETA_DEG

STUDIES: tuple[str, ...] = ("task1", "task2", "task3", "phase2")

STUDY_TITLES: dict[str, str] = {
    "task1": "Task 1: feature identification while approaching (face, edge, corner)",
    "task2": "Task 2: stationary contact, orientation-specific vs uniform",
    "task3": "Task 3: texture discrimination while sliding rightward",
    "phase2": "Phase 2: free exploration under UA, CAM and TactDeform",
}

EDGE_ORIENTATIONS: tuple[str, ...] = ("h", "v", "d1", "d2")
THETA_LEVEL_NAMES: tuple[str, ...] = ("steep-left", "shallow-left", "shallow-right", "steep-right")
PHASE2_OBJECTS: tuple[str, ...] = ("sphere", "cube", "teapot", "bunny")
PHASE2_APPROACHES: tuple[str, ...] = ("ua", "cam", "tactdeform")

#: How far into the surface a Task 1 approach goes.  On a face, 5 mm (two and a half electrode spacings)
#: shows every frame of the diverging ring (three rings on the 6 × 6 pad) once.  On an edge or a corner
#: the press stops at 3.5 mm: deeper, the pad centre's nearest surface point moves more than the 3 mm
#: feature band away from the edge (5 mm / √2 = 3.5 mm on a right-angled edge) and the renderer rightly
#: reads a face; 3.5 mm shows two expansion frames.
TASK1_PENETRATION_MM: dict[str, float] = {"face": 5.0, "edge": 3.5, "corner": 3.5}
#: Where every approach starts and ends: beyond the 8 cm the study withdrew to between approaches.
START_DISTANCE_MM = 100.0
#: The paper's worked sliding example (rough shifts at 10 Hz, rougher at 5 Hz).
TASK3_SPEED_MM_S = 20.0
QUICK_TASK3_SPEED_MM_S = 40.0
PHASE2_SPEED_MM_S = 40.0
QUICK_PHASE2_SPEED_MM_S = 80.0


@dataclass(frozen=True)
class Segment:
    """One synthetic trajectory of a trial.

    ``trajectory`` is a name of :func:`~tactdeform_hw.render.trajectories.make_trajectory`; it is planned
    on ``plan_object`` alone (so a press or a stroke lands on the object the trial means even when the
    scene holds two), or on the whole scene when None.  ``expect`` says what the renderer should show
    there (keys: ``feature``, ``orientation``, ``theta_level``, ``texture``, ``object``).
    """

    trajectory: str
    plan_object: str | None = None
    speed_mm_s: float | None = None
    penetration_mm: float = 3.0
    expect: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "trajectory": self.trajectory,
            "object": self.plan_object,
            "speed_mm_s": self.speed_mm_s,
            "penetration_mm": self.penetration_mm,
            "expect": dict(self.expect),
        }


@dataclass(frozen=True)
class Trial:
    """One trial: a scene under one approach and contact mode, with per-object texture levels."""

    index: int
    id: str
    study: str
    scene: str
    segments: tuple[Segment, ...]
    approach: str = "tactdeform"
    contact_mode: str = "orientation"
    textures: tuple[tuple[str, int], ...] = ()
    block: str = ""
    condition: str = ""
    description: str = ""

    def to_json(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "id": self.id,
            "study": self.study,
            "scene": self.scene,
            "approach": self.approach,
            "contact_mode": self.contact_mode,
            "textures": {name: TEXTURE_NAMES[level] for name, level in self.textures},
            "block": self.block,
            "condition": self.condition,
            "description": self.description,
            "segments": [s.to_json() for s in self.segments],
        }


@dataclass(frozen=True)
class Study:
    """A study's trials and the renderer settings it ran with (:class:`ManagerConfig` field overrides)."""

    name: str
    title: str
    trials: tuple[Trial, ...]
    manager: dict[str, Any] = field(default_factory=dict)
    quick: bool = False
    seed: int = 0
    notes: tuple[str, ...] = ()
    selection: str | None = None  # the --trials list when only some trials are run

    def to_json(self) -> dict[str, Any]:
        manager = {k: (sorted(v) if isinstance(v, frozenset) else v) for k, v in self.manager.items()}
        return {
            "name": self.name,
            "title": self.title,
            "quick": self.quick,
            "seed": self.seed,
            "selection": self.selection,
            "manager": manager,
            "trials": len(self.trials),
        }


def _number(trials: list[Trial], study: str) -> tuple[Trial, ...]:
    out = []
    for i, t in enumerate(trials, start=1):
        out.append(
            Trial(
                i,
                f"{study}-{i:02d}-{t.condition}",
                t.study,
                t.scene,
                t.segments,
                t.approach,
                t.contact_mode,
                t.textures,
                t.block,
                t.condition,
                t.description,
            )
        )
    return tuple(out)


# --- task 1 -------------------------------------------------------------------------------------------------


def task1(seed: int = 0, quick: bool = False, contact_mode: str = "orientation") -> Study:
    rng = random.Random(f"task1:{seed}")
    conditions: list[tuple[str, str | None]] = []
    if quick:
        conditions = [("face", None), ("corner", None)] + [("edge", o) for o in EDGE_ORIENTATIONS]
    else:
        once = rng.choice(EDGE_ORIENTATIONS)
        edges = [o for o in EDGE_ORIENTATIONS for _ in range(1 if o == once else 2)]
        conditions = [("face", None)] * 7 + [("corner", None)] * 7 + [("edge", o) for o in edges]
    rng.shuffle(conditions)
    trials = []
    for feature, orientation in conditions:
        name = (
            "approach-face"
            if feature == "face"
            else "approach-corner"
            if feature == "corner"
            else f"approach-edge-{orientation}"
        )
        cond = feature if orientation is None else f"edge-{orientation}"
        expect: dict[str, Any] = {"feature": feature, "orientation": orientation, "object": "cube"}
        if orientation is not None:
            expect["edge_angle_deg"] = APPROACH_EDGE_ANGLES_DEG[orientation]
        seg = Segment(name, None, None, TASK1_PENETRATION_MM[feature], expect)
        desc = f"approach {'an' if feature == 'edge' else 'a'} {feature}" + (
            f" shown {orientation} on the pad" if orientation else ""
        )
        trials.append(
            Trial(
                0, "", "task1", "task1", (seg,), contact_mode=contact_mode, condition=cond, description=desc
            )
        )
    counts = {o: sum(1 for f, oo in conditions if oo == o) for o in EDGE_ORIENTATIONS}
    notes = [f"edge orientations shown: {', '.join(f'{o}×{n}' for o, n in counts.items())} (seed {seed})"]
    return Study("task1", STUDY_TITLES["task1"], _number(trials, "task1"), {}, quick, seed, tuple(notes))


# --- task 2 -------------------------------------------------------------------------------------------------


def task2(seed: int = 0, quick: bool = False, contact_mode: str = "orientation") -> Study:
    # Both contact modes are the task's comparison: ``contact_mode`` (a participant's preference) is not used.
    rng = random.Random(f"task2:{seed}")
    blocks = ["orientation", "uniform"]
    rng.shuffle(blocks)
    trials: list[Trial] = []
    for mode in blocks:
        cells: list[tuple[str, int]] = []
        for level in range(len(THETA_LEVEL_NAMES)):
            if quick:
                cells.append((("left", "right")[level % 2], level))
            else:
                cells += [("left", level), ("right", level)]
        rng.shuffle(cells)
        for obj, level in cells:
            name = THETA_LEVEL_NAMES[level]
            expect = {
                "feature": "face",
                "object": obj,
                "theta_level": level,
                "theta_name": name,
                "theta_deg": CONTACT_THETA_DEG[name],
                "contact_mode": mode,
            }
            seg = Segment(f"contact-{name}", obj, None, 3.0, expect)
            trials.append(
                Trial(
                    0,
                    "",
                    "task2",
                    "task2",
                    (seg,),
                    contact_mode=mode,
                    block=mode,
                    condition=f"{mode}-{obj}-{name}",
                    description=(
                        f"press the {obj} bar with θ {CONTACT_THETA_DEG[name]:+.0f}° ({name}), {mode} contact"
                    ),
                )
            )
    notes = [
        f"block order: {' then '.join(blocks)} (seed {seed})",
        "stimulation only while the pad is stationary",
    ]
    return Study(
        "task2",
        STUDY_TITLES["task2"],
        _number(trials, "task2"),
        {"render_sliding": False},
        quick,
        seed,
        tuple(notes),
    )


# --- task 3 -------------------------------------------------------------------------------------------------

TASK3_SURFACES: tuple[str, str] = ("upper", "lower")


def task3(seed: int = 0, quick: bool = False, contact_mode: str = "orientation") -> Study:
    # Nothing is rendered in stationary contact in Task 3, so the contact mode does not matter.
    rng = random.Random(f"task3:{seed}")
    pairs = [(a, b) for a in range(3) for b in range(a, 3)]
    cells: list[tuple[int, int]] = []
    for a, b in pairs:
        if quick:
            cells.append((a, b) if rng.random() < 0.5 else (b, a))
        else:
            cells += [(a, b), (a, b), (b, a), (b, a)]
    rng.shuffle(cells)
    speed = QUICK_TASK3_SPEED_MM_S if quick else TASK3_SPEED_MM_S
    trials = []
    for upper, lower in cells:
        segs = tuple(
            Segment(
                f"slide-{TEXTURE_NAMES[level]}",
                surface,
                speed,
                3.0,
                {"feature": "face", "object": surface, "texture": level, "direction": "E"},
            )
            for surface, level in zip(TASK3_SURFACES, (upper, lower))
        )
        cond = f"{TEXTURE_NAMES[upper]}-{TEXTURE_NAMES[lower]}"
        trials.append(
            Trial(
                0,
                "",
                "task3",
                "task3",
                segs,
                textures=(("upper", upper), ("lower", lower)),
                condition=cond,
                description=(
                    f"stroke the upper ({TEXTURE_NAMES[upper]}) then the lower ({TEXTURE_NAMES[lower]}) "
                    "surface rightward"
                ),
            )
        )
    notes = [
        f"strokes at {speed:g} mm/s, rightward; texture patterns rendered only while sliding rightward, "
        "nothing in stationary contact",
        "the touchdown before each stroke still shows the approach expansion (frames_sent_by_context: "
        "approaching): the renderer's settings switch off stationary contact and other sliding directions, "
        "not the approach",
    ]
    manager = {"slide_directions": frozenset({"E"}), "render_contact": False}
    return Study("task3", STUDY_TITLES["task3"], _number(trials, "task3"), manager, quick, seed, tuple(notes))


# --- phase 2 ------------------------------------------------------------------------------------------------


def phase2(seed: int = 0, quick: bool = False, contact_mode: str = "orientation") -> Study:
    rng = random.Random(f"phase2:{seed}")
    speed = QUICK_PHASE2_SPEED_MM_S if quick else PHASE2_SPEED_MM_S
    trials = []
    for obj in PHASE2_OBJECTS:
        order = list(PHASE2_APPROACHES)
        rng.shuffle(order)
        for approach in order:
            expect: dict[str, Any] = {"object": obj, "approach": approach}
            if approach == "tactdeform":
                expect["features"] = ["face"] if obj == "sphere" else ["face", "edge", "corner"]
                expect["texture"] = 1 if obj == "bunny" else 0
            seg = Segment("explore", None, speed, 3.0, expect)
            trials.append(
                Trial(
                    0,
                    "",
                    "phase2",
                    obj,
                    (seg,),
                    approach=approach,
                    contact_mode=contact_mode,
                    block=obj,
                    condition=f"{obj}-{approach}",
                    description=f"explore the {obj} under "
                    f"{approach.upper() if approach != 'tactdeform' else 'TactDeform'}",
                )
            )
    notes = [f"exploration strokes at {speed:g} mm/s", "the bunny is the textured object (rough)"]
    return Study("phase2", STUDY_TITLES["phase2"], _number(trials, "phase2"), {}, quick, seed, tuple(notes))


_BUILDERS = {"task1": task1, "task2": task2, "task3": task3, "phase2": phase2}


def build_study(name: str, seed: int = 0, quick: bool = False, contact_mode: str = "orientation") -> Study:
    """The trial list of study ``name`` (``task1``, ``task2``, ``task3``, ``phase2``).  ``contact_mode``
    (a participant's preference, Task 2's finding) applies where the study does not fix it: Task 1 and
    Phase 2."""
    builder = _BUILDERS.get(name)
    if builder is None:
        raise ConfigurationError(f"unknown study {name!r}; choose from {', '.join(STUDIES)}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigurationError(f"seed={seed!r} must be an integer")
    if contact_mode not in ("orientation", "uniform"):
        raise ConfigurationError(f"contact_mode={contact_mode!r} must be 'orientation' or 'uniform'")
    return builder(seed, quick, contact_mode)


def select_trials(study: Study, spec: str | None) -> Study:
    """The study restricted to the trials named by ``spec``: 1-based numbers and ranges (``"1-3,8"``) or
    conditions (``"face,edge-h"``; every trial of that condition)."""
    if spec is None or not spec.strip():
        return study
    chosen: set[int] = set()
    n = len(study.trials)
    for part in spec.split(","):
        item = part.strip()
        if not item:
            continue
        if item.replace("-", "").isdigit() and not item.startswith("-"):
            lo_text, _, hi_text = item.partition("-")
            lo = int(lo_text)
            hi = int(hi_text) if hi_text else lo
            if not (1 <= lo <= hi <= n):
                raise ConfigurationError(f"--trials {item!r}: trials are numbered 1 to {n}")
            chosen.update(range(lo, hi + 1))
            continue
        hits = {t.index for t in study.trials if t.condition == item or t.id == item}
        if not hits:
            known = ", ".join(sorted({t.condition for t in study.trials}))
            raise ConfigurationError(
                f"--trials {item!r} names no trial of {study.name} (conditions: {known})"
            )
        chosen.update(hits)
    trials = tuple(t for t in study.trials if t.index in chosen)
    return Study(
        study.name, study.title, trials, study.manager, study.quick, study.seed, study.notes, spec.strip()
    )
