"""Running many independent tasks: a local pool of spawned processes, or a Dask cluster.

`run_tasks(fn, items, ...)` calls ``fn(item)`` for every item on `workers` local processes (a
``ProcessPoolExecutor`` with the ``spawn`` start method, so that no worker inherits the caller's
JAX, Mitsuba or thread state) or, given a ``dask.distributed`` Client, as tasks on its workers; it
yields ``(item, result)`` as the tasks finish (in any order). A task that returns no result is not
raised: its result is a `Failure` (the exception's line and traceback, or what happened to its
worker), so that the caller decides whether one failure ends the run (`vdo.calib.montecarlo`) or
is recorded while the others go on (`vdo sweep`); `TaskFailed` is the one-line error of a
caller that ends.

What every task needs alike (a geometry, a load path) goes to each worker once, not with every
task: `run_tasks(..., shared=obj)` calls ``fn(obj, item)``, `obj` pickled into each local
worker's start-up arguments, or scattered to every Dask worker once (``Client.scatter``,
broadcast) and handed to each task as a reference.

Each worker sets itself up once, before its first task (`configure_worker`: `vdo.core.configure`
with `threads` Dr.Jit threads, and one XLA:CPU thread when `threads` is 1), so that the workers
of one machine share its cores instead of each taking all of them. A local worker also leaves
when the process that started it is gone (a killed run leaves no worker computing). A task whose
local worker process dies (killed, out of memory) is tried again in a fresh pool, `MAX_ATTEMPTS`
times in all; on Dask the scheduler retries lost workers itself and a task it gives up on
(``KilledWorker``) is a `Failure`.

When the caller stops iterating (an error, Ctrl-C, a time limit), the pool is shut down at once:
queued tasks are cancelled, and a running one is not awaited (its worker leaves when it ends, or
when this process does), or every unfinished task is cancelled (Dask). `fn` and the items must
be picklable: `fn` a module's top-level function.

`blas_threads(n)` runs a block with n OpenBLAS threads, so that small solves are not slowed by
threads fighting over loaded cores, and so that the block computes the same in every process that
started with the same OpenBLAS thread count: a local worker inherits this process's; a Dask
worker starts with 1 unless its environment says otherwise (`blas_environment`).

dask and distributed are imported only inside the functions that need them.
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing
import os
import shutil
import tempfile
import threading
import time
import traceback
import uuid
from collections import Counter
from contextlib import contextmanager
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

from vdo.core import interrupts
from vdo.core.errors import ConfigError

MAX_ATTEMPTS = 3           # a task whose local worker process dies is tried this many times
WATCH_S = 0.5              # a local worker checks this often whether its parent is gone
_SHARED: list = []         # a local worker's `shared` object of `run_tasks` (none: empty)


class TaskFailed(RuntimeError):
    """A task that returned no result, for a caller whose run ends with it: one line naming the
    task (`what`, e.g. "load path step 7") and its `Failure`'s error, the worker's traceback kept
    in `traceback`. The command line prints the line and exits with status 1."""

    def __init__(self, what: str, failure: "Failure"):
        self.what, self.traceback = what, failure.traceback
        super().__init__(f"{what}: {failure.error}")


@dataclass(frozen=True)
class Failure:
    """A task that returned no result: `error` one line ("ValueError: message", or what happened
    to its worker), `traceback` the worker's traceback text ("" when the task raised nothing)."""

    error: str
    traceback: str = ""


def cores() -> int:
    """The CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def configure_worker(threads: int | None) -> None:
    """Set up a worker process once, before its first task (`vdo.core.configure`): float64 in
    JAX, the compilation cache, freed memory kept in the heap, and `threads` CPU threads for
    Dr.Jit (and one for XLA:CPU when `threads` is 1; None: all the cores)."""
    if threads == 1:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                                   + " --xla_cpu_multi_thread_eigen=false").strip()
    from vdo.core.configure import configure

    configure(threads=threads)


def _local_worker(threads: int | None, shared: tuple = ()) -> None:
    """Initializer of the local pool's workers: leave when the parent process is gone, then
    `configure_worker`, and keep `run_tasks`' `shared` object (a tuple of it, or empty)."""
    _SHARED[:] = shared
    parent = os.getppid()

    def watch():
        while os.getppid() == parent:
            time.sleep(WATCH_S)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="vdo-parent-watch").start()
    configure_worker(threads)


