"""The read stage and the final write: every format, the registry, the readers, and failing writes."""

from __future__ import annotations

import base64
import errno
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest

import dftpcc
from dftpcc import files
from dftpcc.cli import main
from dftpcc.errors import InvalidInputError, MissingDependencyError, UnsupportedFormatError
from dftpcc.io import FORMATS, REGISTRY, Reader, format_of, open_chunked, open_reader

from .conftest import data_file

# A cloud with Lambert-93-size coordinates: float64 must keep them to the micrometre.
BIG = np.array([[484649.123456, 6632629.654321, 99.125],
                [484700.5, 6632700.25, 101.5],
                [484999.999, 6632999.999, 120.42]])


@pytest.mark.parametrize("ext", [".las", ".laz", ".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy"])
def test_round_trip_every_format(tmp_path, ext):
    path = tmp_path / f"cloud{ext}"
    dftpcc.write(path, BIG)
    back = dftpcc.read(path).points
    # LAS stores millimetre integers; text keeps 6 decimals; the others are float64.
    tol = {".las": 5e-4, ".laz": 5e-4, ".xyz": 1e-6, ".txt": 1e-6, ".csv": 1e-6}.get(ext, 0.0)
    np.testing.assert_allclose(back, BIG, rtol=0, atol=tol)


def test_format_from_extension_and_override(tmp_path):
    assert format_of("a.LAZ") == "laz"
    assert format_of("a.bin", "ply") == "ply"
    with pytest.raises(UnsupportedFormatError):
        format_of("a.bin")
    with pytest.raises(UnsupportedFormatError):
        format_of("a.las", "e57")


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(InvalidInputError, match="no such file"):
        dftpcc.read(tmp_path / "nope.laz")


def test_garbage_file_is_a_clear_error(tmp_path):
    path = tmp_path / "bad.laz"
    path.write_bytes(b"this is not a LAZ file")
    with pytest.raises(InvalidInputError, match="cannot read as laz"):
        dftpcc.read(path)


def test_text_with_header_line(tmp_path):
    path = tmp_path / "pts.csv"
    path.write_text("x,y,z\n1,2,3\n4,5,6\n")
    np.testing.assert_array_equal(dftpcc.read(path).points, [[1, 2, 3], [4, 5, 6]])


def test_las_classes_keep_only_ground():
    path = data_file("pointclouds/field_gentle_ign.laz")
    everything = dftpcc.read(path).points
    ground = dftpcc.read(path, classes=[2]).points
    assert 0.9 * everything.shape[0] < ground.shape[0] < everything.shape[0]
    # MANIFEST.md: 697721 points, 98 % ground; ANCHORS.md counts 683023 ground points.
    assert ground.shape[0] == 683023


def test_classes_that_match_nothing():
    with pytest.raises(InvalidInputError, match="no points of the selected classes"):
        dftpcc.read(data_file("pointclouds/mountain_arid_alirt.las"), classes=[250])


def test_crs_survives_las_to_dftpc_to_las(tmp_path):
    src = data_file("pointclouds/field_gentle_ign.laz")
    original = dftpcc.read(src, classes=[2])
    assert "Lambert-93" in original.crs["wkt"]
    dftpcc.compress_file(src, tmp_path / "m.dftpc", resolution=2.0, classes=[2])
    dftpcc.decompress_file(tmp_path / "m.dftpc", tmp_path / "back.laz")
    back = dftpcc.read(tmp_path / "back.laz")
    assert back.crs["wkt"] == original.crs["wkt"]
    assert [base64.b64decode(v["data"]) for v in back.crs["las_vlrs"]] == \
           [base64.b64decode(v["data"]) for v in original.crs["las_vlrs"]]


def test_geotiff_keys_survive_las12(tmp_path):
    # A LAS 1.2 file georeferenced by GeoTIFF keys, not WKT.
    src = data_file("pointclouds/forest_hills_topography.laz")
    original = dftpcc.read(src)
    assert original.crs["las_vlrs"] and original.crs["wkt"] is None
    dftpcc.compress_file(src, tmp_path / "m.dftpc", resolution=2.0)
    dftpcc.decompress_file(tmp_path / "m.dftpc", tmp_path / "back.las")
    back = dftpcc.read(tmp_path / "back.las")
    assert [v["data"] for v in back.crs["las_vlrs"]] == [v["data"] for v in original.crs["las_vlrs"]]


