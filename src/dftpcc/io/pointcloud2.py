"""``sensor_msgs/PointCloud2``: the x, y, z of a message, from a bag or a live topic alike."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InvalidInputError

__all__ = ["POINTCLOUD2", "pointcloud2_xyz"]


POINTCLOUD2 = ("sensor_msgs/msg/PointCloud2", "sensor_msgs/PointCloud2")


#: PointField datatype codes -> numpy types.
_FIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def pointcloud2_xyz(msg: Any) -> np.ndarray:
    """x, y, z of a deserialised ``sensor_msgs/PointCloud2`` as an (n, 3) float64 array.

    Invalid points of a non-dense message (a NaN or infinite coordinate) are left out.
    """
    fields = {f.name: f for f in msg.fields}
    if not {"x", "y", "z"} <= set(fields):
        raise InvalidInputError(f"a PointCloud2 message has no x, y or z field (fields: {', '.join(fields)})")
    order = ">" if msg.is_bigendian else "<"
    step = int(msg.point_step)
    names, formats, offsets = [], [], []
    for name in "xyz":
        f = fields[name]
        if f.datatype not in _FIELD_TYPES:
            raise InvalidInputError(f"PointCloud2 field {name} has unknown datatype {f.datatype}")
        kind = order + _FIELD_TYPES[f.datatype]
        if not 0 <= f.offset <= step - np.dtype(kind).itemsize:
            raise InvalidInputError(f"PointCloud2 field {name} at byte {f.offset} does not fit in a {step}-byte point")
        names.append(name)
        formats.append(kind)
        offsets.append(f.offset)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    width, height, row_step = int(msg.width), int(msg.height), int(msg.row_step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if width * height == 0:
        return np.zeros((0, 3))
    if step <= 0 or row_step < width * step or data.size < row_step * (height - 1) + width * step:
        raise InvalidInputError(f"a PointCloud2 message is inconsistent: {width} x {height} points of "
                                f"{step} B in rows of {row_step} B need more than its {data.size} B")
    # Rows may be padded: take width points from the start of each row.
    rows = np.lib.stride_tricks.as_strided(data, shape=(height, width * step), strides=(row_step, 1))
    records = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    xyz = np.column_stack([records[n].astype(np.float64) for n in names])
    if not msg.is_dense:
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
    return xyz

