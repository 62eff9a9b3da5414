"""The campaign engine without a cluster (``tools/campaign_engine.py``): chunk tallies merge into the
figures of one run, in any order and once each; progress on stderr; a missing Dask is one line naming the
extra."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest

from tactdeform_hw.errors import install_command

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import campaign_engine as engine  # noqa: E402
import safety_campaign as sc  # noqa: E402

from tactdeform_hw.errors import ConfigurationError  # noqa: E402

#: Fields that are run times, not figures.
TIMES = ("session_s", "ms_per_session")


def figures(summary: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in summary.items() if k not in TIMES}


@pytest.fixture(scope="module")
def results() -> list[sc.SessionResult]:
    # seed 100 has failing sessions among 20-31 (torn patterns on v1.2): the failure list is merged too
    return [sc.run_session(i, 100) for i in range(20, 32)]


def test_chunks_merged_in_any_order_give_the_figures_of_one_run(results: list[sc.SessionResult]) -> None:
    whole = sc.summarize(results, faults=False)
    assert whole["failed_sessions"] > 0, "the merge of failures is exercised"
    for size in (1, 5, 12):
        chunks = [sc.tally(results[i : i + size], faults=False) for i in range(0, len(results), size)]
        merged = chunks.pop()  # the last chunk first: completion order is not index order
        for t in chunks:
            merged.merge(t)
        assert figures(merged.summary()) == figures(whole), size


def test_the_failures_listed_are_those_of_lowest_index(results: list[sc.SessionResult]) -> None:
    failed = [r for r in results if not r.ok]
    t = sc.CampaignTally()
    for r in reversed(results):  # every failure arrives as its own chunk, the highest index first
        one = sc.tally([r], faults=False)
        t.merge(one)
    assert [f["index"] for f in t.summary()["failures"]] == [r.index for r in failed][: sc.LISTED_FAILURES]
    assert all(f["reproduce"].endswith(f"--seed 100 --only {f['index']}") for f in t.summary()["failures"])


def test_a_chunk_accepted_twice_counts_once(results: list[sc.SessionResult]) -> None:
    job = sc.campaign_job(12, seed=100, chunk=6)
    merger = engine.Merger(job, progress=False)
    first = sc.tally(results[:6], faults=False)
    assert merger.accept(0, first)
    assert not merger.accept(0, sc.tally(results[:6], faults=False))  # the same chunk run again elsewhere
    assert not merger.accept(2, sc.tally(results[:6], faults=False))  # no such chunk
    assert merger.accept(1, sc.tally(results[6:], faults=False))
    assert merger.complete and merger.duplicates == 2
    assert figures(merger.total.summary()) == figures(sc.summarize(results, faults=False))


def test_one_core_run_reports_progress_and_the_same_figures(
    results: list[sc.SessionResult], capsys: pytest.CaptureFixture[str]
) -> None:
    job = sc.campaign_job(12, seed=100, chunk=5, first=20)
    total = engine.run(job, jobs=1, progress=True)
    assert figures(total.summary()) == figures(sc.summarize(results, faults=False))
    err = capsys.readouterr().err
    last = err.strip().split("\r")[-1]
    assert "12/12 sessions" in last and f"{total.pulses} pulses" in last and f"{total.failed} failed" in last
    assert "/s" in last and "s left" in last


def test_a_missing_dask_is_one_line_naming_the_extra(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    assert sc.main(["--cluster", "local:2", "--sessions", "4"]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in captured.err
    assert "--cluster" in lines[0] and install_command("cluster") in lines[0]


@pytest.mark.parametrize(
    ("spec", "says"),
    [("local:0", "N >= 1"), ("local:x", "N >= 1"), ("dask://nohost", "HOST:PORT"), ("tcp://a:1", "local:N")],
)
def test_a_malformed_cluster_is_refused_by_name(spec: str, says: str) -> None:
    with pytest.raises(ConfigurationError, match=says) as exc:
        engine.parse_cluster(spec)
    assert spec in str(exc.value)


def test_an_empty_campaign_is_refused() -> None:
    with pytest.raises(ConfigurationError, match="at least 1"):
        engine.run(sc.campaign_job(0), jobs=1)


def test_a_worker_with_other_code_fails_the_chunk() -> None:
    job = sc.campaign_job(2, seed=100, chunk=2)
    other = engine.Job(job.module, job.function, job.args, job.total, chunk=job.chunk, fingerprint="0" * 16)
    with pytest.raises(engine.EngineError, match="runs other code"):
        engine.run_chunk(other, 0)
