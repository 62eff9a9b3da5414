"""The fuzz campaign: a short run of every target passes, a planted bug is found and shrunk to a minimal
example that still fails, and the figures do not depend on how the examples are cut into chunks."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import campaign_engine as engine  # noqa: E402
import fuzz_campaign as fz  # noqa: E402

from tactdeform_hw.protocol import decoder  # noqa: E402


def test_a_short_run_of_every_target_passes() -> None:
    targets = tuple(fz.TARGETS)
    budget = 4
    tally = fz.tally_chunk(0, targets, budget, 0, budget * len(targets))
    assert tally.examples == dict.fromkeys(targets, budget)
    assert tally.failed == 0, fz.summary(tally, 0, budget, targets)
    assert set(targets) >= {
        "decoder",
        "parser_v1_2",
        "parser_v2",
        "timed_v1_2",
        "timed_v2",
        "profile",
        "calibration",
        "array_file",
        "configure",
        "set_current",
        "send_pattern",
        "interlock",
        "trajectory",
        "tracking",
    }


def _planted(monkeypatch: pytest.MonkeyPatch) -> None:
    """The decoder breaks on any 0xFF (an IndexError: not one of the package's documented errors)."""
    real = decoder.decode

    def broken(data: bytes, *args: object, **kw: object) -> list[decoder.DecodedCommand]:
        if 0xFF in data:
            raise IndexError("planted: 0xFF")
        return real(data, *args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(decoder, "decode", broken)


def test_a_planted_decoder_bug_is_reported_with_a_minimal_example(monkeypatch: pytest.MonkeyPatch) -> None:
    _planted(monkeypatch)
    tally = engine.run(fz.job(5, ("decoder",), 40, chunk=15))
    assert tally.failures["decoder"] > 0
    finding = tally.findings["decoder"]
    assert "IndexError" in finding.description and "planted" in finding.description
    minimal = bytes.fromhex(finding.minimal_hex)
    original = bytes.fromhex(finding.example_hex)
    assert len(minimal) <= 6 < len(original)  # firmware choice, a length of 1, one byte's two draws
    assert fz.failure_of("decoder", minimal) is not None
    assert fz.failure_of("decoder", minimal)[0] == "IndexError"  # type: ignore[index]
    # the finding is the lowest failing index, whichever chunk found it
    first = min(i for i in range(40) if fz.failure_of("decoder", fz.example_bytes(5, "decoder", i)))
    assert finding.index == first


def test_the_planted_bug_is_not_reported_once_removed() -> None:
    tally = fz.tally_chunk(5, ("decoder",), 40, 0, 40)
    assert tally.failed == 0


def test_the_figures_do_not_depend_on_the_chunks() -> None:
    targets = ("decoder", "tracking", "profile")
    runs = [engine.run(fz.job(3, targets, 6, chunk=c)) for c in (1, 4, 18)]
    summaries = [fz.summary(t, 3, 6, targets) for t in runs]
    assert summaries[0] == summaries[1] == summaries[2]
    assert summaries[0]["examples"] == 18


def test_replay_and_errors_on_the_command_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert fz.main(["--target", "decoder", "--replay", "00"]) == 0
    assert fz.main(["--target", "nope", "--budget-per-target", "1"]) == 2
    err = capsys.readouterr().err
    assert "--target 'nope'" in err and "decoder" in err and "Traceback" not in err
    assert fz.main(["--target", "decoder", "--replay", "zz"]) == 2
