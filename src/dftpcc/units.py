"""What a map's numbers are in: the units its CRS gives, and lengths printed for people.

A ``.dftpc`` keeps coordinates in the units of its source. A projected CRS
says its linear unit (metres, US survey feet); a geographic CRS puts x and y
in degrees of longitude and latitude, so a cell size there is an angle, not a
length. Heights are taken to be in the projected CRS's linear unit, and in
metres on a geographic grid or without a CRS (no vertical CRS is read).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

__all__ = ["Units", "units_of", "length"]

#: Linear units of a CRS (as rasterio names them) -> the symbol dftpcc prints.
_SYMBOLS = {"metre": "m", "meter": "m", "m": "m", "us survey foot": "ftUS", "foot_us": "ftUS",
            "us_survey_foot": "ftUS", "foot": "ft", "ft": "ft", "international foot": "ft", "kilometre": "km"}
#: Significant digits of a printed length.
DIGITS = 3
#: Lengths from this many metres up are printed in metres (0.5 m), smaller ones in mm or µm.
SMALLEST_IN_METRES = 0.1


@dataclass(frozen=True)
class Units:
    """Units of a map's coordinates.

    Attributes
    ----------
    horizontal : str
        Symbol of x and y (and of the cell size): ``m``, ``ftUS``, ``ft`` or ``°``.
    vertical : str
        Symbol of heights and of every error a file states.
    geographic : bool
        x, y are longitude and latitude in degrees.
    crs : str or None
        The CRS as its authority code (``EPSG:2154``) when it has one, else its name.
    """

    horizontal: str = "m"
    vertical: str = "m"
    geographic: bool = False
    crs: str | None = None


def units_of(crs: dict[str, Any] | None) -> Units:
    """The :class:`Units` of a CRS dict as dftpcc carries it (``{"wkt": ..., "las_vlrs": [...]}``).

    Metres throughout when there is no WKT (no CRS, or LAS GeoTIFF keys only).
    """
    wkt = (crs or {}).get("wkt")
    if not wkt:
        return Units(crs="LAS GeoKeys" if (crs or {}).get("las_vlrs") else None)
    try:
        from rasterio.crs import CRS

        parsed = CRS.from_wkt(wkt)
        authority = parsed.to_authority()
        label = f"{authority[0]}:{authority[1]}" if authority else _wkt_name(wkt)
        if parsed.is_geographic:
            return Units("°", "m", True, label)
        unit = str(parsed.linear_units).lower()
        symbol = "m" if unit in ("unknown", "") else _SYMBOLS.get(unit, unit)  # unnamed: metres, as without a CRS
        return Units(symbol, symbol, False, label)
    except Exception:  # noqa: BLE001 - an unparseable WKT is shown by name, lengths in metres
        return Units(crs=_wkt_name(wkt))


def _wkt_name(wkt: str) -> str:
    """The quoted name at the start of a WKT (``PROJCRS["RGF93 / Lambert-93", ...``)."""
    start = wkt.find('"')
    end = wkt.find('"', start + 1)
    return wkt[start + 1:end] if 0 <= start < end else wkt[:40]


def _significant(value: float, digits: int = DIGITS) -> str:
    if value == 0 or not math.isfinite(value):
        return f"{value:g}"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(value))))
    return f"{value:,.{decimals}f}"


def length(value: float | None, unit: str = "m", *, digits: int = DIGITS) -> str:
    """``value`` (in ``unit``) with a few significant digits, metres scaled to nm, µm, mm, m or km.

    The unit is chosen after rounding, so 0.9999 mm reads 1.00 mm, not 1,000 µm.

    >>> length(0.0817469), length(18473.3), length(0.4259984472286371), length(0.0078, "°")
    ('81.7 mm', '18.5 km', '0.426 m', '0.00780°')
    """
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if unit == "m" and value == 0:
        return "0 m"
    if unit == "m":
        size = float(f"{abs(value):.{digits - 1}e}") if math.isfinite(value) else abs(value)
        if size != abs(value) and any(abs(value) < edge <= size for edge in (1e-6, 1e-3, 1.0)):
            value = math.copysign(size, value)  # rounded up to the next unit: print the rounded value
        for scale, symbol in ((1e3, "km"), (1.0, "m"), (1e-3, "mm"), (1e-6, "µm"), (1e-9, "nm")):
            if size >= scale or symbol == "nm":
                if symbol == "km" and size < 1e4:
                    continue  # up to 10 km in metres: 1,234 m reads better than 1.23 km
                if symbol == "mm" and size >= SMALLEST_IN_METRES:
                    return f"{_significant(value, digits)} m"
                return f"{_significant(value / scale, digits)} {symbol}"
    if unit == "°":
        return f"{_significant(value, digits)}°"
    return f"{_significant(value, digits)} {unit}"
