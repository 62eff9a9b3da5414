"""The pytest plugin as a downstream project uses it: a test file of its own, run by pytest with the
plugin loaded (``-p tactdeform_hw.testing.plugin``, what the ``pytest11`` entry point loads once the
package is installed)."""

from __future__ import annotations

import pytest
import serial  # noqa: F401 - loaded once here: an in-process run drops the modules it imported itself

import tactdeform_hw.device  # noqa: F401
import tactdeform_hw.testing.plugin  # noqa: F401

pytest_plugins = ["pytester"]


@pytest.fixture(autouse=True)
def _only_this_plugin(monkeypatch: pytest.MonkeyPatch) -> None:
    """The inner runs load the plugin by name alone (faster, and nothing else installed can help)."""
    monkeypatch.setenv("PYTEST_DISABLE_PLUGIN_AUTOLOAD", "1")


PLUGIN = (
    "-p",
    "tactdeform_hw.testing.plugin",
    "-p",
    "no:cacheprovider",
    "--durations=3",
    "-W",
    "ignore::pytest.PytestAssertRewriteWarning",
)

SESSION = """
import time

import pytest

from tactdeform_hw.device import StimConfig, open_device
from tactdeform_hw.protocol.state import BoardState

CONFIG = StimConfig(electrode_count=8, rate_hz=20, current_ua=500)


def run_session(board, levels=(1, 0, 0, 0, 0, 0, 0, 0)):
    dev = open_device(board.name, settle_s=0.0, guardian=False)
    dev.configure(CONFIG)
    dev.send_pattern(list(levels))
    time.sleep(0.12)
    return dev
"""


def test_a_clean_driver_session_passes(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        SESSION
        + """
def test_app(etactile_board):
    dev = run_session(etactile_board)
    assert etactile_board.path is not None  # the default: a pty
    assert isinstance(etactile_board.state(), BoardState)
    pulses = [p for p in etactile_board.delivered() if p.current_ua > 0]
    assert pulses and {p.electrode for p in pulses} == {0}
    assert all(p.current_ua == 500 and 150 < p.width_us <= 200 for p in pulses)
    etactile_board.assert_no_pulse_above(500)
    etactile_board.assert_no_defect()
    hazards = etactile_board.hazards
    assert len(hazards) > 0 and hazards.defects() == []
    assert all(a.origin.value == "driver" and a.severity.value == "info" for a in hazards), list(hazards)
    assert {a.kind.value for a in hazards} == {"unknown_bytes", "hv513_reinit"}
    dev.all_off()
    etactile_board.assert_off_within(20)
    dev.close()
"""
    )
    result = pytester.runpytest(*PLUGIN)
    result.assert_outcomes(passed=1)


def test_an_over_current_fails_naming_the_pulse(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        SESSION
        + """
@pytest.mark.etactile_board(transport="url")
def test_app(etactile_board):
    dev = run_session(etactile_board, levels=(0, 0, 1, 0, 0, 0, 0, 0))
    dev.close()
    etactile_board.assert_no_pulse_above(300)
"""
    )
    result = pytester.runpytest(*PLUGIN)
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(
        [
            "*delivered pulse(s) above the limit of 300 µA; first: monophasic pulse at t=*ms on electrode 2: "
            "500.0 µA for *µs*"
        ]
    )


def test_a_pulse_after_the_stop_deadline_fails(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        SESSION
        + """
@pytest.mark.etactile_board(transport="url")
def test_app(etactile_board):
    dev = run_session(etactile_board)
    etactile_board.assert_off_within(20)  # nothing stopped it
"""
    )
    result = pytester.runpytest(*PLUGIN)
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(
        ["*pulse(s) with current later than 20 ms after t=*on electrode 0: 500.0 µA*"]
    )


def test_a_planted_defect_fails_with_severity_and_origin(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        SESSION
        + """
import serial

@pytest.mark.etactile_board(transport="url")
def test_app(etactile_board):
    run_session(etactile_board).close()
    port = serial.serial_for_url(etactile_board.url)
    port.write(bytes([0xFC, 0, 0xFE, 1, 2]))  # a pattern for zero electrodes: v1.2's parser locks
    port.close()
    etactile_board.settle()
    etactile_board.assert_no_defect()
"""
    )
    result = pytester.runpytest(*PLUGIN)
    result.assert_outcomes(failed=1)
    result.stdout.fnmatch_lines(
        ["*the emulated board hit * firmware defect(s):*", "*[[]defect, from host] parser_locked @byte*"]
    )


@pytest.mark.parametrize("transport", ["url", "usb"])
def test_every_transport_tells_the_drivers_bytes_from_the_programs(
    pytester: pytest.Pytester, transport: str
) -> None:
    """On the in-process URL (its board's bytes seen through ``watch_shared``) and on the emulated USB
    device (through its server's hook), as on the pty: the package's clean session leaves records of the
    driver's own bytes only, delivered pulses are read, and a program's byte of its own is the host's."""
    if transport == "usb":
        pytest.importorskip("usb.core", reason="the usb transport is opened through pyusb")
    pytester.makepyfile(
        SESSION
        + f"""
@pytest.mark.etactile_board(transport="{transport}")
def test_app(etactile_board):
    prefix = "etactile://" if "{transport}" == "url" else "usb-emulator://"
    assert etactile_board.name.startswith(prefix), etactile_board.name
    dev = run_session(etactile_board)
    pulses = [p for p in etactile_board.delivered() if p.current_ua > 0]
    assert pulses and {{p.electrode for p in pulses}} == {{0}}
    hazards = etactile_board.hazards
    assert len(hazards) > 0 and hazards.defects() == []
    assert all(a.origin.value == "driver" for a in hazards), list(hazards)
    assert len(etactile_board.received) > 0
    dev.close()
"""
    )
    result = pytester.runpytest(*PLUGIN)
    result.assert_outcomes(passed=1)


