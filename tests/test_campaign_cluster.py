"""The safety campaign on a Dask cluster (``--cluster``): the figures of one core whatever runs the
chunks, and a worker killed mid-run loses and duplicates nothing (``tools/campaign_engine.py``)."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("distributed", reason="the cluster engine is the optional [cluster] extra (dask)")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import campaign_engine as engine  # noqa: E402
import safety_campaign as sc  # noqa: E402

SESSIONS = 24
SEED = 100  # failing sessions among the first 24 (torn patterns on v1.2): the failures merge too


def figures(summary: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in summary.items() if k not in ("session_s", "ms_per_session")}


@pytest.fixture(scope="module")
def one_core() -> dict[str, Any]:
    return figures(sc.summarize([sc.run_session(i, SEED) for i in range(SESSIONS)], faults=False))


@pytest.fixture
def worker_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """The local cluster's workers find the package under test by PYTHONPATH: restored afterwards."""
    monkeypatch.setenv("PYTHONPATH", os.environ.get("PYTHONPATH", ""))


def test_one_core_jobs_and_a_local_cluster_give_identical_figures(
    one_core: dict[str, Any], worker_path: None
) -> None:
    job = sc.campaign_job(SESSIONS, seed=SEED, chunk=4)
    assert one_core["failed_sessions"] > 0
    assert figures(engine.run(job, jobs=1).summary()) == one_core
    assert figures(engine.run(job, jobs=2).summary()) == one_core
    assert figures(engine.run(job, cluster="local:2").summary()) == one_core


@pytest.mark.parametrize("scheduler_retries", [True, False], ids=["scheduler_reruns", "engine_resubmits"])
def test_a_worker_killed_mid_run_loses_and_duplicates_nothing(
    one_core: dict[str, Any], worker_path: None, scheduler_retries: bool
) -> None:
    """The scheduler runs a lost worker's chunk again; when it gives up on the chunk at once (no failures
    allowed: ``KilledWorker``), the engine submits it again itself."""
    import dask

    job = sc.campaign_job(SESSIONS, seed=SEED, chunk=3)
    killed: list[int] = []

    def kill_a_busy_worker(k: int, total: Any, client: Any) -> None:
        if killed:
            return
        busy = [w for w, keys in client.processing().items() if keys]
        assert busy, "a worker is running a chunk when the first chunk comes back"
        pid = client.run(os.getpid, workers=[busy[0]])[busy[0]]
        os.kill(pid, signal.SIGKILL)
        killed.append(pid)

    allowed = {} if scheduler_retries else {"distributed.scheduler.allowed-failures": 0}
    with dask.config.set(allowed):
        total = engine.run(job, cluster="local:2", on_accept=kill_a_busy_worker)
    assert killed, "a worker was killed during the run"
    assert total.items == SESSIONS
    assert figures(total.summary()) == one_core


def test_the_command_line_on_a_local_cluster(worker_path: None, capsys: pytest.CaptureFixture[str]) -> None:
    argv = [
        "--firmware",
        "v2",
        "--sessions",
        "6",
        "--seed",
        "7",
        "--cluster",
        "local:1",
        "--chunk",
        "2",
        "--json",
    ]
    assert sc.main(argv) == 0
    out = capsys.readouterr()
    assert '"cluster": "local:1"' in out.out and '"sessions": 6' in out.out
    assert "6/6 sessions" in out.err


def test_an_unreachable_scheduler_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(engine, "CONNECT_TIMEOUT_S", 1.0)
    with pytest.raises(engine.EngineError, match="no Dask scheduler answered at tcp://127.0.0.1:9"):
        engine.run(sc.campaign_job(2, seed=0), cluster="dask://127.0.0.1:9")


def test_the_exhaustive_enumeration_on_a_local_cluster_gives_the_figures_of_one_core(
    worker_path: None,
) -> None:
    import exhaustive_campaign as ex

    job = ex.job(1, ("v1.2",), chunk=8)
    one = engine.run(job, jobs=1).summary()
    assert one["sequences"] == 60 and one["failed_sequences"] == 0
    assert engine.run(job, cluster="local:2").summary() == one
