"""Every error metric between an original cloud and a compressed or rebuilt map, from files."""

from __future__ import annotations

import os
import warnings
from typing import Any, Callable, Sequence

from .. import metrics
from ..errors import InputMismatchWarning, InvalidInputError
from ..io import read
from ..mapfile import is_dftpc
from ..mapfile import open as open_map
from ..units import units_of

__all__ = ["evaluate_files"]

Row = dict[str, Any]


def evaluate_files(original: str | os.PathLike[str], candidate: str | os.PathLike[str], *,
                   classes: Sequence[int] | None = None, max_cells: int | None = None,
                   on_stage: Callable[..., None] | None = None) -> Row:
    """Every metric of :func:`dftpcc.metrics.evaluate` between two files.

    Parameters
    ----------
    original : path
        The reference cloud.
    candidate : path
        A ``.dftpc`` file (decoded here; bits per point from its size over
        the original's points) or any point cloud file (a rebuilt map).
    classes : sequence of int, optional
        LAS/LAZ classes of the original to keep (use what was compressed).
    max_cells : int, optional
        Largest grid a ``.dftpc`` candidate may ask for (see :func:`dftpcc.open`).
    on_stage : callable, optional
        Called with each stage's name as it starts (``read``, ``decode``, ``measure``).

    Returns
    -------
    dict
        The metrics (metres, dB, bits per point) plus ``original``,
        ``candidate`` and, for a ``.dftpc``, ``points_in_header``: the point
        count the file was made from.
    """
    if is_dftpc(original) and not is_dftpc(candidate):
        raise InvalidInputError(f"{original} is a compressed map and {candidate} is not: the original point cloud "
                                f"comes first (dftpcc evaluate ORIGINAL COMPRESSED_OR_REBUILT); swap them")
    if is_dftpc(original):
        raise InvalidInputError(f"{original}: the original must be a point cloud, not a .dftpc file")
    stage = on_stage or (lambda *_: None)
    stage("read")
    cloud = read(original, classes=classes)
    ref = cloud.points
    extra: Row = {"original": str(original), "candidate": str(candidate)}
    # x, y in degrees and z in metres: only heights compared at the same x, y mean something.
    geographic = units_of(cloud.crs).geographic
    if geographic:
        extra["note"] = ("x and y are degrees of longitude and latitude, z metres: only vertical errors are "
                         "reported (D1, PSNR, Chamfer and Hausdorff would add degrees to metres)")
    if is_dftpc(candidate):
        stage("decode")
        with open_map(candidate, max_cells=max_cells) as cmap:
            rebuilt = cmap.read_points()
            size = cmap.size
            made_from = extra["points_in_header"] = cmap.header.point_count
        if made_from != ref.shape[0]:
            warnings.warn(
                f"{candidate} was made from {made_from:,} points but {original} gives {ref.shape[0]:,}"
                + (" with these classes" if classes else "") + ": the errors are measured against other points "
                "than were compressed (give the --classes the map was compressed with)", InputMismatchWarning,
                stacklevel=2)
        stage("measure")
        result = metrics.evaluate(ref, rebuilt, compressed_bytes=size, vertical_only=geographic)
    else:
        rebuilt = read(candidate).points
        stage("measure")
        result = metrics.evaluate(ref, rebuilt, vertical_only=geographic)
    return {**extra, **result}