def call(fn: Callable, item, shared: tuple = ()):
    """``fn(*shared, item)`` in a worker, or the `Failure` of the exception it raised (a
    KeyboardInterrupt is not caught: it ends the run)."""
    try:
        return fn(*shared, item)
    except Exception as exc:
        return Failure(f"{type(exc).__name__}: {exc}", traceback.format_exc())


def _call_local(fn: Callable, item):
    """`call` in a local worker, with the `shared` object its initializer kept."""
    return call(fn, item, tuple(_SHARED))


def run_tasks(fn: Callable, items: Iterable, *, workers: int | None = None, threads: int | None = None,
              client=None, keys: Sequence[str] | None = None, name: str = "vdo",
              shared=None) -> Iterator[tuple]:
    """Yield ``(item, fn(item))`` for every item as the tasks finish, a `Failure` in place of a
    result that did not come (module docstring). Without `client`: a local pool of `workers`
    spawned processes (default: one per core, never more than there are items); with a
    ``distributed.Client``: its workers, each task under the Dask key ``keys[i]`` (default
    ``{name}-<random>-{i}``). `threads`: each worker's CPU threads (`configure_worker`).
    `shared` (not None): sent to each worker once and passed first, ``fn(shared, item)``."""
    items = list(items)
    if not items:
        return
    extra = () if shared is None else (shared,)
    if client is not None:
        if keys is None:
            token = uuid.uuid4().hex[:12]
            keys = [f"{name}-{token}-{i}" for i in range(len(items))]
        yield from _dask(fn, items, client, threads, list(keys), name, extra)
    else:
        yield from _local(fn, items, workers or cores(), threads, extra)


def run_chunks(fn: Callable, chunks: Sequence, workers: int, log: logging.Logger, total: int,
               desc: str, unit: str) -> None:
    """fn(chunk) for every chunk, on `workers` threads of this process (for work whose heavy calls
    release the GIL: NumPy, SciPy, XLA), each call's return value (the items it did) advancing a
    progress bar of `total` `unit`s (`vdo.core.progress.bar`: shown when `log` passes INFO
    records). Ctrl-C: the chunks not started are dropped, the running ones end."""
    from concurrent.futures import ThreadPoolExecutor

    from vdo.core.progress import bar as progress_bar

    bar = progress_bar(log, total=total, desc=desc, unit=unit)
    pool = ThreadPoolExecutor(min(int(workers), len(chunks))) if workers > 1 and len(chunks) > 1 else None
    try:
        for done in (pool.map(fn, chunks) if pool else map(fn, chunks)):
            bar.update(done)
    finally:
        if pool:
            pool.shutdown(wait=True, cancel_futures=True)
        bar.close()


def _local(fn, items: list, workers: int, threads: int | None, shared: tuple):
    attempts = Counter()
    pending = list(range(len(items)))
    while pending:
        pool = ProcessPoolExecutor(max_workers=min(workers, len(pending)),
                                   mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_local_worker, initargs=(threads, shared))
        ended = False
        try:
            futures = {pool.submit(_call_local, fn, items[i]): i for i in pending}
            pending = []
            for future in as_completed(futures):
                i = futures[future]
                try:
                    result = future.result()
                except BrokenProcessPool:
                    attempts[i] += 1
                    if attempts[i] < MAX_ATTEMPTS:
                        pending.append(i)
                        continue
                    result = Failure(f"its worker process died {MAX_ATTEMPTS} times (out of memory?)")
                yield items[i], result
            ended = True
        finally:   # stopped early (Ctrl-C, an error): no wait for the running tasks; each worker
            pool.shutdown(wait=ended, cancel_futures=True)   # leaves after its task or with us


def _dask(fn, items: list, client, threads: int | None, keys: list, name: str, shared: tuple):
    from distributed import as_completed as dask_completed
    from distributed.diagnostics.plugin import WorkerPlugin

    class Setup(WorkerPlugin):
        def setup(self, worker):
            configure_worker(threads)

    client.register_plugin(Setup(), name=f"{name}-setup")
    # a scattered object's reference, resolved on the worker (inside the tuple too)
    scattered = [client.scatter(s, broadcast=True, hash=False) for s in shared]
    futures = {client.submit(call, fn, item, tuple(scattered), key=key, pure=False): i
               for i, (item, key) in enumerate(zip(items, keys))}
    try:
        for future in dask_completed(futures):
            try:
                result = future.result()
            except Exception as exc:  # KilledWorker, a worker lost for good: the task failed
                result = Failure(f"Dask: {type(exc).__name__}: {exc}")
            yield items[futures[future]], result
    finally:
        unfinished = [f for f in futures if not f.done()]
        if unfinished:
            client.cancel(unfinished)


