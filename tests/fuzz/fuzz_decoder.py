"""Fuzz the ``.dftpc`` decoder: any bytes must decode or raise a dftpcc error.

For every input the decoder must (docs/errors.md, "Fuzzing"):

* raise nothing but :class:`dftpcc.DftpccError` subclasses (no IndexError,
  no struct.error, no OverflowError, no MemoryError ...);
* decode to finite points when it does not raise;
* finish within :data:`TIME_LIMIT_S` (a campaign) or within a number of
  Python events (the CI test, which must not depend on the machine's speed:
  see tests/workbound.py);
* allocate at most :data:`DECODE_BYTES_PER_CELL` per cell of the grid the
  header was validated to have, plus a few bytes per input byte.

The first byte of an input is a mode: bit 0 recomputes every checksum of
the rest (a crafted file rather than a damaged one, so mutations reach the
checks behind the CRCs), bit 1 decodes progressively from a prefix
(``max_bytes``), bit 2 also decodes at a larger cutoff, bit 3 decodes only
a region (``bbox``, the corner of the map the high four bits choose). A
tiled (1.1) map refuses a prefix and a cutoff: bits 1 and 2 apply to it only
when the high bits are all set, so most tiled inputs reach the tiles.

The allowed allocation of a tiled map is per cell of what the file can
justify (:func:`dftpcc.format.validate.cells_allowed` of its size, at most its
grid), not of its grid, which may reach 2**36 cells.

Two engines share :func:`check`:

``python tests/fuzz/fuzz_decoder.py --iterations 100000 [--seed N] [--report FILE]``
    Built-in structure-aware mutator over the seed maps (tests/fuzz/seeds.py);
    needs nothing beyond the test dependencies. The CI test runs it bounded.
``python tests/fuzz/fuzz_decoder.py --atheris [libFuzzer flags] [CORPUS_DIR]``
    Coverage-guided atheris/libFuzzer (``pip install -e .[fuzz]``), seeded
    with the same maps; e.g. ``-atheris_runs=100000 -timeout=1 -rss_limit_mb=4096``.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import os
import random
import resource
import signal
import struct
import sys
import time
import tracemalloc
import traceback
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

if __name__ == "__main__" and "--atheris" in sys.argv:  # pragma: no cover - needs atheris
    # Coverage feedback from dftpcc's own code only: instrumenting numpy and
    # scipy as well would make start-up take a minute for no useful signal.
    import atheris

    with atheris.instrument_imports(include=["dftpcc"]):
        import dftpcc  # noqa: F401

try:  # as part of the test package, or run as a script from this folder
    from . import craft
    from ..workbound import WorkLimitExceeded, measure_work
    from .seeds import legacy_files, seed_files
except ImportError:  # pragma: no cover - script mode
    sys.path[:0] = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parents[1])]
    import craft  # type: ignore[no-redef]
    from seeds import legacy_files, seed_files  # type: ignore[no-redef]
    from workbound import WorkLimitExceeded, measure_work  # type: ignore[no-redef]

import dftpcc
from dftpcc import format as fmt
from dftpcc import limits

#: No input may take longer to decode (seconds).
TIME_LIMIT_S = 1.0
#: An input still running after this many seconds is aborted as a hang.
WATCHDOG_S = 10.0
#: Allowed allocation: per cell of the validated grid ...
DECODE_BYTES_PER_CELL = limits.DECODE_BYTES_PER_CELL
#: ... plus per byte of input (copies of the input and its sections) ...
BYTES_PER_INPUT_BYTE = 16
#: ... plus a fixed allowance for interpreter and library overhead.
SLACK_BYTES = 4 << 20
#: Address-space cap of a campaign process, so a runaway allocation fails
#: as MemoryError (and is reported) instead of exhausting the machine.
CAMPAIGN_ADDRESS_SPACE = 8 << 30

MODE_FIX_CRCS = 1
MODE_PREFIX = 2
MODE_CUTOFF = 4
MODE_BBOX = 8
#: Mode values at or above this apply MODE_PREFIX and MODE_CUTOFF to a tiled map too (refused).
MODE_TILED_REFUSALS = 0xF0
#: Decode-time cutoff used by MODE_CUTOFF (coarser than any seed's).
FUZZ_CUTOFF = 0.97


class _Hang(Exception):
    pass


@dataclass
class Outcome:
    kind: str  # "decoded", "refused" (a DftpccError), or a failure: "crash", "slow", "runaway", "memory", "nonfinite"
    detail: str = ""
    seconds: float = 0.0
    peak_bytes: int = 0
    allowed_bytes: int = 0
    events: int = 0  # Python events of the decode, when counted

    @property
    def failed(self) -> bool:
        return self.kind not in ("decoded", "refused")


def _decode(data: bytes, validated: list[int]) -> np.ndarray:
    """Decode one input as the mode byte says; appends the validated grid's cells to ``validated``."""
    mode, body = (data[0], data[1:]) if data else (0, b"")
    if mode & MODE_FIX_CRCS:
        body = craft.fix_crcs(body)
    # A tiled map (minor version 1) refuses max_bytes and cutoff: mostly leave them out.
    untiled = body[9:10] != b"\x01" or mode >= MODE_TILED_REFUSALS
    max_bytes = None
    if mode & MODE_PREFIX and body and untiled:
        max_bytes = max(1, len(body) * (1 + (mode >> 4)) // 17)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a warning is not a failure
        with dftpcc.open(body, max_bytes=max_bytes) as cmap:
            grid = cmap.grid
            validated.append(grid.size if not cmap.tiled else
                             min(grid.size, fmt.validate.cells_allowed(len(body), None)))
            cutoff = (FUZZ_CUTOFF if mode & MODE_CUTOFF and untiled and cmap.params.cutoff <= FUZZ_CUTOFF
                      else None)
            bbox = None
            if mode & MODE_BBOX:  # the south-west corner, a fraction (1 to 16 sixteenths) of each side
                xmin, ymin, xmax, ymax = cmap.bounds()
                f = (1 + (mode >> 4)) / 16
                bbox = (xmin, ymin, xmin + f * (xmax - xmin), ymin + f * (ymax - ymin))
            return cmap.read_points(cutoff=cutoff, bbox=bbox)


def _on_alarm(_signum, _frame):
    raise _Hang()


def check(data: bytes, *, trace_memory: bool = True, time_limit: float | None = TIME_LIMIT_S,
          max_events: int | None = None, watchdog: float | None = WATCHDOG_S) -> Outcome:
    """Decode ``data`` and classify what happened (see the module docstring).

    The time is that of a plain decode; with ``trace_memory`` the input is
    decoded a second time under tracemalloc (which slows numpy-heavy code
    several times over) to measure its peak allocation. Without a
    ``time_limit`` there is no plain decode: the traced one alone, which also
    counts Python events when ``max_events`` is given and stops the decode as
    "runaway" past it. ``watchdog=None`` sets no alarm (nothing timed at all).
    """
    if time_limit is None and trace_memory:
        outcome = Outcome("decoded")
    else:
        outcome, cells = _run(data, trace=False, max_events=max_events, watchdog=watchdog)
    if not outcome.failed and time_limit is not None and outcome.seconds > time_limit:
        outcome.kind, outcome.detail = "slow", f"{outcome.seconds:.2f} s"
    if trace_memory and outcome.kind in ("decoded", "refused"):
        traced, cells = _run(data, trace=True, max_events=max_events, watchdog=watchdog)
        if time_limit is None:
            outcome.kind, outcome.detail, outcome.seconds = traced.kind, traced.detail, traced.seconds
        outcome.peak_bytes, outcome.events = traced.peak_bytes, traced.events
        outcome.allowed_bytes = BYTES_PER_INPUT_BYTE * len(data) + SLACK_BYTES + DECODE_BYTES_PER_CELL * cells
        if traced.failed and traced.kind != "slow":  # tracing is slow: time comes from the plain run
            outcome.kind, outcome.detail = traced.kind, traced.detail
        elif outcome.peak_bytes > outcome.allowed_bytes:
            outcome.kind = "memory"
            outcome.detail = f"peak {outcome.peak_bytes:,} B > allowed {outcome.allowed_bytes:,} B for {cells:,} cells"
    return outcome


def _run(data: bytes, *, trace: bool, max_events: int | None = None,
         watchdog: float | None = WATCHDOG_S) -> tuple[Outcome, int]:
    validated: list[int] = []
    if trace:
        tracemalloc.start()
        tracemalloc.reset_peak()
    if watchdog is not None:
        previous = signal.signal(signal.SIGALRM, _on_alarm)
        signal.setitimer(signal.ITIMER_REAL, watchdog)
    counter = measure_work(max_events, trace_memory=False) if trace and max_events is not None else None
    work = counter.__enter__() if counter is not None else None
    t0 = time.perf_counter()
    try:
        try:
            points = _decode(data, validated)
        finally:
            if counter is not None:
                counter.__exit__(None, None, None)
        outcome = Outcome("decoded")
        if not np.isfinite(points).all():
            outcome = Outcome("nonfinite", "decoded points are not finite")
    except WorkLimitExceeded:
        outcome = Outcome("runaway", f"more than {max_events:,} Python events")
    except _Hang:
        outcome = Outcome("slow", f"still running after {watchdog} s")
    except dftpcc.DftpccError as exc:
        outcome = Outcome("refused", f"{type(exc).__name__}: {exc}")
    except MemoryError:
        outcome = Outcome("memory", "MemoryError")
    except Exception as exc:  # noqa: BLE001 - exactly what the fuzzer looks for
        outcome = Outcome("crash", "".join(traceback.format_exception(exc)))
    finally:
        if watchdog is not None:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, previous)
    outcome.seconds = time.perf_counter() - t0
    if work is not None:
        outcome.events = work.events
    if trace:
        outcome.peak_bytes = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return outcome, (validated[0] if validated else 0)


