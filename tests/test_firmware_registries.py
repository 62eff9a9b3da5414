"""Adding a firmware is a checklist, and this test is that checklist: every version the protocol knows has
an entry in every layer's registry, the identification tells it from every other, and the architecture
guide's steps name each registry."""

from __future__ import annotations

import ast
import itertools
import re
from dataclasses import replace
from pathlib import Path

import pytest

from tactdeform_hw.device.driver.dialects import DIALECTS
from tactdeform_hw.device.driver.firmware_probe import classify, signature_reply
from tactdeform_hw.device.safety.readings import READINGS
from tactdeform_hw.emulator.firmware.models import MODELS
from tactdeform_hw.protocol.commands import commands_for
from tactdeform_hw.protocol.firmware import FIRMWARES, V1_2, FirmwareSpec

#: Every registry keyed by a firmware spec, by the name the architecture guide uses for it.
REGISTRIES = {"MODELS": MODELS, "DIALECTS": DIALECTS, "READINGS": READINGS}
GUIDE = Path(__file__).resolve().parent.parent / "docs" / "architecture.md"


def missing_registrations(firmware: FirmwareSpec) -> list[str]:
    """The registries that lack ``firmware``; the protocol's formats are built from its table."""
    missing = [name for name, registry in REGISTRIES.items() if firmware not in registry]
    if firmware not in FIRMWARES.values():
        missing.append("FIRMWARES")
    return missing


@pytest.mark.parametrize("firmware", list(FIRMWARES.values()), ids=list(FIRMWARES))
def test_every_known_firmware_is_in_every_registry(firmware: FirmwareSpec) -> None:
    assert missing_registrations(firmware) == []
    assert commands_for(firmware).firmware is firmware


def test_a_version_added_to_the_table_alone_is_caught() -> None:
    """A version written into the protocol's table but registered nowhere else fails the checklist."""
    new = replace(V1_2, name="v1.3")
    assert missing_registrations(new) == ["MODELS", "DIALECTS", "READINGS", "FIRMWARES"]


@pytest.mark.parametrize("name", list(REGISTRIES))
def test_no_registry_holds_a_version_the_protocol_does_not_know(name: str) -> None:
    assert set(REGISTRIES[name]) <= set(FIRMWARES.values())


def test_the_identification_tells_every_version_from_every_other() -> None:
    """For every HV513 count and electrode count in force, each version's answer to the signature is its
    own: classify names that version and no other answer collides with it."""
    for firmware, count, hv513 in itertools.product(FIRMWARES.values(), (0, 1, 32, 255), range(256)):
        answer = signature_reply(firmware, hv513, count)
        assert classify(answer, count=count) is firmware, (firmware.name, hv513, count, answer.hex())
    for a, b in itertools.combinations(FIRMWARES.values(), 2):
        for hv513, count in itertools.product(range(256), (0, 1, 32, 255)):
            assert signature_reply(a, hv513, count) != signature_reply(b, hv513, count)


def test_the_guides_checklist_names_every_registry() -> None:
    text = GUIDE.read_text(encoding="utf-8")
    section = re.search(r"### Adding a firmware version\n(.*?)\n## ", text, re.S)
    assert section is not None, "docs/architecture.md has no 'Adding a firmware version' section"
    for name in [*REGISTRIES, "FIRMWARES", "tests/test_firmware_registries.py"]:
        assert name in section.group(1), f"the checklist does not name {name}"


# --- tests follow the same shape ---------------------------------------------------------------------------

TESTS = Path(__file__).resolve().parent
#: A file of one version's own behaviour: ``test_v2_*.py``, ``test_v1_2_*.py`` (the version's name with its
#: dots as underscores).
PER_VERSION_FILE = re.compile(r"test_(v\d+(?:_\d+)*)_\w+\.py")
#: The registries a test runs over to run once per firmware version.
REGISTRY_NAMES = {"FIRMWARES", "DIALECTS", "MODELS", "ENTRIES", "SPECS", "DEFAULT_FIRMWARES"}
#: Files that still run over a literal list of today's versions (each to be moved onto the registry; the
#: check fails when one of them no longer does, so the list only shrinks).
LITERAL_VERSION_LISTS = frozenset(
    {
        "benchmarks/test_bench_campaign.py",
        "test_cli_promises.py",
        "test_exhaustive_campaign.py",
        "test_identification_seams.py",
        "test_identification_transports.py",
        "test_safety_calibration_mapping.py",
        "test_safety_lost_tracking.py",
        "test_safety_probe_turn.py",
        "test_safety_pty_timed.py",
        "test_safety_tcp_guardian.py",
        "test_timed_bursts.py",
        "test_usb_served.py",
    }
)


