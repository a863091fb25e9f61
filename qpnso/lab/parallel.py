"""Run independent study jobs on every core or on a Dask cluster, with a checkpoint.

A study is a list of jobs ``0 … n_jobs-1``; job ``i`` is a pure function of
``(i, seed)``: its random numbers come from :func:`job_rng`, a generator seeded
by ``np.random.SeedSequence(seed, spawn_key=(i,))``, so the results do not
depend on the number of workers nor on the order in which jobs finish.

:func:`run_jobs` runs the jobs that the checkpoint does not hold yet and appends
each result, as it completes, to ``OUT/checkpoint.jsonl`` (first line: a header
naming the study, seed, number of jobs and options; then one
``{"index": i, "result": {...}}`` per line).  A rerun with the same header skips
the finished jobs; a different header is refused (:class:`ConfigError`); a torn
last line (the process was killed while writing) is dropped.  A job that raises
stops the run with :class:`JobError` naming the job index and the error; the
finished jobs stay in the checkpoint.

Back ends: in-process (``workers=1``), a ``ProcessPoolExecutor`` whose
initialiser builds each worker's expensive state once, or a Dask distributed
cluster (``scheduler="tcp://host:port"``, or a ``distributed`` cluster object),
where the same state is built lazily on first use in each worker process.
"""

from __future__ import annotations

import json
import os
import traceback
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from qpnso.errors import ConfigError, JobError

CHECKPOINT = "checkpoint.jsonl"
"""Name of the checkpoint file inside the output folder."""


def job_seed_sequence(seed: int, index: int) -> np.random.SeedSequence:
    """The seed sequence of job ``index`` (independent of workers and scheduling)."""
    if seed < 0 or index < 0:
        raise ConfigError(f"seed and job index must be >= 0, got seed={seed}, index={index}")
    return np.random.SeedSequence(seed, spawn_key=(index,))


def job_rng(seed: int, index: int) -> np.random.Generator:
    """Random generator of job ``index`` of a study run with ``seed``."""
    return np.random.default_rng(job_seed_sequence(seed, index))


@dataclass(frozen=True)
class RunSpec:
    """What identifies a study run: a rerun resumes only when all of it matches.

    ``options`` must be JSON-serialisable (it is stored in the checkpoint header).
    """

    study: str
    n_jobs: int
    seed: int
    options: dict[str, Any] = field(default_factory=dict)

    def header(self) -> dict[str, Any]:
        return {"study": self.study, "n_jobs": self.n_jobs, "seed": self.seed, "options": self.options}


# ------------------------------------------------------------------ checkpoint
def _normalise(data: Any) -> Any:
    """``data`` as it reads back from JSON (tuples → lists), for header comparison."""
    return json.loads(json.dumps(data))


def read_checkpoint(out: Path, spec: RunSpec) -> dict[int, dict]:
    """Finished results ``{index: result}`` in ``out`` for ``spec``; {} if there is no checkpoint.

    Refuses (ConfigError) a checkpoint written for another study, seed, size or
    options.  Drops a torn last line and truncates the file after the last
    complete line so that new results append cleanly.
    """
    path = out / CHECKPOINT
    if not path.is_file():
        return {}
    raw = path.read_bytes()
    complete = raw[: raw.rfind(b"\n") + 1]
    if len(complete) != len(raw):
        with open(path, "r+b") as f:
            f.truncate(len(complete))
    lines = complete.decode().splitlines()
    if not lines:
        return {}
    try:
        header = json.loads(lines[0])["header"]
    except (ValueError, KeyError, TypeError):
        raise ConfigError(f"{path}: not a qpnso study checkpoint (no header line); use another --out") from None
    wanted = _normalise(spec.header())
    if header != wanted:
        diff = {k: (header.get(k), wanted[k]) for k in wanted if header.get(k) != wanted[k]}
        differences = ", ".join(f"{k}: {a!r} there, {b!r} asked" for k, (a, b) in diff.items())
        raise ConfigError(
            f"{out} holds a different run ({differences}); "
            "rerun with the same arguments to resume, or use another --out"
        )
    done: dict[int, dict] = {}
    for number, line in enumerate(lines[1:], start=2):
        try:
            row = json.loads(line)
            done[int(row["index"])] = row["result"]
        except (ValueError, KeyError, TypeError):
            raise ConfigError(f"{path}: line {number} is not a job result; use another --out") from None
    return {i: r for i, r in done.items() if 0 <= i < spec.n_jobs}


def _start_checkpoint(out: Path, spec: RunSpec) -> None:
    """Write the header line atomically (temp file + rename) if there is no checkpoint."""
    path = out / CHECKPOINT
    if path.is_file() and path.stat().st_size > 0:
        return
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{CHECKPOINT}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps({"header": spec.header()}) + "\n")
    os.replace(tmp, path)


