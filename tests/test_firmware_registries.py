"""Adding a firmware is a checklist, and this test is that checklist: every version the protocol knows has
an entry in every layer's registry, the identification tells it from every other, and the architecture
guide's steps name each registry."""

from __future__ import annotations

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
