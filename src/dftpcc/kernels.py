"""Kernel backends: the stages' inner loops on numpy, or compiled (numba), with the same bytes.

A :class:`Backend` is a value chosen once per call (:func:`use`: ``dftpcc.compress``,
``dftpcc.decompress`` and the file functions choose it, or take the caller's ``backend=``) and
read by every kernel the call runs (:func:`current`), the way :mod:`decimal` carries its context:
the stages take no backend argument and hold no ``if compiled:``. Each stage keeps both
implementations of its kernels side by side, the numpy one decorated with :func:`kernel` naming
its compiled twin (a function of :mod:`dftpcc._compiled`, which holds the numba code, or one
beside it in the stage when it needs the stage's tables). A compiled implementation may decline
an input (``NotImplemented``: a dtype or an edge case where its bits could differ) and the numpy one
runs.

Both backends write the same bytes, bit for bit (``tests/test_kernels.py``, ``DFTPCC_JIT=1
scripts/digests.py``): the compiled kernels do numpy's float operations in numpy's order, its
pairwise summation included, and code with constriction's ANS coder, its probabilities
quantized as constriction quantizes them. So the choice is one of speed alone:

- numba installed (the ``fast`` extra) and a call large enough to pay for loading it (a compress of
  at least :data:`COMPILED_MIN_POINTS` points, a decompress of a map of at least
  :data:`COMPILED_MIN_MAP_CELLS` rebuilt cells), or the compiled kernels already loaded in this process (a second
  call, a :class:`~dftpcc.mapbuilder.MapBuilder`, :func:`load`): compiled. A fresh process pays for
  numba's import and the first call of each kernel (0.2-0.3 s with numba's cache warm, seconds on a
  machine's very first run, while numba compiles into its cache beside the package or in
  ``NUMBA_CACHE_DIR``), and a kernel saves some tens of nanoseconds a point: smaller calls do not earn
  that back (``benchmarks/bench_backend.py``).
- otherwise numpy.
- ``DFTPCC_JIT=0`` or ``1`` overrides that choice (``1``: compiled wherever numba is installed);
  a caller's explicit ``backend=`` overrides both.

As the compiled kernels release the GIL, a stage of a map can run on another core beside the
caller's work on the same map (:class:`Side`: the occupancy mask while the spectrum is coded or
decoded), with the same bytes.
"""

from __future__ import annotations

import contextvars
import enum
import functools
import importlib.util
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from types import ModuleType
from typing import Any, Callable, Iterator

from ._optional import import_optional
from .errors import InvalidInputError

__all__ = ["Backend", "use", "current", "load", "carried", "rows_of", "kernel", "Kernel", "compiled_module", "Side", "CORES",
           "SIDE_MIN_CELLS", "COMPILED_MIN_POINTS", "COMPILED_MIN_MAP_CELLS", "JIT_VARIABLE",
           "available_cores"]

#: The environment variable that overrides the automatic choice: ``0`` numpy, ``1`` compiled.
JIT_VARIABLE = "DFTPCC_JIT"

#: A compress of at least this many points takes the compiled backend in a process that has not
#: loaded it yet. Measured (``benchmarks/bench_backend.py --quick``, each call in a fresh process, CPU
#: time, a machine at load 21-27 on 2 cores): on crops of the 2.8 M-point forest the compiled backend's
#: import and first calls cost 0.65 s more and it saves 66 ns a point: even at 9.8 M points. The
#: field's crops (0.7 M points at most, so a longer extrapolation) put it at 3.8 M; the forest's line,
#: which reaches closer, is the one taken.
COMPILED_MIN_POINTS = 10_000_000
#: The same for a decompress, counting the cells it rebuilds (a header's cell count, which the reader
#: bounds by the file's size; not its point count, which a crafted header may set to anything): decoding
#: the forest saved 31 ns an original point, 3.6 of them a rebuilt cell (the same run's 58.9 against
#: 16.3 M points/s), so about 110 ns a cell against the same 0.62 s to load: even at 5.5 M cells.
COMPILED_MIN_MAP_CELLS = 5_500_000

#: :mod:`dftpcc._compiled` once loaded; whether a load was tried; whether numba can be found.
_state: dict[str, Any] = {"module": None, "tried": False, "found": None}
_load_lock = threading.Lock()


