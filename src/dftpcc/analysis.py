"""The encoder's view of one DEM: conditioned and transformed once, then tried at many (cutoff, step).

:class:`Analysis` holds what does not change between trials (the plane, the
filled DEM's sorted transform, the frequency of every stored value);
:meth:`Analysis.trial` quantizes a prefix of the spectrum and rebuilds the
DEM the decoder will see, so rate control (:mod:`dftpcc.ratecontrol`) can
measure a candidate exactly before it is coded.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .sums import dot
from . import coding, kernels, quantizer, spectrum
from .dem import DEM
from .fill import fill_empty, fit_plane, footprint, plane_values
from .params import Params

__all__ = ["Analysis", "Trial", "REFILL_ROUNDS"]

#: Rounds of refilling the empty cells from the rebuilt map (fill='consistent');
#: measured on the field and coastal plain, a third round gains nothing.
REFILL_ROUNDS = 2


@dataclass
class Trial:
    """One (cutoff, step) tried against a spectrum."""

    cutoff: float
    step: float
    stream: np.ndarray  # what gets entropy-coded (int64 or complex64)
    heights: np.ndarray  # the DEM the decoder will rebuild (relative to z0)
    rmse: float  # on occupied cells, metres
    max_error: float  # on occupied cells, metres
    #: The rebuilt minus the gridded heights on the occupied cells (metres, row-major), when the
    #: trial was asked to keep them (``Analysis.trial(..., keep_errors=True)``): the file's
    #: statistics are made of them, and rate control's many trials need not hold them.
    errors: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)


@kernels.kernel("masked_errors")
def _trial_errors(heights: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float, float]:
    """``err = (heights - ref)[mask]`` (metres, row-major), its RMS and its largest magnitude."""
    err = (heights - ref)[mask]
    return err, float(np.sqrt(np.mean(err * err))), float(np.abs(err).max())


class Analysis:
    """What does not change between trials: detrended, filled DEM and its sorted transform.

    Parameters
    ----------
    dem : DEM
    params : Params
    searching : bool
        Whether trials may ask for any cutoff (rate control choosing it);
        otherwise only ``params.cutoff_or_default``'s circle is transformed and sorted.
    fill : callable, optional
        ``fill(heights, mask, method=...)`` giving the empty cells their heights before the
        transform (default :func:`dftpcc.fill.fill_empty`); for experiments with other fills.
    outside_energy : bool
        Measure the energy outside the sorted circle (:attr:`outside_energy`, which
        :meth:`proxy_rmse` needs); coding at a known (cutoff, step) does not.
    """

    def __init__(self, dem: DEM, params: Params, *, searching: bool, fill: Callable[..., np.ndarray] | None = None,
                 outside_energy: bool = True):
        self.dem, self.params = dem, params
        self._measure_outside = outside_energy
        self.mask = dem.mask
        self.kept_cells = footprint(dem.mask) if params.mask == "footprint" else dem.mask
        self.plane = fit_plane(dem) if params.detrend == "plane" else (0.0, 0.0, 0.0)
        self.trend = plane_values(self.plane, dem.grid.shape) if params.detrend == "plane" else 0.0
        # A consistent fill starts from the smooth one (see refilled()).
        method = "smooth" if params.fill == "consistent" else params.fill
        filled = (fill or fill_empty)(dem.heights - self.trend, dem.mask, method=method)
        if fill is not None:  # an experiment's fill may hand back an array it keeps: the transform overwrites
            filled = np.array(filled, dtype=np.float64, order="C")
        self.lay = spectrum.layout(params.transform, params.storage, dem.grid.shape)
        order, radii, angles = spectrum.kept_order(self.lay, 0.0 if searching else params.cutoff_or_default)
        self.order = order
        self.coefs = self._sorted_transform(filled)
        # Frequency of every stored value (a complex one may be stored as two reals).
        self.radii = radii
        per_coef = spectrum.values_per_coefficient(self.lay, params.storage)
        self.radius = np.repeat(radii, per_coef)
        self.angle = np.repeat(angles, per_coef)
        self.parseval = spectrum.mse_per_squared_error(self.lay)

    def _sorted_transform(self, filled: np.ndarray) -> np.ndarray:
        """The kept coefficients of ``filled`` (a grid of this analysis's own, which the transform
        overwrites), sorted; also sets :attr:`outside_energy`."""
        #: Squared magnitude of the coefficients outside the sorted circle (0 when searching):
        #: what any trial loses to the low-pass, for :meth:`proxy_rmse` (None: not measured).
        self.outside_energy: float | None = 0.0 if self._measure_outside else None
        if self.lay.kind == "dct" and not self._measure_outside:
            # Only the corner that holds the circle: the rest of the transform is never used.
            shape, where = self._corner(self.order.size)
            return spectrum.forward(filled, self.lay, overwrite=True, corner=shape).ravel()[where]
        full = spectrum.forward(filled, self.lay, overwrite=True).ravel()
        if self.order.size < full.size and self._measure_outside:
            outside = np.ones(full.size, dtype=bool)
            outside[self.order] = False
            rest = full[outside]
            rest = rest.view(np.float64) if np.iscomplexobj(rest) else rest
            self.outside_energy = dot(rest, rest)
        return full[self.order]

    @property
    def refillable(self) -> bool:
        """Whether ``fill='consistent'`` has empty cells to refill."""
        return self.params.fill == "consistent" and not bool(self.mask.all())

    def refilled(self, trial: Trial) -> Analysis:
        """This analysis with the empty cells refilled from what ``trial`` rebuilds there.

        The decoder never shows empty cells (or shows them rebuilt, with
        ``mask='footprint'``), so any fill is as good as another except in
        bits. Refilling them with the rebuilt map, quantizing again and
        repeating (a Gerchberg-Papoulis iteration) drives the fill towards
        heights the coded spectrum already holds, which needs fewer
        coefficients at the same step than the smooth interpolation.
        """
        out = copy.copy(self)
        out._tail_energy = None
        data = self.dem.heights - self.trend
        for round_ in range(REFILL_ROUNDS):
            if round_:
                trial = out.trial(trial.cutoff, trial.step)
            out.coefs = out._sorted_transform(np.where(self.mask, data, trial.heights - self.trend))
        return out

    def untrended(self) -> Analysis:
        """This analysis with a plane of 0 (the file still says ``detrend='plane'``), for a trial
        whose coefficients are all 0, so that its residual is the heights themselves: on steps of
        the residual's quantizer a sloping plane would add a staircase, which a predictor of
        neighbouring heights pays for (``RESD`` kind 5)."""
        out = copy.copy(self)
        if self.params.detrend == "plane":
            out.plane, out.trend = (0.0, 0.0, 0.0), 0.0
        return out

    def count(self, cutoff: float) -> int:
        """Coefficients kept at ``cutoff``."""
        return spectrum.kept_count(self.lay, cutoff, self.radii)

    def reals(self, n: int) -> np.ndarray:
        kept = self.coefs[:n]
        return kept.view(np.float64) if np.iscomplexobj(kept) else kept

    def largest(self, cutoff: float) -> np.ndarray:
        """The values kept at ``cutoff`` (as :meth:`TiledAnalysis.largest`: for the steps that
        depend on the largest of them)."""
        return self.reals(self.count(cutoff))

    def tiny_step(self) -> float:
        """A step fine enough that quantization is negligible next to any sensible target (0 unquantized)."""
        scale = float(np.abs(self.reals(min(self.coefs.size, 1))).max()) if self.coefs.size else 1.0
        return max(scale, 1.0) * 1e-9 if self.params.storage == "quantized" else 0.0

    def synthesise(self, values: np.ndarray) -> np.ndarray:
        """Heights (relative to z0) from the first ``len(values)`` sorted coefficients."""
        if self.lay.kind == "dct":
            # Only the low-frequency corner is non-zero: its rows alone go through
            # the first pass (along axis 1, the order the whole array takes, so the
            # same bits as inverting the zero-padded array).
            shape, where = self._corner(values.size)
            coefs = np.zeros(shape, dtype=values.dtype)
            coefs.ravel()[where] = values
            heights = spectrum.inverse(coefs, self.lay, first_axis=1, overwrite=True)
            heights += self.trend  # in place: the inverse's grid is this trial's own
            return heights
        coefs = np.zeros(self.lay.coef_shape, dtype=values.dtype)
        coefs.ravel()[self.order[: values.size]] = values
        return spectrum.inverse(coefs, self.lay) + self.trend

    def _corner(self, n: int) -> tuple[tuple[int, int], np.ndarray]:
        """:func:`spectrum.corner` of the first ``n`` coefficients, cached: trials ask again and again."""
        cached = getattr(self, "_corner_cache", None)
        if cached is None or cached[0] != n:
            cached = (n, spectrum.corner(self.lay, self.order[:n]))
            self._corner_cache = cached
        return cached[1]

    def quantized(self, cutoff: float, step: float) -> np.ndarray:
        """The integers a quantized trial at (cutoff, step) codes, without rebuilding the DEM."""
        return quantizer.quantize(self.reals(self.count(cutoff)), quantizer.short_step(step), self.params.deadzone)

    def rebuilt(self, cutoff: float, step: float) -> tuple[np.ndarray, np.ndarray]:
        """The stream a trial at (cutoff, step) codes and the heights the decoder rebuilds from it
        (relative to z0), without measuring them: :meth:`trial` with no errors."""
        n = self.count(cutoff)
        step = quantizer.short_step(step)
        if self.params.storage == "complex64":
            stream = self.coefs[:n].astype(np.complex64)
            decoded = stream.astype(np.complex128)
        else:
            stream = self.quantized(cutoff, step)
            decoded = quantizer.dequantize(stream, step)
            if np.iscomplexobj(self.coefs):
                decoded = decoded.view(np.complex128)
        return stream, self.synthesise(decoded)

    def trial(self, cutoff: float, step: float, *, keep_errors: bool = False) -> Trial:
        """Quantize the coefficients inside ``cutoff`` with ``step`` and rebuild the DEM from them
        (``keep_errors``: with :attr:`Trial.errors`)."""
        step = quantizer.short_step(step)
        stream, heights = self.rebuilt(cutoff, step)
        err, rmse, largest = _trial_errors(heights, self.dem.heights, self.mask)
        out = Trial(cutoff, step, stream, heights, rmse, largest)
        if keep_errors:
            out.errors = err
        return out

    def energy_at(self, cutoff: float) -> tuple[np.ndarray, float]:
        """The values kept at ``cutoff`` and the energy (squared metres, summed over the
        transform) of every value the low-pass drops, sorted or not: by Parseval, what the
        cutoff alone costs the whole grid's squared error (rate control's model)."""
        kept = self.reals(self.count(cutoff))
        if self.outside_energy is None:
            raise ValueError("energy_at needs an Analysis that measures its outside energy")
        tail = getattr(self, "_tail_energy", None)
        if tail is None:  # energy from each sorted value on: every cutoff's in one pass
            values = self.reals(self.coefs.size)
            tail = np.zeros(values.size + 1)
            tail[:-1] = np.cumsum((values * values)[::-1])[::-1]
            self._tail_energy = tail
        return kept, float(tail[kept.size]) + self.outside_energy

    def proxy_rmse(self, cutoff: float, step: float) -> float:
        """Whole-grid RMSE predicted in the coefficient domain, without an inverse transform.

        Counts the quantization error of the kept coefficients and the energy
        of every coefficient the low-pass drops, sorted or not.
        """
        n = self.count(cutoff)
        reals = self.reals(n)
        dropped = self.reals(self.coefs.size)[reals.size:]
        if self.outside_energy is None:
            raise ValueError("proxy_rmse needs an Analysis that measures its outside energy")
        err = reals - quantizer.dequantize(quantizer.quantize(reals, step, self.params.deadzone), step)
        total = dot(err, err) + dot(dropped, dropped) + self.outside_energy
        return math.sqrt(total * self.parseval)

    def encode(self, trial: Trial, *, exhaustive: bool = True, progressive: bool = True) -> bytes:
        """The COEF section of ``trial`` (``progressive=False``: one chunk, a tile's)."""
        return self.encode_stream(trial.stream, exhaustive=exhaustive, progressive=progressive)

    def estimate(self, trial: Trial, *, exhaustive: bool = False, progressive: bool = True) -> float:
        """Bytes of :meth:`encode`'s COEF section of ``trial``, estimated without coding it
        (:func:`~dftpcc.coding.estimated_size`)."""
        return self.estimate_stream(trial.stream, exhaustive=exhaustive, progressive=progressive)

    def estimate_stream(self, stream: np.ndarray, *, exhaustive: bool = False, progressive: bool = True) -> float:
        n = stream.size
        return coding.estimated_size(stream, radius=self.radius[:n], angle=self.angle[:n], coder=self.params.coder,
                                     exhaustive=exhaustive, progressive=progressive)

    def encode_stream(self, stream: np.ndarray, *, exhaustive: bool = True, progressive: bool = True) -> bytes:
        n = stream.size
        return coding.encode_coefficients(stream, radius=self.radius[:n], angle=self.angle[:n],
                                          coder=self.params.coder, exhaustive=exhaustive, progressive=progressive)
