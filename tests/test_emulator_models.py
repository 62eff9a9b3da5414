"""What every firmware version's models promise alike, checked for each entry of the registry.

The untimed emulator, the parsers, the typed board state and the timed models keep one contract whatever
the version (``emulator/firmware/models.py``); what differs comes from the version's table.  Each test
here runs once per entry of ``MODELS``, so a version added to the registry is held to the same promises.
"""

from __future__ import annotations

import dataclasses
import json

import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from tactdeform_hw.emulator.core import Emulator
from tactdeform_hw.emulator.firmware.contract import CallOutcome
from tactdeform_hw.emulator.firmware.models import MODELS, ModelEntry, model_entry
from tactdeform_hw.emulator.serving.realtime import RealtimeEmulator
from tactdeform_hw.emulator.serving.usb_backend import EmulatedUsbDevice
from tactdeform_hw.emulator.timed.base import TimedModelBase
from tactdeform_hw.emulator.timed.model_v1_2 import timed_emulator
from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.protocol.firmware import DEFAULT_FIRMWARE, FIRMWARES
from tactdeform_hw.protocol.state import BoardState

from .conftest import DATA

ENTRIES = list(MODELS.values())
IDS = [e.spec.name for e in ENTRIES]
VECTORS = {"v1.2": "protocol_vectors.jsonl", "v2": "protocol_vectors_v2.jsonl"}

#: bytes of any version's commands, values and unknown bytes
streams = st.lists(
    st.one_of(st.integers(0xF4, 0xFF), st.integers(0, 8), st.integers(0, 255)), max_size=160
).map(bytes)


def _configure(electrodes: int) -> bytes:
    """ELECTRODE_NUM then MEASURE: the same bytes mean the same on every version."""
    return bytes([0xFC, electrodes, 0xFF])


@pytest.mark.parametrize("entry", ENTRIES, ids=IDS)
def test_every_modelled_version_has_one_entry(entry: ModelEntry) -> None:
    assert set(MODELS) == set(FIRMWARES.values())
    assert model_entry(entry.spec.name) is entry is model_entry(entry.spec)
    assert issubclass(entry.timed_class(), TimedModelBase) and entry.timed_class().firmware is entry.spec


def test_an_unknown_version_is_refused_naming_the_choices() -> None:
    for build in (Emulator, timed_emulator):
        with pytest.raises(ConfigurationError, match=r"firmware='v3' .*choices: v1\.2, v2"):
            build(firmware="v3")


@pytest.mark.parametrize("entry", ENTRIES, ids=IDS)
def test_the_timed_factory_builds_the_versions_model_with_the_options_given(entry: ModelEntry) -> None:
    timed = timed_emulator(firmware=entry.spec.name, link="uart")
    assert type(timed) is entry.timed_class() and timed.link.name == "uart"
    assert type(timed_emulator()) is model_entry(DEFAULT_FIRMWARE).timed_class()  # no version named


@pytest.mark.parametrize("entry", ENTRIES, ids=IDS)
def test_power_on_state_is_the_tables(entry: ModelEntry) -> None:
    """The typed state at power-on holds the table's power-on registers; the register the version lacks
    is None, and the golden vectors' names are exactly what ``as_dict`` gives."""
    state = Emulator(firmware=entry.spec).state()
    assert isinstance(state, BoardState) and state.firmware is entry.spec
    regs = state.as_dict()
    for name, value in entry.spec.power_on.items():
        assert regs[name] == value, name
    assert (state.pulse_height is None) == ("pulse_height" not in entry.spec.power_on)
    assert (state.stim_mode is None) == ("stim_mode" not in entry.spec.power_on)
    assert state.rx_pending == 0 and len(state.stim_pattern) == entry.spec.pattern_buffer_size
    vectors = (DATA / VECTORS[entry.spec.name]).read_text().splitlines()
    expect_names = set().union(*(json.loads(line)["expect"] for line in vectors if line.strip()))
    assert expect_names - {"tx"} == set(regs)


