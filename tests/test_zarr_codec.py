"""dftpcc as a Zarr v3 and a numcodecs codec: real DEMs written and read back within the bound.

Importing the codec modules registers them (as zarr's and numcodecs' own codecs do);
the entry points do it without an import once dftpcc is installed from this tree
(``test_entry_points*`` check those).
"""

from __future__ import annotations

import importlib
import math
import os
import pickle
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dftpcc.chunkcodec import NO_DATA_MAGIC, chunk_params, coding_bound, decode_chunk, encode_chunk
from dftpcc.errors import CorruptFileError, InvalidInputError, MissingDependencyError

from .conftest import data_file

zarr = pytest.importorskip("zarr")
numcodecs = pytest.importorskip("numcodecs")
xr = pytest.importorskip("xarray")
dask = pytest.importorskip("dask")

from dftpcc.numcodecs_codec import Dftpcc  # noqa: E402
from dftpcc.zarr_codec import CODEC_NAME, DftpccCodec  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
#: Chunk edge of the real-DEM tests: Gale's 337 x 348 pixels become 3 x 3 chunks, the last ones partial.
CHUNK = 128
#: Relative slack on a float bound: none is needed, the codec keeps it exactly; this only
#: absorbs the float64 subtraction of the check itself at heights of -4400 m.
CHECK_SLACK = 1e-12


def _read_dem(name: str) -> tuple[np.ndarray, float | None]:
    import rasterio

    with rasterio.open(data_file(f"dems/{name}")) as src:
        return src.read(1), src.nodata


def _max_error(decoded: np.ndarray, original: np.ndarray) -> float:
    """Largest |decoded - original| over cells where both hold data, metres."""
    d, o = decoded.astype(np.float64), original.astype(np.float64)
    both = np.isfinite(d) & np.isfinite(o)
    return float(np.abs(d - o)[both].max())


def _chunk_bytes(store) -> int:
    return sum(len(v.to_bytes()) for k, v in store._store_dict.items() if "/c/" in k or k.startswith("c/"))


# --- real DEMs ------------------------------------------------------------------------

def test_mars_gale_through_xarray_and_dask_keeps_the_bound():
    """Gale (float32) with a no-data disc, written by xarray with the v3 codec in 128 x 128 chunks
    (partial at the right and bottom edges), read back lazily with dask: every cell within 5 cm,
    the no-data cells exactly NaN, the dtype float32, and far fewer bytes than raw."""
    heights, _ = _read_dem("mars_gale_1m.tif")
    assert heights.dtype == np.float32
    rows, cols = np.indices(heights.shape)
    heights = heights.copy()
    heights[(rows - 60) ** 2 + (cols - 300) ** 2 < 40 ** 2] = np.nan  # a hole across four chunks
    bound = 0.05
    store = zarr.storage.MemoryStore()
    da = xr.DataArray(heights, dims=("y", "x"), name="height")
    da.to_dataset().to_zarr(store, consolidated=False, encoding={"height": {
        "serializer": DftpccCodec(max_error=bound), "compressors": None, "chunks": (CHUNK, CHUNK)}})

    opened = xr.open_zarr(store, consolidated=False)["height"]
    assert opened.chunks == ((128, 128, 81), (128, 128, 92))  # dask-backed, one task per chunk
    assert opened.dtype == np.float32
    worst = float(np.abs(opened - da).max().compute(scheduler="threads"))
    assert 0 < worst <= bound
    decoded = opened.values
    assert np.array_equal(np.isnan(decoded), np.isnan(heights))
    assert _chunk_bytes(store) < heights.nbytes / 4