def test_geotiff_dem_reads_as_points_and_keeps_crs():
    cloud = dftpcc.read(data_file("dems/mars_gale_1m.tif"))
    assert cloud.points.shape == (337 * 348, 3)
    assert -4472.7 < cloud.points[:, 2].min() < cloud.points[:, 2].max() < -4437.8
    assert cloud.crs["wkt"]


# --- the registry and the readers ---------------------------------------------------------------

FORMAT_LIBRARIES = ("laspy", "rasterio", "plyfile", "pypcd4", "rosbags", "DracoPy")


def test_every_format_has_a_reader_and_every_extension_a_format():
    assert set(FORMATS.values()) == set(REGISTRY)
    for entry in REGISTRY.values():
        assert issubclass(entry.reader_class(), Reader)
        if entry.writer is None:
            with pytest.raises(UnsupportedFormatError, match="read, not written|holds a DEM"):
                entry.writer_function()
        else:
            assert callable(entry.writer_function())
    assert format_of("map.DRC") == "drc"


def test_importing_dftpcc_leaves_the_format_libraries_to_first_use():
    # `dftpcc --help` imports the package: rasterio and pypcd4 alone would add half a second.
    code = f"import sys, dftpcc, dftpcc.cli; print([m for m in {FORMAT_LIBRARIES!r} if m in sys.modules])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_a_reader_knows_its_count_and_crs_and_a_whole_read_is_one_chunk():
    path = data_file("pointclouds/field_gentle_ign.laz")
    with open_reader(path, classes=[2], chunk_points=100_000) as reader:
        # MANIFEST.md: 697,721 points, 683,023 of them ground (class 2).
        assert reader.stored_points == 697_721
        assert "Lambert-93" in reader.crs["wkt"]
        parts = list(reader.chunks())
        ones = list(reader.chunks(10 ** 9))
        whole = reader.read()
    assert len(parts) == 7 and max(p.shape[0] for p in parts) <= 100_000
    assert len(ones) == 1
    np.testing.assert_array_equal(np.concatenate(parts), whole.points)
    np.testing.assert_array_equal(ones[0], whole.points)
    assert whole.points.shape == (683_023, 3) and whole.crs == reader.crs


@pytest.mark.parametrize("name", ["pointclouds/redrocks_rough.ply", "pointclouds/mountain_arid_alirt.las",
                                  "dems/mars_gale_1m.tif"])
def test_chunks_of_any_size_are_the_whole_read(name):
    path = data_file(name)
    whole = dftpcc.read(path).points
    with open_reader(path) as reader:
        for n in (None, 999, whole.shape[0]):
            np.testing.assert_array_equal(np.concatenate(list(reader.chunks(n))), whole)


@pytest.mark.parametrize("option,name", [({"classes": [2]}, "classes"), ({"topic": "/map"}, "topic")])
def test_an_option_the_format_cannot_honour_is_refused_when_opened(tmp_path, option, name):
    npy = tmp_path / "t.npy"
    np.save(npy, BIG)
    for path, fmt in ((data_file("dems/mars_gale_1m.tif"), "tif"), (npy, "npy")):
        with pytest.raises(InvalidInputError, match=f"the {name} option does not apply to {fmt} files"):
            open_reader(path, **option)
    if name == "topic":
        with pytest.raises(InvalidInputError, match="the topic option does not apply to laz files"):
            open_reader(data_file("pointclouds/field_gentle_ign.laz"), topic="/map")


def test_a_geotiff_with_classes_topic_or_chunks_is_refused_before_any_work(tmp_path, monkeypatch):
    # It used to be compressed on its own grid with the options silently ignored.
    src = data_file("dems/mars_gale_1m.tif")
    out = tmp_path / "m.dftpc"

    def no_read(*args, **kwargs):
        raise AssertionError("the pixels were read")

    monkeypatch.setattr(dftpcc.io.geotiff, "read_raster_dem", no_read)
    for option, message in (({"classes": [2]}, "the classes option does not apply to tif files"),
                            ({"topic": "/map"}, "the topic option does not apply to tif files"),
                            ({"chunk_points": 1000}, "tif files cannot be read in chunks")):
        with pytest.raises(InvalidInputError, match=message):
            files.compress_file(src, out, **option)
    assert not out.exists()