@pytest.mark.parametrize("entry", ENTRIES, ids=IDS)
def test_a_state_is_a_frozen_copy(entry: ModelEntry) -> None:
    emu = Emulator(firmware=entry.spec)
    before = emu.state()
    emu.feed(_configure(5))
    assert before.electrode_num == 0 and emu.state().electrode_num == 5
    assert before != emu.state() and emu.state() == emu.state()
    with pytest.raises(dataclasses.FrozenInstanceError):
        before.electrode_num = 3  # type: ignore[misc]


@pytest.mark.parametrize("entry", ENTRIES, ids=IDS)
def test_a_state_read_back_from_its_variables_is_the_same_state(entry: ModelEntry) -> None:
    """``from_variables`` reads exactly the names ``as_dict`` writes: every register, the pattern and the
    register the version lacks (None) come back equal."""
    emu = Emulator(firmware=entry.spec)
    emu.feed(_configure(5) + bytes([0xFD, 0, 0xF7, 40]))
    state = emu.state()
    again = BoardState.from_variables(
        state.firmware,
        state.as_dict(),
        rx_pending=state.rx_pending,
        rx_dropped=state.rx_dropped,
        command_in_progress=state.command_in_progress,
    )
    assert again == state and (again.polarity, again.discharge_time_us) == (0, 40)


def test_a_state_missing_a_variable_is_refused_naming_it() -> None:
    variables = Emulator(firmware="v2").state().as_dict()
    del variables["sense_pulse_width"]
    with pytest.raises(ConfigurationError, match="sense_pulse_width missing, a v2 board state needs"):
        BoardState.from_variables(FIRMWARES["v2"], variables, rx_pending=0)


@pytest.mark.parametrize("entry", ENTRIES, ids=IDS)
@settings(max_examples=60, deadline=None)
@given(data=streams)
def test_call_by_call_equals_the_fast_path(entry: ModelEntry, data: bytes) -> None:
    """Calling the parser one call at a time until a call is quiet reaches the state and replies the
    untimed fast path does, and each call says what it did in the one contract."""
    fast = Emulator(firmware=entry.spec)
    tx = fast.feed(data)
    slow = Emulator(firmware=entry.spec)
    slow.parser.receive(data)
    for _ in range(len(data) + 2):
        out = slow.call()
        assert isinstance(out, CallOutcome) and out.consumed >= 0 and out.wrote >= 0
        if out.quiet or slow.locked:
            break
    else:
        raise AssertionError("the parser never went quiet")
    slow.parser.note_pending(slow.now_us)
    assert slow.parser.take_tx() == tx
    if not slow.locked and slow.parser.pending <= 1:  # a half u16 spins: the call never returns
        assert slow.state() == fast.state()


@pytest.mark.parametrize("entry", ENTRIES, ids=IDS)
def test_a_cut_command_waits_or_times_out_as_the_table_says(entry: ModelEntry) -> None:
    emu = Emulator(firmware=entry.spec)
    emu.feed(b"\xfc", at_us=1)  # ELECTRODE_NUM without its value
    assert emu.parser.processing
    timeout_us = entry.spec.command_timeout_us
    emu.advance(1 + (timeout_us if timeout_us is not None else 10_000_000) + 1)
    assert emu.parser.processing == (timeout_us is None)
    assert emu.feed(b"\x02") == b"" and emu.state().electrode_num == (2 if timeout_us is None else 0)


