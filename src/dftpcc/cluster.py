"""Where the tiles of a map are coded: in this process, or on a dask.distributed cluster.

Tiles code independently (:func:`dftpcc.tiles.code_tile` is a pure function
of one tile's data), so a tiled map is a ``map`` over its tiles. :func:`executor`
gives that map: the built-in one, a :class:`distributed.LocalCluster` of
``workers`` processes, or a running scheduler at ``scheduler``. The results
are gathered in tile order, so the file is byte-identical whichever runs it.
Needs the optional ``distributed`` package (``pip install 'dftpcc[dask]'``).
"""

from __future__ import annotations

import functools
import logging
import multiprocessing
import os
import time
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

from ._optional import import_optional, install_hint
from .errors import ClusterError, DftpccError, InvalidInputError
from . import kernels
from .kernels import available_cores

__all__ = ["Map", "executor", "serial", "CONNECT_TIMEOUT_S", "NO_WORKER_TIMEOUT_S", "MAX_WORKERS_PER_CORE"]

INSTALL_HINT = install_hint("dask")
#: Seconds to wait for a scheduler to answer before giving up.
CONNECT_TIMEOUT_S = 10
#: Seconds a computation may wait with no worker at all before it is abandoned.
NO_WORKER_TIMEOUT_S = 30
#: How often the wait for results checks that workers are left, seconds.
POLL_S = 1.0
#: A local cluster has at most this many workers per core: each is a process of its own (a hundred
#: MB and a second to start), and more than a few per core only queue for the same cores; a
#: larger cluster is one on other machines, reached with ``scheduler``.
MAX_WORKERS_PER_CORE = 4
#: Seconds a stopped run gives its client and local cluster each to close (their workers are killed
#: first), so that the whole stop stays well within 10 s.
STOP_CLOSE_S = 1
#: Times the scheduler retries a task whose worker died before giving up on it (dask's
#: ``allowed-failures``): a tile that kills its workers fails the run quickly.
ALLOWED_FAILURES = 1

#: glibc's largest adaptive mmap threshold on 64-bit (``DEFAULT_MMAP_THRESHOLD_MAX``), bytes: what a
#: process that has freed a few large arrays works with; and its trim threshold then (twice that).
MMAP_THRESHOLD_BYTES = 32 * 1024 ** 2
#: ``mallopt`` parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3

#: Items of one map up to this many bytes in all go inside the task graph (rerun if their worker
#: dies); larger ones (blocks carrying their cells) are scattered to the workers first.
INLINE_BYTES = 1 << 20

#: ``map(func, items, *args)``: ``[func(item, *args) for item in items]``, in order.
Map = Callable[..., list]


def serial(func: Callable[..., Any], items: Sequence[Any], *args: Any) -> list:
    """The map of this process."""
    return [func(item, *args) for item in items]


def check_executor(workers: int | None, scheduler: str | None) -> None:
    """Refuse, before any work, workers and a scheduler together or a worker count below 1."""
    if workers is not None and scheduler is not None:
        raise InvalidInputError("give workers (a local cluster) or a scheduler address, not both")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise InvalidInputError(f"workers must be a whole number >= 1, got {workers!r}")
    if workers is not None and workers > MAX_WORKERS_PER_CORE * available_cores():
        raise InvalidInputError(
            f"workers {workers:,} is more than {MAX_WORKERS_PER_CORE} per core of the {available_cores()} this "
            f"process may use (at most {MAX_WORKERS_PER_CORE * available_cores()}): a larger cluster runs on other "
            f"machines; start a dask scheduler and workers there and give its address with --scheduler")
    if scheduler is not None and (not isinstance(scheduler, str) or not scheduler):
        raise InvalidInputError(f"scheduler must be an address such as tcp://host:8786, got {scheduler!r}")


