"""The compiled backend (numba) writes the numpy backend's bytes, bit for bit, and can be switched off."""

from __future__ import annotations

import contextlib
import warnings

import numpy as np
import pytest

from dftpcc import analysis, coding, fill, geometric, grid, kernels, occupancy, quantizer, sums
from dftpcc.errors import CorruptFileError, InvalidInputError
from dftpcc.kernels import Backend

pytest.importorskip("numba")

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import constriction


@pytest.fixture
def jit():
    """The compiled backend in use; yields a switch: ``use(False)`` runs the codec on numpy, ``use(True)``
    compiled again (each a :func:`kernels.use` scope, left at the test's end)."""
    kernels.compiled_module()
    with contextlib.ExitStack() as scope:

        def use(on: bool) -> None:
            scope.close()
            wanted = Backend.COMPILED if on else Backend.NUMPY
            assert scope.enter_context(kernels.use(wanted)) is kernels.current() is wanted

        use(True)
        yield use


def _masks(rng: np.random.Generator):
    """Masks of every kind a map has: noise, a blob, lidar rings (sparse, the hardest), a few cells,
    full and empty, on shapes from one cell to several stripes."""
    for t in range(120):
        h, w = (int(v) for v in rng.integers(1, 260, 2))
        yy, xx = np.mgrid[:h, :w]
        kind = t % 6
        if kind == 0:
            m = rng.random((h, w)) < rng.random()
        elif kind == 1:
            m = np.hypot(xx - w / 2, yy - h / 2) < rng.random() * max(h, w)
        elif kind == 2:
            m = (np.mod(np.hypot(xx - w / 3, yy - h / 2), 7) < 1) & (rng.random((h, w)) < 0.6)
        elif kind == 3:
            m = np.zeros((h, w), bool)
            m[rng.integers(0, h, 5), rng.integers(0, w, 5)] = True
        elif kind == 4:
            m = np.ones((h, w), bool)
        else:
            m = np.zeros((h, w), bool)
        yield m, [None, 1, 2, 3, 64, 5][t % 6]


def test_mask_contexts_equal_numpys(jit):
    # Each cell's context (the line before, the line before last, per stripe) from one compiled pass.
    for mask, stripe in _masks(np.random.default_rng(4)):
        lines = mask.astype(np.uint8)
        for s in {stripe or lines.shape[0], 1, 2, 64}:
            assert np.array_equal(occupancy._contexts.compiled(lines, s), occupancy._contexts.numpy(lines, s)), \
                (mask.shape, s)


def test_mask_coder_bytes_equal(jit):
    for mask, stripe in _masks(np.random.default_rng(0)):
        jit(True)
        fast = occupancy.encode_mask(mask, stripe=stripe)
        jit(False)
        slow = occupancy.encode_mask(mask, stripe=stripe)
        assert fast == slow, (mask.shape, stripe)
        assert np.array_equal(occupancy.decode_mask(fast, mask.shape), mask)


def test_mask_coder_bytes_equal_on_a_striped_map(jit):
    # Over STRIPED_CELLS: 64-line stripes, seeds, lockstep steps across stripes.
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[:700, :530]
    mask = (np.hypot(xx - 200, yy - 300) < 260) & (rng.random(yy.shape) < 0.97)
    assert mask.size >= occupancy.STRIPED_CELLS
    jit(True)
    fast = occupancy.encode_mask(mask)
    jit(False)
    assert fast == occupancy.encode_mask(mask)


def _context_blob(mask: np.ndarray, stripe: int | None, first_seed: bool = False) -> bytes:
    """The mask context-coded whatever the bitmap would cost (noise and full masks too), as encode_mask
    lays it out (kind 3 with ``first_seed``)."""
    if stripe is None:
        stripe = occupancy.STRIPE_LINES if mask.size >= occupancy.STRIPED_CELLS else max(mask.shape)
    transposed = mask.shape[0] > mask.shape[1]
    lines = (mask.T if transposed else mask).astype(np.uint8)
    kind = occupancy.KIND_SEEDED if first_seed else occupancy.KIND_CONTEXT
    return occupancy._HEAD.pack(kind, transposed) + occupancy._encode_context(
        lines, min(stripe, lines.shape[0]), first_seed=first_seed)


def _decoded(jit, blob: bytes, shape: tuple[int, int]):
    """What each path makes of a blob: ``{True: kernel, False: numpy}``, a mask or CorruptFileError's
    message (any other exception fails the test)."""
    out = {}
    for on in (True, False):
        jit(on)
        try:
            out[on] = occupancy.decode_mask(blob, shape)
        except CorruptFileError as exc:
            out[on] = str(exc)
    return out


def _same(out) -> bool:
    fast, slow = out[True], out[False]
    if isinstance(fast, str) or isinstance(slow, str):
        return fast == slow
    return fast.shape == slow.shape and fast.dtype == slow.dtype and np.array_equal(fast, slow)


def test_kind_3_words_equal(jit):
    # Kind 3 (a tile's mask: the first line a seed too), whatever the bitmap would cost.
    for mask, stripe in _masks(np.random.default_rng(2)):
        jit(True)
        fast = _context_blob(mask, stripe, first_seed=True)
        jit(False)
        assert fast == _context_blob(mask, stripe, first_seed=True), (mask.shape, stripe)


def test_mask_decoder_gives_the_numpy_paths_mask(jit):
    for mask, stripe in _masks(np.random.default_rng(0)):
        for blob in (_context_blob(mask, stripe), _context_blob(mask, stripe, first_seed=True),
                     occupancy.encode_mask(mask, stripe=stripe, first_seed=True)):
            out = _decoded(jit, blob, mask.shape)
            assert _same(out), (mask.shape, stripe)
            assert np.array_equal(out[True], mask), (mask.shape, stripe)


@pytest.mark.parametrize("shape", [(700, 530), (530, 700)])
def test_mask_decoder_gives_the_numpy_paths_mask_on_a_striped_map(jit, shape):
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    mask = (np.hypot(xx - 200, yy - 300) < 260) & (rng.random(yy.shape) < 0.97)
    mask[:, 400:] |= (np.mod(np.hypot(xx - 450, yy - 300), 7) < 1)[:, 400:]  # rings beside the blob
    assert mask.size >= occupancy.STRIPED_CELLS
    for first_seed in (False, True):
        blob = _context_blob(mask, None, first_seed)
        assert occupancy._STRIPES.unpack_from(blob, occupancy._HEAD.size)[0] == occupancy.STRIPE_LINES
        out = _decoded(jit, blob, shape)
        assert _same(out) and np.array_equal(out[True], mask)


