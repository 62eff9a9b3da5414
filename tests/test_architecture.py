"""The package's architecture rules, measured on its source (``tools/architecture_report.py`` shows where).

A firmware is a value: it is compared by name only where a user's words are parsed (``protocol/``,
``cli/``).  Objects keep their private state private, modules their private names, imports point one way
(no circle, not even one hidden by an import deferred into a function), and no class or function grows
past what one reader holds in mind.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

TOOL = Path(__file__).resolve().parent.parent / "tools" / "architecture_report.py"


def _tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("architecture_report", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def report():  # type: ignore[no-untyped-def]
    return _tool().measure()


@pytest.mark.parametrize(
    ("rule", "most"),
    [
        ("firmware_comparisons", 0),
        ("private_imports", 0),
        ("import_cycles", 0),
        ("import_circles", 0),
        ("long_classes", 0),
        ("long_functions", 0),
        ("private_reaches", 10),
    ],
)
def test_the_package_keeps_its_architecture_rule(report, rule: str, most: int) -> None:  # type: ignore[no-untyped-def]
    places = getattr(report, rule)
    assert len(places) <= most, f"{rule}: {len(places)} (at most {most}):\n" + "\n".join(map(str, places))


def test_the_measure_sees_what_it_forbids(tmp_path: Path) -> None:
    """Each rule finds a planted breach, so a clean report means clean code, not a blind tool."""
    tool = _tool()
    pkg = tmp_path / "tactdeform_hw"
    (pkg / "device").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "device" / "__init__.py").write_text("")
    (pkg / "device" / "a.py").write_text(
        "from tactdeform_hw.device.b import _hidden\n"
        "def f(fw, other):\n"
        "    if fw == 'v2':\n"
        "        return other._state\n" + "    x = 1\n" * 90
    )
    (pkg / "device" / "b.py").write_text("_hidden = 1\ndef g():\n    from tactdeform_hw.device import a\n")
    found = tool.measure(pkg)
    assert len(found.firmware_comparisons) == 1
    assert len(found.private_reaches) == 1
    assert len(found.private_imports) == 1
    assert found.import_cycles == []
    assert found.import_circles == [["tactdeform_hw.device.a", "tactdeform_hw.device.b"]]
    assert len(found.long_functions) == 1
