"""The command line: every command works, every user mistake is one line and a non-zero exit."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import dftpcc
from dftpcc.cli import main

from .conftest import data_file


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dftpcc", *args], capture_output=True, text=True, timeout=300)


@pytest.fixture()
def cloud_file(tmp_path, small_terrain):
    path = tmp_path / "terrain.ply"
    dftpcc.write(path, small_terrain)
    return path


def test_compress_info_decompress(tmp_path, cloud_file, small_terrain, capsys):
    out = tmp_path / "t.dftpc"
    assert main(["compress", str(cloud_file), str(out), "-r", "0.5", "-c", "0.8", "-q"]) == 0
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["params"]["cutoff"] == 0.8 and info["params"]["profile"] == "compact"
    assert info["points_original"] == small_terrain.shape[0]
    assert main(["info", str(out)]) == 0
    assert "bits/point" in capsys.readouterr().out
    for ext in (".las", ".ply", ".npy", ".tif"):
        assert main(["decompress", str(out), str(tmp_path / f"back{ext}"), "-q"]) == 0
    back = dftpcc.read(tmp_path / "back.ply").points
    assert back.shape[0] == info["points_rebuilt"]


def test_info_names_the_residual_layers_layout(tmp_path, capsys):
    """A maximum-error file says how its residual layer is coded: on rough terrain at a fine bound
    it is predicted from decoded neighbours (RESD kind 5), the spectrum empty; coarser, sparse."""
    rng = np.random.default_rng(3)
    z = np.cumsum(np.cumsum(rng.normal(0, 0.03, (40, 52)), 0), 1) + rng.normal(0, 0.02, (40, 52))
    yy, xx = np.mgrid[:40, :52] + 0.5
    cloud = tmp_path / "rough.npy"
    np.save(cloud, np.column_stack([xx.ravel() + 4.5e5, yy.ravel() + 5.2e6, z.ravel() + 300.0]))
    layouts = {}
    for bound in ("0.005", "0.5"):
        out = tmp_path / f"rough_{bound}.dftpc"
        assert main(["compress", str(cloud), str(out), "-r", "1", "--target-max-error", bound, "-q"]) == 0
        assert main(["info", str(out), "--json"]) == 0
        layouts[bound] = json.loads(capsys.readouterr().out)["residual_layout"]
        assert main(["info", str(out)]) == 0
        assert "residual" in capsys.readouterr().out
    assert layouts["0.005"] == "predicted" and layouts["0.5"] != "predicted", layouts
    assert main(["info", str(tmp_path / "rough_0.005.dftpc")]) == 0
    assert "(predicted from decoded neighbours)" in capsys.readouterr().out


def test_an_rmse_target_met_by_a_residual_layer_says_so(tmp_path, capsys):
    """Rough terrain near its floor: the smallest file within the RMSE asked for is the heights on
    steps of 2E, predicted from their neighbours, and the file states E as its target. The
    summary names the target asked for and how it was met, not only the bound the file states;
    so does ``info`` later, from the target the file keeps in STAT (and the document's reader)."""
    from . import spec_decoder

    rng = np.random.default_rng(3)
    z = np.cumsum(np.cumsum(rng.normal(0, 0.03, (40, 52)), 0), 1) + rng.normal(0, 0.02, (40, 52))
    yy, xx = np.mgrid[:40, :52] + 0.5
    cloud = tmp_path / "rough.npy"
    np.save(cloud, np.column_stack([xx.ravel() + 4.5e5, yy.ravel() + 5.2e6, z.ravel() + 300.0]))
    out = tmp_path / "rough.dftpc"
    assert main(["compress", str(cloud), str(out), "-r", "1", "--target-rmse", "0.003"]) == 0
    said = capsys.readouterr().out
    assert "for DEM RMSE <= 3.00 mm, met by a residual layer of max error <= " in said, said
    with dftpcc.open(out) as cmap:
        assert cmap.params.target_max_error > 0 and cmap.info()["residual_layout"] == "predicted"
        assert cmap.info()["stats"]["dem_rmse_m"] <= 0.003
        assert cmap.params.target_rmse == 0.0 and cmap.header.stats["target_rmse_m"] == pytest.approx(0.003)
    assert spec_decoder._header(spec_decoder._sections(out.read_bytes()))[2]["target_rmse_m"] == pytest.approx(0.003)
    assert main(["info", str(out)]) == 0
    shown = capsys.readouterr().out
    assert "target      DEM RMSE <= 3.00 mm, met by a residual layer of max error <= " in shown, shown


def test_paper_profile_from_the_command_line(tmp_path, cloud_file, capsys):
    out = tmp_path / "p.dftpc"
    assert main(["compress", str(cloud_file), str(out), "-r", "0.5", "--profile", "paper", "-q"]) == 0
    assert dftpcc.open(out).params.storage == "complex64"


def test_geotiff_in_and_out(tmp_path):
    src = data_file("dems/mars_gale_1m.tif")
    out = tmp_path / "gale.dftpc"
    assert main(["compress", str(src), str(out), "-c", "0.5", "-q"]) == 0
    m = dftpcc.open(out)
    assert m.grid.shape == (337, 348) and m.grid.resolution == pytest.approx(1.0, rel=1e-3)
    assert main(["decompress", str(out), str(tmp_path / "gale.tif"), "-q"]) == 0
    import rasterio

    stats = m.header.stats
    with rasterio.open(src) as a, rasterio.open(tmp_path / "gale.tif") as b:
        assert a.crs == b.crs
        assert a.transform.almost_equals(b.transform)
        original, back = a.read(1), b.read(1)
    assert np.isfinite(original).all() and np.isfinite(back).all()  # no nodata pixel in this file
    diff = back.astype(np.float64) - original
    # The GeoTIFF holds the rebuilt heights as float32: at -4,470 m that rounds
    # each by up to half a float32 spacing (0.24 mm), which adds in quadrature
    # to the 4.4 mm the file states: +0.048 % measured, so 0.1 % allowed.
    half_spacing = float(np.spacing(np.float32(np.abs(original).max()))) / 2
    assert np.sqrt(np.mean(diff**2)) == pytest.approx(stats["dem_rmse_m"], rel=1e-3)
    assert np.abs(diff).max() <= stats["dem_max_error_m"] + half_spacing


def test_demo_runs(capsys):
    assert main(["demo", "--points", "20000", "--resolution", "0.5"]) == 0
    out = capsys.readouterr().out
    assert "paper" in out and "compact" in out and "0.95" in out


def test_help_on_every_command():
    for cmd in ("compress", "decompress", "info", "demo"):
        result = run(cmd, "--help")
        assert result.returncode == 0 and "usage" in result.stdout


BAD = [
    (["compress", "{missing}", "{out}", "-r", "1"], 3, "no such file"),
    (["compress", "{cloud}", "{out}", "--cutoff", "1.5"], 2, "must be in [0, 1)"),
    (["compress", "{cloud}", "{out}", "--resolution", "-1"], 2, "positive"),
    (["compress", "{cloud}", "{weird}", "-r", "1"], 0, None),  # any output name is fine
    (["compress", "{unknown}", "{out}", "-r", "1"], 4, "cannot tell the format"),
    (["compress", "{empty}", "{out}", "-r", "1"], 3, "no points"),
    (["compress", "{nan}", "{out}", "-r", "1"], 3, "NaN or infinite"),
    (["compress", "{huge}", "{out}", "-r", "0.1"], 3, "limit"),
    (["decompress", "{garbage}", "{out_ply}"], 5, "not a .dftpc file"),
    (["decompress", "{truncated}", "{out_ply}"], 5, "truncated"),
    (["info", "{garbage}"], 5, "not a .dftpc file"),
    (["decompress", "{good}", "{out_bad_ext}"], 4, "cannot tell the format"),
    (["compress", "{cloud}", "{nodir}", "-r", "1"], 3, "does not exist"),
]


@pytest.mark.parametrize("argv,code,message", BAD)
def test_user_mistakes_end_in_one_line(tmp_path, cloud_file, argv, code, message):
    files = {
        "missing": tmp_path / "missing.laz",
        "cloud": cloud_file,
        "out": tmp_path / "out.dftpc",
        "weird": tmp_path / "out.bin",
        "unknown": tmp_path / "cloud.e57",
        "empty": tmp_path / "empty.xyz",
        "nan": tmp_path / "nan.xyz",
        "huge": tmp_path / "huge.xyz",
        "garbage": tmp_path / "garbage.dftpc",
        "truncated": tmp_path / "truncated.dftpc",
        "good": tmp_path / "good.dftpc",
        "out_ply": tmp_path / "out.ply",
        "out_bad_ext": tmp_path / "out.xls",
        "nodir": tmp_path / "no" / "such" / "dir.dftpc",
    }
    files["unknown"].write_bytes(b"x")
    files["empty"].write_text("")
    files["nan"].write_text("0 0 0\n1 1 nan\n2 2 2\n")
    files["huge"].write_text("0 0 0\n10000000 10000000 1\n")
    files["garbage"].write_bytes(b"hello world" * 10)
    good = dftpcc.compress(dftpcc.read(cloud_file).points, resolution=1.0)
    files["good"].write_bytes(good)
    files["truncated"].write_bytes(good[: len(good) // 2])
    before = set(tmp_path.rglob("*"))
    result = run(*[a.format(**files) for a in argv])
    assert result.returncode == code, result.stderr
    if message is None:
        return
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("dftpcc: error") or lines[0].startswith("usage") or "error:" in lines[0]
    assert message in result.stderr
    assert "Traceback" not in result.stderr
    # never a partial or temporary output file
    assert set(tmp_path.rglob("*")) == before


def test_failed_compress_keeps_the_previous_file(tmp_path):
    out = tmp_path / "map.dftpc"
    out.write_bytes(b"previous content")
    (tmp_path / "nan.xyz").write_text("0 0 nan\n")
    assert run("compress", str(tmp_path / "nan.xyz"), str(out), "-r", "1").returncode == 3
    assert out.read_bytes() == b"previous content"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.dftpc", "nan.xyz"]


@pytest.mark.parametrize("name", ["moon_kepler_lola_48m.tif", "mars_korolev_mola.tif"])
def test_non_square_planetary_dems_keep_their_grid(tmp_path, name):
    # LOLA and MOLA products come on grids whose pixels are not square.
    src = data_file(f"dems/{name}")
    out = tmp_path / "m.dftpc"
    assert main(["compress", str(src), str(out), "-c", "0.3", "-q"]) == 0
    assert main(["decompress", str(out), str(tmp_path / "m.tif"), "-q"]) == 0
    import rasterio

    with rasterio.open(src) as a, rasterio.open(tmp_path / "m.tif") as b:
        assert a.transform.almost_equals(b.transform, precision=1e-9)
        valid = a.read(1, masked=True)
        back = b.read(1, masked=True)  # the source's nodata value, or NaN
        assert np.array_equal(~np.ma.getmaskarray(valid), ~np.ma.getmaskarray(back))
    # points of the rebuilt map sit on the original pixel centres
    pts = dftpcc.read(tmp_path / "m.tif").points
    orig = dftpcc.read(src).points
    np.testing.assert_allclose(np.sort(pts[:, 0]), np.sort(orig[:, 0]), rtol=0, atol=1e-6 * np.abs(orig[:, 0]).max())


def test_progressive_decode_from_the_command_line(tmp_path, cloud_file):
    out = tmp_path / "t.dftpc"
    assert main(["compress", str(cloud_file), str(out), "-r", "0.5", "-c", "0.3", "-q"]) == 0
    m = dftpcc.open(out)
    head = m.size - m.header.stats["coef_bytes"]
    partial = tmp_path / "partial.npy"
    assert main(["decompress", str(out), str(partial), "--max-bytes", str(head + 2000), "-q"]) == 0
    assert np.load(partial).shape == (m.header.cell_count, 3)
    result = run("decompress", str(out), str(tmp_path / "x.npy"), "--max-bytes", "200")
    assert result.returncode == 5
    assert "a partial decode needs at least the first" in result.stderr
    assert not (tmp_path / "x.npy").exists()


def test_a_closed_output_pipe_stops_quietly(tmp_path, cloud_file):
    path = tmp_path / "map.dftpc"
    assert main(["compress", str(cloud_file), str(path), "-q"]) == 0
    proc = subprocess.Popen([sys.executable, "-m", "dftpcc", "info", "--json", str(path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # before the interpreter has even started: its first write hits a closed pipe
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 141
    assert err == b""


def _no_reading(monkeypatch):
    """Make any attempt to read the input fail loudly: output checks must come first."""
    import dftpcc.files

    def refuse(*args, **kwargs):
        raise AssertionError("the input was read before the output was checked")

    monkeypatch.setattr(dftpcc.files, "open_reader", refuse)


def test_an_unwritable_output_is_refused_before_the_input_is_read(tmp_path, cloud_file, capsys, monkeypatch):
    import errno

    import dftpcc.io.atomic as atomic

    _no_reading(monkeypatch)
    real_open = atomic.os.open

    def read_only(path, *args, **kwargs):  # a read-only folder, as a non-root user meets it
        if str(path).startswith(str(tmp_path / "ro")):
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, *args, **kwargs)

    (tmp_path / "ro").mkdir()
    monkeypatch.setattr(atomic.os, "open", read_only)
    assert main(["compress", str(cloud_file), str(tmp_path / "ro" / "x.dftpc")]) == 7
    err = capsys.readouterr().err
    assert err == f"dftpcc: error: [Errno 13] Permission denied: '{tmp_path / 'ro' / 'x.dftpc'}'\n"  # the user's path
    assert main(["compress", str(cloud_file), str(tmp_path)]) == 3
    assert "is a folder" in capsys.readouterr().err
    assert main(["compress", str(cloud_file), str(tmp_path / "nowhere" / "x.dftpc")]) == 3
    assert "does not exist" in capsys.readouterr().err
    assert main(["decompress", str(cloud_file), str(tmp_path / "ro" / "x.ply")]) == 7


def test_a_write_protected_output_needs_force(tmp_path, cloud_file, capsys):
    out = tmp_path / "x.dftpc"
    assert main(["compress", str(cloud_file), str(out), "-r", "0.5", "-q"]) == 0
    out.chmod(0o444)
    before = out.read_bytes()
    assert main(["compress", str(cloud_file), str(out), "-r", "1", "-q"]) == 3
    assert "write-protected; use --force" in capsys.readouterr().err and out.read_bytes() == before
    assert main(["compress", str(cloud_file), str(out), "-r", "1", "-q", "--force"]) == 0
    assert out.read_bytes() != before


def test_a_compressed_output_named_like_a_point_cloud_is_refused(tmp_path, cloud_file, capsys, monkeypatch):
    _no_reading(monkeypatch)
    assert main(["compress", str(cloud_file), str(tmp_path / "out.ply")]) == 3
    err = capsys.readouterr().err
    assert "would be written under the .ply extension" in err and "--force" in err
    assert not (tmp_path / "out.ply").exists()


def test_standard_input_and_output_as_dash(tmp_path, cloud_file, small_terrain):
    import subprocess
    import sys

    xyz = tmp_path / "t.xyz"
    dftpcc.write(xyz, small_terrain)
    dftpcc_cmd = [sys.executable, "-m", "dftpcc"]
    packed = subprocess.run(dftpcc_cmd + ["compress", "-", "-", "--format", "xyz", "-r", "0.5", "-q"],
                            input=xyz.read_bytes(), capture_output=True, check=True).stdout
    direct = tmp_path / "d.dftpc"
    assert main(["compress", str(xyz), str(direct), "-r", "0.5", "-q"]) == 0
    assert packed == direct.read_bytes()  # the stream is the file
    rebuilt = subprocess.run(dftpcc_cmd + ["decompress", "-", "-", "--format", "npy"], input=packed,
                             capture_output=True, check=True)
    import io

    assert np.array_equal(np.load(io.BytesIO(rebuilt.stdout)), dftpcc.decompress(packed))
    assert b"points" in rebuilt.stderr  # the summary goes to stderr when the map goes to stdout
    cog = subprocess.run(dftpcc_cmd + ["decompress", "-", str(tmp_path / "c.tif"), "--cog", "-q"], input=packed,
                         capture_output=True)
    assert cog.returncode == 0, cog.stderr  # band by band from a pipe: held in memory
    assert main(["decompress", str(direct), str(tmp_path / "d.tif"), "--cog", "-q"]) == 0
    assert (tmp_path / "c.tif").read_bytes() == (tmp_path / "d.tif").read_bytes()
    via_dev = subprocess.run(dftpcc_cmd + ["compress", "/dev/stdin", str(tmp_path / "s.dftpc"), "--format", "xyz",
                                           "-r", "0.5", "-q"], input=xyz.read_bytes(), capture_output=True)
    assert via_dev.returncode == 0, via_dev.stderr
    assert (tmp_path / "s.dftpc").read_bytes() == packed
    no_format = subprocess.run(dftpcc_cmd + ["compress", "-", str(tmp_path / "n.dftpc")], input=b"",
                               capture_output=True)
    assert no_format.returncode == 3 and b"name its format" in no_format.stderr


# -- a user's first day (issue 42) ------------------------------------------------------------------


def _two_storey_cloud(path):
    """A flat plain with a 5 m step inside some cells: a MultiHeightWarning on compress."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 20, (4000, 2))
    z = np.where(rng.random(4000) < 0.2, 5.0, 0.0) + rng.normal(0, 0.01, 4000)
    np.save(path, np.column_stack([xy, z]))
    return path


def test_quiet_prints_no_warning(tmp_path):
    cloud = _two_storey_cloud(tmp_path / "walls.npy")
    loud = run("compress", str(cloud), str(tmp_path / "a.dftpc"), "-r", "1")
    assert loud.returncode == 0 and "warning" in loud.stderr, loud.stderr
    quiet = run("compress", str(cloud), str(tmp_path / "b.dftpc"), "-r", "1", "-q")
    assert quiet.returncode == 0, quiet.stderr
    assert quiet.stdout == "" and quiet.stderr == "", (quiet.stdout, quiet.stderr)


def test_help_texts_read_as_written():
    """No doubled percent sign, every --profile explained, .drc among compress's inputs."""
    for cmd in ("recommend", "sweep", "compare", "compress"):
        result = run(cmd, "--help")
        assert result.returncode == 0, result.stderr
        assert "%%" not in result.stdout, result.stdout
        text = " ".join(result.stdout.split())
        assert "--profile {paper,compact} compact (default)" in text, (cmd, text)
    assert ".drc" in run("compress", "--help").stdout


def test_an_unknown_output_extension_lists_only_what_is_written(tmp_path, cloud_file):
    out = tmp_path / "t.dftpc"
    assert main(["compress", str(cloud_file), str(out), "-r", "1", "-q"]) == 0
    result = run("decompress", str(out), str(tmp_path / "back.xyzw"))
    assert result.returncode == 4, result.stderr
    listed = result.stderr.split("use one of", 1)[1]
    for ext in (".las", ".ply", ".tif", ".npy"):
        assert ext in listed, result.stderr
    for ext in (".bag", ".drc", ".mcap", ".db3"):
        assert ext not in listed, result.stderr


def run_on_terminal(*args: str, stdin: bytes | None = None, timeout: float = 300) -> tuple[int, str]:
    """Run the CLI with standard output and error on a pseudo-terminal, as a user at a shell sees it."""
    import os
    import pty
    import select

    import fcntl
    import struct
    import termios

    main_fd, child_fd = pty.openpty()
    # 24 x 80 like a terminal window: a pty of 0 x 0 gets tqdm's bar drawn 0 columns wide.
    fcntl.ioctl(child_fd, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
    proc = subprocess.Popen([sys.executable, "-m", "dftpcc", *args], stdout=child_fd, stderr=child_fd,
                            stdin=subprocess.PIPE if stdin is not None else subprocess.DEVNULL)
    os.close(child_fd)
    if stdin is not None:
        proc.stdin.write(stdin)
        proc.stdin.close()
    out = bytearray()
    while True:
        ready, _, _ = select.select([main_fd], [], [], timeout)
        if not ready:
            proc.kill()
            raise TimeoutError(f"dftpcc {' '.join(args)} wrote nothing for {timeout} s")
        try:
            chunk = os.read(main_fd, 65536)
        except OSError:  # the child closed the terminal
            break
        if not chunk:
            break
        out += chunk
    os.close(main_fd)
    return proc.wait(timeout=timeout), out.decode("utf-8", "replace")


def test_standard_streams_as_a_user_meets_them(tmp_path, cloud_file):
    """``info -`` reads standard input; a PLY on standard input needs no --format (its magic bytes
    say it); binary output to a terminal is refused as gzip refuses it, text output is not."""
    out = tmp_path / "t.dftpc"
    piped = subprocess.run([sys.executable, "-m", "dftpcc", "compress", "-", str(out), "-r", "1", "-q"],
                           input=cloud_file.read_bytes(), capture_output=True, timeout=300)
    assert piped.returncode == 0, piped.stderr
    info = subprocess.run([sys.executable, "-m", "dftpcc", "info", "-"], input=out.read_bytes(),
                          capture_output=True, timeout=300)
    assert info.returncode == 0 and b"bits/point" in info.stdout, info.stderr
    code, said = run_on_terminal("compress", str(cloud_file), "-", "-r", "1")
    assert code == 3 and "terminal" in said and said.count("\n") == 1, said
    code, said = run_on_terminal("decompress", str(out), "-", "--format", "npy")
    assert code == 3 and "terminal" in said, said
    code, said = run_on_terminal("decompress", str(out), "-", "--format", "xyz", "-q")
    assert code == 0 and len(said.splitlines()) > 10, said


def test_the_python_api_as_a_user_meets_it(tmp_path, cloud_file):
    """A missing file is a FileNotFoundError (and still an InvalidInputError); a CRS reads as WKT or a
    rasterio CRS; a map has a repr; dir(dftpcc) is the API, not this package's own imports."""
    for call in (lambda: dftpcc.read(tmp_path / "nope.las"), lambda: dftpcc.open(tmp_path / "nope.dftpc")):
        with pytest.raises(FileNotFoundError, match="no such file"):
            call()
        with pytest.raises(dftpcc.InvalidInputError):
            call()
    assert not {"Any", "TYPE_CHECKING", "importlib", "annotations"} & set(dir(dftpcc))
    assert {"compress", "read", "open", "CompressedMap"} <= set(dir(dftpcc))
    las = dftpcc.read(data_file("pointclouds/mountain_arid_alirt.las"), classes=[2])
    assert "UTM zone 42N" in las.crs_wkt and las.parse_crs().to_epsg() == 32642
    cmap = dftpcc.compress(las.points, resolution=2.0, crs=las.crs)
    with dftpcc.open(cmap) as opened:
        assert opened.parse_crs().to_epsg() == 32642
        text = repr(opened)
    assert text.startswith("<CompressedMap") and "EPSG:32642" in text and "cells" in text, text
    assert f"{las.points.shape[0]:,} points" in repr(las)


def test_info_reads_well_on_every_kind_of_map(tmp_path, capsys):
    """No step where no spectrum was kept; the values a tiled map stores counted; lengths in units that
    read well (not '1,000 µm' for 1 mm, nor a fraction of a µm)."""
    rng = np.random.default_rng(3)
    z = np.cumsum(np.cumsum(rng.normal(0, 0.03, (40, 52)), 0), 1) + rng.normal(0, 0.02, (40, 52))
    yy, xx = np.mgrid[:40, :52] + 0.5
    cloud = tmp_path / "rough.npy"
    np.save(cloud, np.column_stack([xx.ravel() + 4.5e5, yy.ravel() + 5.2e6, z.ravel() + 300.0]))
    residual_only = tmp_path / "r.dftpc"
    assert main(["compress", str(cloud), str(residual_only), "-r", "1", "--target-max-error", "0.005", "-q"]) == 0
    assert main(["info", str(residual_only)]) == 0
    said = capsys.readouterr().out
    assert "no spectrum (residual layer only)" in said and " km" not in said, said
    import re

    assert not re.search(r"step \d", said) and "values, all 0)" in said, said

    tiled = tmp_path / "tiled.dftpc"
    assert main(["compress", str(data_file("dems/mars_gale_1m.tif")), str(tiled), "--tile-size", "128", "-q"]) == 0
    assert main(["info", str(tiled), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["coefficients"] > info["stats"]["coef_count"] > 0
    assert main(["info", str(tiled)]) == 0
    said = capsys.readouterr().out
    assert f"({info['coefficients']:,} values)" in said and "(0 values)" not in said, said
    assert "µm" not in said, said


def test_a_truncated_file_is_named_and_its_prefix_offered(tmp_path, cloud_file):
    out = tmp_path / "t.dftpc"
    assert main(["compress", str(cloud_file), str(out), "-r", "0.5", "-c", "0.5", "-q"]) == 0
    cut = tmp_path / "cut.dftpc"
    data = out.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.7)])
    result = run("decompress", str(cut), str(tmp_path / "back.ply"))
    assert result.returncode == 5 and result.stderr.count("\n") == 1, result.stderr
    assert str(cut) in result.stderr and f"--max-bytes {cut.stat().st_size}" in result.stderr, result.stderr
    # info shows the intact header, then says what is wrong, and still fails.
    result = run("info", str(cut))
    assert result.returncode == 5 and "bits/point" in result.stdout and "truncated" in result.stderr, result
    assert run("decompress", str(cut), str(tmp_path / "back.ply"), "--max-bytes",
               str(cut.stat().st_size)).returncode == 0


def test_an_integer_dem_comes_back_in_its_type_and_nodata(tmp_path):
    """An int16 DEM coded within half a unit rounds back to its own values, in int16 with its nodata;
    coded coarser it comes back float32 (keeping its nodata) with a warning that says why; --dtype and
    --nodata choose; the file records the source (STAT source_dtype and source_nodata, read by the
    document's decoder too)."""
    import rasterio

    from . import spec_decoder

    rng = np.random.default_rng(5)
    heights = np.cumsum(np.cumsum(rng.integers(-2, 3, (60, 70)), 0), 1).astype(np.int16) + 100
    heights[:5, :9] = -32768
    src = tmp_path / "srtm.tif"
    with rasterio.open(src, "w", driver="GTiff", height=60, width=70, count=1, dtype="int16", nodata=-32768,
                       transform=rasterio.Affine(30, 0, 4.5e5, 0, -30, 5.2e6), crs="EPSG:32611") as dst:
        dst.write(heights, 1)
    fine, coarse = tmp_path / "fine.dftpc", tmp_path / "coarse.dftpc"
    assert main(["compress", str(src), str(fine), "--target-max-error", "0.45", "-q"]) == 0
    assert main(["compress", str(src), str(coarse), "-c", "0.95", "-q"]) == 0
    with dftpcc.open(coarse) as cmap:
        assert cmap.header.stats["dem_max_error_m"] >= 0.5  # the coarse case is coarse
    with dftpcc.open(fine) as cmap:
        assert cmap.header.stats["source_dtype"] == 4 and cmap.header.stats["source_nodata"] == -32768
    stats = spec_decoder._stat(spec_decoder._sections(fine.read_bytes())[b"STAT"])
    assert stats["source_dtype"] == 4 and stats["source_nodata"] == -32768

    result = run("decompress", str(fine), str(tmp_path / "fine.tif"))
    assert result.returncode == 0 and result.stderr == "", result.stderr
    assert "int16 raster" in result.stdout and "nodata -32768" in result.stdout, result.stdout
    with rasterio.open(tmp_path / "fine.tif") as back:
        assert back.dtypes[0] == "int16" and back.nodata == -32768
        assert np.array_equal(back.read(1), heights)

    result = run("decompress", str(coarse), str(tmp_path / "coarse.tif"))
    assert result.returncode == 0 and "warning" in result.stderr and "not below half a unit" in result.stderr
    with rasterio.open(tmp_path / "coarse.tif") as back:
        assert back.dtypes[0] == "float32" and back.nodata == -32768

    result = run("decompress", str(coarse), str(tmp_path / "asked.tif"), "--dtype", "int16", "--nodata", "-9999")
    assert result.returncode == 0 and "warning" not in result.stderr, result.stderr
    with rasterio.open(tmp_path / "asked.tif") as back:
        assert back.dtypes[0] == "int16" and back.nodata == -9999
        assert np.array_equal(back.read(1) == -9999, heights == -32768)
    result = run("decompress", str(fine), str(tmp_path / "nan.tif"), "--dtype", "float32", "--nodata", "nan")
    with rasterio.open(tmp_path / "nan.tif") as back:
        assert back.dtypes[0] == "float32" and np.isnan(back.nodata)
    bad = run("decompress", str(fine), str(tmp_path / "bad.tif"), "--dtype", "uint8")
    assert bad.returncode == 3 and "nodata -32768 is not a value of uint8" in bad.stderr, bad.stderr
    bad = run("decompress", str(fine), str(tmp_path / "bad.tif"), "--dtype", "uint8", "--nodata", "255")
    assert bad.returncode == 3 and "do not fit in uint8" in bad.stderr, bad.stderr
    assert not (tmp_path / "bad.tif").exists()
    assert "int16 raster, nodata -32768" in run("info", str(fine)).stdout


def test_a_box_cuts_every_output_alike(tmp_path):
    """--bbox with every output format and option: the same cells, none outside the box (a COG of a
    tiled map wrote the whole map, exit 0); a GeoTIFF's summary gives the raster written."""
    import rasterio

    from dftpcc.mapfile import open as open_map

    tiled = tmp_path / "tiled.dftpc"
    assert main(["compress", str(data_file("dems/mars_gale_1m.tif")), str(tiled), "--tile-size", "128", "-q"]) == 0
    with open_map(tiled) as cmap:
        x0, y0, x1, y1 = cmap.bounds()
    box = (x0 + 40.2, y0 + 90.7, x0 + 151.3, y0 + 170.9)
    text = ",".join(f"{v:.3f}" for v in box)
    inside = dftpcc.decompress_file(tiled, tmp_path / "ref.npy", bbox=[float(v) for v in text.split(",")])
    assert 0 < inside.shape[0] < 0.2 * 337 * 348
    counts = {}
    for name, extra in [("a.las", ()), ("a.laz", ()), ("a.ply", ()), ("a.pcd", ()), ("a.xyz", ()), ("a.csv", ()),
                        ("a.npy", ()), ("dense.npy", ("--densify", "2")), ("a.tif", ()), ("cog.tif", ("--cog",)),
                        ("workers.npy", ("--workers", "1"))]:
        if extra == ("--workers", "1"):
            pytest.importorskip("distributed")
        out = tmp_path / name
        result = run("decompress", str(tiled), str(out), "--bbox", text, *extra)
        assert result.returncode == 0, (name, result.stderr)
        if name.endswith(".tif"):
            with rasterio.open(out) as r:
                valid = ~np.isnan(r.read(1))
                left, bottom, right, top = r.bounds
                shape = (r.height, r.width)
            assert f"a {shape[0]:,} x {shape[1]:,} float32 raster" in result.stdout, result.stdout
            assert shape[0] * shape[1] < 0.2 * 337 * 348, (name, shape)
            assert left >= box[0] - 1 and right <= box[2] + 1 and bottom >= box[1] - 1 and top <= box[3] + 1
            counts[name] = int(valid.sum())
            continue
        points = dftpcc.read(out).points
        assert points[:, 0].min() >= box[0] and points[:, 0].max() <= box[2], name
        assert points[:, 1].min() >= box[1] - 0.5 and points[:, 1].max() <= box[3] + 0.5, name
        counts[name] = points.shape[0] // (4 if name == "dense.npy" else 1)
    assert set(counts.values()) == {inside.shape[0]}, counts
    pytest.importorskip("rosbags")
    result = run("decompress", str(tiled), str(tmp_path / "bag") + "/", "--bbox", text)
    assert result.returncode == 0 and f"{inside.shape[0]:,} points" in result.stdout, result.stdout + result.stderr


def test_long_commands_show_progress_on_a_terminal_only(tmp_path, cloud_file):
    """A tqdm bar on a terminal (decompress, evaluate, compare, update showed nothing), none when
    piped or with -q; -v prints each stage's time for every command."""
    out = tmp_path / "t.dftpc"
    assert main(["compress", str(cloud_file), str(out), "-r", "0.5", "-q"]) == 0
    commands = {
        "decompress": ["decompress", str(out), str(tmp_path / "back.ply")],
        "evaluate": ["evaluate", str(cloud_file), str(out)],
        "update": ["update", str(tmp_path / "grow.dftpc"), str(cloud_file), "-r", "1"],
    }
    for name, argv in commands.items():
        code, said = run_on_terminal(*argv)
        assert code == 0 and "%" in said and "\r" in said, (name, said)
        if name == "update":
            (tmp_path / "grow.dftpc").unlink()
            (tmp_path / "grow.dftpc.state").unlink()
        code, said = run_on_terminal(*argv, "-q")
        assert code == 0 and said == "", (name, said)
        if name == "update":
            (tmp_path / "grow.dftpc").unlink()
            (tmp_path / "grow.dftpc.state").unlink()
        piped = run(*argv, "-v")
        assert piped.returncode == 0 and "%" not in piped.stderr, (name, piped.stderr)
        assert [line for line in piped.stderr.splitlines() if line.startswith("dftpcc: ") and line.endswith(" s")], \
            (name, piped.stderr)
        if name == "update":
            (tmp_path / "grow.dftpc").unlink()
            (tmp_path / "grow.dftpc.state").unlink()


def test_messages_name_flags_on_the_command_line_and_arguments_in_python(tmp_path):
    """'drop them first (dftpcc.grid.drop_nonfinite, or read(..., drop_nonfinite=True))' told a
    command-line user to write Python; a Python caller still gets the argument."""
    cloud = tmp_path / "nan.xyz"
    cloud.write_text("0 0 1\n1 0 1\n0 1 nan\n1 1 1\n")
    result = run("compress", str(cloud), str(tmp_path / "o.dftpc"), "-r", "1")
    assert result.returncode == 3 and "--drop-nonfinite" in result.stderr, result.stderr
    assert "drop_nonfinite=True" not in result.stderr and "dftpcc.grid" not in result.stderr, result.stderr
    with pytest.raises(dftpcc.InvalidInputError, match="drop_nonfinite=True"):
        dftpcc.compress_file(cloud, tmp_path / "o.dftpc", resolution=1.0)
    protected = tmp_path / "p.dftpc"
    protected.write_bytes(b"x")
    protected.chmod(0o444)
    result = run("compress", str(cloud), str(protected), "-r", "1", "--drop-nonfinite")
    assert result.returncode == 3 and "use --force to replace it" in result.stderr, result.stderr
    assert main(["info", str(tmp_path / "missing.dftpc"), "-q"]) == 3  # in-process: Python's wording comes back
    with pytest.raises(dftpcc.InvalidInputError, match=r"use force=True to replace it"):
        dftpcc.compress_file(cloud, protected, resolution=1.0, drop_nonfinite=True)


def test_a_coarse_default_map_says_so_and_what_to_give(tmp_path):
    """A rough all-returns cloud at the defaults: 5.85 m cells, max error 19.5 m, and only the
    vegetation warning; the summary now says plainly the map is coarse and what to pass instead."""
    rocks = data_file("pointclouds/redrocks_rough.ply")
    result = run("compress", str(rocks), str(tmp_path / "r.dftpc"), "--no-warnings")
    assert result.returncode == 0, result.stderr
    assert "coarse: heights off by up to" in result.stdout and "--target-max-error" in result.stdout, result.stdout
    finer = run("compress", str(rocks), str(tmp_path / "f.dftpc"), "--no-warnings", "--target-max-error", "5")
    assert finer.returncode == 0 and "coarse:" not in finer.stdout, finer.stdout


def test_one_overwrite_rule_stated_in_every_help():
    for cmd in ("compress", "decompress", "update", "patch"):
        text = " ".join(run(cmd, "--help").stdout.split())
        assert "an existing output (a file, or a ROS 2 bag folder) is replaced; a write-protected one only with " \
               "--force" in text, (cmd, text)