def test_dask_distributed_workers_read_the_chunks_in_parallel(tmp_path):
    """Two worker processes decode Gale's chunks from a store on disk (the codec travels by
    pickle and registers itself there on import) and the result equals a serial read."""
    distributed = pytest.importorskip("distributed")
    heights, _ = _read_dem("mars_gale_1m.tif")
    path = tmp_path / "gale.zarr"
    xr.DataArray(heights, dims=("y", "x"), name="height").to_dataset().to_zarr(
        path, consolidated=False, encoding={"height": {
            "serializer": DftpccCodec(max_error=0.2), "compressors": None, "chunks": (CHUNK, CHUNK)}})
    serial = xr.open_zarr(path, consolidated=False)["height"].compute(scheduler="synchronous")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=40) as cluster, distributed.Client(cluster):
        lazy = xr.open_zarr(path, consolidated=False)["height"]
        parallel = lazy.compute()
        worst = float(np.abs(lazy - heights).max().compute())
    assert np.array_equal(parallel.values, serial.values)
    assert 0 < worst <= 0.2


def test_moon_kepler_int16_rounds_to_whole_metres():
    """Kepler (int16) in a v3 array: a bound of 2.5 m leaves at most 2 whole metres, and a bound
    below 1 m gives every height back exactly."""
    heights, nodata = _read_dem("moon_kepler_lola_48m.tif")
    assert heights.dtype == np.int16
    crop = heights[200:460, 300:560]  # the crater wall: 3 x 3 chunks of steep terrain
    z = zarr.create_array(zarr.storage.MemoryStore(), shape=crop.shape, chunks=(CHUNK, CHUNK), dtype="int16",
                          fill_value=int(nodata), serializer=DftpccCodec(max_error=2.5), compressors=None)
    z[:] = crop
    back = z[:]
    assert back.dtype == np.int16
    err = np.abs(back.astype(np.int64) - crop)
    assert err.max() == 2  # whole metres, and the bound is used

    small = crop[:40, :40]
    exact = zarr.create_array(zarr.storage.MemoryStore(), shape=small.shape, chunks=(40, 40), dtype="int16",
                              serializer=DftpccCodec(max_error=0.9), compressors=None)
    exact[:] = small
    assert np.array_equal(exact[:], small)


def test_mars_korolev_numcodecs_in_zarr_format_2_with_nodata():
    """Korolev (int16, 22 % nodata = 0) through the numcodecs codec in a format 2 array:
    the nodata cells come back exactly 0, the others within 10 m."""
    heights, nodata = _read_dem("mars_korolev_mola.tif")
    assert nodata == 0
    crop = heights[:, :300]
    assert (crop == 0).mean() > 0.05  # the crop includes nodata
    codec = Dftpcc(max_error=10.0, dtype="int16", fill_value=0)
    z = zarr.create_array(zarr.storage.MemoryStore(), shape=crop.shape, chunks=(CHUNK, CHUNK), dtype="int16",
                          fill_value=0, zarr_format=2, compressors=codec, filters=None)
    z[:] = crop
    back = z[:]
    assert np.array_equal(back == 0, crop == 0)
    assert np.abs(back.astype(np.int64) - crop).max() <= 10


# --- chunks at the edges of what zarr passes -----------------------------------------------

def _round_trip(values, bound, fill_value=None):
    data = encode_chunk(values, chunk_params(bound), fill_value=fill_value)
    return data, decode_chunk(data, values.dtype, fill_value=fill_value, shape=values.shape)


def test_a_chunk_without_data_is_a_short_record():
    nan = np.full((5, 9), np.nan, dtype=np.float32)
    data, back = _round_trip(nan, 0.1)
    assert data.startswith(NO_DATA_MAGIC) and len(data) == 16
    assert back.dtype == np.float32 and back.shape == (5, 9) and np.isnan(back).all()
    ints = np.full((4, 4), -32768, dtype=np.int16)
    _, back = _round_trip(ints, 1.0, fill_value=-32768)
    assert np.array_equal(back, ints)
    with pytest.raises(CorruptFileError, match="chunks are 4 x 4"):
        decode_chunk(encode_chunk(nan, chunk_params(0.1)), "float32", shape=(4, 4))