@pytest.mark.parametrize("entry", ENTRIES, ids=IDS)
def test_timed_models_keep_one_outer_api(entry: ModelEntry) -> None:
    """Write, run to a time, read the replies that reached the host, read the typed state, reset: the
    same calls, the same meaning, on every version's timed model."""
    timed = timed_emulator(firmware=entry.spec.name)
    assert isinstance(timed, entry.timed_class()) and timed.firmware is entry.spec
    assert timed.host_offset == 0 and timed.in_waiting == 0 and timed.now_us == 0.0
    timed.write(_configure(3))
    assert timed.in_flight == 3
    timed.advance(50_000)
    assert timed.in_flight == 0 and timed.now_us == 50_000.0 and timed.host_offset == 3
    assert timed.in_waiting == entry.spec.reply_bytes(0xFF, 3) == len(timed.read_tx())
    state = timed.state()
    assert state.firmware is entry.spec and state.electrode_num == 3 and state.rx_pending == 0
    assert timed.run_until_idle() and timed.scan_rate(timed.now_us)[0] > 0
    timed.reset("test")
    timed.advance_to(timed.now_us + 1_000_000)
    assert timed.state().electrode_num == 0 and timed.reboots == 1


@pytest.mark.parametrize("entry", ENTRIES, ids=IDS)
def test_every_server_takes_its_model_from_the_registry(entry: ModelEntry) -> None:
    rt = RealtimeEmulator(firmware=entry.spec.name)
    assert rt.firmware is entry.spec and type(rt.timed) is entry.timed_class()
    usb = EmulatedUsbDevice(firmware=entry.spec.name)
    assert usb.firmware is entry.spec and type(usb.timed) is entry.timed_class()
    assert usb.timed.state().firmware is entry.spec
    for timed in ("1", "0"):
        port = serial.serial_for_url(f"etactile://?firmware={entry.spec.name}&timed={timed}", timeout=0.1)
        try:
            assert port.board_state().firmware is entry.spec and port.emulator.firmware is entry.spec
        finally:
            port.close()


def test_the_url_handler_refuses_an_unknown_version_naming_the_choices() -> None:
    with pytest.raises(
        serial.SerialException, match=r"in 'etactile://\?firmware=v3': firmware='v3' .*choices: v1\.2, v2"
    ):
        serial.serial_for_url("etactile://?firmware=v3", timeout=0.1)


#: What running a scan takes from each version's scan engine module (the rest of a module, such as the
#: engine's signal names, is vocabulary other models may share).
SCAN_ENTRY_POINTS = {
    "tactdeform_hw.emulator.firmware.scan": {"ScanEngine", "ScanVoltages", "firmware_trace"},
    "tactdeform_hw.emulator.firmware.firmware_scan": {"trace_scan", "budget", "scan_duration_us"},
}


def _imported_names(module: str) -> set[tuple[str, str]]:
    """(module, name) of every ``from module import name`` in ``module``'s source, deferred ones too."""
    import ast
    import importlib

    source = importlib.import_module(module).__file__
    assert source is not None
    tree = ast.parse(open(source, encoding="utf-8").read())
    return {
        (node.module, alias.name)
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.module
        for alias in node.names
    }


def test_each_version_has_exactly_one_scan_engine() -> None:
    """No two versions share a scan engine and every engine is some version's; the engine of one version
    refuses another (the statement walker scans v2 alone)."""
    from tactdeform_hw.emulator.firmware import firmware_scan

    engines = [e.scan_module for e in ENTRIES]
    assert len(set(engines)) == len(engines) and set(engines) == set(SCAN_ENTRY_POINTS)
    for entry in ENTRIES:
        if entry.scan_module == firmware_scan.__name__:
            continue
        cfg = firmware_scan.FirmwareScanConfig(1, [100], 200, 45)
        for walk in (firmware_scan.trace_scan, firmware_scan.budget, firmware_scan.scan_duration_us):
            with pytest.raises(
                ConfigurationError, match=rf"firmware {entry.spec.name}: .* {entry.scan_module}"
            ):
                walk(cfg, entry.spec)


@pytest.mark.parametrize("entry", ENTRIES, ids=IDS)
def test_each_timed_model_scans_with_its_versions_engine_only(entry: ModelEntry) -> None:
    imported = _imported_names(entry.timed_model.split(":")[0])
    for module, entry_points in SCAN_ENTRY_POINTS.items():
        used = {name for m, name in imported if m == module} & entry_points
        assert bool(used) is (module == entry.scan_module), (module, used)