# --- Draco ----------------------------------------------------------------------------------------

#: MANIFEST.md: redrocks_rough.ply is the decoded .drc plus this offset (metres, to the millimetre).
REDROCKS_OFFSET = np.array([-0.0154, -0.3536, 92.709])


def test_a_draco_file_reads_as_the_ply_it_was_decoded_to(tmp_path):
    pytest.importorskip("DracoPy", reason="the 'draco' extra is not installed")
    drc = dftpcc.read(data_file("pointclouds/redrocks_rough.drc"))
    ply = dftpcc.read(data_file("pointclouds/redrocks_rough.ply")).points
    assert drc.points.shape == ply.shape == (43_041, 3) and drc.crs == {}
    np.testing.assert_allclose(drc.points + REDROCKS_OFFSET, ply, rtol=0, atol=1e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # rough terrain: multi-height cells
        cmap = files.compress_file(data_file("pointclouds/redrocks_rough.drc"), tmp_path / "r.dftpc", resolution=5.0)
    assert cmap.header.point_count == 43_041
    with pytest.raises(InvalidInputError, match="drc files cannot be read in chunks"):
        files.compress_file(data_file("pointclouds/redrocks_rough.drc"), tmp_path / "r.dftpc", chunk_points=1000)
    with pytest.raises(UnsupportedFormatError, match="Draco files are read, not written"):
        dftpcc.write(tmp_path / "out.drc", BIG)


def test_a_draco_file_without_dracopy_says_how_to_install_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "DracoPy", None)  # as if the extra were not installed
    with pytest.raises(MissingDependencyError, match=r"needs DracoPy.*pip install 'dftpcc\[draco\]'"):
        dftpcc.read(data_file("pointclouds/redrocks_rough.drc"))


# --- NPY: real numbers only -----------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["plain", "structured"])
def test_a_complex_npy_is_refused_on_every_path(tmp_path, capsys, kind):
    # The API refused complex points, the CLI took their real part with numpy's ComplexWarning.
    src = tmp_path / "c.npy"
    if kind == "plain":
        np.save(src, BIG.astype(np.complex128))
    else:
        rec = np.zeros(3, dtype=[("x", "c16"), ("y", "c16"), ("z", "c16")])
        rec["x"], rec["y"], rec["z"] = BIG.T
        np.save(src, rec)
    out = tmp_path / "c.dftpc"
    message = "points must be real numbers, got dtype complex128"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ComplexWarning on the way
        for attempt in (lambda: dftpcc.read(src),
                        lambda: open_chunked(src),
                        lambda: files.compress_file(src, out, resolution=1.0),
                        lambda: files.compress_file(src, out, resolution=1.0, chunk_points=2)):
            with pytest.raises(InvalidInputError, match=message):
                attempt()
        assert main(["compress", str(src), str(out), "-r", "1", "-q"]) == 3
    assert message in capsys.readouterr().err
    assert not out.exists()


# --- failing writes: one line naming the output ---------------------------------------------------