def _is_version_literal(node: ast.AST | None, names: set[str]) -> bool:
    """A list, tuple or set literal of strings that are exactly ``names``."""
    if not isinstance(node, (ast.List, ast.Tuple, ast.Set)) or not node.elts:
        return False
    values = [e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)]
    return len(values) == len(node.elts) and set(values) == names


def _iterated(tree: ast.Module) -> list[ast.AST]:
    """What a test runs over: a ``parametrize``'s values, a fixture's ``params``, what a loop or a
    comprehension iterates."""
    out: list[ast.AST] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if name == "parametrize" and len(node.args) >= 2:
                out.append(node.args[1])
            out += [k.value for k in node.keywords if k.arg in ("argvalues", "params")]
        elif isinstance(node, (ast.For, ast.comprehension)):
            out.append(node.iter)
    return out


def literal_version_lists(source: str, names: set[str]) -> list[int]:
    """The lines where a test runs over a literal list of exactly the known versions (itself, or a
    module-level name bound to one): a version added to the registry would silently be left out."""
    tree = ast.parse(source)
    bound = {
        t.id
        for node in tree.body
        if isinstance(node, ast.Assign) and _is_version_literal(node.value, names)
        for t in node.targets
        if isinstance(t, ast.Name)
    }
    lines = []
    for node in _iterated(tree):
        if _is_version_literal(node, names) or (isinstance(node, ast.Name) and node.id in bound):
            lines.append(node.lineno)
    return sorted(lines)


def runs_over_several_versions(source: str, names: set[str]) -> list[int]:
    """The lines where a test runs over more than one version: over a registry, or over a literal
    holding two or more version names."""
    lines = []
    for node in _iterated(ast.parse(source)):
        used = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}
        literal = {n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and n.value in names}
        if used & REGISTRY_NAMES or len(literal) >= 2:
            lines.append(node.lineno)
    return lines


def _test_files() -> dict[str, str]:
    return {
        p.relative_to(TESTS).as_posix(): p.read_text(encoding="utf-8")
        for p in sorted(TESTS.rglob("test_*.py"))
    }


def test_tests_run_over_the_registry_not_a_literal_list_of_versions() -> None:
    names = set(FIRMWARES)
    found = {path for path, source in _test_files().items() if literal_version_lists(source, names)}
    assert found - LITERAL_VERSION_LISTS == set(), (
        "run over list(FIRMWARES) (or DIALECTS, MODELS), not a literal"
    )
    assert LITERAL_VERSION_LISTS - found == set(), (
        "no longer a literal list: take it off LITERAL_VERSION_LISTS"
    )


def test_a_per_version_file_holds_only_that_versions_behaviour() -> None:
    """``test_v2_*.py`` is for what v2 alone does; a test that runs over several versions is behaviour
    that does not depend on the version and belongs in the file named for that behaviour."""
    names = set(FIRMWARES)
    for path, source in _test_files().items():
        match = PER_VERSION_FILE.fullmatch(Path(path).name)
        if match is None:
            continue
        version = match.group(1).replace("_", ".")
        assert version in names, f"{path}: {version} is not a firmware the protocol knows"
        lines = runs_over_several_versions(source, names)
        assert lines == [], f"{path}:{lines}: runs over several firmwares; move it to a behaviour's file"


def test_the_shape_checks_catch_what_they_name() -> None:
    """The controls: each check sees a literal list of the versions, bound to a name or not, and a test
    over the registry, and lets the registry and one version's own test pass."""
    names = set(FIRMWARES)
    literal = repr(sorted(names))
    assert literal_version_lists(f"@pytest.mark.parametrize('fw', {literal})\ndef test(fw): ...", names) == [
        1
    ]
    assert literal_version_lists(f"FWS = {literal}\nfor fw in FWS:\n    pass", names) == [2]
    assert literal_version_lists("@pytest.fixture(params=list(FIRMWARES))\ndef fw(request): ...", names) == []
    assert literal_version_lists(f"assert out == {literal}", names) == []  # an expected output, not a loop
    over = "@pytest.mark.parametrize('fw', list(FIRMWARES))\ndef test(fw): ..."
    assert runs_over_several_versions(over, names) == [1]
    assert runs_over_several_versions(f"for fw in {literal}:\n    pass", names) == [1]
    assert runs_over_several_versions("for seed in range(6):\n    pass", names) == []
