"""LAS and LAZ point clouds (laspy, with lazrs for LAZ): read chunk by chunk, written at millimetres.

A CRS travels as the file's ``LASF_Projection`` records, raw, so a
LAS -> .dftpc -> LAS round trip gives back the very same records; their WKT,
when one is there, is the ``wkt`` of the CRS dict.
"""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any, ClassVar, Iterable, Iterator, Sequence

import laspy
import numpy as np
from laspy.vlrs.vlr import VLR

from .reader import Reader

__all__ = ["LasReader", "write_las", "las_scales", "LAS_SCALE", "LAS_SCALE_DEGREES"]

#: LAS VLRs that carry georeferencing (LASF_Projection).
_LAS_CRS_USER = "LASF_Projection"
_WKT_RECORD = 2112
#: LAS output stores coordinates as integers of this many metres (or of the CRS's linear unit).
LAS_SCALE = 0.001
#: ... and longitude and latitude as integers of this many degrees (about 1.1 mm of latitude).
LAS_SCALE_DEGREES = 1e-8
#: The largest integer a LAS coordinate record holds (int32): scales grow tenfold until the extent fits.
_LAS_INT_MAX = 2**31 - 1
#: The classification code of what dftpcc writes: a terrain model is ground.
GROUND = 2


class LasReader(Reader):
    """A LAS or LAZ file (a path or a URL): the count and CRS from its header, the points in chunks of its records.

    ``classes`` keeps points of those classification codes (2 = ground);
    :attr:`stored_points` counts every point, before that selection.
    """

    options: ClassVar[frozenset[str]] = frozenset({"classes"})

    def _open(self) -> None:
        with laspy.open(self._binary()) as fh:
            header = fh.header
            self.stored_points = int(header.point_count)
            self.crs = las_crs(list(header.vlrs) + list(getattr(header, "evlrs", None) or []))

    def _raw_chunks(self, n: int | None) -> Iterator[np.ndarray]:
        wanted = None if self.classes is None else np.asarray(list(self.classes))
        with laspy.open(self._binary()) as fh:
            for part in fh.chunk_iterator(n or max(int(fh.header.point_count), 1)):
                pts = np.column_stack([np.asarray(part.x, dtype=np.float64), np.asarray(part.y, dtype=np.float64),
                                       np.asarray(part.z, dtype=np.float64)])
                yield pts if wanted is None else pts[np.isin(np.asarray(part.classification), wanted)]


def las_crs(records: Sequence[Any]) -> dict[str, Any]:
    """The CRS dict of a LAS file's (E)VLRs: its WKT and its georeferencing records, raw."""
    vlrs, wkt = [], None
    for vlr in records:
        if getattr(vlr, "user_id", "") != _LAS_CRS_USER:
            continue
        data = vlr.record_data_bytes() if hasattr(vlr, "record_data_bytes") else bytes(vlr.record_data)
        vlrs.append({"record_id": int(vlr.record_id), "description": str(vlr.description),
                     "data": base64.b64encode(data).decode("ascii")})
        if vlr.record_id == _WKT_RECORD:
            wkt = data.rstrip(b"\0").decode("utf-8", "replace")
    return {"wkt": wkt, "las_vlrs": vlrs} if vlrs else {}


def las_scales(crs: dict[str, Any], low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """x, y, z scales for points from ``low`` to ``high``, chosen as PDAL's ``scale auto`` does:
    the CRS's units (:data:`LAS_SCALE_DEGREES` for longitude and latitude, :data:`LAS_SCALE` of a
    metre or the CRS's linear unit otherwise), ten times coarser as often as the extent from the
    offset (``low``) needs to fit LAS's 32-bit integers."""
    from ..units import units_of

    scales = np.array([LAS_SCALE_DEGREES if units_of(crs).geographic else LAS_SCALE] * 2 + [LAS_SCALE])
    extent = np.maximum(np.asarray(high, dtype=float) - np.asarray(low, dtype=float), 0.0)
    while np.any(extent / scales > _LAS_INT_MAX):
        scales = np.where(extent / scales > _LAS_INT_MAX, scales * 10, scales)
    return scales


def las_header(crs: dict[str, Any], offsets: np.ndarray, *, high: np.ndarray | None = None) -> laspy.LasHeader:
    """The header dftpcc writes: the CRS's LAS records as they came (a WKT alone makes LAS 1.4,
    point format 6, which requires WKT; GeoTIFF keys LAS 1.2), ``offsets``, and the scales of
    :func:`las_scales` for points up to ``high`` (default: the units' scales)."""
    vlrs = [VLR(user_id=_LAS_CRS_USER, record_id=v["record_id"], description=v.get("description", ""),
                record_data=base64.b64decode(v["data"])) for v in crs.get("las_vlrs", [])]
    has_wkt = any(v.record_id == _WKT_RECORD for v in vlrs)
    if not vlrs and crs.get("wkt"):
        vlrs = [VLR(user_id=_LAS_CRS_USER, record_id=_WKT_RECORD, description="OGC WKT",
                    record_data=crs["wkt"].encode() + b"\0")]
        has_wkt = True
    header = laspy.LasHeader(point_format=6 if has_wkt or not vlrs else 0,
                             version="1.4" if has_wkt or not vlrs else "1.2")
    if has_wkt:
        header.global_encoding.wkt = True
    header.vlrs.extend(vlrs)
    header.scales = las_scales(crs, offsets, offsets if high is None else high)
    header.offsets = np.asarray(offsets, dtype=float)
    return header


def write_las(tmp: Path, points: np.ndarray, crs: dict[str, Any], fmt: str) -> None:
    """Write ``points`` as LAS, or LAZ when ``fmt`` is ``laz``, at the scales of :func:`las_scales`
    (millimetres of a projected map, 1e-8 degrees of a geographic one).

    The CRS's LAS records go back as they came; a WKT alone makes a LAS 1.4
    file (point format 6, which requires WKT); GeoTIFF keys a LAS 1.2 file.
    """
    low = np.floor(points.min(axis=0)) if points.size else np.zeros(3)
    header = las_header(crs, low, high=points.max(axis=0) if points.size else None)
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    las.classification = np.full(points.shape[0], GROUND, dtype=np.uint8)
    with open(tmp, "wb") as fh:
        las.write(fh, do_compress=(fmt == "laz"))


def write_las_chunks(path: Path, chunks: Iterable[np.ndarray], crs: dict[str, Any], offsets: np.ndarray,
                     fmt: str) -> int:
    """:func:`write_las` of points that arrive in chunks (a map decoded band by band), each appended as it
    comes, at the scales of :func:`las_scales` about ``offsets``. Returns the points written."""
    header = las_header(crs, offsets)
    count = 0
    with open(path, "wb") as fh, laspy.open(fh, mode="w", header=header, do_compress=(fmt == "laz"),
                                           closefd=False) as writer:
        for points in chunks:
            if not points.size:
                continue
            record = laspy.ScaleAwarePointRecord.zeros(points.shape[0], header=header)
            record.x, record.y, record.z = points[:, 0], points[:, 1], points[:, 2]
            record.classification = np.full(points.shape[0], GROUND, dtype=np.uint8)
            writer.write_points(record)
            count += points.shape[0]
    return count