@contextmanager
def executor(workers: int | None = None, scheduler: str | None = None, *, tiles: int | None = None) -> Iterator[Map]:
    """A map over tiles: serial by default, else on a local cluster or a running scheduler.

    ``tiles``, when known, is how many tiles the map has: a map of one tile (an untiled map is one)
    has nothing to share out, so it is mapped here and no cluster is started or reached.

    Raises
    ------
    MissingDependencyError
        ``distributed`` is not installed.
    ClusterError
        The scheduler cannot be reached, a worker died on a tile, or no
        worker is left: in a bounded time (:data:`CONNECT_TIMEOUT_S`,
        :data:`NO_WORKER_TIMEOUT_S`), never a hang.
    """
    check_executor(workers, scheduler)
    if (workers is None and scheduler is None) or (tiles is not None and tiles < 2):
        yield serial
        return
    distributed = import_optional("distributed", "dask", needed_for="parallel coding", name="dask.distributed")
    import dask  # distributed's own dependency
    # dask starts its workers with MALLOC_TRIM_THRESHOLD_ set, which turns off glibc's adaptive mmap
    # threshold: every large numpy temporary is then a fresh mapping, page-faulted in, and a tile
    # cost 1.6-2.4x the CPU time it costs here (measured on 4-tile blocks of a 4,824² GeoTIFF).
    environ = {key: value for key, value in dask.config.get("distributed.nanny.pre-spawn-environ", {}).items()
               if key != "MALLOC_TRIM_THRESHOLD_"}
    with dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES,
                          "distributed.comm.timeouts.connect": f"{CONNECT_TIMEOUT_S}s",
                          "distributed.nanny.pre-spawn-environ": environ}):
        cluster = client = None
        started = _local_clusters()
        children = {p.pid for p in multiprocessing.active_children()}
        stopped = False
        try:
            try:
                if scheduler is None:
                    # Processes, one thread each: the tiles' numpy work holds the GIL in places.
                    # No dashboard, and the scheduler's own HTTP server on a free port: on its default
                    # (8787) a second cluster on the machine made dask print three lines of warning.
                    cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                                       dashboard_address=None, silence_logs=logging.ERROR,
                                                       scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
                    client = distributed.Client(cluster, timeout=CONNECT_TIMEOUT_S)
                else:
                    client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S)
            except (OSError, TimeoutError, RuntimeError) as exc:  # RuntimeError: a local worker failed to start
                where = f"scheduler {scheduler}" if scheduler else f"a local cluster of {workers} workers"
                raise ClusterError(f"cannot reach {where} within {CONNECT_TIMEOUT_S} s: {exc}") from None
            yield lambda func, items, *args: _gather(client, func, items, args)
        except BaseException as exc:
            # A stop (SIGTERM, Ctrl-C) does not wait for the tiles at work, nor for a cluster still
            # starting: a graceful close waits for both, and took 10 s to 43 s. Their work is lost anyway.
            stopped = not isinstance(exc, Exception)
            raise
        finally:
            clusters = [cluster] if cluster is not None else []
            if not stopped:
                if client is not None:
                    client.close()
                for c in clusters:
                    c.close()
            else:  # the signal may have landed inside LocalCluster(), before it was ours
                _stop(client, clusters + [c for c in _local_clusters() - started if c is not cluster], children)


def _stop(client: Any, clusters: list, children: set[int]) -> None:
    """Close a client and local clusters at once on a stop: no restart, no waiting for tiles, no error
    logs for what is meant; their worker processes (this process's children since ``children``) killed."""
    logging.getLogger("distributed").setLevel(logging.CRITICAL)
    for c in clusters:
        for nanny in list(getattr(c, "workers", {}).values()):
            nanny.auto_restart = False
    _kill_new_children(children)
    for closing in ([client] if client is not None else []) + clusters:
        try:
            closing.close(timeout=STOP_CLOSE_S)
        except BaseException:  # noqa: BLE001 - its workers are killed; the stop goes on
            pass
    for c in clusters:  # else distributed closes it again at exit, waiting up to 10 s more
        c.shutdown_on_close = False
    _kill_new_children(children)


def _local_clusters() -> set:
    """The dask clusters of this process (distributed keeps a weak set of them)."""
    from distributed.deploy.spec import SpecCluster

    return set(getattr(SpecCluster, "_instances", ()))


def _kill_new_children(before: set[int]) -> None:
    """SIGKILL the processes this one started since ``before`` (pids): a local cluster's workers,
    which run their nannies in this process and are its multiprocessing children."""
    for child in multiprocessing.active_children():
        if child.pid not in before:
            child.kill()
            child.join(STOP_CLOSE_S)


def _cancelled() -> tuple[type[BaseException], ...]:
    """The exceptions of a future the cluster gave up on (their names vary across distributed releases)."""
    import distributed.client as dc
    return tuple(getattr(dc, name) for name in ("FutureCancelledError", "FuturesCancelledError") if hasattr(dc, name))


