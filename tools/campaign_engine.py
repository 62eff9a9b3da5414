"""Runs a campaign's items (sessions, or enumerated sequences) in fixed chunks by index, on this process,
on local worker processes (``--jobs``) or on a Dask cluster (``--cluster``), and merges the chunks' tallies.

Why chunks by index: item ``i`` is always drawn from the same seed and lands in chunk ``i // chunk``,
whatever runs it, and a chunk's tally merges exactly (integer counts, exact sums of floats, the failures
of lowest index kept) and in any order; so a run gives IDENTICAL figures on one core, on ``--jobs J``, or
on any number of cluster workers, whatever order the chunks complete in.  Each chunk's tally is accepted
once, keyed by its index: a worker lost mid-run has its chunk run again elsewhere (by the scheduler, or
resubmitted here), and a result that arrives twice is counted once.

Engines:

* ``--jobs 1``: this process, chunk after chunk;
* ``--jobs J``: ``J`` local worker processes (multiprocessing);
* ``--cluster dask://HOST:PORT``: the workers of a running Dask scheduler; they need ``tactdeform_hw``
  installed (the same source: every chunk checks a fingerprint of the package and the tools, and a worker
  running other code fails the run rather than mix its figures in); the tool files are uploaded to them;
* ``--cluster local:N``: a local Dask cluster of ``N`` worker processes (one thread each), started and
  stopped by the run.

Dask is an optional extra (``pip install 'tactdeform_hw[cluster]'``); without it ``--cluster`` fails
with one line naming the extra.

A chunk function is named by module and function (``module.function(*args, first, count)``) rather than
passed as an object, so a worker imports it by name: the tools directory is on every worker's path.
"""

from __future__ import annotations

import contextlib
import gc
import hashlib
import importlib
import multiprocessing as mp
import os
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

TOOLS = Path(__file__).resolve().parent
ROOT = TOOLS.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))

from tactdeform_hw.errors import ConfigurationError, MissingDependencyError, TactDeformError  # noqa: E402

#: Items per chunk unless the command line says otherwise: large enough that a chunk's scheduling cost
#: (a few ms on a cluster) is small beside its run time (about 20 ms per session), small enough that a
#: lost worker costs little to run again and progress moves often.
DEFAULT_CHUNK = 50
#: How many times a chunk whose worker died is submitted again before the run gives up.
CHUNK_ATTEMPTS = 4
#: How long a run waits for a remote scheduler to answer.
CONNECT_TIMEOUT_S = 10.0
#: Tool files a cluster's workers need beside the installed package (uploaded to them).
TOOL_FILES = (
    "campaign_engine.py",
    "safety_campaign.py",
    "seam_sessions.py",
    "exhaustive_campaign.py",
    "byte_fault_campaign.py",
    "fuzz_campaign.py",
)


class EngineError(TactDeformError):
    """The engine could not run the campaign as asked (a cluster unreachable, a worker with other code)."""


class Tally(Protocol):
    """What a chunk returns: merged exactly and in any order; ``items``, ``pulses`` and ``failed`` feed the
    progress line."""

    items: int
    pulses: int
    failed: int

    def merge(self, other: Any) -> None: ...


@dataclass
class Results:
    """A tally that keeps every item's result (a campaign whose summary needs them all, such as the seam
    sessions): merged by concatenation, read in index order (:meth:`ordered`)."""

    rows: list[Any]

    @property
    def items(self) -> int:
        return len(self.rows)

    @property
    def pulses(self) -> int:
        return sum(int(getattr(r, "pulses", 0)) for r in self.rows)

    @property
    def failed(self) -> int:
        return sum(1 for r in self.rows if not r.ok)

    def merge(self, other: Results) -> None:
        self.rows.extend(other.rows)

    def ordered(self) -> list[Any]:
        return sorted(self.rows, key=lambda r: int(r.index))


@dataclass(frozen=True)
class Job:
    """A campaign cut into chunks: ``module.function(*args, first, count)`` runs items ``first ..
    first + count - 1`` and returns their :class:`Tally`."""

    module: str
    function: str
    args: tuple[Any, ...]
    total: int
    first: int = 0
    chunk: int = DEFAULT_CHUNK
    fingerprint: str = ""
    unit: str = "sessions"

    @property
    def chunks(self) -> int:
        return (self.total + self.chunk - 1) // self.chunk

    def span(self, k: int) -> tuple[int, int]:
        """Chunk ``k``'s first item and its number of items."""
        lo = k * self.chunk
        return self.first + lo, min(self.chunk, self.total - lo)