def test_zarr_array_with_all_nan_chunks_written():
    """With write_empty_chunks the all-NaN chunks reach the codec too, and read back NaN."""
    values = np.full((6, 10), np.nan)
    values[:3, :4] = [[1, 2, 3, 4], [2, 3, 4, 5], [3, 4, 5, 7]]
    store = zarr.storage.MemoryStore()
    z = zarr.create_array(store, shape=values.shape, chunks=(3, 4), dtype="float64", fill_value=np.nan,
                          serializer=DftpccCodec(max_error=0.01), compressors=None,
                          config={"write_empty_chunks": True})
    z[:] = values
    assert len([k for k in store._store_dict if k.startswith("c/")]) == 6
    back = z[:]
    assert np.array_equal(np.isnan(back), np.isnan(values))
    assert _max_error(back, values) <= 0.01


def test_partial_edge_chunks_are_padded_with_the_fill_value():
    """A 5 x 7 array in 4 x 4 chunks: zarr hands the codec full 4 x 4 chunks padded with the
    fill value, which the codec treats as no data, so the edges cost little and read back right."""
    rng = np.random.default_rng(5)
    values = (1000 + rng.normal(size=(5, 7))).astype(np.float32)
    z = zarr.create_array(zarr.storage.MemoryStore(), shape=values.shape, chunks=(4, 4), dtype="float32",
                          serializer=DftpccCodec(max_error=0.02), compressors=None)  # zarr's fill value 0.0
    z[:] = values
    assert _max_error(z[:], values) <= 0.02
    padded = np.zeros((4, 4), np.float32)
    padded[:1, :3] = values[4:, 4:]
    _, back = _round_trip(padded, 0.02, fill_value=np.float32(0.0))
    assert np.array_equal(back == 0, padded == 0)


@pytest.mark.parametrize("shape", [(1, 1), (1, 17), (23, 1), (2, 2)])
@pytest.mark.parametrize("dtype", ["float16", "float32", "float64", "int16", "uint16"])
def test_tiny_and_constant_chunks(shape, dtype):
    rng = np.random.default_rng(sum(shape))
    varied = (3000 + 40 * rng.normal(size=shape)).astype(dtype)
    constant = np.full(shape, 1234, dtype=dtype)
    for values in (varied, constant):
        _, back = _round_trip(values, 1.5)
        assert back.dtype == np.dtype(dtype) and back.shape == shape
        err = np.abs(back.astype(np.float64) - values.astype(np.float64))
        assert err.max() <= (1.0 if values.dtype.kind in "iu" else 1.5)


def test_float32_bound_includes_the_rounding_to_float32():
    """At -4450 m float32 cells are 0.5 mm apart: a 0.4 mm bound is still kept after rounding."""
    rng = np.random.default_rng(7)
    values = (-4450 + np.cumsum(rng.normal(scale=0.01, size=(30, 30)), axis=1)).astype(np.float32)
    bound = 4e-4
    assert coding_bound(bound, values) < bound
    _, back = _round_trip(values, bound)
    assert back.dtype == np.float32
    assert _max_error(back, values) <= bound


FLOAT_SETTINGS = settings(max_examples=30, deadline=None, derandomize=bool(os.environ.get("CI")),
                          suppress_health_check=[HealthCheck.too_slow])


@FLOAT_SETTINGS
@given(seed=st.integers(0, 2**32 - 1), rows=st.integers(1, 12), cols=st.integers(1, 12),
       dtype=st.sampled_from(["float32", "float64"]), bound=st.floats(1e-3, 10.0),
       scale=st.floats(0.01, 500.0), offset=st.floats(-9000.0, 9000.0), holes=st.floats(0.0, 0.9))
def test_round_trip_within_the_bound(seed, rows, cols, dtype, bound, scale, offset, holes):
    rng = np.random.default_rng(seed)
    values = (offset + scale * np.cumsum(rng.normal(size=(rows, cols)), axis=0)).astype(dtype)
    values[rng.random((rows, cols)) < holes] = np.nan
    data, back = _round_trip(values, bound)
    assert back.dtype == np.dtype(dtype)
    assert np.array_equal(np.isnan(back), np.isnan(values))
    if not np.isnan(values).all():
        assert _max_error(back, values) <= bound * (1 + CHECK_SLACK)


