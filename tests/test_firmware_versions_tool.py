"""``tools/firmware_versions.py`` runs and gives figures of the right shape (one write moment)."""

from __future__ import annotations

from .test_tools import run_tool


def test_firmware_versions_figures() -> None:
    out = run_tool("tools/firmware_versions.py", "--phases", "1", "--json")
    assert isinstance(out, dict)
    assert out["v2_vectors"] == {"matched": 300, "total": 300}
    b = out["budget_tactdeform"]
    assert b["v1.2 cs inside"]["scan_us"] == 7850.25 and b["v2 cs costed"]["scan_us"] == 7645.45
    lat = out["pattern_in_force"]
    assert set(lat) == {"v1.2 usb", "v2 usb whole", "v2 usb upstream"}
    assert lat["v2 usb upstream"]["first_channel_us"]["min"] > lat["v2 usb whole"]["first_channel_us"]["min"]