_LIMITED = """
import resource, signal, sys
from dftpcc.cli import main
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit then fails with EFBIG
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]), int(sys.argv[1])))
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="file size limit set with setrlimit (Linux)")
@pytest.mark.parametrize("out", ["gale.tif", "gale.ply", "gale.las", "again.dftpc"])
def test_a_write_the_system_refuses_is_one_line_naming_the_output(tmp_path, out):
    # A file size limit fails writes as a full disk does, inside GDAL too (which printed its own
    # lines of libtiff text and then "Write failed. See previous exception for details.").
    src = data_file("dems/mars_gale_1m.tif")
    cmap = tmp_path / "gale.dftpc"
    files.compress_file(src, cmap)
    target = tmp_path / out
    argv = ["compress", str(src), str(target)] if out.endswith(".dftpc") else ["decompress", str(cmap), str(target)]
    limit = cmap.stat().st_size // 2  # every output here is larger than this
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    result = subprocess.run([sys.executable, "-c", _LIMITED, str(limit), *argv, "-q"], capture_output=True,
                            text=True, timeout=300, env=env)
    assert result.returncode == 7, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0] == f"dftpcc: error: [Errno {errno.EFBIG}] {os.strerror(errno.EFBIG)}: '{target}'"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gale.dftpc"]  # no partial file, no temporary


def test_a_full_disk_names_the_users_file_not_the_temporary(tmp_path, monkeypatch):
    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    dem = dftpcc.open(dftpcc.compress(BIG, resolution=100.0)).read_dem()
    monkeypatch.setattr(dftpcc.io.atomic.os, "fsync", full)
    for target, attempt in ((tmp_path / "p.ply", lambda t: dftpcc.write(t, BIG)),
                            (tmp_path / "p.npy", lambda t: dftpcc.write(t, BIG)),
                            (tmp_path / "d.tif", lambda t: dftpcc.io.write_geotiff(t, dem)),
                            (tmp_path / "m.dftpc", lambda t: files.compress_file(data_file(
                                "pointclouds/mountain_arid_alirt.las"), t, resolution=5.0))):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with pytest.raises(OSError) as failure:
                attempt(target)
        assert failure.value.errno == errno.ENOSPC and failure.value.filename == str(target)
        assert str(failure.value) == f"[Errno {errno.ENOSPC}] No space left on device: '{target}'"
    assert list(tmp_path.iterdir()) == []


def test_geotiff_outputs_are_tiled_and_compressed(tmp_path):
    import rasterio

    from dftpcc.cli import main

    src = data_file("dems/moon_kepler_lola_48m.tif")
    assert main(["compress", str(src), str(tmp_path / "k.dftpc"), "-q"]) == 0
    assert main(["decompress", str(tmp_path / "k.dftpc"), str(tmp_path / "k.tif"), "-q"]) == 0
    with rasterio.open(tmp_path / "k.tif") as out:
        assert out.compression == rasterio.enums.Compression.deflate
        assert out.block_shapes == [(256, 256)]
        assert out.tags(ns="IMAGE_STRUCTURE").get("PREDICTOR") == "3"
        heights = out.read(1, masked=True)
    assert (tmp_path / "k.tif").stat().st_size < 0.7 * 804 * 804 * 4  # measured 0.58 of the raw float32 raster
    rebuilt = dftpcc.open(tmp_path / "k.dftpc").read_dem()
    assert int(heights.count()) == int(rebuilt.mask.sum())


def test_las_output_of_a_geographic_map_keeps_its_precision(tmp_path):
    """A latitude/longitude map was written at 0.001 (degrees: up to 30 m on Mars, 1/16 of a cell):
    the scale follows the CRS's units, and the extent, as PDAL's scale auto does."""
    import laspy

    from dftpcc.io.las import LAS_SCALE, LAS_SCALE_DEGREES, las_scales

    korolev = data_file("dems/mars_korolev_mola.tif")
    out = tmp_path / "k.dftpc"
    cmap = dftpcc.compress_file(korolev, out)
    points = dftpcc.decompress_file(out, tmp_path / "k.las")
    with laspy.open(tmp_path / "k.las") as f:
        assert list(f.header.scales) == [LAS_SCALE_DEGREES, LAS_SCALE_DEGREES, LAS_SCALE]
    back = dftpcc.read(tmp_path / "k.las").points
    cell = cmap.grid.resolution
    assert np.abs(back[:, :2] - points[:, :2]).max() <= LAS_SCALE_DEGREES / 2 + 1e-12 < cell / 1000
    # A projected map keeps millimetres; an extent past 2**31 mm takes centimetres.
    utm = {"wkt": 'PROJCS["WGS 84 / UTM zone 42N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,'
                  '298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION['
                  '"Transverse_Mercator"],PARAMETER["central_meridian",69],PARAMETER["scale_factor",0.9996],'
                  'PARAMETER["false_easting",500000],UNIT["metre",1],AUTHORITY["EPSG","32642"]]'}
    assert list(las_scales(utm, [0, 0, 0], [1e5, 1e5, 10])) == [LAS_SCALE] * 3
    assert list(las_scales(utm, [0, 0, 0], [3e6, 1e5, 10])) == [10 * LAS_SCALE, LAS_SCALE, LAS_SCALE]