@FLOAT_SETTINGS
@given(seed=st.integers(0, 2**32 - 1), rows=st.integers(1, 12), cols=st.integers(1, 12),
       dtype=st.sampled_from(["int16", "uint16", "int32"]), bound=st.floats(0.1, 20.0),
       scale=st.floats(0.5, 300.0), nodata=st.booleans())
def test_integers_round_to_whole_units_within_the_bound(seed, rows, cols, dtype, bound, scale, nodata):
    rng = np.random.default_rng(seed)
    info = np.iinfo(dtype)
    middle = (int(info.min) + int(info.max)) // 2
    values = np.clip(middle + scale * np.cumsum(rng.normal(size=(rows, cols)), axis=1), info.min, info.max)
    values = np.rint(values).astype(dtype)
    fill = info.max if nodata else None  # the top of the range: no data
    if nodata:
        values[rng.random((rows, cols)) < 0.3] = fill
    _, back = _round_trip(values, bound, fill_value=fill)
    assert back.dtype == np.dtype(dtype)
    if nodata:
        assert np.array_equal(back == fill, values == fill)
    err = np.abs(back.astype(np.int64) - values.astype(np.int64))
    assert err.max() <= math.floor(bound)


# --- what the codecs refuse ------------------------------------------------------------------

@pytest.mark.parametrize("bound", [5e-324, 2.5e-323])
def test_a_bound_the_arithmetic_cannot_honour_is_refused(bound):
    """Issue 41, item 8: 5e-324 halved to 0.0, which means "no target", and a chunk came back 28 m off."""
    rng = np.random.default_rng(2)
    values = 3000 + 30 * np.cumsum(rng.normal(size=(24, 24)), axis=0)
    with pytest.raises(InvalidInputError, match="too fine"):
        encode_chunk(values, chunk_params(bound))
    with pytest.raises(InvalidInputError, match="too fine"):
        Dftpcc(max_error=bound, dtype="f8").encode(values)
    with pytest.raises(InvalidInputError, match="too fine"):
        zarr.create_array({}, shape=values.shape, chunks=values.shape, dtype="float64",
                          serializer=DftpccCodec(max_error=bound), compressors=None)[:] = values


@pytest.mark.parametrize("shape", [(4096, 4096), (2049, 2048), (1, (1 << 22) + 1)])
def test_a_chunk_larger_than_the_codec_codes_is_refused_with_the_reason(shape):
    """Issue 41, item 9: one 4096 x 4096 float64 chunk at max_error=0.1 did not finish in 9 minutes."""
    from dftpcc.chunkcodec import MAX_CHUNK_CELLS

    assert math.prod(shape) > MAX_CHUNK_CELLS == 2048 * 2048
    values = np.zeros(shape)
    with pytest.raises(InvalidInputError, match=r"more than the 4,194,304 \(2048 x 2048\).*faster than the chunk"):
        encode_chunk(values, chunk_params(0.1))
    with pytest.raises(InvalidInputError, match="use smaller chunks"):
        Dftpcc(max_error=0.1, dtype="f8").encode(values)
    with pytest.raises(InvalidInputError, match="use smaller chunks"):  # when the array is made, before any data
        zarr.create_array({}, shape=shape, chunks=shape, dtype="float64",
                          serializer=DftpccCodec(max_error=0.1), compressors=None)


def test_the_codec_checks_the_bound_after_coding(monkeypatch):
    """Issue 41, item 8: whatever the encoder does, a chunk beyond its bound is not handed to the array."""
    import dftpcc.chunkcodec as chunkcodec
    from dftpcc.errors import DftpccError

    rng = np.random.default_rng(3)
    values = 3000 + 30 * np.cumsum(rng.normal(size=(24, 24)), axis=0)
    sloppy = chunkcodec.encode_dem
    monkeypatch.setattr(chunkcodec, "encode_dem",
                        lambda dem, params: sloppy(dem, params.replace(target_max_error=50 * params.target_max_error)))
    with pytest.raises(DftpccError, match="beyond its max_error of 0.1 m"):
        encode_chunk(values, chunk_params(0.1))
    with pytest.raises(DftpccError, match="beyond its max_error of 2.5 m"):
        encode_chunk(np.rint(values).astype(np.int16), chunk_params(2.5))



