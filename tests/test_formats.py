"""Reading and writing every supported point cloud format."""

from __future__ import annotations

import base64

import numpy as np
import pytest

import dftpcc
from dftpcc.errors import InvalidInputError, UnsupportedFormatError
from dftpcc.io import format_of

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
