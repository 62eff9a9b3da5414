"""The Lab Streaming Layer inlet and outlet through the real pylsl (the ``lsl`` extra), on this machine's
loopback: what a tracking outlet pushes is what ``--tracking lsl://NAME`` receives, and what
``--lsl-out NAME`` publishes is what a study's recorder pulls."""

from __future__ import annotations

import time
import uuid

import pytest

from tactdeform_hw.render.live import LslPatternOutlet, LslTrackingSource, parse_sample
from tactdeform_hw.render.pipeline import FrameRecord

pylsl = pytest.importorskip("pylsl", reason="the lsl extra (pylsl) is not installed")


def _name(what: str) -> str:
    return f"tactdeform-test-{what}-{uuid.uuid4().hex[:8]}"  # no other stream on the network answers


def test_a_tracking_outlet_reaches_the_source_sample_for_sample() -> None:
    name = _name("tracking")
    info = pylsl.StreamInfo(name, "Tracking", 8, 0, "float32", name)
    outlet = pylsl.StreamOutlet(info)
    source = LslTrackingSource(name, resolve_timeout_s=10.0)
    try:
        deadline = time.monotonic() + 10.0
        assert outlet.have_consumers()  # the source connected when it was made
        sent = [[0.01 * i, 100.0 + i, 0.0, 20.0, 1.0, 0.0, 0.0, 0.0] for i in range(5)]
        for s in sent:
            outlet.push_sample(s)
        got = []
        while len(got) < len(sent) and time.monotonic() < deadline:
            sample = source.receive(0.5)
            if sample is not None:
                got.append([float(v) for v in sample[0]])
        assert len(got) == len(sent)
        for g, s in zip(got, sent, strict=True):
            assert g == pytest.approx(s, abs=1e-6)
        assert all(parse_sample(g, 0.0) not in ("columns", "text", "nan", "metres") for g in got)
    finally:
        source.close()


def test_an_unknown_stream_name_is_refused_naming_it() -> None:
    from tactdeform_hw.errors import ConfigurationError

    name = _name("absent")
    with pytest.raises(ConfigurationError, match=name):
        LslTrackingSource(name, resolve_timeout_s=0.5)


def test_the_pattern_outlet_publishes_what_a_recorder_pulls() -> None:
    name = _name("patterns")
    outlet = LslPatternOutlet(name, 4)
    found = pylsl.resolve_byprop("name", name, timeout=10.0)
    assert found, "the pattern outlet is not visible on LSL"
    inlet = pylsl.StreamInlet(found[0])
    inlet.open_stream(timeout=10.0)
    assert inlet.info().channel_count() == 3 + 4
    record = FrameRecord(
        t_s=1.5, state="interacting", feature="edge", texture=None, electrodes=(1, 0, 1, 0), sent=True
    )
    deadline = time.monotonic() + 10.0
    sample = None
    while sample is None and time.monotonic() < deadline:
        outlet.push(record, 800)
        sample, _stamp = inlet.pull_sample(timeout=0.2)
    assert sample == pytest.approx([1.5, 3.0, 2.0, 800.0, 0.0, 800.0, 0.0])
