"""How a map is compressed: one frozen dataclass that travels in the file header.

Every choice the pipeline makes is a field here, so a ``.dftpc`` file always
says how it was made (``dftpcc info``) and can be re-made from that record.
Profiles are named presets of these fields.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any

from .errors import InvalidInputError

__all__ = ["Params", "PROFILES", "CHOICES", "DEFAULT_CUTOFF", "MAX_COORDINATE_M", "MIN_RESOLUTION_M", "make_params", "check_cutoff",
           "check_tile_size", "tile_size_for", "TILE_SIZES", "DEFAULT_TILE_SIZE", "AUTO_TILE_CELLS"]

#: Cutoff ratio used when neither a cutoff nor a rate-control target is given.
DEFAULT_CUTOFF = 0.8

#: Largest coordinate, height, grid extent, quantizer step or height error a
#: ``.dftpc`` file may state, metres (about 7 astronomical units): beyond it a
#: number is not a map coordinate but a damaged or crafted field, and it could
#: overflow. Here because both sides use it: Params refuses a step or target
#: beyond it when compressing and when reading a file's PARM, and the container
#: checks the geometry against it (docs/format-validation.md).
MAX_COORDINATE_M = 1e12
#: The smallest cell a ``.dftpc`` file may state, metres (a nanometre): no survey resolves less, and
#: below it a box's extent divided by the cell size leaves the floats (from 5e-324 m any bbox did).
MIN_RESOLUTION_M = 1e-9

AGGREGATES = ("mean", "median", "min", "max")
FRAMES = ("axis", "oriented")
TRANSFORMS = ("dft", "dct")
DETRENDS = ("none", "plane")
FILLS = ("zero", "smooth", "consistent")
STORAGES = ("complex64", "quantized")
CODERS = ("ans", "zstd")
MASKS = ("exact", "footprint")
#: The allowed values of every field that takes a name (the CLI offers these).
#: Smallest and largest tile side, cells (docs/format.md: 16 to 65536).
TILE_SIZES = (16, 65536)
#: Tile side when ``tile_size='auto'`` tiles a map (see benchmarks/bench_tiles.py).
DEFAULT_TILE_SIZE = 1024
#: ``tile_size='auto'`` codes a grid of up to this many cells whole, as version 1.0.
AUTO_TILE_CELLS = 16_000_000

CHOICES: dict[str, tuple[str, ...]] = {
    "aggregate": AGGREGATES, "frame": FRAMES, "transform": TRANSFORMS, "detrend": DETRENDS,
    "fill": FILLS, "storage": STORAGES, "coder": CODERS, "mask": MASKS,
}


@dataclass(frozen=True)
class Params:
    """Parameters of one compression.

    Attributes
    ----------
    resolution : float or 'auto'
        Cell size of the DEM in metres (same unit as x and y); ``auto`` aims
        at a few points per cell (a GeoTIFF keeps its own pixels). A file
        records the resolution of its grid.
    cutoff : float or None
        Cutoff ratio ``f_c = 1 - r / r_M`` in [0, 1); 0 keeps every
        coefficient. None: chosen by rate control when a target is set,
        else :data:`DEFAULT_CUTOFF`. A file records the cutoff used.
    profile : str
        Name of the preset the other fields came from (``paper`` or ``compact``).
    aggregate : str
        Height of a cell from its points: ``mean``, ``median``, ``min`` or ``max``.
    frame : str
        ``axis``: axis-aligned bounding rectangle (the paper);
        ``oriented``: minimum-area rotated rectangle.
    transform : str
        ``dft``: the paper's periodic 2D DFT; ``dct``: DCT-II, i.e. the DFT of
        the DEM mirrored about its borders, which has no wrap-around jump.
    detrend : str
        ``plane`` removes a least-squares plane before the transform.
    fill : str
        Height given to empty cells before the transform: ``zero`` (the
        projection plane), ``smooth`` (a push-pull interpolation) or
        ``consistent`` (push-pull; then, under rate control, the chosen
        cutoff is tried again with the empty cells refilled twice from the
        map the coded spectrum rebuilds, which needs fewer coefficients for
        the same error, and the better file is kept).
    storage : str
        ``complex64``: the paper's raw coefficients; ``quantized``: integer
        coefficients, entropy-coded.
    step : float
        Quantizer step in metres (orthonormal transform, so a step is a
        height). 0 with ``storage='quantized'`` means choose automatically.
    deadzone : float
        Rounding offset of the dead-zone quantizer in steps, in [0, 0.5):
        values with ``|c| < (0.5 + deadzone) * step`` become zero.
    coder : str
        Entropy coder of quantized coefficients: ``ans`` (Laplace model per
        frequency band) or ``zstd``.
    mask : str
        ``exact``: rebuild exactly the occupied cells. ``footprint``: also
        the empty cells enclosed by the map (gaps between scan lines,
        occluded spots), which makes the mask far cheaper; those cells get
        interpolated heights.
    target_rmse : float
        If > 0, rate control: the smallest file whose rebuilt DEM is within
        this RMSE (metres) of the gridded DEM on occupied cells.
    target_max_error : float
        If > 0, every occupied cell of the rebuilt DEM is within this many
        metres of the gridded DEM (a residual layer guarantees it).
    target_bpp : float
        If > 0, the most accurate file of at most this many bits per
        original point.
    tile_size : int or 'auto'
        Side of a tile in cells (``TILE_SIZES``): a grid larger than one
        tile is coded in tiles a reader decodes one by one (docs/format.md,
        *Tiles*). 0 codes the map whole; ``'auto'`` tiles only a grid over
        :data:`AUTO_TILE_CELLS`, at :data:`DEFAULT_TILE_SIZE`.
    """

    resolution: float | str = "auto"
    cutoff: float | None = None
    profile: str = "compact"
    aggregate: str = "mean"
    frame: str = "axis"
    transform: str = "dct"
    detrend: str = "plane"
    fill: str = "consistent"
    storage: str = "quantized"
    step: float = 0.0
    deadzone: float = 0.1
    coder: str = "ans"
    mask: str = "exact"
    target_rmse: float = 0.0
    target_max_error: float = 0.0
    target_bpp: float = 0.0
    tile_size: int | str = "auto"

    def __post_init__(self) -> None:
        if self.resolution != "auto":
            _check_positive("resolution", self.resolution)
            if self.resolution < MIN_RESOLUTION_M:
                raise InvalidInputError(f"resolution {self.resolution!r} m is below the smallest cell size a map "
                                        f"may have, {MIN_RESOLUTION_M:g} m")
        if self.cutoff is not None:
            check_cutoff(self.cutoff)
        for name, allowed in CHOICES.items():
            value = getattr(self, name)
            if value not in allowed:
                raise InvalidInputError(f"{name} must be one of {', '.join(allowed)}; got {value!r}")
        if self.storage == "complex64" and self.transform != "dft":
            raise InvalidInputError("complex64 storage holds the paper's complex DFT coefficients: it needs "
                                    "transform='dft' (the DCT's are real; use storage='quantized')")
        _check_height("quantizer step", self.step, "0 chooses it")
        if not (0.0 <= self.deadzone < 0.5):
            raise InvalidInputError(f"deadzone must be in [0, 0.5), got {self.deadzone!r}")
        targets = {name: getattr(self, name) for name in ("target_rmse", "target_max_error", "target_bpp")}
        for name, value in targets.items():
            if name != "target_bpp":  # a height error, in metres
                _check_height(name, value, "0 sets no target")
            elif not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise InvalidInputError(f"{name} must be a finite number >= 0, got {value!r}")
        if sum(v > 0 for v in targets.values()) > 1:
            raise InvalidInputError("give at most one of target_rmse, target_max_error, target_bpp")
        check_tile_size(self.tile_size)

    @property
    def has_target(self) -> bool:
        """True when rate control chooses the step (and the cutoff, unless one is given)."""
        return self.target_rmse > 0 or self.target_max_error > 0 or self.target_bpp > 0

    @property
    def cutoff_or_default(self) -> float:
        """The cutoff without rate control: the one given, else :data:`DEFAULT_CUTOFF`."""
        return DEFAULT_CUTOFF if self.cutoff is None else self.cutoff

    def replace(self, **changes: Any) -> "Params":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "Params":
        data = json.loads(text)
        if not isinstance(data, dict):
            raise InvalidInputError("parameters must be a JSON object")
        known = {f.name for f in dataclasses.fields(cls)}
        # Fields written by a newer minor version are ignored, not fatal.
        return cls(**{k: v for k, v in data.items() if k in known})


def check_tile_size(value: Any) -> None:
    """Refuse a tile size other than ``'auto'``, 0 (untiled) or a whole number of cells in :data:`TILE_SIZES`."""
    if value == "auto" and isinstance(value, str):
        return
    if isinstance(value, bool) or not isinstance(value, int) or not (
            value == 0 or TILE_SIZES[0] <= value <= TILE_SIZES[1]):
        raise InvalidInputError(f"tile_size must be 'auto', 0 (no tiles) or a whole number of cells from "
                                f"{TILE_SIZES[0]} to {TILE_SIZES[1]}; got {value!r}")


def tile_size_for(params: "Params", shape: tuple[int, int]) -> int:
    """The tile side a map of ``shape`` is coded with: 0 when it is coded whole (one tile holds it)."""
    size = params.tile_size
    if size == "auto":
        size = DEFAULT_TILE_SIZE if shape[0] * shape[1] > AUTO_TILE_CELLS else 0
    return size if size and max(shape) > size else 0


def check_cutoff(value: Any) -> float:
    """``value`` if it is a cutoff ratio in [0, 1), else :class:`InvalidInputError`."""
    if isinstance(value, bool) or not (isinstance(value, (int, float)) and 0.0 <= value < 1.0):
        raise InvalidInputError(f"cutoff must be in [0, 1), got {value!r}")
    return float(value)


def _check_height(name: str, value: Any, zero: str) -> None:
    """A height in metres a file states: 0 (``zero`` says what it means) up to :data:`MAX_COORDINATE_M`."""
    if isinstance(value, bool) or not (isinstance(value, (int, float)) and 0 <= value <= MAX_COORDINATE_M):
        raise InvalidInputError(f"{name} must be a number of metres from 0 ({zero}) to at most "
                                f"{MAX_COORDINATE_M:g} m, the largest height a .dftpc file holds; got {value!r}")


def _check_positive(name: str, value: Any) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise InvalidInputError(f"{name} must be a positive finite number, got {value!r}")


#: Named presets. ``paper`` is the method exactly as published; ``compact``
#: is the default codec.
PROFILES: dict[str, dict[str, Any]] = {
    "paper": dict(
        transform="dft", detrend="none", fill="smooth", storage="complex64", frame="axis",
    ),
    "compact": dict(
        transform="dct", detrend="plane", fill="consistent", storage="quantized",
    ),
}


def make_params(*, resolution: float | str = "auto", cutoff: float | None = None, profile: str = "compact",
                **overrides: Any) -> Params:
    """Build :class:`Params` from a profile name plus explicit overrides.

    Parameters
    ----------
    resolution : float or 'auto'
        DEM cell size in metres.
    cutoff : float, optional
        Cutoff ratio f_c in [0, 1); default: chosen by rate control, or :data:`DEFAULT_CUTOFF`.
    profile : str
        ``compact`` (default) or ``paper``.
    **overrides
        Any other :class:`Params` field; ``None`` values are ignored.
    """
    if profile not in PROFILES:
        raise InvalidInputError(f"profile must be one of {', '.join(PROFILES)}; got {profile!r}")
    fields = dict(PROFILES[profile])
    fields.update({k: v for k, v in overrides.items() if v is not None})
    unknown = set(fields) - {f.name for f in dataclasses.fields(Params)}
    if unknown:
        raise InvalidInputError(f"unknown parameter(s): {', '.join(sorted(unknown))}")
    return Params(resolution=resolution, cutoff=cutoff, profile=profile, **fields)