class Backend(enum.Enum):
    """Where the kernels run: ``NUMPY`` (always there) or ``COMPILED`` (numba, the ``fast`` extra)."""

    NUMPY = "numpy"
    COMPILED = "compiled"

    def is_available(self) -> bool:
        """Whether this backend can run in this process (numba is looked up, not imported)."""
        if self is Backend.NUMPY or _state["module"] is not None:
            return True
        if _state["tried"]:  # numba is there but failed to import
            return False
        if _state["found"] is None:
            _state["found"] = importlib.util.find_spec("numba") is not None
        return bool(_state["found"])

    @classmethod
    def detect_available(cls) -> tuple[Backend, ...]:
        """The backends that can run here, numpy first."""
        return tuple(b for b in cls if b.is_available())

    @classmethod
    def default(cls, work: int | None = None, *, min_work: int | None = None) -> Backend:
        """The backend a call of ``work`` points takes when its caller names none (see the module's
        docstring): compiled from ``min_work`` points on (:data:`COMPILED_MIN_POINTS` by default);
        ``work=None``: a call of unknown size, compiled only once loaded."""
        jit = os.environ.get(JIT_VARIABLE, "").strip()
        if jit == "0":
            return cls.NUMPY
        large = work is not None and work >= (COMPILED_MIN_POINTS if min_work is None else min_work)
        # A small call looks nothing up (finding numba costs a call more than it decodes in a small map).
        if (jit == "1" or _state["module"] is not None or large) and cls.COMPILED.is_available():
            return cls.COMPILED if _load() else cls.NUMPY  # loaded: its import is paid already
        return cls.NUMPY

    @classmethod
    def of(cls, value: Backend | str) -> Backend:
        """``value`` as a backend: a member, or its name (``"numpy"``, ``"compiled"``)."""
        if isinstance(value, cls):
            return value
        try:
            return cls(str(value).lower())
        except ValueError:
            raise InvalidInputError(f"backend must be one of {', '.join(b.value for b in cls)}; "
                                    f"got {value!r}") from None


def _load() -> bool:
    """Import the compiled kernels once (numba's import: a few tenths of a second); True if they load."""
    with _load_lock:
        if not _state["tried"]:
            _state["tried"] = True
            try:
                from . import _compiled
            except ImportError:
                _state["module"] = None
            else:
                _state["module"] = _compiled
    return _state["module"] is not None


def load() -> bool:
    """Load the compiled kernels, so that every later call in this process takes them by default
    (a long-running program: a :class:`~dftpcc.mapbuilder.MapBuilder` does); True if they are in use.

    Idempotent; ``DFTPCC_JIT=0`` makes it a no-op that returns False.
    """
    if os.environ.get(JIT_VARIABLE, "").strip() == "0" or not Backend.COMPILED.is_available():
        return False
    return _load()


def compiled_module() -> ModuleType:
    """:mod:`dftpcc._compiled`, loaded now if need be.

    Raises
    ------
    MissingDependencyError
        numba (the ``fast`` extra) is not installed.
    """
    if not _load():
        import_optional("numba", "fast", needed_for="the compiled backend")
        from . import _compiled  # numba imports, but the kernels do not: say why, in the import's words

        return _compiled
    return _state["module"]


#: The backend of the call running in this context (None outside every :func:`use`).
_active: contextvars.ContextVar[Backend | None] = contextvars.ContextVar("dftpcc_backend", default=None)


def current() -> Backend:
    """The backend of the call in progress, or :meth:`Backend.default` outside every :func:`use`."""
    active = _active.get()
    return Backend.default() if active is None else active


@contextmanager
def use(backend: Backend | str | None = None, *, work: int | None = None,
        min_work: int | None = None) -> Iterator[Backend]:
    """Inside: every kernel runs on ``backend``, chosen once here.

    Parameters
    ----------
    backend : Backend or {'numpy', 'compiled'}, optional
        The caller's choice; None: the enclosing call's backend, or :meth:`Backend.default` of ``work``.
    work : int, optional
        Points the call handles, for the default: compiled from ``min_work`` on.
    min_work : int, optional
        :data:`COMPILED_MIN_POINTS` (compress, the default), or :data:`COMPILED_MIN_MAP_CELLS` (decompress).

    Raises
    ------
    InvalidInputError
        ``backend`` names no backend.
    MissingDependencyError
        ``backend`` is compiled and numba is not installed.
    """
    if backend is None:
        active = _active.get()
        chosen = Backend.default(work, min_work=min_work) if active is None else active
    else:
        chosen = Backend.of(backend)
        if chosen is Backend.COMPILED:
            compiled_module()  # a missing numba fails here, before any work
    token = _active.set(chosen)
    try:
        yield chosen
    finally:
        _active.reset(token)


def carried(func: Callable[..., Any]) -> Callable[..., Any]:
    """``func`` bound to the backend of the call in progress: called in another process (a dask
    worker, where this process's choice does not reach), it runs on that backend there too."""
    return functools.partial(_on_backend, current(), func)