def _nbytes(item: Any) -> int:
    """Bytes an item holds, its fields' for an object (dask's ``sizeof`` sees an object's shell only)."""
    from dask.sizeof import sizeof

    return sizeof(vars(item)) if hasattr(item, "__dict__") else sizeof(item)


@functools.cache
def _adaptive_heap() -> None:
    """Undo, in a worker started with ``MALLOC_TRIM_THRESHOLD_`` (dask's nanny sets it in every
    worker it starts, ``dask worker`` on the command line too), what that variable does to glibc:
    it freezes the mmap threshold at 128 kB, so every large temporary of a tile is a fresh mapping,
    page-faulted in and unmapped. The thresholds are set to where glibc's adaptive ones end up
    after the first large arrays are freed. Measured on the 20,000² compress with one
    ``dask worker``: 41 s of system time instead of 9 s (116 against 81 CPU seconds)."""
    if "MALLOC_TRIM_THRESHOLD_" not in os.environ:
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
        libc.mallopt(_M_TRIM_THRESHOLD, 2 * MMAP_THRESHOLD_BYTES)
    except (OSError, AttributeError):  # not glibc: the variable means nothing there
        pass


def _task(func: Callable[..., Any], item: Any, *args: Any) -> Any:
    """``func(item, *args)`` on a worker. The library's own errors go back to the client without the
    errors of other libraries they were raised from: dask pickles that chain too, and some do not
    unpickle (GDAL's), so the client got a bare ``Exception`` (and the command a traceback)."""
    _adaptive_heap()
    try:
        return func(item, *args)
    except DftpccError as exc:
        error = exc
    error.__cause__ = error.__context__ = None
    raise error


def _gather(client: Any, func: Callable[..., Any], items: Sequence[Any], args: tuple) -> list:
    """``func(item, *args)`` for every item on the cluster, in order; a dead worker or an empty
    cluster ends in :class:`ClusterError`."""
    import distributed

    # The tiles' data travel to the workers as data, not inside the task graph; the arguments every
    # item shares (a raster to read from, the base layer) travel once to each worker, not once a task.
    # Keys of their own (hash=False): data scattered under a content key by the previous call may
    # still be being forgotten by the scheduler, and a task then waits for data no worker has.
    shared = client.scatter(list(args), broadcast=True, hash=False) if args else []
    # Items that carry cells travel as data; small ones (a block a worker reads itself) travel in the
    # graph, so that the scheduler can rerun the task of a worker that died: scattered data die with it.
    small = sum(_nbytes(item) for item in items) <= INLINE_BYTES
    # The function carries the client's backend: a worker, a process of its own, ran numpy's kernels
    # where the client ran the compiled ones.
    futures = client.map(functools.partial(_task, kernels.carried(func)), list(items) if small else client.scatter(list(items), hash=False),
                         *[[a] * len(items) for a in shared], pure=False)
    idle_since: float | None = None
    cancelled = _cancelled()
    try:
        while True:
            try:
                distributed.wait(futures, timeout=POLL_S)
                break
            except TimeoutError:  # not all done yet: check that someone is working on them
                pass
            if any(f.status == "error" for f in futures):
                break  # gather raises it below
            pending = [f for f in futures if f.status == "pending"]
            workers = client.scheduler_info().get("workers", {})
            if workers:
                idle_since = None
            elif idle_since is None:
                idle_since = time.monotonic()
            elif time.monotonic() - idle_since > NO_WORKER_TIMEOUT_S:
                raise ClusterError(f"no dask worker left for {NO_WORKER_TIMEOUT_S} s with {len(pending)} tile(s) "
                                   f"to code; nothing was written")
        return client.gather(futures)
    except cancelled as exc:
        # The scheduler forgets a tile whose worker died past the allowed failures.
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ClusterError(f"a dask worker died or the cluster dropped a tile ({first}); nothing was written") from None
    except distributed.KilledWorker as exc:
        raise ClusterError(f"a dask worker died while coding a tile ({exc}); nothing was written") from None
    except (OSError, TimeoutError) as exc:
        raise ClusterError(f"lost the dask scheduler: {exc}; nothing was written") from None
    finally:
        client.cancel(futures)