def test_refusals_are_clear():
    with pytest.raises(InvalidInputError, match="max_error must be a positive number"):
        DftpccCodec(max_error=0)
    with pytest.raises(InvalidInputError, match="profile must be one of"):
        DftpccCodec(max_error=1, profile="fast")
    with pytest.raises(InvalidInputError, match="cutoff must be in"):
        Dftpcc(max_error=1, dtype="f4", cutoff=1.5)
    for dtype in ("bool", "complex64", "longdouble", "U4"):
        with pytest.raises(InvalidInputError, match="floats .* or integers"):
            Dftpcc(max_error=1, dtype=dtype)
    with pytest.raises(InvalidInputError, match="2D DEM arrays"):
        zarr.create_array({}, shape=(2, 8, 8), chunks=(1, 8, 8), dtype="float32",
                          serializer=DftpccCodec(max_error=1), compressors=None)
    with pytest.raises(InvalidInputError, match="floats .* or integers"):
        zarr.create_array({}, shape=(8, 8), chunks=(8, 8), dtype="complex64",
                          serializer=DftpccCodec(max_error=1), compressors=None)
    values = np.ones((4, 4))
    values[0, 0] = np.nan
    with pytest.raises(InvalidInputError, match="fill value is 0.0.*fill_value=nan"):
        encode_chunk(values, chunk_params(0.1), fill_value=0.0)
    values[0, 0] = np.inf
    with pytest.raises(InvalidInputError, match="infinite heights"):
        encode_chunk(values, chunk_params(0.1))
    codec = Dftpcc(max_error=0.1, dtype="float32")
    with pytest.raises(InvalidInputError, match="flat buffer"):
        codec.encode(np.ones(16, np.float32).tobytes())
    with pytest.raises(InvalidInputError, match="give dtype='<f8'"):
        codec.encode(np.ones((4, 4)))


def test_corrupt_chunks_are_refused():
    with pytest.raises(CorruptFileError):
        decode_chunk(b"not a chunk at all", "float32")
    data = encode_chunk(np.arange(16.0).reshape(4, 4), chunk_params(0.1))
    with pytest.raises(CorruptFileError):
        decode_chunk(data[:-3], "float64")
    with pytest.raises(CorruptFileError, match="16 bytes"):
        decode_chunk(NO_DATA_MAGIC + b"\x00" * 4, "float32")
    holes = np.arange(9.0).reshape(3, 3)
    holes[1, 1] = np.nan
    for values in (np.full((3, 3), np.nan), holes):  # no data, but nothing to give those cells
        with pytest.raises(CorruptFileError, match="integer array without a fill value"):
            decode_chunk(encode_chunk(values, chunk_params(1)), "int16")


# --- configuration, registration ----------------------------------------------------------

def test_configurations_round_trip():
    v3 = DftpccCodec(max_error=0.25, cell_size=2.0, profile="paper", cutoff=0.5)
    assert DftpccCodec.from_dict(v3.to_dict()) == v3
    assert v3.to_dict() == {"name": "dftpcc", "configuration": {"max_error": 0.25, "cell_size": 2.0,
                                                                "profile": "paper", "cutoff": 0.5}}
    assert pickle.loads(pickle.dumps(v3)) == v3  # dask.distributed ships codecs to workers
    assert zarr.registry.get_codec_class("dftpcc") is DftpccCodec  # registered by importing it

    v2 = Dftpcc(max_error=0.25, dtype="float32", fill_value=-32767.0)
    again = numcodecs.get_codec(v2.get_config())
    assert isinstance(again, Dftpcc) and again.get_config() == v2.get_config()
    assert v2.get_config()["dtype"] == "<f4"
    assert Dftpcc(max_error=1, dtype="f8", fill_value=math.nan).get_config().get("fill_value") is None
    values = np.linspace(0, 30, 64, dtype=np.float32).reshape(8, 8)
    out = np.empty(64, np.float32)
    v2.decode(v2.encode(values), out=out)
    assert np.abs(out.reshape(8, 8) - values).max() <= 0.25
    assert repr(pickle.loads(pickle.dumps(v2))) == repr(v2)