class _Appender:
    """Appends one JSON line per finished job and flushes it."""

    def __init__(self, path: Path) -> None:
        self._f = open(path, "a", encoding="utf-8")

    def write(self, index: int, result: dict) -> None:
        self._f.write(json.dumps({"index": index, "result": result}) + "\n")
        self._f.flush()

    def close(self) -> None:
        self._f.close()


# ---------------------------------------------------------------------- jobs
def call_job(job: Callable[[int, int], dict], seed: int, index: int) -> tuple[int, dict]:
    """Run one job; any exception becomes a :class:`JobError` naming the index (picklable)."""
    try:
        return index, job(index, seed)
    except Exception as exc:  # noqa: BLE001 - reported with the job index, then re-raised in the parent
        tail = "".join(traceback.format_exception(exc)[-3:]).strip()
        raise JobError(f"job {index} failed: {type(exc).__name__}: {exc}\n{tail}") from None


def _in_process(job, seed: int, pending: list[int], init) -> Iterator[tuple[int, dict]]:
    if init is not None:
        init()
    for i in pending:
        yield call_job(job, seed, i)


def _pool(job, seed: int, pending: list[int], init, workers: int) -> Iterator[tuple[int, dict]]:
    with ProcessPoolExecutor(max_workers=workers, initializer=init) as pool:
        futures: set[Future] = {pool.submit(call_job, job, seed, i) for i in pending}
        try:
            while futures:
                finished, futures = wait(futures, return_when=FIRST_COMPLETED)
                for fut in sorted(finished, key=id):
                    yield fut.result()
        finally:
            for fut in futures:
                fut.cancel()
            pool.shutdown(wait=True, cancel_futures=True)


def _dask(job, seed: int, pending: list[int], scheduler: Any, spec: RunSpec) -> Iterator[tuple[int, dict]]:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ConfigError("--scheduler needs Dask: pip install 'qpnso[cluster]'") from None
    with Client(scheduler) as client:
        keys = [f"qpnso-{spec.study}-{spec.seed}-{spec.n_jobs}-{i}" for i in pending]
        futures = client.map(call_job, [job] * len(pending), [seed] * len(pending), pending, key=keys, pure=False)
        try:
            for fut in as_completed(futures):
                yield fut.result()
        finally:
            client.cancel(futures)


def run_jobs(
    spec: RunSpec,
    job: Callable[[int, int], dict],
    out: Path,
    init: Callable[[], None] | None = None,
    workers: int | None = None,
    scheduler: Any = None,
    progress: bool = False,
) -> list[dict]:
    """Run the jobs of ``spec`` not yet in ``out``'s checkpoint; all results by job index.

    ``job(index, seed) -> dict`` must be a picklable (module-level) function
    returning JSON-serialisable results; ``init()`` builds per-worker state
    (pool initialiser; called once in-process for ``workers=1``; Dask workers
    must build it lazily inside ``job``).  ``workers`` defaults to the number
    of cores.  ``progress`` draws a tqdm bar on stderr.
    """
    if spec.n_jobs < 1:
        raise ConfigError(f"a study needs at least one job, got {spec.n_jobs}")
    out = Path(out)
    done = read_checkpoint(out, spec)
    pending = [i for i in range(spec.n_jobs) if i not in done]
    if pending:
        _start_checkpoint(out, spec)
        n_workers = workers or os.cpu_count() or 1
        if n_workers < 1:
            raise ConfigError(f"workers must be >= 1, got {workers}")
        if scheduler is not None:
            stream = _dask(job, spec.seed, pending, scheduler, spec)
        elif n_workers == 1 or len(pending) == 1:
            stream = _in_process(job, spec.seed, pending, init)
        else:
            stream = _pool(job, spec.seed, pending, init, min(n_workers, len(pending)))
        _collect(stream, out / CHECKPOINT, done, spec, progress)
    return [done[i] for i in range(spec.n_jobs)]


def _collect(
    stream: Iterator[tuple[int, dict]], path: Path, done: dict[int, dict], spec: RunSpec, progress: bool
) -> None:
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=spec.n_jobs, initial=len(done), desc=spec.study, unit="job", mininterval=0.5)
    appender = _Appender(path)
    try:
        for index, result in stream:
            appender.write(index, result)
            done[index] = json.loads(json.dumps(result))  # exactly what a resumed run reads back
            if bar is not None:
                bar.update(1)
    except JobError as exc:
        raise JobError(f"study {spec.study} (seed {spec.seed}): {exc}") from None
    finally:
        appender.close()
        if bar is not None:
            bar.close()
