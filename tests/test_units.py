"""Units: what a map's numbers are in, and how the command line prints them."""

from __future__ import annotations

import json

import pytest

import dftpcc
from dftpcc.cli import main
from dftpcc.units import length, units_of

from .conftest import data_file


@pytest.mark.parametrize("value, unit, text", [
    (0.0817469, "m", "81.7 mm"), (18473.3, "m", "18.5 km"), (0.4259984472286371, "m", "0.426 m"),
    (1234.5, "m", "1,234 m"), (4.39e-8, "m", "43.9 nm"), (3.02e-9, "m", "3.02 nm"),
    (0.00099996, "m", "1.00 mm"), (0.99999, "m", "1.00 m"), (9.9996e-7, "m", "1.00 µm"), (0.0, "m", "0 m"), (0.0078134526, "°", "0.00781°"),
    (3.5, "ftUS", "3.50 ftUS"), (None, "m", "n/a"),
])
def test_lengths_are_scaled_to_their_size(value, unit, text):
    assert length(value, unit) == text


def test_units_follow_the_crs():
    assert units_of({}) == dftpcc.units.Units()
    from rasterio.crs import CRS

    lambert = units_of({"wkt": CRS.from_epsg(2154).to_wkt()})
    assert (lambert.horizontal, lambert.vertical, lambert.geographic, lambert.crs) == ("m", "m", False, "EPSG:2154")
    feet = units_of({"wkt": CRS.from_epsg(2264).to_wkt()})  # NAD83 / North Carolina (ftUS)
    assert (feet.horizontal, feet.crs) == ("ftUS", "EPSG:2264")
    wgs = units_of({"wkt": CRS.from_epsg(4326).to_wkt()})
    assert (wgs.horizontal, wgs.vertical, wgs.geographic) == ("°", "m", True)


def test_a_geographic_dem_is_described_in_degrees(tmp_path, capsys):
    out = tmp_path / "k.dftpc"
    assert main(["compress", str(data_file("dems/mars_korolev_mola.tif")), str(out)]) == 0
    summary = capsys.readouterr().out
    assert "cells of 0.00781°" in summary and " m)" not in summary.splitlines()[0]
    assert main(["info", str(out)]) == 0
    info = capsys.readouterr().out
    assert "of longitude x latitude" in info and "CRS         ESRI:104905" in info
    assert main(["info", "--json", str(out)]) == 0
    units = json.loads(capsys.readouterr().out)["units"]
    assert units == {"horizontal": "°", "vertical": "m", "geographic": True, "crs": "ESRI:104905"}


def test_compress_says_what_rate_control_chose_and_what_the_file_promises(tmp_path, capsys):
    out = tmp_path / "f.dftpc"
    assert main(["compress", str(data_file("pointclouds/field_gentle_ign.laz")), str(out), "--classes", "2",
                 "-r", "0.5", "--target-rmse", "0.03"]) == 0
    lines = capsys.readouterr().out.splitlines()
    m = dftpcc.open(out)
    assert lines[0].startswith(f"{out}: {m.size:,} bytes") and "cells of 0.500 m" in lines[0]
    # At this target the field's smallest file is a coarse low-pass with a sparse residual layer:
    # the summary names the bound it was made for, which the file promises too.
    assert m.params.target_max_error > 0.03
    assert lines[1].strip() == (f"cutoff {m.params.cutoff:g}, step {length(m.params.step)} (cutoff and step chosen by "
                                f"rate control for DEM RMSE <= 30.0 mm, met by a residual layer of max error <= "
                                f"{length(m.params.target_max_error)})")
    assert lines[2].strip().startswith(f"promises DEM RMSE {length(m.header.stats['dem_rmse_m'])}, max ")
    assert main(["info", str(out)]) == 0
    assert "CRS         EPSG:2154" in capsys.readouterr().out  # an authority code, not WKT cut at 70 characters


@pytest.mark.parametrize("command", ["compress", "decompress", "info", "demo", "evaluate", "sweep", "compare"])
def test_every_command_has_help_quiet_verbose_and_no_warnings(command, capsys):
    with pytest.raises(SystemExit) as stop:
        main([command, "--help"])
    assert stop.value.code == 0
    text = capsys.readouterr().out
    for flag in ("--quiet", "--verbose", "--no-warnings"):
        assert flag in text
    positional = text.split("positional arguments:")[1].split("options:")[0] if "positional" in text else ""
    lines = positional.strip("\n").splitlines()
    for i, line in enumerate(lines):
        if line.startswith("  ") and not line.startswith("   ") and len(line.split()) == 1:
            # argparse puts the help of a long name on the next, further indented line
            assert i + 1 < len(lines) and lines[i + 1].startswith("   "), f"{command}: {line.strip()} has no help"


def test_quiet_prints_nothing_and_verbose_times_the_stages(tmp_path, capsys, small_terrain):
    import numpy as np

    src = tmp_path / "t.npy"
    np.save(src, small_terrain)
    assert main(["compress", str(src), str(tmp_path / "q.dftpc"), "-r", "0.5", "-q"]) == 0
    assert main(["info", "-q", str(tmp_path / "q.dftpc")]) == 0
    out = capsys.readouterr()
    assert out.out == "" and out.err == ""
    assert main(["compress", str(src), str(tmp_path / "v.dftpc"), "-r", "0.5", "-v"]) == 0
    err = capsys.readouterr().err
    for stage in ("read", "spectrum", "encode", "write"):
        assert f"dftpcc: {stage}: " in err
    assert "dftpcc: parameters {" in err


def test_a_geographic_comparison_is_drawn_in_degrees(tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    from dftpcc.experiments import compare, figures

    seen = {}
    real = figures.plot_compare

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(compare, "plot_compare", spy)
    path = compare.compare_file(data_file("dems/mars_korolev_mola.tif"), out=tmp_path, cutoffs=(0.8,))
    assert path.is_file() and seen["units"].horizontal == "°" and "0.00781° cells" in seen["title"]