# --- the built-in structure-aware mutator ----------------------------------------------------------

_INTS = (0, 1, 2, 0x7F, 0x80, 0xFF, 0x7FFF, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF, 1 << 32, 1 << 40, (1 << 63) - 1,
         (1 << 64) - 1)
_FLOATS = (0.0, -0.0, 1.0, -1.0, 0.5, 1e-300, 5e-324, 1e12, 1e15, 1e308, -1e308, math.inf, -math.inf, math.nan)
_TILED_JSON_VALUES = (15, 16, 17, 32, 65536, 65537, 0, "dft", "complex64", "footprint", 0.05)
_JSON_VALUES = (None, True, False, 0, -1, 1, 2**31, 2**63, 10**400, 0.5, 1.5, -0.5, 1e308, "x", "", [], {},
                [[[[[]]]]], {"a": {}})


class Mutator:
    """Random mutations of seed maps: bytes, fields, sections, JSON, truncations, splices."""

    def __init__(self, seeds: list[bytes], rng: random.Random):
        self.seeds = seeds
        self.rng = rng

    def __call__(self) -> bytes:
        rng = self.rng
        data = rng.choice(self.seeds)
        ops = (self._flip, self._interesting_int, self._interesting_float, self._truncate, self._insert,
               self._delete, self._splice, self._geom, self._table, self._json, self._stat, self._blob,
               self._tile_index, self._tiles)
        # The tiled mutations do nothing to an untiled seed: weigh them by what they can reach.
        tiled = data[9:10] == b"\x01"
        weights = (4, 2, 2, 2, 1, 1, 1, 3, 2, 2, 1, 2) + ((3, 3) if tiled else (0, 0))
        for _ in range(rng.choice((1, 1, 1, 2, 3))):
            try:
                data = rng.choices(ops, weights)[0](data)
            except (struct.error, ValueError, KeyError, RecursionError, OverflowError, ZeroDivisionError):
                pass  # a structural mutation that does not apply to these bytes
        mode = rng.getrandbits(8)
        if rng.random() < 0.5:
            mode |= MODE_FIX_CRCS  # half the inputs look crafted rather than damaged
        return bytes([mode]) + data

    def _pos(self, data: bytes) -> int:
        # Headers are small and dense with fields: aim there more often.
        if data and self.rng.random() < 0.5:
            return self.rng.randrange(min(len(data), 512))
        return self.rng.randrange(len(data)) if data else 0

    def _flip(self, data: bytes) -> bytes:
        if not data:
            return data
        buf = bytearray(data)
        for _ in range(self.rng.choice((1, 1, 2, 8))):
            i = self._pos(data)
            buf[i] ^= 1 << self.rng.randrange(8)
        return bytes(buf)

    def _interesting_int(self, data: bytes) -> bytes:
        if len(data) < 8:
            return data
        fmt = self.rng.choice(("<B", "<H", "<I", "<Q"))
        value = self.rng.choice(_INTS) & ((1 << (8 * struct.calcsize(fmt))) - 1)
        i = min(self._pos(data), len(data) - struct.calcsize(fmt))
        buf = bytearray(data)
        struct.pack_into(fmt, buf, i, value)
        return bytes(buf)

    def _interesting_float(self, data: bytes) -> bytes:
        if len(data) < 8:
            return data
        i = min(self._pos(data), len(data) - 8)
        buf = bytearray(data)
        struct.pack_into("<d", buf, i, self.rng.choice(_FLOATS))
        return bytes(buf)

    def _truncate(self, data: bytes) -> bytes:
        return data[: self.rng.randrange(len(data) + 1)]

    def _insert(self, data: bytes) -> bytes:
        i = self.rng.randrange(len(data) + 1)
        return data[:i] + self.rng.randbytes(self.rng.choice((1, 4, 8, 64))) + data[i:]

    def _delete(self, data: bytes) -> bytes:
        if not data:
            return data
        i = self.rng.randrange(len(data))
        return data[:i] + data[i + self.rng.choice((1, 4, 8, 64)):]

    def _splice(self, data: bytes) -> bytes:
        other = self.rng.choice(self.seeds)
        i, j = self.rng.randrange(len(data) + 1), self.rng.randrange(len(other) + 1)
        return data[:i] + other[j:]

    def _sections(self, data: bytes) -> list[tuple[bytes, int, bytes]] | None:
        """``[(tag, tile, payload), ...]``, or None when ``data`` holds no complete table."""
        try:
            return craft.split_tiled(data)
        except struct.error:
            return None

    @staticmethod
    def _join(data: bytes, sections: list[tuple[bytes, int, bytes]], count: int | None = None) -> bytes:
        """``sections`` laid out again with ``data``'s version (and tile numbers), checksums fixed."""
        return craft.join_tiled(sections, version=craft.version_of(data), count=count)

    def _geom(self, data: bytes) -> bytes:
        try:
            fields = craft.geom(data)
        except (struct.error, KeyError):
            return data
        name = self.rng.choice(craft.GEOM_FIELDS)
        if isinstance(fields[name], int):
            value = self.rng.choice(_INTS + (fields[name] + 1, max(0, fields[name] - 1), fields[name] * 2))
            value &= (1 << 32) - 1 if name in ("rows", "cols") else (1 << 64) - 1
        else:
            value = self.rng.choice(_FLOATS + (fields[name] * 2, -fields[name]))
        try:
            return craft.with_geom(data, **{name: value})
        except (struct.error, KeyError):
            return data

    def _table(self, data: bytes) -> bytes:
        sections = self._sections(data)
        if not sections:
            return data
        rng = self.rng
        choice = rng.randrange(5)
        if choice == 0:  # drop a section
            del sections[rng.randrange(len(sections))]
            return self._join(data, sections)
        if choice == 1:  # duplicate one
            sections.insert(rng.randrange(len(sections) + 1), rng.choice(sections))
            return self._join(data, sections)
        if choice == 2:  # reorder
            rng.shuffle(sections)
            return self._join(data, sections)
        if choice == 3:  # a lying count
            return self._join(data, sections, count=rng.choice((0, 1, len(sections) + 1, 1024, 1025, 1 << 24,
                                                                (1 << 24) + 1, 0xFFFFFFFF)))
        try:  # a lying entry: length, tile or checksum
            index = rng.randrange(len(sections))
            name = rng.choice(("length", "tile", "crc"))
            value = rng.choice(_INTS) & ((1 << 32) - 1 if name == "crc" else (1 << 64) - 1)
            return craft.with_table_entry(data, index, **{name: value})
        except (struct.error, TypeError):
            return data

    def _json(self, data: bytes) -> bytes:
        sections = self._sections(data)
        if not sections:
            return data
        rng = self.rng
        index = rng.choice([i for i, (t, _k, _p) in enumerate(sections) if t in (b"PARM", b"CRS ")] or [0])
        tag, tile, payload = sections[index]
        try:
            obj = json.loads(fmt.sections.json_text(memoryview(payload), tag.decode()))
        except (ValueError, RecursionError, dftpcc.DftpccError):
            obj = {}
        if isinstance(obj, dict) and obj and rng.random() < 0.8:
            key = rng.choice(sorted(obj))
            if "tile_size" in obj and rng.random() < 0.3:  # a tiled map's own fields
                key = rng.choice(("tile_size", "transform", "storage", "mask", "target_max_error"))
            obj[key] = rng.choice(_JSON_VALUES + _TILED_JSON_VALUES)
            text = json.dumps(obj)
        elif rng.random() < 0.5:
            text = rng.choice(("[" * 100_000, "{}", "[]", "null", "\"x\"", "1e999", "{\"a\": NaN}"))
        else:
            text = json.dumps(rng.choice(_JSON_VALUES))
        sections[index] = (tag, tile, text.encode("utf-8", "surrogatepass"))
        return self._join(data, sections)

    def _stat(self, data: bytes) -> bytes:
        """A binary STAT record changed: a field's value, a field dropped, a record of an id the
        reader does not know, or an integer cut short or wider than 64 bits."""
        try:
            fields = craft.stat_of(data)
            raw = craft.section(data, b"STAT")
        except (struct.error, KeyError, dftpcc.DftpccError):
            return data
        rng = self.rng
        choice = rng.randrange(4)
        if choice < 2 and fields:
            key = rng.choice(sorted(fields))
            if choice == 1:
                return craft.with_stat(data, **{key: None})
            integer = key in ("coef_count", "cells_interpolated", "source_dtype")
            value = rng.choice(_INTS + ((1 << 64), (1 << 70))) if integer else rng.choice(_FLOATS)
            return craft.with_stat(data, **{key: value})
        if choice == 2:  # a later version's field, before or after the others
            record = (bytes([rng.randrange(9, 128)]) + struct.pack("<f", rng.random())
                      if rng.random() < 0.5 else bytes([rng.randrange(131, 256)]) + craft.leb128(rng.choice(_INTS)))
            stat = raw[:1] + record + raw[1:] if rng.random() < 0.5 else raw + record
        else:  # an integer record whose LEB128 is cut short or too wide
            tails = (b"", b"\xff", b"\xff" * 10, b"\x80" * 9 + b"\x02", b"\x80" * 9 + b"\x01")
            stat = raw + bytes([128]) + rng.choice(tails)
        return craft.replace_section(data, b"STAT", stat)

    def _blob(self, data: bytes) -> bytes:
        sections = self._sections(data)
        if not sections:
            return data
        import zstandard

        rng = self.rng
        index = rng.choice([i for i, (t, _k, _p) in enumerate(sections)
                            if t in (b"MASK", b"COEF", b"RESD", b"BASE", b"TIDX")] or [0])
        tag, tile, payload = sections[index]
        choice = rng.randrange(4)
        if choice == 0:  # a zstd frame that expands enormously (a bomb)
            payload = zstandard.ZstdCompressor().compress(b"\xff" * rng.choice((10, 1000, 10**6, 10**7)))
        elif choice == 1:  # random bytes
            payload = rng.randbytes(rng.choice((0, 1, 16, 100, len(payload))))
        elif choice == 2:  # a field inside the payload
            if len(payload) >= 4:
                buf = bytearray(payload)
                struct.pack_into("<I", buf, rng.randrange(0, len(buf) - 3), rng.choice(_INTS) & 0xFFFFFFFF)
                payload = bytes(buf)
        else:  # another section's payload (of another tile, perhaps)
            payload = rng.choice(sections)[2]
        sections[index] = (tag, tile, payload)
        return self._join(data, sections)

    def _tile_index(self, data: bytes) -> bytes:
        """TIDX lies: counts (their sum, over a tile's size, an empty tile made full), T, the overlap,
        the coding, figures, a frame without its size, or one declaring a gigabyte."""
        import zstandard

        try:
            index = craft.tile_index(data)
        except (struct.error, StopIteration, ValueError, KeyError, zstandard.ZstdError):
            return data
        rng = self.rng
        cells = index["cells"].copy()
        choice = rng.randrange(8)
        if choice == 0 and cells.size:  # one count changed
            k = rng.randrange(cells.size)
            cells[k] = rng.choice((0, 1, cells[k] + 1, max(0, cells[k] - 1), index["size"] ** 2,
                                   index["size"] ** 2 + 1, 0xFFFFFFFF))
            return craft.with_tile_index(data, cells=cells)
        if choice == 1 and cells.size > 1:  # two counts swapped, or moved keeping the sum
            i, j = rng.sample(range(cells.size), 2)
            if rng.random() < 0.5:
                cells[i], cells[j] = cells[j], cells[i]
            else:
                moved = rng.randrange(1, max(2, int(cells[i]) + 1))
                cells[i], cells[j] = cells[i] - moved, cells[j] + moved
            return craft.with_tile_index(data, cells=np.maximum(cells, 0))
        if choice == 2:  # more or fewer tiles than the grid has
            extra = rng.choice((-1, 1, 2, 1000))
            cells = np.concatenate([cells, np.ones(extra, np.int64)]) if extra > 0 else cells[:extra]
            return craft.with_tile_index(data, cells=cells)
        if choice == 3:
            name = rng.choice(("size", "overlap", "coding"))
            value = rng.choice(_INTS + (index[name] + 1, max(0, index[name] - 1), index[name] * 2, 15, 16, 65536,
                                        65537))
            return craft.with_tile_index(data, **{name: value & (0xFFFF if name == "overlap" else
                                                                 0xFF if name == "coding" else 0xFFFFFFFF)})
        if choice == 4:  # figures NaN, negative, infinite
            figures = index["figures"].copy()
            if figures.size:
                figures[rng.randrange(figures.size)] = rng.choice((math.nan, -1.0, math.inf, -0.0, 3e38))
            return craft.with_tile_index(data, figures=figures)
        raw = craft.section(data, b"TIDX")
        head = raw[:craft.TIDX_HEAD.size]
        if choice == 5:  # the frame without its content size
            body = zstandard.ZstdDecompressor().decompress(raw[craft.TIDX_HEAD.size:])
            frame = zstandard.ZstdCompressor(write_content_size=False).compress(body)
        elif choice == 6:  # a frame declaring (and holding) far more than the index needs
            frame = zstandard.ZstdCompressor().compress(bytes(rng.choice((10**3, 10**6, 10**7))))
        else:  # a frame header declaring a gigabyte, and little data
            frame = zstd_header_claiming(1 << 30, rng.randbytes(rng.choice((0, 3, 64))))
        return craft.replace_section(data, b"TIDX", head + frame)

    def _tiles(self, data: bytes) -> bytes:
        """Tile sections: a tile number beyond the count, 0 or another tile; a tile's section dropped,
        doubled or swapped with another tile's; an empty tile given sections; BASE dropped or moved."""
        sections = self._sections(data)
        if not sections:
            return data
        rng = self.rng
        tiled = [i for i, (_t, k, _p) in enumerate(sections) if k]
        count = max((k for _t, k, _p in sections), default=0)
        choice = rng.randrange(6)
        if choice == 0 and tiled:  # another tile number
            i = rng.choice(tiled)
            tag, _k, payload = sections[i]
            sections[i] = (tag, rng.choice((0, 1, count, count + 1, count + 2, 1 << 20, (1 << 20) + 1, (1 << 64) - 1,
                                            rng.randrange(1, count + 1))), payload)
        elif choice == 1 and tiled:  # a tile's section dropped
            del sections[rng.choice(tiled)]
        elif choice == 2 and tiled:  # a tile's section repeated, for its tile or another
            tag, k, payload = sections[rng.choice(tiled)]
            sections.insert(rng.randrange(len(sections) + 1), (tag, rng.choice((k, rng.randrange(1, count + 2))), payload))
        elif choice == 3 and len(tiled) > 1:  # two tiles' payloads swapped
            i, j = rng.sample(tiled, 2)
            (ti, ki, pi), (tj, kj, pj) = sections[i], sections[j]
            sections[i], sections[j] = (ti, ki, pj), (tj, kj, pi)
        elif choice == 4:  # BASE dropped, or moved to a tile
            base = [i for i, (t, _k, _p) in enumerate(sections) if t == b"BASE"]
            if not base:
                return data
            if rng.random() < 0.5:
                del sections[base[0]]
            else:
                tag, _k, payload = sections[base[0]]
                sections[base[0]] = (tag, rng.randrange(1, count + 2), payload)
        else:  # a section of an unknown tag, or a TIDX, at a tile
            sections.insert(rng.randrange(len(sections) + 1),
                            (rng.choice((b"XTRA", b"TIDX", b"GEOM", b"STAT")), rng.randrange(0, count + 2),
                             rng.randbytes(rng.choice((0, 4, 32)))))
        return self._join(data, sections)