def test_the_marker_selects_v2_on_tcp(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        SESSION
        + """
@pytest.mark.etactile_board(firmware="v2", transport="tcp")
def test_app(etactile_board):
    assert etactile_board.url.startswith("socket://") and etactile_board.path is None
    dev = run_session(etactile_board)
    assert dev.firmware == "v2"
    assert etactile_board.state().stim_mode is not None  # v2's register
    assert any(p.current_ua == 500 for p in etactile_board.delivered())
    etactile_board.assert_no_defect()
    assert all(a.origin.value == "driver" for a in etactile_board.hazards)
    dev.close()
"""
    )
    result = pytester.runpytest(*PLUGIN)
    result.assert_outcomes(passed=1)


def test_indirect_parametrization_chooses_the_board(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
import pytest

@pytest.mark.parametrize(
    "etactile_board", [{"transport": "url"}, {"transport": "url", "firmware": "v2"}], indirect=True
)
def test_app(etactile_board):
    assert etactile_board.url.startswith("etactile://")
    assert etactile_board.emulator.firmware.name == etactile_board.firmware

@pytest.mark.etactile_board(transprot="tcp")
def test_typo(etactile_board):
    pass
"""
    )
    result = pytester.runpytest(*PLUGIN)
    result.assert_outcomes(passed=2, errors=1)
    assert "unknown option(s) ['transprot']; use firmware, transport, board, switching_boards" in str(
        result.stdout
    )


def test_the_marker_is_registered(pytester: pytest.Pytester) -> None:
    result = pytester.runpytest(*PLUGIN, "--markers")
    result.stdout.fnmatch_lines(["@pytest.mark.etactile_board(firmware='v1.2', transport='pty'*"])
    assert "--etactile-device" in pytester.runpytest(*PLUGIN, "--help").stdout.str()


def test_a_project_runs_the_conformance_checks_on_its_device(pytester: pytest.Pytester) -> None:
    checks = "from tactdeform_hw.testing.conformance.checks_v1_2 import *  # noqa: F403\n"
    pytester.makepyfile(test_etactile_conformance=checks)
    result = pytester.runpytest(
        *PLUGIN, "--etactile-device", "etactile://?timed=0", "-k", "hv513_reply or locks_the_parser", "-v"
    )
    result.assert_outcomes(passed=2)
    result.stdout.fnmatch_lines(
        [
            "*test_hv513_reply?etactile://?timed=0? PASSED*",
            "*eTactileKit conformance report*",
            "target etactile://?timed=0:",
            "*HV513 count*4",
        ]
    )
    absent = pytester.runpytest(
        *PLUGIN, "--etactile-device", "/dev/no-such-board", "-k", "hv513_reply", "-rs"
    )
    absent.assert_outcomes(skipped=1)
    absent.stdout.fnmatch_lines(["*no board at /dev/no-such-board*"])


def test_the_marker_serves_a_host_built_firmware(pytester: pytest.Pytester) -> None:
    """``firmware_src=``: the upstream v1.2 tree built on this machine is the board; the same session and
    assertions run on the firmware's own code (``TACTDEFORM_HW_UPSTREAM_V1_2``)."""
    import os

    tree = os.environ.get("TACTDEFORM_HW_UPSTREAM_V1_2")
    if not tree:
        pytest.skip("set TACTDEFORM_HW_UPSTREAM_V1_2 to the v1.2 PlatformIO tree (platform_io_project)")
    pytester.makepyfile(
        SESSION
        + f"""
@pytest.mark.parametrize("etactile_board", [{{"transport": "pty"}}, {{"transport": "url"}}], indirect=True)
@pytest.mark.etactile_board(firmware_src={tree!r})
def test_app(etactile_board):
    assert etactile_board.firmware == "v1.2"
    dev = run_session(etactile_board, levels=(0, 0, 1, 0, 0, 0, 0, 0))
    assert etactile_board.state().electrode_num == 8
    pulses = [p for p in etactile_board.delivered() if p.current_ua > 0]
    assert pulses and {{p.electrode for p in pulses}} == {{2}}
    assert all(p.current_ua == 500 and p.kind == "monophasic" for p in pulses)
    etactile_board.assert_no_pulse_above(500)
    dev.all_off()
    etactile_board.assert_off_within(20)
    dev.close()
"""
    )
    result = pytester.runpytest(*PLUGIN)
    result.assert_outcomes(passed=2)


def test_a_host_built_firmware_must_declare_the_version_asked_for() -> None:
    from pathlib import Path

    from tactdeform_hw.errors import ConfigurationError
    from tactdeform_hw.testing.board import EmulatedBoard

    tiny = Path(__file__).parent / "data" / "firmware_tiny"
    with pytest.raises(ConfigurationError, match="firmware='v2', but firmware_src=.*declares no version"):
        EmulatedBoard(firmware="v2", firmware_src=tiny)
    with pytest.raises(ConfigurationError, match="etactile_board firmware_src='/nonexistent'.*src/"):
        EmulatedBoard(firmware_src="/nonexistent")