def _on_backend(backend: Backend, func: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    with use(backend):
        return func(*args, **kwargs)


def rows_of(points: Any) -> int | None:
    """The rows of an array (the ``work`` of a cloud, for :func:`use`), None for anything else: the
    call's own checks refuse what is not a cloud, with their messages."""
    shape = getattr(points, "shape", None)
    return int(shape[0]) if shape else None


class Kernel:
    """A stage's kernel: its numpy implementation and its compiled twin, run on :func:`current`'s backend.

    ``compiled``: the name of a function of :mod:`dftpcc._compiled` (called with ``bound`` as keyword
    arguments too: the codec's constants it takes), or a function beside the numpy one in the stage.
    The compiled implementation returns ``NotImplemented`` for an input it declines; the numpy one
    then runs.
    """

    def __init__(self, numpy: Callable[..., Any], compiled: str | Callable[..., Any], **bound: Any):
        self.numpy = numpy
        self._compiled = compiled
        self._bound = bound
        functools.update_wrapper(self, numpy)

    def compiled(self, *args: Any, **kwargs: Any) -> Any:
        """The compiled implementation's result, or ``NotImplemented`` where it declines."""
        if callable(self._compiled):
            return self._compiled(*args, **kwargs)
        return getattr(compiled_module(), self._compiled)(*args, **kwargs, **self._bound)

    def on(self, backend: Backend) -> Callable[..., Any]:
        """The implementation ``backend`` runs."""
        return _RUNS[backend](self)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return _RUNS[current()](self)(*args, **kwargs)

    def _compiled_or_numpy(self, *args: Any, **kwargs: Any) -> Any:
        found = self.compiled(*args, **kwargs)
        return self.numpy(*args, **kwargs) if found is NotImplemented else found


#: What each backend runs of a kernel.
_RUNS: dict[Backend, Callable[[Kernel], Callable[..., Any]]] = {
    Backend.NUMPY: lambda k: k.numpy,
    Backend.COMPILED: lambda k: k._compiled_or_numpy,
}


def kernel(compiled: str | Callable[..., Any], **bound: Any) -> Callable[[Callable[..., Any]], Kernel]:
    """Decorate a numpy implementation with its compiled twin: see :class:`Kernel`."""
    return lambda numpy: Kernel(numpy, compiled, **bound)


#: Cores one map's coding may use at once; None: every core this process may run on
#: (:func:`available_cores`). 1 keeps every stage in the caller's thread.
CORES: int | None = None

#: A stage runs beside the caller only on grids of at least this many cells, where a patchy mask's
#: coder takes milliseconds (2.4-2.8 ms at 512 x 512 here, against 0.6-0.8 ms at 256 x 256 and 30-40 us
#: for a thread's hand-over): smaller maps, zarr chunks among them, have little to gain.
SIDE_MIN_CELLS = 1 << 18

_pool: dict[str, ThreadPoolExecutor] = {}
_pool_lock = threading.Lock()


def available_cores() -> int:
    """The cores this process may run on (``os.sched_getaffinity``, so ``taskset`` counts)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _cores() -> int:
    return available_cores() if CORES is None else max(1, int(CORES))


class Side:
    """``fn(*args)`` run on a thread of its own, beside the caller's work on the same map, or at once.

    Beside the caller when the call's backend is compiled (its kernels release the GIL for their whole
    pass; numpy's many short passes and constriction's calls would mostly wait for each other),
    the process may use more than one core (:data:`CORES`) and the grid has at least
    :data:`SIDE_MIN_CELLS` cells; otherwise ``fn`` runs at once, in the caller's thread, as a serial
    coder would. Either way :meth:`result` gives its value or raises its error: the bytes do not
    depend on where it ran. The occupancy mask's coder is the stage that runs so (its own
    arrays, nothing shared with the spectrum's): ``encoder`` and ``decoder`` use it.
    """

    def __init__(self, fn: Callable[..., Any], *args: Any, cells: int):
        cores = _cores() if current() is Backend.COMPILED and cells >= SIDE_MIN_CELLS else 1
        self._future: Future | None = None
        self._left = cores - 1
        if cores > 1:
            # In the caller's context: the thread runs the kernels on the call's backend.
            self._future = _executor().submit(contextvars.copy_context().run, fn, *args)
        else:
            self._value = fn(*args)

    def cores_left(self) -> int | None:
        """The cores the caller's own work may use now: all but this stage's while it runs, None
        (no limit) once it is done or when it ran at once. For :func:`dftpcc.spectrum.fft_workers`,
        which asks before each transform: a map whose mask codes in no time (a full raster) keeps
        every core for its transforms."""
        return None if self._future is None or self._future.done() else self._left

    def result(self) -> Any:
        """``fn(*args)``, waiting for it if it runs beside; its exception if it raised one."""
        return self._value if self._future is None else self._future.result()


if hasattr(os, "register_at_fork"):  # a forked child has none of the pool's threads: it makes its own
    os.register_at_fork(after_in_child=_pool.clear)


def _executor() -> ThreadPoolExecutor:
    # One pool for the process; several callers (zarr's chunk threads) may each have a stage beside.
    with _pool_lock:
        if "pool" not in _pool:
            _pool["pool"] = ThreadPoolExecutor(max_workers=max(2, os.cpu_count() or 2),
                                               thread_name_prefix="dftpcc-side")
        return _pool["pool"]
