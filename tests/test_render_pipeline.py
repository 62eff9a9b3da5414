"""End to end: poses → scene → pattern manager or baseline → the emulated eTactileKit, and the
``render`` command."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from tactdeform_hw.device import StimConfig, open_device
from tactdeform_hw.device.driver.readback import pattern_readback
from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.render.array import ElectrodeArray
from tactdeform_hw.render.baselines import ContactAreaMapping, UniformActivation
from tactdeform_hw.render.manager import INTERACTING
from tactdeform_hw.render.pipeline import FrameRecord, Renderer

from .render_fakes import PAD_DOWN, FakeFloor, hold_poses, line_poses, pad_down


def session(rate: float = 72.0, q=PAD_DOWN) -> list:
    """Press onto the floor, rest, slide right, lift off."""
    poses = line_poses(0.0, (0, 0, 4.0), (0, 0, -3.0), 20.0, rate, q)
    poses += hold_poses(poses[-1][0], (0, 0, -3.0), 0.8, rate, q)
    poses += line_poses(poses[-1][0] + 1 / rate, (0, 0, -3.0), (40.0, 0, -3.0), 20.0, rate, q)
    poses += line_poses(poses[-1][0] + 1 / rate, (40.0, 0, -3.0), (40.0, 0, 15.0), 50.0, rate, q)
    return poses


def emulator_pattern(dev, array: ElectrodeArray) -> list[int]:
    hw = list(dev.port.emulator.state().stim_pattern[: array.hw_channels])
    return array.channel_mapping().to_application(hw)


def test_session_on_the_emulator_sends_only_changes_and_matches_the_buffer() -> None:
    array = ElectrodeArray.tactdeform()
    scene = FakeFloor(texture_level=1)
    records: list[FrameRecord] = []
    with open_device("emulator", mapping=array.channel_mapping()) as dev:
        configures = []
        real_configure = dev.configure
        dev.configure = lambda cfg: (configures.append(cfg), real_configure(cfg))[1]  # type: ignore[method-assign]
        sends = []
        real_send = dev.send_pattern
        dev.send_pattern = lambda lv: (sends.append(tuple(lv)), real_send(lv))[1]  # type: ignore[method-assign]
        r = Renderer(scene, dev, array=array, current_ua=1200, verify=True)
        summary = r.run(session(), on_record=records.append)
        assert (
            len(configures) == 1 and configures[0].electrode_count == 32 and configures[0].current_ua == 1200
        )
        assert summary.mismatches == 0
        sent = [rec.electrodes for rec in records if rec.sent]
        assert sent == sends and summary.frames_sent == len(sends)
        # Event-driven: never the same pattern twice in a row, and far fewer sends than poses.
        assert all(a != b for a, b in zip(sends, sends[1:]))
        assert len(sends) < summary.poses / 3
        assert emulator_pattern(dev, array) == list(records[-1].electrodes) == [0] * 32
        states = [rec.state for rec in records]
        assert {"idle", "approaching", "interacting"} <= set(states)
        ctx = {rec.context for rec in records}
        assert {"approaching", "contact", "sliding"} <= ctx
    assert summary.poses == len(session())


def test_a_remapped_array_reaches_the_right_hardware_channels() -> None:
    array = ElectrodeArray.tactdeform(mapping=list(range(31, -1, -1)))
    scene = FakeFloor()
    with open_device("emulator", mapping=array.channel_mapping()) as dev:
        r = Renderer(scene, dev, array=array, verify=True)
        recs: list[FrameRecord] = []
        r.run(line_poses(0.0, (0, 0, 2.0), (0, 0, -0.5), 20.0, 72.0), on_record=recs.append)
        assert r.summary.mismatches == 0
        app = list(recs[-1].electrodes)
        hw = list(dev.port.emulator.state().stim_pattern[:32])
        assert hw == app[::-1] and any(app)


def test_a_device_without_the_arrays_mapping_is_refused() -> None:
    array = ElectrodeArray.tactdeform(mapping=list(range(31, -1, -1)))
    with open_device("emulator") as dev:
        with pytest.raises(ConfigurationError, match="mapping"):
            Renderer(FakeFloor(), dev, array=array).start()


def test_the_verification_can_fail() -> None:
    def liar() -> tuple[int, ...]:
        return (1,) * 32

    with open_device("emulator") as dev:
        r = Renderer(FakeFloor(), dev, verify=liar)
        r.run(line_poses(0.0, (0, 0, 2.0), (0, 0, -2.5), 20.0, 72.0))
        assert r.summary.mismatches > 0 and r.summary.first_mismatch is not None


def test_verification_is_the_callback_it_is_given() -> None:
    seen: list[tuple[int, ...]] = []
    with open_device("emulator") as dev:
        held = pattern_readback(dev)
        assert held is not None

        def spy() -> tuple[int, ...]:
            seen.append(held())
            return seen[-1]

        s = Renderer(FakeFloor(), dev, verify=spy).run(line_poses(0.0, (0, 0, 2.0), (0, 0, -2.5), 20.0, 72.0))
    assert s.frames_sent > 0 and len(seen) == s.frames_sent and s.mismatches == 0


def test_a_port_that_cannot_show_its_pattern_gives_no_readback() -> None:
    class Board:
        port = object()  # declares nothing, as a real serial port

    assert pattern_readback(Board()) is None


def test_uniform_activation_is_all_or_nothing() -> None:
    ua = UniformActivation()
    scene = FakeFloor()
    outs = [
        ua.update(t, p, q, scene.query(p), scene)
        for t, p, q in line_poses(0.0, (0, 0, 3.0), (0, 0, -3.0), 20.0, 72.0)
    ]
    for o in outs:
        inside = o.t_s >= 0.15 - 1e-9  # z ≤ 0 from t = 0.15 s
        assert o.pattern == ((1,) * 32 if inside else (0,) * 32)
    assert sum(len(o.frames) for o in outs) == 2  # off once, on once


@pytest.mark.parametrize("roll", [0.0, 20.0, -35.0])
def test_contact_area_mapping_lights_exactly_the_electrodes_inside(roll: float) -> None:
    cam = ContactAreaMapping()
    scene = FakeFloor()
    q = pad_down(roll_deg=roll)
    for z in (-0.5, 0.0, 1.0, 3.0):
        p = np.array([0.0, 0.0, z])
        o = cam.update(z + 10.0, p, q, scene.query(p), scene)
        world = cam.electrode_positions(tuple(p), tuple(q))
        expect = tuple(1 if w[2] <= 0.0 else 0 for w in world)
        assert o.pattern == expect
        if roll == 0.0:
            assert sum(expect) == (32 if z <= 0 else 0)
        elif z == 1.0:
            assert 0 < sum(expect) < 32  # the tilted pad is partly in


def test_baselines_drop_bad_samples() -> None:
    scene = FakeFloor()
    for b in (UniformActivation(), ContactAreaMapping()):
        p = np.array([0.0, 0.0, -1.0])
        assert b.update(0.0, p, PAD_DOWN, scene.query(p), scene).pattern == (1,) * 32
        o = b.update(math.nan, p, PAD_DOWN, scene.query(p), scene)
        assert o.dropped == "time" and o.pattern == (1,) * 32 and not o.frames
        o = b.update(1.0, p, (0.0, 0.0, 0.0, 0.0), scene.query(p), scene)
        assert o.dropped == "orientation-norm"


@pytest.mark.parametrize("approach", ["ua", "cam"])
def test_baselines_run_on_the_emulator(approach: str) -> None:
    with open_device("emulator") as dev:
        r = Renderer(FakeFloor(), dev, approach=approach, verify=True)
        recs: list[FrameRecord] = []
        r.run(session(q=pad_down(roll_deg=10.0)), on_record=recs.append)
        assert r.summary.mismatches == 0
        assert any(rec.state == INTERACTING for rec in recs)
        assert {rec.approach for rec in recs} == {approach}


def test_approach_per_object() -> None:
    class TwoFloors(FakeFloor):
        def query(self, point_mm):  # type: ignore[no-untyped-def]
            q = super().query(point_mm)
            name = "left" if point_mm[0] < 0 else "right"
            return type(q)(
                name,
                q.signed_distance_mm,
                q.closest_point_mm,
                q.normal,
                q.feature,
                q.edge_direction,
                q.texture_level,
            )

    r = Renderer(TwoFloors(), None, approach={"left": "ua", "right": "tactdeform"})
    left = [
        rec for pose in line_poses(0.0, (-20, 0, 2.0), (-20, 0, -1.0), 20.0, 72.0) for rec in r.step(pose)
    ]
    assert left[-1].approach == "ua" and left[-1].electrodes == (1,) * 32
    right = [rec for pose in line_poses(1.0, (20, 0, 2.0), (20, 0, -1.0), 20.0, 72.0) for rec in r.step(pose)]
    assert right[-1].approach == "tactdeform" and right[-1].electrodes != (1,) * 32
    with pytest.raises(LimitError, match="approach"):
        Renderer(FakeFloor(), None, approach={"left": "magic"})


def test_current_hook_sets_the_current_before_a_frame() -> None:
    seen: list[FrameRecord] = []

    def hook(rec: FrameRecord) -> int | None:
        seen.append(rec)
        return 800 if rec.state == INTERACTING else None

    with open_device("emulator") as dev:
        r = Renderer(FakeFloor(), dev, current_ua=500, current_hook=hook, verify=True)
        r.run(session())
        assert seen and dev.current_ua == 800
        assert r.summary.mismatches == 0


def test_contact_mode_is_selectable_per_participant() -> None:
    q = pad_down(roll_deg=60.0)
    poses = line_poses(0.0, (0, 0, 2.0), (0, 0, -2.0), 20.0, 72.0, q) + hold_poses(
        0.2, (0, 0, -2.0), 1.0, 72.0, q
    )
    orient = Renderer(FakeFloor(), None, contact_mode="orientation")
    uniform = Renderer(FakeFloor(), None, contact_mode="uniform")
    a = [rec for p in poses for rec in orient.step(p)][-1]
    b = [rec for p in poses for rec in uniform.step(p)][-1]
    pos = ElectrodeArray.tactdeform().positions_mm
    assert a.state == b.state == INTERACTING
    # Steep right: the face's whole pattern (every electrode) moved 4 mm right, P_base(x - 4, y).
    assert pos[np.array(a.electrodes, dtype=bool), 0].min() == pytest.approx(-1.0)
    pad = ElectrodeArray.tactdeform()
    src = [pad.index_at(float(x) - 4.0, float(y)) for x, y in pos]
    assert a.electrodes == tuple(1 if i >= 0 else 0 for i in src)
    assert b.electrodes == (1,) * 32


def test_bad_poses_give_unsent_records_with_null_time() -> None:
    r = Renderer(FakeFloor(), None)
    r.step((0.0, np.array([0, 0, -1.0]), PAD_DOWN))
    recs = r.step((math.nan, np.array([0, 0, -1.0]), PAD_DOWN))
    # 50 ms after the last valid sample: still within the lost-tracking time (80 ms)
    recs += r.step((0.05, np.array([math.nan, 0, -1.0]), PAD_DOWN))
    assert [rec.dropped for rec in recs] == ["time", "position"]
    assert all(not rec.sent for rec in recs)
    line = recs[0].to_json()
    assert line["t"] is None and json.dumps(line)
    assert r.summary.dropped == {"time": 1, "position": 1}


def test_frame_record_json_has_the_contract_fields() -> None:
    rec = FrameRecord(1.5, "interacting", "edge", 2, (1, 0) * 16, True)
    line = rec.to_json()
    assert list(line) == ["t", "state", "feature", "texture", "electrodes", "sent"]
    assert line["texture"] == "rougher" and len(line["electrodes"]) == 32


def test_stim_config_can_be_given_whole() -> None:
    with open_device("emulator") as dev:
        r = Renderer(
            FakeFloor(), dev, stim_config=StimConfig(electrode_count=32, current_ua=300, rate_hz=100)
        )
        r.start()
        assert dev.config is not None and dev.config.rate_hz == 100 and dev.current_ua == 300


# --- the command --------------------------------------------------------------------------------------------


def _cli(argv: list[str]) -> int:
    from tactdeform_hw.cli import main

    return main(argv)


@pytest.mark.parametrize(
    ("scene", "trajectory", "approach"),
    [
        ("cube", "approach-face", "tactdeform"),
        ("cube", "approach-edge-d1", "tactdeform"),
        ("cube", "approach-corner", "cam"),
        ("sphere", "slide-rough", "tactdeform"),
        ("cube", "contact-steep-left", "tactdeform"),
        ("sphere", "explore", "ua"),
    ],
)
def test_render_command_writes_frames_and_checks_the_emulator(
    tmp_path: Path, scene: str, trajectory: str, approach: str
) -> None:
    out = tmp_path / "frames.jsonl"
    code = _cli(
        [
            "render",
            "--scene",
            scene,
            "--trajectory",
            trajectory,
            "--approach",
            approach,
            "--device",
            "emulator",
            "--frames",
            str(out),
        ]
    )
    assert code == 0
    lines = [json.loads(s) for s in out.read_text().splitlines()]
    assert lines
    for line in lines:
        assert set(line) >= {"t", "state", "feature", "texture", "electrodes", "sent"}
        assert line["state"] in ("idle", "approaching", "interacting")
        assert len(line["electrodes"]) == 32 and set(line["electrodes"]) <= {0, 1}
    assert any(line["sent"] for line in lines)
    assert any(line["state"] != "idle" for line in lines)
    ts = [line["t"] for line in lines]
    assert ts == sorted(ts)


@pytest.mark.parametrize(("device", "verified"), [("emulator", True), ("etactile://render-rt", False)])
def test_render_reports_whether_it_verified(
    capsys: pytest.CaptureFixture[str], device: str, verified: bool
) -> None:
    """On an instant port (offline) every frame is read back; a real-time port is driven as a board."""
    args = ["render", "--scene", "cube", "--trajectory", "approach-face", "--device", device, "--json"]
    assert _cli(args) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["verified"] is verified and report["mismatches"] == 0 and report["frames_sent"] > 0


def test_the_study_trajectories_select_what_they_were_built_for() -> None:
    """On the real scene and trajectory modules: each Task 1 edge approach shows its line, each Task 2
    contact its θ level, each Task 3 stroke slides rightward (E) and shifts at v / (d k)."""
    from tactdeform_hw.render.scene import load_scene
    from tactdeform_hw.render.trajectories import make_trajectory, scene_for_trajectory

    scene = load_scene("task1")
    for o in ("h", "v", "d1", "d2"):
        r = Renderer(scene, None)
        recs = [rec for p in make_trajectory(f"approach-edge-{o}", scene) for rec in r.step(p)]
        touched = [rec for rec in recs if rec.state != "idle"]
        assert {(rec.feature, rec.orientation) for rec in touched} == {("edge", o)}
    corner = Renderer(scene, None)
    recs = [rec for p in make_trajectory("approach-corner", scene) for rec in corner.step(p)]
    assert {rec.feature for rec in recs if rec.state != "idle"} == {"corner"}
    for level, name in enumerate(("steep-left", "shallow-left", "shallow-right", "steep-right")):
        r = Renderer(load_scene("task2"), None)
        for p in make_trajectory(f"contact-{name}", r.scene):
            r.step(p)
            if r.renderers["tactdeform"].context == "contact":
                assert r.renderers["tactdeform"].theta.value == level
    for k, name in ((1, "rough"), (2, "rougher")):
        sc = scene_for_trajectory(f"slide-{name}", load_scene("task3"))
        r = Renderer(sc, None)
        m = r.renderers["tactdeform"]
        poses = make_trajectory(f"slide-{name}", sc, speed_mm_s=20.0)
        sliding_t = []
        for p in poses:
            for rec in r.step(p):
                if rec.context == "sliding" and rec.sent:
                    sliding_t.append(rec.t_s)
                    assert m.direction.value == 0
        span = sliding_t[-1] - sliding_t[0]
        assert (len(sliding_t) - 1) / span == pytest.approx(20.0 / (2.0 * k), rel=0.15)


def test_the_renderer_builds_only_what_the_scene_needs() -> None:
    from tactdeform_hw.render.scene import RenderOptions, load_scene

    smooth = Renderer(load_scene("cube"), None)
    assert smooth.config.use_texture is False  # no texture machinery on an all-smooth scene
    textured = Renderer(load_scene("task3"), None)
    assert textured.config.use_texture is True
    uniform = Renderer(load_scene("cube", options=RenderOptions(contact_mode="uniform")), None)
    assert uniform.config.contact_mode == "uniform"
    from tactdeform_hw.render.tracking import frame_from_z_y, matrix_to_quat

    m = uniform.renderers["tactdeform"]
    # pad down on the top, rolled
    q = tuple(matrix_to_quat(frame_from_z_y((0.3, -1.0, 0.0), (0.0, 0.0, 1.0))))
    for pose in line_poses(0.0, (0, -97.0, 450.0), (0, -102.0, 450.0), 20.0, 72.0, q) + hold_poses(
        0.3, (0, -102.0, 450.0), 1.0, 72.0, q
    ):
        uniform.step(pose)
    assert m.state == INTERACTING and m.context == "contact"
    assert m.theta_deg is None  # θ (eq. 4) never computed in uniform mode
    assert set(uniform.renderers) == {"tactdeform"}


def test_offline_render_audit_log_runs_on_the_trajectory_clock(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """An offline run on the emulator stamps its audit log with session time, so a replay delivers what the
    session delivered instead of a run compressed to however fast the host computed."""
    import json

    from tactdeform_hw.cli import main

    audit = tmp_path / "audit.jsonl"
    assert (
        main(
            [
                "render",
                "--scene",
                "cube",
                "--trajectory",
                "approach-face",
                "--frames",
                str(tmp_path / "f.jsonl"),
                "--current-ua",
                "500",
                "--audit-log",
                str(audit),
                "--quiet",
            ]
        )
        == 0
    )
    times = [
        json.loads(line)["t"]
        for line in audit.read_text().splitlines()
        if '"type":"tx"' in line.replace(" ", "")
    ]
    poses = [json.loads(line)["t"] for line in (tmp_path / "f.jsonl").read_text().splitlines()]
    assert times and max(times) >= 0.9 * (poses[-1] - poses[0])


def test_cli_option_overrides_only_its_own_field_of_the_scene_file(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    """--contact-mode must not reset the scene file's approach (nor --approach its contact mode)."""
    import json

    from tactdeform_hw.cli import main

    scene = tmp_path / "bar.json"
    scene.write_text(
        json.dumps(
            {
                "name": "bar",
                "options": {"contact_mode": "uniform", "approach": "cam"},
                "objects": [
                    {"type": "box", "name": "bar", "size_mm": [200, 50, 50], "center_mm": [0, -200, 400]}
                ],
            }
        )
    )
    for extra, field, want in (
        (["--contact-mode", "orientation"], "approach", "cam"),
        (["--approach", "tactdeform"], "contact_mode", "uniform"),
    ):
        rc = main(
            [
                "render",
                "--scene",
                str(scene),
                "--trajectory",
                "approach-face",
                "--frames",
                str(tmp_path / "f.jsonl"),
                "--quiet",
                "--json",
                *extra,
            ]
        )
        assert rc == 0
        summary = json.loads(capsys.readouterr().out)
        assert summary[field] == want