def zstd_header_claiming(size: int, tail: bytes = b"") -> bytes:
    """The header of a zstd frame declaring ``size`` bytes of content, then ``tail``.

    Descriptor 0xC0: an 8-byte content size, a window descriptor, no dictionary, no checksum;
    window 0x58 is 2 MiB, within what every decoder accepts.
    """
    return b"\x28\xb5\x2f\xfd" + bytes([0xC0, 0x58]) + struct.pack("<Q", size) + tail


@dataclass
class Campaign:
    iterations: int = 0
    outcomes: collections.Counter = field(default_factory=collections.Counter)
    refusals: collections.Counter = field(default_factory=collections.Counter)
    failures: list[dict] = field(default_factory=list)
    max_seconds: float = 0.0
    max_seconds_input: str = ""
    max_passing_seconds: float = 0.0
    total_seconds: float = 0.0
    max_peak_bytes: int = 0
    max_peak_fraction: float = 0.0
    max_events: int = 0
    seconds: list[float] = field(default_factory=list)

    def add(self, data: bytes, outcome: Outcome, save_to: Path | None) -> None:
        self.iterations += 1
        self.outcomes[outcome.kind] += 1
        if outcome.kind == "refused":
            self.refusals[outcome.detail.split(":", 1)[0]] += 1
        self.total_seconds += outcome.seconds
        self.seconds.append(outcome.seconds)
        if outcome.seconds > self.max_seconds:
            self.max_seconds, self.max_seconds_input = outcome.seconds, data[:64].hex()
        if not outcome.failed:
            self.max_passing_seconds = max(self.max_passing_seconds, outcome.seconds)
        self.max_peak_bytes = max(self.max_peak_bytes, outcome.peak_bytes)
        self.max_events = max(self.max_events, outcome.events)
        if outcome.allowed_bytes:
            self.max_peak_fraction = max(self.max_peak_fraction, outcome.peak_bytes / outcome.allowed_bytes)
        if outcome.failed:
            name = f"failure-{zlib.crc32(data):08x}.bin"
            if save_to is not None:
                save_to.mkdir(parents=True, exist_ok=True)
                (save_to / name).write_bytes(data)
            self.failures.append({"kind": outcome.kind, "input": name, "detail": outcome.detail[-2000:]})

    def report(self) -> dict:
        secs = sorted(self.seconds)
        return {
            "iterations": self.iterations,
            "outcomes": dict(self.outcomes),
            "refusals_by_error": dict(self.refusals),
            "failures": len(self.failures),
            "failure_details": self.failures[:20],
            "decode_seconds_max": round(self.max_seconds, 4),
            "decode_seconds_max_of_passing_inputs": round(self.max_passing_seconds, 4),
            "decode_seconds_p99": round(secs[int(0.99 * (len(secs) - 1))], 4) if secs else 0.0,
            "decode_seconds_mean": round(self.total_seconds / max(1, self.iterations), 5),
            "slowest_input_prefix_hex": self.max_seconds_input,
            "peak_traced_bytes_max": self.max_peak_bytes,
            "peak_over_allowed_max": round(self.max_peak_fraction, 4),
            "python_events_max": self.max_events,
            "max_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        }


def run(iterations: int, *, seed: int = 0, time_budget: float | None = None, save_to: Path | None = None,
        trace_memory: bool = True, progress: bool = False, time_limit: float | None = TIME_LIMIT_S,
        max_events: int | None = None, watchdog: float | None = WATCHDOG_S) -> dict:
    """Run the built-in engine; returns the report (see :meth:`Campaign.report`).

    ``time_limit``, ``max_events`` and ``watchdog`` are those of :func:`check`.
    """
    rng = random.Random(seed)
    seeds = list(seed_files().values()) + list(legacy_files().values())
    mutate = Mutator(seeds, rng)
    campaign = Campaign()
    # The unmutated seeds first (each must decode), then mutations.
    inputs = ([bytes([0]) + s for s in seeds] + [bytes([MODE_PREFIX | MODE_CUTOFF]) + s for s in seeds])
    start = time.perf_counter()
    for i in range(iterations):
        data = inputs[i] if i < len(inputs) else mutate()
        campaign.add(data, check(data, trace_memory=trace_memory, time_limit=time_limit, max_events=max_events,
                                 watchdog=watchdog), save_to)
        if time_budget is not None and time.perf_counter() - start > time_budget:
            break
        if progress and (i + 1) % 10_000 == 0:
            print(f"{i + 1:,} inputs, {len(campaign.failures)} failures, "
                  f"{time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)
    report = campaign.report()
    report.update(engine="builtin", seed=seed, wall_seconds=round(time.perf_counter() - start, 1),
                  seeds=len(seeds))
    return report


def _atheris(argv: list[str]) -> None:  # pragma: no cover - needs atheris
    import atheris

    seeds = seed_files() | legacy_files()
    corpus = [a for a in argv[1:] if not a.startswith("-")]
    for folder in corpus:
        Path(folder).mkdir(parents=True, exist_ok=True)
        for name, data in seeds.items():
            for mode in (0, MODE_FIX_CRCS, MODE_PREFIX):
                (Path(folder) / f"{name}-{mode}").write_bytes(bytes([mode]) + data)

    def test_one_input(data: bytes) -> None:
        # Coverage instrumentation slows Python several times over: libFuzzer's
        # -timeout and -rss_limit_mb watch time and memory instead.
        outcome = check(data, trace_memory=False, time_limit=None)
        if outcome.failed:
            raise RuntimeError(f"{outcome.kind}: {outcome.detail}")

    atheris.Setup(argv, test_one_input)
    atheris.Fuzz()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv
    if "--atheris" in argv:
        _atheris([a for a in argv if a != "--atheris"])
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iterations", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--time-budget", type=float, help="stop after this many seconds")
    parser.add_argument("--report", type=Path, help="write the JSON report here")
    parser.add_argument("--failures", type=Path, default=Path("fuzz-failures"),
                        help="folder for inputs that failed (default ./fuzz-failures)")
    parser.add_argument("--no-memory", action="store_true", help="skip the per-input allocation check (faster)")
    args = parser.parse_args(argv[1:])
    resource.setrlimit(resource.RLIMIT_AS, (CAMPAIGN_ADDRESS_SPACE, resource.getrlimit(resource.RLIMIT_AS)[1]))
    report = run(args.iterations, seed=args.seed, time_budget=args.time_budget, save_to=args.failures,
                 trace_memory=not args.no_memory, progress=True)
    text = json.dumps(report, indent=2)
    print(text)
    if args.report:
        args.report.write_text(text + "\n")
    return 1 if report["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