def fingerprint() -> str:
    """A digest of the package's and the tools' source: two processes with the same digest judge alike."""
    cached = _FINGERPRINT.get("value")
    if cached is not None:
        return cached
    import tactdeform_hw

    h = hashlib.sha256()
    pkg = Path(tactdeform_hw.__file__).resolve().parent
    for p in sorted(pkg.rglob("*.py")):
        h.update(str(p.relative_to(pkg)).encode())
        h.update(p.read_bytes())
    for name in TOOL_FILES:
        p = Path(__file__).resolve().parent / name
        if p.exists():
            h.update(name.encode())
            h.update(p.read_bytes())
    _FINGERPRINT["value"] = h.hexdigest()[:16]
    return _FINGERPRINT["value"]


_FINGERPRINT: dict[str, str] = {}


def run_chunk(job: Job, k: int) -> tuple[int, Any]:
    """Run chunk ``k`` of ``job`` (in whatever process runs it) and return ``(k, tally)``."""
    if job.fingerprint and job.fingerprint != fingerprint():
        raise EngineError(
            f"worker {os.getpid()} runs other code (fingerprint {fingerprint()}, the run's "
            f"{job.fingerprint}): install the same tactdeform_hw on every worker"
        )
    first, count = job.span(k)
    fn = getattr(importlib.import_module(job.module), job.function)
    with _few_collections():
        return k, fn(*job.args, first, count)


#: The cyclic collector's first threshold while a chunk runs (Python's default: 700 allocations).
CHUNK_GC_THRESHOLD = 20_000
_FROZEN: dict[int, bool] = {}


@contextlib.contextmanager
def _few_collections() -> Iterator[None]:
    """Run a chunk with fewer cyclic collections.  A session allocates hundreds of thousands of small
    objects and leaves few cycles, so at the default threshold the collector runs every few hundred
    allocations and each of its full passes walks every module and array loaded: about a tenth of a
    session's CPU.  What was loaded before the first chunk is frozen once per process (never collected:
    modules), and the first threshold is raised while the chunk runs; the cycles a session leaves are
    still collected, in fewer passes.  Results do not depend on when the collector runs."""
    if not _FROZEN.get(os.getpid()):
        gc.freeze()
        _FROZEN[os.getpid()] = True
    was = gc.get_threshold()
    gc.set_threshold(max(was[0], CHUNK_GC_THRESHOLD), *was[1:])
    try:
        yield
    finally:
        gc.set_threshold(*was)


def _pool_chunk(arg: tuple[Job, int]) -> tuple[int, Any]:
    return run_chunk(*arg)


class Merger:
    """Accepts each chunk's tally once, keyed by chunk index, and reports progress on stderr."""

    def __init__(self, job: Job, progress: bool) -> None:
        self.job = job
        self.progress = progress
        self.total: Any = None
        self.accepted: set[int] = set()
        self.duplicates = 0
        self.t0 = time.perf_counter()
        self._shown = 0.0

    def accept(self, k: int, tally: Any) -> bool:
        """Merge chunk ``k``'s tally unless one was accepted already (a chunk run twice counts once)."""
        if k in self.accepted or not 0 <= k < self.job.chunks:
            self.duplicates += 1
            return False
        self.accepted.add(k)
        if self.total is None:
            self.total = tally
        else:
            self.total.merge(tally)
        self._show()
        return True

    @property
    def complete(self) -> bool:
        return len(self.accepted) == self.job.chunks

    def _show(self) -> None:
        now = time.perf_counter()
        if not self.progress or (now - self._shown < 0.5 and not self.complete):
            return
        self._shown = now
        t = self.total
        rate = t.items / max(1e-9, now - self.t0)
        left = (self.job.total - t.items) / rate if rate > 0 else float("inf")
        print(
            f"\r{t.items}/{self.job.total} {self.job.unit}, {t.pulses} pulses, {t.failed} failed, "
            f"{rate:.0f}/s, {left:.0f} s left   ",
            end="\n" if self.complete else "",
            file=sys.stderr,
            flush=True,
        )


def run(
    job: Job,
    *,
    jobs: int = 1,
    cluster: str | None = None,
    progress: bool = False,
    on_accept: Callable[[int, Any, Any], None] | None = None,
) -> Any:
    """The merged tally of every chunk of ``job``; ``on_accept(k, tally, client)`` after each accepted
    chunk (``client``: the Dask client, or None)."""
    if job.total < 1:
        raise ConfigurationError(f"a campaign of {job.total} {job.unit}: at least 1")
    merger = Merger(job, progress)
    if cluster is not None:
        _run_dask(job, cluster, merger, on_accept)
    elif jobs <= 1:
        for k in range(job.chunks):
            merger.accept(*run_chunk(job, k))
            if on_accept is not None:
                on_accept(k, merger.total, None)
    else:
        ctx = mp.get_context("fork" if sys.platform != "win32" else "spawn")
        with ctx.Pool(jobs) as pool:
            for k, tally in pool.imap_unordered(_pool_chunk, [(job, k) for k in range(job.chunks)]):
                merger.accept(k, tally)
                if on_accept is not None:
                    on_accept(k, merger.total, None)
    if not merger.complete:  # pragma: no cover - every engine above runs every chunk or raises
        raise EngineError(f"{job.chunks - len(merger.accepted)} chunks never completed")
    return merger.total