def _damaged(rng: np.random.Generator, blob: bytes):
    """Mutations of a context-coded blob's ANS words: bit flips, truncation to any number of words,
    words appended (random, zero, one, copies), random words, a zero last word."""
    stripe, seed_bytes = occupancy._STRIPES.unpack_from(blob, occupancy._HEAD.size)
    at = occupancy._HEAD.size + occupancy._STRIPES.size + seed_bytes
    head, words = blob[:at], np.frombuffer(blob, dtype="<u4", offset=at).copy()
    n = words.size
    for kind in range(7):
        w = words.copy()
        if kind == 0 and n:  # a few bits flipped anywhere
            for _ in range(int(rng.integers(1, 4))):
                i = int(rng.integers(0, n))
                w[i] ^= np.uint32(1 << int(rng.integers(0, 32)))
        elif kind == 1 and n:  # one bit flipped in the last two words (the coder's first state)
            i = n - 1 - int(rng.integers(0, min(n, 2)))
            w[i] ^= np.uint32(1 << int(rng.integers(0, 32)))
        elif kind == 2:  # truncated: the first k words, or the last k
            k = int(rng.integers(0, n + 1))
            w = w[:k] if rng.random() < 0.5 else w[n - k:]
        elif kind == 3:  # words appended
            choices = [rng.integers(0, 2**32, 3, dtype=np.uint64), np.zeros(1), np.ones(1), w[-2:] if n else np.ones(2)]
            extra = choices[int(rng.integers(0, len(choices)))]
            w = np.concatenate([w, np.asarray(extra, dtype=np.uint64).astype(np.uint32)])
        elif kind == 4:  # random words, as many as the real ones or a few
            w = rng.integers(0, 2**32, int(rng.choice([n, rng.integers(0, 5)])), dtype=np.uint64).astype(np.uint32)
        elif kind == 5 and n:  # a zero last word (constriction refuses it)
            w[-1] = 0
        elif kind == 6 and n:  # a tiny last word: a one-word state that runs out early
            w[-1] = np.uint32(int(rng.integers(1, 4)))
        else:
            continue
        yield kind, head + w.astype("<u4").tobytes()


def test_mask_decoder_matches_the_numpy_path_on_damaged_words(jit):
    # Every damage decodes to the numpy path's mask or fails with its CorruptFileError, never otherwise.
    rng = np.random.default_rng(5)
    blobs = [(_context_blob(mask, stripe, first_seed=t % 3 == 0), mask.shape)
             for t, (mask, stripe) in enumerate(_masks(np.random.default_rng(4)))]
    yy, xx = np.mgrid[:600, :450]
    big = np.hypot(xx - 220, yy - 300) < 200
    blobs.append((occupancy.encode_mask(big), big.shape))
    outcomes = {"mask": 0, "error": 0}
    tried = 0
    for round_ in range(6):
        for blob, shape in blobs if round_ < 5 else blobs[-1:] * 20:
            for kind, bad in _damaged(rng, blob):
                out = _decoded(jit, bad, shape)
                assert _same(out), (shape, kind, out[True] if isinstance(out[True], str) else "mask",
                                    out[False] if isinstance(out[False], str) else "mask")
                outcomes["error" if isinstance(out[False], str) else "mask"] += 1
                tried += 1
    assert tried >= 3000
    assert outcomes["error"] and outcomes["mask"]


def test_push_pull_fill_bits_equal(jit):
    # Every level of push-pull the kernels take (odd sizes, zeros and negative zeros among the
    # known values, which the blend keeps), against the numpy path, bit for bit.
    rng = np.random.default_rng(2)
    for mask, _ in _masks(rng):
        heights = rng.normal(0, 5, mask.shape)
        heights[rng.random(mask.shape) < 0.05] = 0.0
        heights[rng.random(mask.shape) < 0.05] = -0.0
        jit(True)
        fast = fill.fill_empty(heights, mask)
        jit(False)
        slow = fill.fill_empty(heights, mask)
        assert fast.tobytes() == slow.tobytes(), mask.shape
        assert np.array_equal(fast[mask], heights[mask])


def test_packed_tables_are_the_frequencies_tables_of_every_scale(jit):
    """The compiled coders' tables, made in one pass from the weights, are the running sums of
    table_frequencies (the constriction models' integers) for every scale code, narrow and wide
    bounds, one table and many packed end to end."""
    rng = np.random.default_rng(5)
    codes = np.arange(1, 256)
    for max_abs in (1, 2, 7, 255, 256, 3000, 32767):
        bounds = rng.choice([max_abs, 1, 40], codes.size)
        lows, csum, near_bounds = geometric.packed_tables(bounds, codes)
        for k, (code, bound) in enumerate(zip(codes.tolist(), bounds.tolist())):
            lo, near = geometric.table_frequencies(bound, code)
            at = near_bounds[k] + k
            assert near_bounds[k + 1] - near_bounds[k] == near.size and lows[k] == lo, (code, bound)
            assert csum[at] == 0 and np.array_equal(np.diff(csum[at:at + near.size + 1]), near), (code, bound)
            assert csum[at + near.size] == (1 << 24) - (2 * bound + 1 - near.size), (code, bound)


def test_table_coder_words_equal_constriction(jit):
    rng = np.random.default_rng(3)
    for t in range(200):
        max_abs = int(rng.choice([1, 2, 3, 20, 255, 300, 9000, 12000, 30000, 200000]))
        groups = []
        for code in sorted(rng.choice(np.arange(1, 256), int(rng.integers(1, 5)), replace=False)):
            scale = max(1, int(rng.exponential(geometric.scale_of(np.array([code], np.uint8))[0] + 0.5)))
            q = np.clip(np.round(rng.laplace(0, scale, int(rng.integers(1, 300)))), -max_abs, max_abs)
            q = q.astype(np.int64)
            q[:2] = [max_abs, -max_abs][:q.size]  # both ends of the table
            groups.append((int(code), q + max_abs))
        coder = constriction.stream.stack.AnsCoder()
        for code, symbols in reversed(groups):
            coder.encode_reverse(symbols.astype(np.int32), geometric.build_table_model(max_abs, code))
        tables = geometric.packed_tables(max_abs, [code for code, _ in groups])
        bounds = np.cumsum([0] + [s.size for _, s in groups])
        words = kernels.compiled_module().encode_table_words(np.concatenate([s for _, s in groups]), bounds, tables,
                                                             2 * max_abs + 1)
        assert np.array_equal(words, coder.get_compressed()), (t, max_abs)


def _coefficient_chunks(rng: np.random.Generator):
    """ANS chunks as encode_coefficients writes them: a ring-ordered stream of decaying values, of
    lengths from one value to a long chunk, wide and narrow alphabets, every band layout."""
    for t in range(60):
        n = int(rng.choice([1, 2, 7, 256, 1000, 5000, 20000]))
        radius = np.sort(rng.uniform(0, 300, n))
        angle = rng.uniform(0, 1, n)
        scale = 40.0 * np.exp(-radius / rng.uniform(5, 200)) * rng.uniform(0.1, 10)
        q = np.round(rng.laplace(0, scale)).astype(np.int64)
        if t % 7 == 0:
            q[rng.random(n) < 0.9] = 0  # mostly empty bands
        if t % 11 == 0:
            q[0] = 20000  # a wide alphabet
        yield q, radius, angle


def test_coefficient_decoder_gives_constrictions_values(jit):
    """The compiled coefficient decoder reads the values the numpy path (constriction) reads, for the
    chunk's own layout and for every other layout forced on it."""
    rng = np.random.default_rng(12)
    layouts_seen = set()
    for q, radius, angle in _coefficient_chunks(rng):
        payload = coding._encode_ans(q, radius, angle, exhaustive=True)
        if payload is None:
            continue
        layouts_seen.add(payload[0])
        for b in (coding._Bands.of(q, radius, angle, k) for k in range(len(coding.BAND_LAYOUTS))):
            if b.table_work(int(np.abs(q).max())) > geometric.table_budget(q.size):
                continue
            forced = coding._encode_ans_with(q, b, int(np.abs(q).max()))
            for on in (True, False):
                jit(on)
                np.testing.assert_array_equal(coding._decode_ans(forced, radius, angle, "chunk"), q)
    assert len(layouts_seen) > 1