def test_scene_cost_tool_reads_a_scene_file_relative_to_the_callers_directory(tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """The tool measures each scene in a child process that runs in the repository: a relative path must
    mean the caller's working directory, not the repository's."""
    import importlib.util
    import json

    path = Path(__file__).resolve().parents[1] / "tools" / "scene_cost.py"
    spec = importlib.util.spec_from_file_location("scene_cost", path)
    assert spec is not None and spec.loader is not None
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    (tmp_path / "two-bars.json").write_text(
        json.dumps(
            {
                "name": "two-bars",
                "objects": [
                    {"type": "box", "name": "left", "size_mm": [200, 50, 50], "center_mm": [-200, -200, 400]},
                    {"type": "box", "name": "right", "size_mm": [200, 50, 50], "center_mm": [200, -200, 400]},
                ],
            }
        )
    )
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(tool, "CONFIGS", (("tactdeform", "orientation"),))
    (row,) = tool.measure(["two-bars.json"])
    assert "error" not in row, row
    assert (
        row["scene"] == "two-bars.json" and row["objects"] == 2 and row["build_ms"] >= 0 and "peak_mib" in row
    )
    assert tool.scene_argument("cube", tmp_path) == "cube"  # built-in names go through unchanged
    assert tool.scene_argument("sub/x.toml", tmp_path) == str(tmp_path / "sub" / "x.toml")
