"""The quick start in docs/quickstart.md runs as written, and importing the package does only what its
docstring says."""

from __future__ import annotations

import contextlib
import io
import re
import subprocess
import sys
from pathlib import Path

import tactdeform_hw

QUICKSTART = Path(__file__).resolve().parents[1] / "docs" / "quickstart.md"


def _code() -> str:
    blocks = re.findall(r"```python\n(.*?)```", QUICKSTART.read_text(encoding="utf-8"), re.S)
    assert len(blocks) == 1, "the quick start has one Python block"
    return str(blocks[0])


def test_the_quick_start_runs_as_written() -> None:
    code = _code()
    assert len(code.strip().splitlines()) <= 10
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(code, str(QUICKSTART), "exec"), {"__name__": "quickstart"})
    assert out.getvalue().strip() == "4 frames sent, 0 mismatches"
    assert "prints `4 frames sent, 0 mismatches`" in QUICKSTART.read_text(encoding="utf-8")


def test_the_readme_shows_the_same_quick_start() -> None:
    readme = (QUICKSTART.parents[1] / "README.md").read_text(encoding="utf-8")
    block = re.search(r"## In Python\n\n```python\n(.*?)```", readme, re.S)
    assert block is not None and block.group(1) == _code()
    assert "It prints `4 frames sent, 0 mismatches`" in readme


def test_the_front_door_names() -> None:
    from tactdeform_hw.device import StimConfig, open_device
    from tactdeform_hw.errors import LimitError, TactDeformError
    from tactdeform_hw.render import ElectrodeArray, Renderer, load_scene

    assert tactdeform_hw.open_device is open_device and tactdeform_hw.StimConfig is StimConfig
    assert tactdeform_hw.Renderer is Renderer and tactdeform_hw.load_scene is load_scene
    assert tactdeform_hw.ElectrodeArray is ElectrodeArray
    assert tactdeform_hw.LimitError is LimitError and tactdeform_hw.TactDeformError is TactDeformError
    for name in tactdeform_hw.__all__:
        assert getattr(tactdeform_hw, name) is not None, name


def test_importing_the_package_only_registers_the_url_handler() -> None:
    code = (
        "import sys, threading, serial\n"
        "before = set(sys.modules); handlers = list(serial.protocol_handler_packages)\n"
        "import tactdeform_hw\n"
        "new = sorted(m for m in set(sys.modules) - before if m.startswith('tactdeform_hw'))\n"
        "added = [p for p in serial.protocol_handler_packages if p not in handlers]\n"
        "print(new, added, threading.active_count(), 'numpy' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).resolve().parents[1],
    ).stdout.strip()
    assert out == "['tactdeform_hw'] ['tactdeform_hw.emulator.serving.urlhandler'] 1 False"


def test_the_approaches_share_one_protocol() -> None:
    from tactdeform_hw.render import APPROACH_FACTORIES, Approach, make_approach

    assert set(APPROACH_FACTORIES) == {"tactdeform", "ua", "cam"}
    for name in APPROACH_FACTORIES:
        a = make_approach(name)
        assert isinstance(a, Approach) and a.name == name
        out = a.update(0.0, (0.0, 0.0, 500.0), (1.0, 0.0, 0.0, 0.0), None, None)
        assert out.state == "idle" and not any(out.pattern)