def test_coefficient_decoder_matches_the_numpy_path_on_damaged_words(jit):
    """Damaged words decode to the same values on both paths, or both refuse them with one message."""
    rng = np.random.default_rng(5)
    kinds = set()
    for trial, (q, radius, angle) in enumerate(_coefficient_chunks(rng)):
        payload = coding._encode_ans(q, radius, angle, exhaustive=True)
        if payload is None or len(payload) < 16:
            continue
        damaged = bytearray(payload)
        for _ in range(1 + trial % 3):
            at = int(rng.integers(len(payload) // 2, len(payload)))
            damaged[at] ^= 1 << int(rng.integers(0, 8))
        if trial % 5 == 0:
            damaged[-4:] = b"\0\0\0\0"
        outcomes = []
        for on in (True, False):
            jit(on)
            try:
                outcomes.append(coding._decode_ans(bytes(damaged), radius, angle, "chunk"))
            except CorruptFileError as exc:
                outcomes.append(str(exc))
        kinds.add(type(outcomes[0]))
        if isinstance(outcomes[0], str):
            assert outcomes[0] == outcomes[1]
        else:
            np.testing.assert_array_equal(outcomes[0], outcomes[1])
    assert kinds == {str, np.ndarray}


def test_whole_files_equal(jit):
    """A map with a patchy footprint, untiled and tiled, at a fixed step and at a max-error bound:
    the same bytes with the kernels and without."""
    import dftpcc

    rng = np.random.default_rng(7)
    x, y = rng.uniform(0, 120, (2, 60_000))
    keep = np.hypot(x - 60, y - 60) < 58
    z = 3 * np.sin(x / 9) + 2 * np.cos(y / 13) + 0.05 * rng.standard_normal(x.size)
    points = np.c_[x, y, z][keep]
    for options in ({}, {"tile_size": 64}, {"target_max_error": 0.05}, {"tile_size": 64, "target_max_error": 0.05}):
        out = {}
        for on in (True, False):
            jit(on)
            out[on] = dftpcc.compress(points, resolution=0.5, cutoff=0.7, **options)
        assert out[True] == out[False], options


def test_map_builder_loads_the_kernels_and_writes_the_same_map(jit, monkeypatch, tmp_path):
    from dftpcc.mapbuilder import MapBuilder

    rng = np.random.default_rng(11)
    scans = [np.c_[rng.uniform(k * 10, k * 10 + 40, (2, 20_000)).T, rng.normal(0, 0.3, 20_000)] for k in range(3)]
    files = {}
    for on in (True, False):
        jit(on)
        builder = MapBuilder(0.25, tile_size=64)
        for scan in scans:
            builder.add(scan)
            builder.encode()
        files[on] = builder.encode()
    assert files[True] == files[False]


def test_switched_off_by_the_environment(monkeypatch):
    monkeypatch.setenv("DFTPCC_JIT", "0")
    assert not kernels.load()
    assert kernels.current() is Backend.default(10**12) is Backend.NUMPY  # however large the call
    with kernels.use(work=10**12) as chosen:
        assert chosen is Backend.NUMPY
    with kernels.use("compiled") as chosen:  # the caller's own choice is not overridden
        assert chosen is kernels.current() is Backend.COMPILED


def test_the_default_is_compiled_where_the_work_pays_for_its_import(monkeypatch):
    # A process that has not loaded the kernels: compiled from COMPILED_MIN_POINTS points on, numpy below.
    monkeypatch.delenv("DFTPCC_JIT", raising=False)
    monkeypatch.setattr(kernels, "_state", {"module": None, "tried": False, "found": None})
    assert Backend.detect_available() == (Backend.NUMPY, Backend.COMPILED)
    assert Backend.default() is Backend.default(kernels.COMPILED_MIN_POINTS - 1) is Backend.NUMPY
    assert Backend.default(kernels.COMPILED_MIN_POINTS, min_work=kernels.COMPILED_MIN_POINTS + 1) is Backend.NUMPY
    assert kernels._state["module"] is None  # deciding on numpy imported nothing
    with kernels.use(work=kernels.COMPILED_MIN_POINTS) as chosen:
        assert chosen is kernels.current() is Backend.COMPILED
        with kernels.use(work=1) as inner:  # chosen once per call: a call inside it keeps it
            assert inner is Backend.COMPILED
    # Once loaded, the import is paid: every call takes the compiled kernels.
    assert kernels.current() is Backend.default(1) is Backend.COMPILED
    monkeypatch.setattr(kernels, "_state", {"module": None, "tried": False, "found": None})
    monkeypatch.setenv("DFTPCC_JIT", "1")
    assert Backend.default(1) is Backend.COMPILED


def test_a_one_shot_call_loads_the_kernels_only_when_it_is_large_enough(monkeypatch):
    """compress and decompress choose from the points: numpy, importing nothing, below the thresholds;
    compiled, loading the kernels in the call, from them on."""
    import dftpcc

    monkeypatch.delenv("DFTPCC_JIT", raising=False)
    points = _patchy_points()
    blob = dftpcc.compress(points, resolution=0.5, cutoff=0.7, backend="compiled")
    assert Backend.default(kernels.COMPILED_MIN_MAP_CELLS - 1, min_work=kernels.COMPILED_MIN_MAP_CELLS) \
        is Backend.default(kernels.COMPILED_MIN_POINTS - 1) is Backend.COMPILED  # loaded already: no cost left
    cells = dftpcc.open(blob).header.cell_count
    for name, call, work in (("COMPILED_MIN_POINTS", lambda: dftpcc.compress(points, resolution=0.5, cutoff=0.7),
                              len(points)),
                             ("COMPILED_MIN_MAP_CELLS", lambda: dftpcc.decompress(blob), cells)):
        monkeypatch.setattr(kernels, "_state", {"module": None, "tried": False, "found": None})
        call()
        assert kernels._state["module"] is None, name  # below the threshold: numba not even imported
        monkeypatch.setattr(kernels, name, work)
        call()
        assert kernels._state["module"] is not None, name


def test_without_numba_every_call_runs_on_numpy_and_asking_for_compiled_names_the_extra(monkeypatch):
    import sys

    import dftpcc
    from dftpcc.errors import MissingDependencyError

    monkeypatch.setattr(kernels, "_state", {"module": None, "tried": False, "found": None})
    monkeypatch.setitem(sys.modules, "numba", None)  # as if the extra were not installed
    monkeypatch.delitem(sys.modules, "dftpcc._compiled")
    monkeypatch.delattr(dftpcc, "_compiled")
    monkeypatch.setenv("DFTPCC_JIT", "1")
    assert Backend.default(10**12) is Backend.NUMPY
    assert Backend.detect_available() == (Backend.NUMPY,)
    points = np.c_[np.random.default_rng(3).uniform(0, 20, (2, 500)).T, np.zeros(500)]
    with pytest.raises(MissingDependencyError, match=r"compiled backend needs numba.*dftpcc\[fast\]"):
        dftpcc.compress(points, resolution=1.0, backend="compiled")
    assert dftpcc.decompress(dftpcc.compress(points, resolution=1.0), backend="numpy").shape[1] == 3


def test_a_backend_is_a_value_of_the_call(jit):
    """compress and decompress take ``backend=``: every stage of the call runs on it (a stage beside
    the caller too), the same bytes and points on each; a name that is no backend is refused."""
    import dftpcc

    points = _patchy_points()
    seen = []
    out = {}
    for backend in Backend.detect_available():
        blob = dftpcc.compress(points, resolution=0.5, cutoff=0.7, backend=backend.value,
                               on_stage=lambda _, done=None: seen.append((backend, kernels.current())))
        out[backend] = blob, dftpcc.decompress(blob, backend=backend)
    assert seen and all(asked is found for asked, found in seen)
    assert out[Backend.NUMPY][0] == out[Backend.COMPILED][0]
    assert np.array_equal(out[Backend.NUMPY][1], out[Backend.COMPILED][1])
    for bad in ("numba", "", 1):
        with pytest.raises(InvalidInputError, match="backend must be one of numpy, compiled"):
            dftpcc.compress(points, resolution=0.5, backend=bad)
        with pytest.raises(InvalidInputError, match="backend must be one of numpy, compiled"):
            dftpcc.decompress(out[Backend.NUMPY][0], backend=bad)


def test_no_stage_asks_which_backend_is_in_use():
    """The stages hold no ``if compiled:``: only kernels.py reads the backend; the others name their
    compiled twins (kernels.kernel) and take the call's backend from it."""
    import ast
    from pathlib import Path

    root = Path(kernels.__file__).parent
    for path in root.rglob("*.py"):
        if path.name in ("kernels.py", "_compiled.py"):
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "kernels":
                assert node.attr not in ("enabled", "current", "_state", "_active"), (path.name, node.attr)
            if isinstance(node, ast.Attribute) and node.attr in ("NUMPY", "COMPILED"):
                assert False, (path.name, ast.unparse(node))


def test_a_second_process_reads_the_compiled_code_from_the_cache(tmp_path):
    # numba compiles afresh, and adds to its cache, whatever it cannot find there (closures that call
    # one another, say): a second process running the same kernels must add nothing.
    import os
    import subprocess
    import sys

    code = ("import numpy as np; from dftpcc import fill, kernels, occupancy, mapbuilder\n"
            "assert kernels.load()\n"
            "m = np.random.default_rng(0).random((80, 90)) < 0.2\n"
            "blob = occupancy.encode_mask(m); fill.fill_empty(np.ones(m.shape), m)\n"
            "assert blob[0] == occupancy.KIND_CONTEXT and (occupancy.decode_mask(blob, m.shape) == m).all()\n"
            "b = mapbuilder.MapBuilder(0.5, tile_size=64); b.add(np.c_[np.random.default_rng(1).uniform(0, 50, (3000, 2)),"
            " np.zeros(3000)]); b.encode()\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "DFTPCC_JIT": "1"}

    def cached() -> dict[str, int]:
        return {p.name: p.stat().st_size for p in tmp_path.rglob("*") if p.is_file()}

    subprocess.run([sys.executable, "-c", code], check=True, env=env)
    first = cached()
    assert any(name.endswith(".nbc") for name in first)
    assert any("decode_mask_lines" in name for name in first)  # the mask decoder is cached too
    subprocess.run([sys.executable, "-c", code], check=True, env=env)
    assert cached() == first


def test_gridding_bits_equal(jit):
    # Cells, counts, mean heights, the gridding RMSE and the spread (far points: two layers in some
    # cells), whole and chunk by chunk, with the kernels and without.
    from dftpcc import grid

    rng = np.random.default_rng(5)
    for n in (1, 7, 5000, 70_000):
        x, y = rng.uniform(-30, 70, (2, n))
        z = 0.3 * x + rng.normal(0, 0.2, n)
        z[rng.random(n) < 0.1] += 25.0  # a canopy above some of the ground
        points = np.c_[x, y, z]
        g = grid.fit_grid(points, 0.7)
        out = {}
        for on in (True, False):
            jit(on)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                whole = grid.rasterize(points, g)
                parts = grid.rasterize_chunks(lambda: iter(np.array_split(points, 3)), g)
            out[on] = [(d.heights.tobytes(), d.mask.tobytes(), d.counts.tobytes(), d.gridding_rmse, d.spread)
                       for d in (whole, parts)]
        assert out[True] == out[False], n


def test_survey_equals_numpys(jit):
    # One compiled pass gives numpy's minima and maxima; a zero among them goes to numpy
    # (which of 0.0 and -0.0 is the minimum is numpy's to say).
    from dftpcc import grid

    rng = np.random.default_rng(6)
    clouds = [rng.normal(0, 1e5, (n, 3)) for n in (1, 2, 17, 100_001)]
    zeros = np.abs(np.round(rng.uniform(-3, 3, (1000, 3))))  # minima 0.0, with -0.0 among them
    zeros[::7] *= -1.0
    zeros[::7] = np.where(zeros[::7] == 0, -0.0, -zeros[::7])
    clouds.append(zeros)
    clouds.append(np.c_[rng.uniform(4e5, 5e5, (500, 2)), rng.uniform(-4e3, 9e3, 500), rng.random((500, 2))])
    # Heights whose sum rounds differently in another order: the mean must be numpy's pairwise one.
    clouds.append(np.c_[rng.random((70_001, 2)), rng.normal(0, 1, 70_001) * 10.0 ** rng.integers(-8, 9, 70_001)])
    for points in clouds:
        jit(True)
        fast = grid.survey(points)[1]
        jit(False)
        slow = grid.survey(points)[1]
        assert np.array(fast).tobytes() == np.array(slow).tobytes()
        assert fast == (points[:, 0].min(), points[:, 0].max(), points[:, 1].min(), points[:, 1].max(),
                        points[:, 2].min(), points[:, 2].max(), points[:, 2].mean())
        assert grid.extremes(points) == fast[:6]
    assert grid._survey_values.compiled(zeros) is NotImplemented


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("column", [0, 1, 2])
def test_survey_refuses_what_numpy_refuses(jit, bad, column):
    """A NaN or an infinity anywhere: both paths refuse the cloud with one message."""
    from dftpcc import grid

    points = np.random.default_rng(2).normal(0, 10, (5000, 3))
    points[4321, column] = bad
    messages = []
    for on in (True, False):
        jit(on)
        with pytest.raises(InvalidInputError) as info:
            grid.survey(points)
        messages.append(str(info.value))
    assert messages[0] == messages[1] and "4321" in messages[0]


def test_rebuilt_points_equal(jit):
    # One point per occupied cell, row-major, the same float64 bits either way.
    from dftpcc import grid, rebuild

    rng = np.random.default_rng(7)
    for rows, cols in ((1, 1), (3, 70), (257, 130)):
        points = np.c_[rng.uniform(4.5e5, 4.5e5 + cols, 4 * rows * cols), rng.uniform(5.2e6, 5.2e6 + rows, 4 * rows * cols),
                       rng.normal(300, 20, 4 * rows * cols)]
        g = grid.fit_grid(points, 1.0)
        dem = grid.rasterize(points[rng.random(len(points)) < 0.3], g)
        out = {}
        for on in (True, False):
            jit(on)
            out[on] = rebuild.dem_to_points(dem)
        assert out[True].dtype == out[False].dtype and out[True].shape == out[False].shape
        assert out[True].tobytes() == out[False].tobytes()


def test_plane_fit_bits_equal(jit):
    # fit_plane's sums in two compiled passes add as numpy's mean and sum do (pairwise), to the bit:
    # masks from one cell to more than numpy's 128-value blocks, holes, lines, a full grid.
    from dftpcc import dem as dem_mod

    rng = np.random.default_rng(9)
    for t in range(60):
        rows, cols = (int(v) for v in rng.integers(1, 90, 2))
        heights = 1e3 * rng.random() + rng.normal(0, rng.uniform(0.01, 50), (rows, cols))
        mask = rng.random((rows, cols)) < [0.02, 0.5, 1.0][t % 3]
        if t % 7 == 0:
            mask[:] = False
            mask[rows // 2] = True  # one line: the normal equations are singular
        g = dem_mod.Grid(x0=0.0, y0=0.0, z0=0.0, resolution=1.0, rows=rows, cols=cols)
        d = dem_mod.DEM(grid=g, heights=np.where(mask, heights, 0.0), mask=mask)
        fits = {}
        for on in (True, False):
            jit(on)
            fits[on] = fill.fit_plane(d)
        assert fits[True] == fits[False], (t, rows, cols)


def test_pairwise_sums_equal_numpys(jit):
    # The compiled sums add as np.sum does (its identity 0.0, then pairwise: blocks of up to 128 in
    # eight accumulators, halved at multiples of 8 above), on sizes around every boundary of that plan.
    from dftpcc import _compiled

    rng = np.random.default_rng(13)
    sizes = [*range(0, 300), 1023, 1024, 1025, 8191, 8192, 8193, 65_537, 1_234_567]
    for n in sizes:
        a = rng.standard_normal(n) * 10.0 ** rng.uniform(-3, 6)
        assert _compiled.array_sum(a) == np.sum(a), n
        leaves = _compiled._pairwise_plan(n)
        assert leaves[leaves[:, 0] >= 0, 1].sum() == n


def test_distance_sums_equal_numpys(jit):
    # The spread's figures from one compiled pass: the sums of the squares and of the far ones (in
    # the points' order), their maximum, how many are far and their cells, as numpy gives them.
    rng = np.random.default_rng(17)
    for n in (0, 1, 7, 8, 129, 5000, 300_001):
        cells = max(1, n // 3)
        idx = rng.integers(0, cells, n)
        z = rng.standard_normal(n)
        heights = 0.5 * rng.standard_normal(cells)
        for tolerance_sq in (0.0, 0.5, 1.5, 100.0):  # all far, some, few, none
            sq = (z - heights[idx]) ** 2
            far = sq > tolerance_sq
            marked = np.zeros(cells, bool)
            marked[idx[far]] = True
            *got, found = grid._distance_sums.compiled(idx, z, heights, tolerance_sq, np.zeros(cells, bool))
            assert tuple(got) == (float(sq.sum()), float(sq.max()) if n else 0.0, int(far.sum()), float(sq[far].sum()))
            assert np.array_equal(found, marked)
            *plain, plain_cells = grid._distance_sums.numpy(idx, z, heights, tolerance_sq, None)
            assert plain == got  # numpy allocates far cells at the first far point only
            assert np.array_equal(marked, plain_cells) if plain_cells is not None else not marked.any()


def test_trial_figures_equal_numpys(jit):
    # A trial's errors, RMSE and largest error, and the step search's quantization error, from
    # compiled passes, as numpy gives them; where numpy would refuse or differ the kernels step aside.
    rng = np.random.default_rng(21)
    for rows, cols in ((1, 1), (3, 50), (40, 37), (200, 300)):
        heights, ref = rng.normal(0, 5, (2, rows, cols))
        for mask in (rng.random((rows, cols)) < 0.6, np.ones((rows, cols), bool)):
            err = (heights - ref)[mask]
            found = analysis._trial_errors.compiled(heights, ref, mask)
            if not err.size:
                assert found is NotImplemented
                continue
            got, rmse, largest = found
            assert np.array_equal(got, err)
            assert (rmse, largest) == (float(np.sqrt(np.mean(err * err))), float(np.abs(err).max()))
        assert analysis._trial_errors.compiled(heights, ref, np.zeros((rows, cols), bool)) is NotImplemented
    nan = np.ones((4, 4))
    nan[1, 1] = np.nan
    assert analysis._trial_errors.compiled(nan, np.zeros((4, 4)), np.ones((4, 4), bool)) is NotImplemented
    for n in (0, 5, 129, 32_768):
        values = rng.laplace(0, 10.0 ** rng.uniform(-2, 2), n)
        for step in (1e-3, 0.05, 0.7, 40.0):
            for deadzone in (0.0, 0.2):
                err = values - quantizer.dequantize(quantizer.quantize(values, step, deadzone), step)
                assert quantizer.quantization_sq_error.compiled(values, step, deadzone) == float(np.sum(err * err))
    # past 2**63: quantize refuses, and so does the numpy twin that runs instead
    assert quantizer.quantization_sq_error.compiled(np.array([1e300, 1.0]), 1e-300, 0.0) is NotImplemented
    assert quantizer.quantization_sq_error.compiled(np.array([np.nan]), 1.0, 0.0) is NotImplemented


def test_weighted_error_sum_equals_numpys(jit):
    # The vertical RMSE's sum of point counts times squared errors, walked over the set cells.
    rng = np.random.default_rng(23)
    for rows, cols in ((1, 1), (2, 300), (64, 65), (300, 200)):
        counts = rng.integers(0, 9, (rows, cols))
        mask = counts > 0
        err = rng.normal(0, 0.3, int(mask.sum()))
        assert sums.weighted_sq_sum.compiled(counts, mask, err) == float(np.sum(counts[mask] * err * err))
    with pytest.raises(ValueError):
        sums.weighted_sq_sum.compiled(counts, mask, err[:-1])
    assert sums.weighted_sq_sum.compiled(counts.astype(np.int32), mask, err) is NotImplemented


def test_plane_added_in_place_equals_numpys(jit):
    rng = np.random.default_rng(29)
    for rows, cols in ((1, 1), (7, 300), (257, 129)):
        heights = rng.normal(0, 3, (rows, cols))
        plane = tuple(float(v) for v in rng.normal(0, [100, 0.1, 0.1]))
        mine = heights.copy()
        assert fill.add_plane.compiled(mine, plane) is None
        assert np.array_equal(mine, heights + fill.plane_values(plane, heights.shape))
        assert fill.add_plane.compiled(mine.astype(np.float32), plane) is NotImplemented  # numpy's, then


def test_predicted_residual_words_match_constriction(jit):
    """RESD kind 5 pushes a group per class and wavefront, many groups sharing a few tables of
    several sizes: the compiled coder writes constriction's words for them, bit for bit."""
    from dftpcc.residual import _decode_predicted, _encode_predicted

    rng = np.random.default_rng(9)
    for shape in ((1, 1), (1, 9), (9, 1), (2, 2), (3, 7), (40, 33), (120, 90)):
        z = np.cumsum(np.cumsum(rng.normal(0, 2.0, shape), 0), 1) + rng.normal(0, 3.0, shape)
        kept = rng.random(shape) < 0.9
        kept[0, 0] = True
        q = np.round(z).astype(np.int64)[kept]
        jit(True)
        compiled = _encode_predicted(q, kept)
        jit(False)
        plain = _encode_predicted(q, kept)
        assert compiled == plain
        np.testing.assert_array_equal(_decode_predicted(plain, kept), q)
        jit(True)
        np.testing.assert_array_equal(_decode_predicted(plain, kept), q)


def test_predicted_residual_decodes_alike_on_both_paths_whatever_its_words(jit):
    """Damaged words decode to the same values on both paths (constriction decodes any words to
    some symbols), or both refuse them: a zero last word, values past 2**31."""
    from dftpcc.residual import _decode_predicted, _encode_predicted

    rng = np.random.default_rng(4)
    z = np.cumsum(np.cumsum(rng.normal(0, 2.0, (30, 41)), 0), 1)
    kept = rng.random(z.shape) < 0.85
    payload = _encode_predicted(np.round(z).astype(np.int64)[kept], kept)
    kinds = set()
    for trial in range(40):
        damaged = bytearray(payload)
        for _ in range(1 + trial % 4):
            at = int(rng.integers(len(payload) - 64, len(payload)))
            damaged[at] ^= 1 << int(rng.integers(0, 8))
        if trial % 10 == 0:
            damaged[-4:] = b"\0\0\0\0"
        outcomes = []
        for on in (True, False):
            jit(on)
            try:
                outcomes.append(_decode_predicted(bytes(damaged), kept))
            except CorruptFileError as exc:
                outcomes.append(str(exc))
        kinds.add(type(outcomes[0]))
        if isinstance(outcomes[0], str):
            assert outcomes[0] == outcomes[1]
        else:
            np.testing.assert_array_equal(outcomes[0], outcomes[1])
    assert kinds == {str, np.ndarray}  # some damage decodes, some is refused


# --- A stage beside the spectrum (kernels.Side) -------------------------------------------------------


@pytest.fixture
def beside(jit, monkeypatch):
    """The kernels loaded; yields a switch: ``use(n)`` lets one map's coding use ``n`` cores,
    on grids of any size (the mask's coder then runs on a thread of its own for ``n`` > 1)."""
    monkeypatch.setattr(kernels, "SIDE_MIN_CELLS", 0)

    def use(cores: int) -> None:
        monkeypatch.setattr(kernels, "CORES", cores)

    return use


def _patchy_points():
    rng = np.random.default_rng(5)
    x, y = rng.uniform(0, 150, (2, 80_000))
    keep = (np.hypot(x - 75, y - 75) < 70) & (rng.random(x.size) < 0.8)
    z = 4 * np.sin(x / 11) + 2 * np.cos(y / 7) + 0.05 * rng.standard_normal(x.size)
    return np.c_[x, y, z][keep]


def test_side_runs_on_a_thread_of_its_own_only_when_it_may(beside, jit, monkeypatch):
    import threading

    where = []

    backends = []

    def stage(value):
        where.append(threading.current_thread())
        backends.append(kernels.current())
        return 2 * value

    for cores, elsewhere in ((2, True), (1, False)):
        beside(cores)
        side = kernels.Side(stage, 21, cells=10)
        assert side.result() == 42
        assert (where[-1] is not threading.current_thread()) is elsewhere
        assert backends[-1] is Backend.COMPILED  # the caller's backend, on a thread of its own too
        assert side.cores_left() is None  # done: no limit left on the caller
    beside(2)
    release = threading.Event()
    side = kernels.Side(release.wait, 30, cells=10)
    assert side.cores_left() == 1  # while it runs, the caller has the other core
    release.set()
    assert side.result() is True and side.cores_left() is None
    monkeypatch.setattr(kernels, "SIDE_MIN_CELLS", 100)  # too small a grid: at once, here
    kernels.Side(stage, 1, cells=99)
    assert where[-1] is threading.current_thread()
    jit(False)  # numpy's passes would wait for each other: at once, here
    kernels.Side(stage, 1, cells=10**6)
    assert where[-1] is threading.current_thread()


def test_side_raises_its_stages_error(beside):
    def stage():
        raise CorruptFileError("the stage's own words")

    for cores in (1, 2):
        beside(cores)
        with pytest.raises(CorruptFileError, match="the stage's own words"):
            kernels.Side(stage, cells=10).result()


def test_files_and_points_equal_with_the_mask_beside(beside):
    """Untiled maps at a fixed step, with the automatic step and at targets: the same bytes, and the
    same decoded points, whether the mask is coded beside the spectrum or before it."""
    import dftpcc

    points = _patchy_points()
    for options in ({"cutoff": 0.7, "step": 0.01}, {"cutoff": 0.7}, {"target_rmse": 0.05},
                    {"target_max_error": 0.05}, {"cutoff": 0.7, "mask": "footprint"}):
        out = {}
        for cores in (1, 2):
            beside(cores)
            blob = dftpcc.compress(points, resolution=0.5, **options)
            out[cores] = blob, dftpcc.decompress(blob)
        assert out[1][0] == out[2][0], options
        assert np.array_equal(out[1][1], out[2][1]), options


def test_a_damaged_file_fails_on_its_mask_first_with_the_mask_beside(beside):
    """A file whose mask and coefficients are both damaged: the mask's error, as a serial decoder
    (which checks the mask first) gives it, on one core or two."""
    import dftpcc

    from .fuzz import craft

    blob = dftpcc.compress(_patchy_points(), resolution=0.5, cutoff=0.7)
    mask = craft.section(blob, b"MASK")
    coef = craft.section(blob, b"COEF")
    other = dftpcc.compress(_patchy_points()[::2], resolution=0.5, cutoff=0.7)  # a valid mask of another count
    for bad_mask, message in ((mask[:3], "occupancy mask"), (craft.section(other, b"MASK"), "disagrees with the header")):
        damaged = craft.fix_crcs(craft.replace_section(craft.replace_section(blob, b"MASK", bad_mask),
                                                       b"COEF", coef[: len(coef) // 3]))
        errors = set()
        for cores in (1, 2):
            beside(cores)
            with pytest.raises(CorruptFileError, match=message) as caught:
                dftpcc.decompress(damaged)
            errors.add(str(caught.value))
        assert len(errors) == 1, errors


def test_the_residual_layer_decodes_beside_the_spectrum(beside, monkeypatch):
    """A map with a residual layer decodes that layer on the side thread with its mask (its integers
    need only the mask), not after the spectrum: the same points on one core or two."""
    import threading

    import dftpcc
    from dftpcc import decoder

    blob = dftpcc.compress(_patchy_points(), resolution=0.5, target_max_error=0.05)
    where, real = [], decoder.decode_residual
    monkeypatch.setattr(decoder, "decode_residual", lambda *a: where.append(threading.current_thread()) or real(*a))
    out = {}
    for cores in (1, 2):
        beside(cores)
        out[cores] = dftpcc.decompress(blob)
        assert (where[-1] is not threading.current_thread()) is (cores == 2)
    assert np.array_equal(out[1], out[2])


def test_a_damaged_residual_layer_fails_after_the_spectrum_with_it_beside(beside):
    """A file whose residual layer is damaged fails with the layer's error; one whose coefficients
    are damaged too fails with theirs (a serial decoder's order: mask, spectrum, residual), on one
    core or two."""
    import dftpcc

    from .fuzz import craft

    blob = dftpcc.compress(_patchy_points(), resolution=0.5, target_max_error=0.05)
    resd, coef = craft.section(blob, b"RESD"), craft.section(blob, b"COEF")
    bad_resd = craft.fix_crcs(craft.replace_section(blob, b"RESD", resd[: len(resd) // 2]))
    bad_coef = craft.fix_crcs(craft.replace_section(blob, b"COEF", coef[: len(coef) // 3]))
    both = craft.fix_crcs(craft.replace_section(bad_resd, b"COEF", coef[: len(coef) // 3]))

    def error(damaged: bytes) -> str:
        with pytest.raises(CorruptFileError) as caught:
            dftpcc.decompress(damaged)
        return str(caught.value)

    found = {}
    for cores in (1, 2):
        beside(cores)
        found[cores] = error(bad_resd), error(bad_coef), error(both)
    layer, spectrum, first = found[1]
    assert found[2] == found[1] and layer != spectrum and first == spectrum, found


def test_a_forked_child_codes_with_the_mask_beside(beside):
    # A child forked after the pool's threads started has none of them: it must start its own, not
    # wait for the parent's.
    import multiprocessing

    import dftpcc

    beside(2)
    points = _patchy_points()
    blob = dftpcc.compress(points, resolution=0.5, cutoff=0.7)
    with multiprocessing.get_context("fork").Pool(1) as pool:
        child = pool.apply_async(dftpcc.compress, (points,), {"resolution": 0.5, "cutoff": 0.7})
        assert child.get(timeout=60) == blob


def test_band_codes_are_the_numpy_bands(jit):
    """Each value's band scale code, worked out value by value in one compiled pass, is numpy's
    ``codes[band_ids(...) - lo]`` under every layout, on the chunks the coder writes and on radii
    that fall exactly on a ring's edge or an angle on a sector's."""
    rng = np.random.default_rng(21)
    chunks = [(radius, angle) for _, radius, angle in _coefficient_chunks(rng)]
    edges = np.arange(0.0, 64.0, 4.0)
    chunks.append((np.repeat(edges, 17), np.tile(np.linspace(0.0, 1.0, 17), edges.size)))
    for radius, angle in chunks:
        for layout, (width, sectors) in enumerate(coding.BAND_LAYOUTS):
            bands = coding.band_ids(radius, angle, layout)
            codes = rng.integers(0, 256, int(bands.max() - bands.min()) + 1).astype(np.uint8)
            expected = codes[bands - bands.min()]
            for on in (True, False):
                jit(on)
                lo, hi, made = coding._band_range(radius, angle, width, sectors)
                assert (lo, hi) == (bands.min(), bands.max())
                np.testing.assert_array_equal(coding._band_codes(radius, angle, width, sectors, codes, lo, made),
                                              expected)


def test_band_totals_are_numpys_bincounts_to_the_bit(jit):
    """Each band's count and sum of magnitudes, added in one compiled pass, are np.bincount's (the
    same sums to the bit: rate control ranks candidates by them), under every layout of the chunks
    the coder writes, with bands that start above 0 and sums of very unequal magnitudes."""
    from dftpcc import geometric

    rng = np.random.default_rng(22)
    for _, radius, angle in _coefficient_chunks(rng):
        for layout in range(len(coding.BAND_LAYOUTS)):
            bands = coding.band_ids(radius, angle, layout) + int(rng.integers(0, 5))
            magnitudes = np.abs(rng.standard_cauchy(bands.size)) * 10.0 ** rng.uniform(-3, 6, bands.size)
            found = []
            for on in (True, False):
                jit(on)
                found.append(geometric._band_totals(bands, magnitudes))
            (lo, count, total), (lo_np, count_np, total_np) = found
            assert lo == lo_np and count.dtype == count_np.dtype
            np.testing.assert_array_equal(count, count_np)
            assert total.tobytes() == total_np.tobytes()


def test_layout_totals_are_numpys_to_the_bit(jit):
    """Each band's count and sum of magnitudes under a layout, the band worked out where the value is
    added, are numpy's (band_ids, then np.bincount): on the coder's chunks and on radii and angles
    that fall exactly on a ring's or a sector's edge."""
    rng = np.random.default_rng(23)
    chunks = [(radius, angle) for _, radius, angle in _coefficient_chunks(rng)]
    edges = np.arange(0.0, 64.0, 4.0)
    chunks.append((np.repeat(edges, 17), np.tile(np.linspace(0.0, 1.0, 17), edges.size)))
    for radius, angle in chunks:
        magnitudes = np.abs(rng.standard_cauchy(radius.size)) * 10.0 ** rng.uniform(-3, 6, radius.size)
        for layout, (width, sectors) in enumerate(coding.BAND_LAYOUTS):
            found = []
            for on in (True, False):
                jit(on)
                found.append(coding._layout_totals(radius, angle, width, sectors, magnitudes))
            (lo, count, total), (lo_np, count_np, total_np) = found
            bands = coding.band_ids(radius, angle, layout)
            assert lo == lo_np == bands.min() and count.size == bands.max() - bands.min() + 1
            np.testing.assert_array_equal(count, count_np)
            assert total.tobytes() == total_np.tobytes()


def test_residual_added_in_one_pass_is_numpys(jit):
    """The residual layer added cell by cell gives numpy's bits (``heights[mask] += q * step``)."""
    from dftpcc import decoder

    rng = np.random.default_rng(8)
    for mask, _ in _masks(rng):
        heights = rng.normal(0.0, 300.0, mask.shape)
        q = rng.integers(-(1 << 40), 1 << 40, int(mask.sum()))
        step = float(rng.uniform(1e-4, 3.0))
        expected = heights.copy()
        expected[mask] += q * step
        for on in (True, False):
            jit(on)
            got = heights.copy()
            decoder._add_residual(got, mask, q, step)
            assert np.array_equal(got.view(np.int64), expected.view(np.int64))


def test_coefficients_dequantized_where_they_go_are_numpys(jit):
    """The decoder's coefficient block written value by value gives numpy's scatter of
    ``q * step`` (the same bits, zeros elsewhere), for a whole grid and a corner of it."""
    rng = np.random.default_rng(9)
    for shape, n in (((337, 348), 337 * 348), ((64, 40), 700), ((1, 1), 1), ((5, 7), 0)):
        where = rng.permutation(shape[0] * shape[1])[:n].astype(np.int64)
        q = rng.integers(-(1 << 40), 1 << 40, n)
        step = float(rng.uniform(1e-4, 3.0))
        expected = np.zeros(shape)
        expected.ravel()[where] = q.astype(np.float64) * step
        for on in (True, False):
            jit(on)
            got = quantizer.dequantize_into(shape, where, q, step)
            assert got.shape == shape and np.array_equal(got.view(np.int64), expected.view(np.int64))


def test_scale_codes_counted_in_one_pass_are_numpys():
    rng = np.random.default_rng(10)
    for n in (0, 1, 1000, 100_000):
        codes = rng.integers(0, 256, n).astype(np.uint8)
        codes[: n // 2] = rng.integers(0, 3, n // 2)  # a few codes carry most values
        assert np.array_equal(kernels.compiled_module().code_counts(codes), np.bincount(codes, minlength=256))


def test_kept_neighbours_are_the_shifted_grids(jit):
    """The predicted residual's neighbours read cell by cell are those of the shifted grids, edges
    included (row 0, column 0, the cell (0, 0)), on every mask shape, of every kept cell or every
    stride-th."""
    from dftpcc import residual

    rng = np.random.default_rng(11)
    for mask, _ in _masks(rng):
        grid = rng.integers(-(1 << 40), 1 << 40, mask.shape)
        offsets = residual.NEIGHBOURS + ((3, -2),)
        expected = np.stack([residual._shifted(grid, up, left)[mask] for up, left in offsets]) \
            if mask.any() else np.zeros((len(offsets), 0), dtype=np.int64)
        for on in (True, False):
            jit(on)
            assert np.array_equal(residual._kept_neighbours(grid, mask, offsets), expected)
            for stride in (2, 7):  # every stride-th kept cell: the predicted layout's fit
                assert np.array_equal(residual._kept_neighbours(grid, mask, offsets, stride), expected[:, ::stride])


def test_sparse_layer_integers_are_numpys(jit):
    """A sparse residual layer's integers placed cell by cell are numpy's (signs, zeros, order)."""
    from dftpcc import residual

    rng = np.random.default_rng(12)
    for mask, _ in _masks(rng):
        picture = mask & (rng.random(mask.shape) < 0.1)
        n = int(picture.sum())
        sizes = rng.integers(0, 1 << 40, n)
        negative = np.unpackbits(rng.integers(0, 256, (n + 7) // 8, dtype=np.uint8))
        negative[n:] = 0
        expected = np.zeros(int(mask.sum()), dtype=np.int64)
        expected[picture[mask]] = np.where(negative[:n] == 1, -(sizes + 1), sizes + 1)
        for on in (True, False):
            jit(on)
            assert np.array_equal(residual._signed_at(picture, mask, sizes, negative), expected)


def test_predicted_errors_and_classes_are_numpys(jit):
    """Kind 5's errors and classes read cell by cell (interior by offset, edges by format.md's rules)
    are the neighbour arrays' ones, on every mask shape, with weights of both signs."""
    from dftpcc import residual

    rng = np.random.default_rng(13)
    for mask, _ in _masks(rng):
        if not mask.any():
            continue
        q = np.cumsum(rng.integers(-300, 301, int(mask.sum())))
        grid = residual._filled(q, mask)
        weights = rng.integers(-(1 << 17), 1 << 17, len(residual.NEIGHBOURS))
        expected = residual._errors_and_classes.numpy(grid, mask, weights)
        found = residual._errors_and_classes.compiled(grid, mask, weights)
        assert found is not NotImplemented
        for a, b in zip(found, expected):
            assert a.dtype == b.dtype and np.array_equal(a, b)


def test_predicted_coding_order_is_numpys(jit):
    """Kind 5's order (wavefront, class, row), group bounds and classes from one counting sort per
    wavefront are the two stable sorts' ones, with classes of code 0 left out."""
    from dftpcc import residual

    rng = np.random.default_rng(14)
    for t, (mask, _) in enumerate(_masks(rng)):
        classes = rng.integers(0, residual.CLASSES, int(mask.sum()))
        codes = [np.zeros(residual.CLASSES, np.uint8), np.ones(residual.CLASSES, np.uint8),
                 rng.integers(0, 3, residual.CLASSES).astype(np.uint8)][t % 3]
        expected = residual._coding_order.numpy(mask, classes, codes)
        found = residual._coding_order.compiled(mask, classes, codes)
        assert found is not NotImplemented
        for a, b in zip(found, expected):
            assert np.array_equal(a, b)


def test_a_geotiff_counts_its_pixels_for_the_backend(monkeypatch, tmp_path):
    """compress_file of a GeoTIFF chooses the backend from its pixels, as a cloud's from its points:
    a 1.6 G-cell raster ran every stage on numpy (its format stated no count)."""
    pytest.importorskip("rasterio")
    import dftpcc
    from dftpcc import files, io

    dem = dftpcc.open(dftpcc.compress(_patchy_points(), resolution=0.5, cutoff=0.7)).read_dem()
    tif = tmp_path / "dem.tif"
    io.write_geotiff(tif, dem)
    pixels = dem.heights.size
    assert files.stored_point_count(tif) == pixels
    monkeypatch.delenv("DFTPCC_JIT", raising=False)
    for threshold, loaded in ((pixels + 1, False), (pixels, True)):
        monkeypatch.setattr(kernels, "_state", {"module": None, "tried": False, "found": None})
        monkeypatch.setattr(kernels, "COMPILED_MIN_POINTS", threshold)
        files.compress_file(tif, tmp_path / f"{threshold}.dftpc", cutoff=0.5)
        assert (kernels._state["module"] is not None) is loaded


def test_median_predictor_errors_are_numpys(jit):
    """The median predictor's errors (rate control's look at the predicted layout) read cell by cell
    are the neighbour arrays' ones, edges included, on every mask shape."""
    from dftpcc import residual

    rng = np.random.default_rng(15)
    for mask, _ in _masks(rng):
        grid = residual._filled(np.cumsum(rng.integers(-300, 301, int(mask.sum()))), mask)
        found = residual._median_errors.compiled(grid, mask)
        assert found is not NotImplemented and np.array_equal(found, residual._median_errors.numpy(grid, mask))


def test_fit_sums_are_numpys(jit):
    """The predicted layout's fit sums taken cell by cell are numpy's exact products, edges
    included, every cell or every stride-th, with cells past FIT_LIMIT left out."""
    from dftpcc import residual

    rng = np.random.default_rng(16)
    for t, (mask, _) in enumerate(_masks(rng)):
        if not mask.any():
            continue
        jump = 1 << 16 if t % 3 == 0 else 300  # some differences past FIT_LIMIT
        grid = residual._filled(np.cumsum(rng.integers(-jump, jump + 1, int(mask.sum()))), mask)
        for stride in (1, 3):
            found = residual._fit_sums.compiled(grid, mask, stride)
            assert found is not NotImplemented and np.array_equal(found, residual._fit_sums.numpy(grid, mask, stride))


def test_filled_grid_is_numpys(jit):
    """The predicted layout's values V (each cell not kept takes its W; column 0 the cell above)
    filled cell by cell are numpy's, on every mask shape."""
    from dftpcc import residual

    rng = np.random.default_rng(17)
    for mask, _ in _masks(rng):
        q = rng.integers(-(1 << 40), 1 << 40, int(mask.sum()))
        found = residual._filled.compiled(q, mask)
        assert found is not NotImplemented and np.array_equal(found, residual._filled.numpy(q, mask))