def connect_dask(address: str, workers: int, timeout: float, scratch: Path, env: dict | None = None):
    """(a dask.distributed Client on `address`, its LocalCluster or None): "local" starts a
    LocalCluster of `workers` spawned processes with one task each (scratch files in `scratch`,
    the environment variables `env` set in the workers); ConfigError (field --dask) when the
    scheduler cannot be reached within `timeout` s."""
    from distributed import Client, LocalCluster

    if address == "local":
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=None, local_directory=str(scratch),
                               silence_logs=logging.ERROR, **({"env": env} if env else {}))
        return Client(cluster), cluster
    try:
        return Client(address, timeout=f"{timeout}s"), None
    except Exception as exc:  # refused, timed out, or something else answering: one line each
        why = (type(exc).__name__ if isinstance(exc, (OSError, TimeoutError))
               else f"what answered is not a Dask scheduler: {type(exc).__name__}")
        raise ConfigError("--dask", "", f"cannot reach the Dask scheduler at {address!r} within "
                                        f"{timeout:g} s ({why}); check the address "
                                        "(tcp://HOST:PORT) and that the scheduler runs") from None


@contextmanager
def dask_client(address: str | None, workers: int, timeout: float = 30.0, prefix: str = "vdo-dask-",
                env: dict | None = None):
    """A Client for the time of the block (`connect_dask`; "local": a LocalCluster of `workers`
    processes with the environment variables `env`, its scratch in a temporary folder removed
    after, also by an interrupt that ends the process at once: `vdo.core.interrupts.register`),
    or None when `address` is None. The client (and the cluster) are closed when the
    block ends, however it ends."""
    if address is None:
        yield None
        return
    scratch = Path(tempfile.mkdtemp(prefix=prefix))
    interrupts.register(scratch)        # removed too when an interrupt ends the process at once
    client = cluster = None
    try:
        client, cluster = connect_dask(address, workers, timeout, scratch, env)
        yield client
    finally:
        for c in (client, cluster):
            if c is not None:
                c.close()
        shutil.rmtree(scratch, ignore_errors=True)
        interrupts.unregister(scratch)


def _openblas_controls() -> list[tuple]:
    """(get, set) thread-count functions of every OpenBLAS this process has loaded (numpy's and
    SciPy's each bundle one; their symbols may carry a "scipy_" prefix and a "64_" suffix), found
    in /proc/self/maps; empty where that does not exist (not Linux) or no OpenBLAS is loaded."""
    try:
        with open("/proc/self/maps") as fh:
            paths = sorted({line.split()[-1] for line in fh
                            if len(line.split()) >= 6 and "openblas" in line.split()[-1].lower()})
    except OSError:
        return []
    controls, seen = [], set()
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix in ("openblas", "scipy_openblas"):
            for suffix in ("", "64_"):
                get = getattr(lib, f"{prefix}_get_num_threads{suffix}", None)
                put = getattr(lib, f"{prefix}_set_num_threads{suffix}", None)
                address = get is not None and ctypes.cast(get, ctypes.c_void_p).value
                if put is not None and address and address not in seen:
                    seen.add(address)
                    controls.append((get, put))
    return controls


def blas_environment() -> dict:
    """{"OPENBLAS_NUM_THREADS": this process's OpenBLAS thread count}, for worker processes that
    must compute as this one does ({} when no OpenBLAS is found). OpenBLAS' results depend on the
    thread count it started with, even inside `blas_threads` (a 300 x 300 product differed in its
    last bits between a process started with 2 threads and set to 1 and one started with 1), and
    a Dask worker starts with 1 unless told."""
    counts = [get() for get, _ in _openblas_controls()]
    return {"OPENBLAS_NUM_THREADS": str(max(counts))} if counts else {}


@contextmanager
def blas_threads(count: int):
    """Run the block with `count` threads in every loaded OpenBLAS (module docstring), the
    earlier counts restored after it. Other BLAS libraries (MKL, Accelerate) are left alone."""
    controls = _openblas_controls()
    before = [get() for get, _ in controls]
    for _, put in controls:
        put(count)
    try:
        yield
    finally:
        for (_, put), n in zip(controls, before):
            put(n)