def _entry_points() -> dict[str, dict[str, str]]:
    with open(REPO / "pyproject.toml", "rb") as fh:
        return tomllib.load(fh)["project"]["entry-points"]


def test_entry_points_in_pyproject_name_the_codecs():
    """The names zarr and numcodecs look a codec up by are the ones the classes declare."""
    eps = _entry_points()
    for group, name, cls in (("zarr.codecs", CODEC_NAME, DftpccCodec), ("numcodecs.codecs", Dftpcc.codec_id, Dftpcc)):
        module, _, attr = eps[group][name].partition(":")
        assert getattr(importlib.import_module(module), attr) is cls
    assert DftpccCodec(max_error=1).to_dict()["name"] == CODEC_NAME == Dftpcc.codec_id == "dftpcc"


def test_entry_points_installed():
    """Once dftpcc is installed from this tree, zarr and numcodecs find both codecs by name."""
    from importlib.metadata import entry_points

    if not entry_points(group="zarr.codecs", name=CODEC_NAME):
        pytest.skip("the installed dftpcc predates its entry points: reinstall it (pip install -e .)")
    for group, name, cls in (("zarr.codecs", CODEC_NAME, DftpccCodec), ("numcodecs.codecs", "dftpcc", Dftpcc)):
        (ep,) = entry_points(group=group, name=name)
        assert ep.value == _entry_points()[group][name]
        assert ep.load() is cls


def test_missing_zarr_names_the_extra(monkeypatch):
    for module in ("dftpcc.zarr_codec", "dftpcc.numcodecs_codec"):
        monkeypatch.delitem(sys.modules, module)
    monkeypatch.setitem(sys.modules, "zarr.abc.codec", None)  # as if the extra were not installed
    monkeypatch.setitem(sys.modules, "numcodecs.abc", None)
    with pytest.raises(MissingDependencyError, match=r"needs zarr 3.*pip install 'dftpcc\[zarr\]'"):
        importlib.import_module("dftpcc.zarr_codec")
    with pytest.raises(MissingDependencyError, match=r"needs numcodecs.*pip install 'dftpcc\[zarr\]'"):
        importlib.import_module("dftpcc.numcodecs_codec")


def test_chunks_code_in_threads_as_they_do_one_by_one():
    """Zarr codes chunks in threads: no state shared between calls may break or change a chunk."""
    import concurrent.futures

    import rasterio

    from dftpcc.chunkcodec import decode_chunk, encode_chunk
    from dftpcc.params import make_params

    with rasterio.open(data_file("dems/mars_korolev_mola.tif")) as ds:
        values = ds.read(1).astype(np.float32)
    chunks = [values[r:r + 128, c:c + 128] for r in range(0, values.shape[0], 128)
              for c in range(0, values.shape[1], 128)]
    params = make_params(target_max_error=5.0, resolution=1.0)
    serial = [encode_chunk(c, params, fill_value=0.0) for c in chunks]
    with concurrent.futures.ThreadPoolExecutor(4) as pool:
        assert list(pool.map(lambda c: encode_chunk(c, params, fill_value=0.0), chunks)) == serial
        decoded = list(pool.map(lambda b: decode_chunk(b, np.float32, fill_value=0.0), serial))
    for chunk, back in zip(chunks, decoded):
        valid = chunk != 0
        assert np.abs(back[valid] - chunk[valid]).max(initial=0.0) <= 5.0
        assert (back[~valid] == 0).all()