# --- Dask ---------------------------------------------------------------------------------------------


def require_dask() -> Any:
    """The ``distributed`` module, or :class:`MissingDependencyError` naming the ``cluster`` extra."""
    try:
        import distributed
    except ImportError as exc:
        raise MissingDependencyError("dask[distributed]", "cluster", "--cluster") from exc
    return distributed


def parse_cluster(spec: str) -> tuple[str, int | str]:
    """``local:N`` -> ("local", N); ``dask://HOST:PORT`` -> ("dask", "tcp://HOST:PORT")."""
    if spec.startswith("local:"):
        n = spec.removeprefix("local:")
        if not n.isdigit() or int(n) < 1:
            raise ConfigurationError(f"--cluster {spec!r}: local:N needs N >= 1 worker processes")
        return "local", int(n)
    if spec.startswith("dask://"):
        address = spec.removeprefix("dask://")
        if ":" not in address:
            raise ConfigurationError(f"--cluster {spec!r}: dask://HOST:PORT (the scheduler's address)")
        return "dask", "tcp://" + address
    raise ConfigurationError(f"--cluster {spec!r}: dask://HOST:PORT or local:N")


def _connect(spec: str) -> tuple[Any, Any]:
    """A client (and the local cluster it owns, or None)."""
    distributed = require_dask()
    kind, where = parse_cluster(spec)
    if kind == "local":
        # workers are spawned processes: they find the package under test and the tools by PYTHONPATH
        path = [str(ROOT), str(TOOLS), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
        os.environ["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(path))
        import dask

        # the workers' statistical profiler samples the running session's stack every 10 ms, under the
        # GIL: it doubled a session's run time; a cluster's own workers are configured by their owner
        with dask.config.set({"distributed.worker.profile.enabled": False}):
            cluster = distributed.LocalCluster(
                n_workers=int(where),
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                silence_logs=50,
            )
        return distributed.Client(cluster), cluster
    try:
        client = distributed.Client(str(where), timeout=f"{CONNECT_TIMEOUT_S}s")
    except OSError as exc:
        raise EngineError(f"--cluster {spec}: no Dask scheduler answered at {where} ({exc})") from exc
    for name in TOOL_FILES:  # the workers have the package; the tools travel with the run
        client.upload_file(str(TOOLS / name), load=False)
    return client, None


def _lost(exc: BaseException) -> bool:
    """A worker died under the chunk (not the chunk's own error)."""
    from distributed import KilledWorker
    from distributed.comm.core import CommClosedError

    return isinstance(exc, KilledWorker | CommClosedError | ConnectionError)


def _run_dask(job: Job, spec: str, merger: Merger, on_accept: Callable[[int, Any, Any], None] | None) -> None:
    distributed = require_dask()
    client, cluster = _connect(spec)
    try:
        workers = max(1, sum(client.nthreads().values()))
        window = 4 * workers  # chunks in flight: keeps every worker busy and the scheduler small
        attempts = dict.fromkeys(range(job.chunks), 0)
        pending: Iterator[int] = iter(range(job.chunks))
        futures = distributed.as_completed()
        owner: dict[str, int] = {}

        def submit(k: int) -> None:
            attempts[k] += 1
            fut = client.submit(run_chunk, job, k, pure=False, key=f"chunk-{k}-{attempts[k]}-{os.getpid()}")
            owner[fut.key] = k
            futures.add(fut)

        for k in pending:
            submit(k)
            if futures.count() >= window:
                break
        for fut in futures:
            k = owner.pop(fut.key)
            if fut.status == "error":
                exc = fut.exception()
                if not _lost(exc) or attempts[k] >= CHUNK_ATTEMPTS:
                    first, n = job.span(k)
                    raise EngineError(
                        f"chunk {k} ({job.unit} {first}-{first + n - 1}) failed: {exc}"
                    ) from exc
                if k not in merger.accepted:
                    submit(k)  # its worker died: run it again elsewhere
                continue
            got_k, tally = fut.result()
            fut.release()
            if merger.accept(got_k, tally) and on_accept is not None:
                on_accept(got_k, merger.total, client)
            nxt = next(pending, None)
            if nxt is not None:
                submit(nxt)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
