"""Rate control: the cutoff and quantizer step that meet a target, found by trials.

Three targets, three functions over one :class:`~dftpcc.analysis.Analysis`:
:func:`for_rmse` (the smallest file within an RMSE), :func:`for_max_error`
(the smallest file, residual layer included, with every cell within a bound)
and :func:`for_bpp` (the most accurate file within a size). Each tries the
cutoffs of :func:`cutoffs` and searches the step at each; :func:`choose` runs
the one the parameters ask for, then, with ``fill='consistent'``, tries the
chosen cutoff again with the empty cells refilled and keeps the better file.

That search codes and rebuilds every candidate. :func:`choose` asks the model first
(:mod:`dftpcc.ratemodel`: the same candidates ranked by Parseval and by the coder's own
probabilities, only the kept one coded) and runs :func:`search` where the model misses;
:func:`method` picks either for a block of code (to compare them), :func:`tally` counts.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from .analysis import Analysis, Trial
from .errors import InvalidInputError
from .params import Params
from .sums import dot
from .residual import encode_residual, predicted_residual, residual_integers, residual_step

__all__ = ["Choice", "search", "cutoffs", "for_rmse", "for_max_error", "for_bpp", "CUTOFF_CANDIDATES", "METHODS",
           "method", "Tally", "tally"]

#: Cutoff ratios rate control tries.
CUTOFF_CANDIDATES = (0.0, 0.3, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.93, 0.95, 0.97)
#: Bisection iterations on the quantizer step (log scale).
STEP_ITERATIONS = 18
#: Rounds of measuring the true error and correcting the step search.
CALIBRATION_ROUNDS = 4
#: An RMSE search stops calibrating once a step meets the target to within this fraction.
CLOSE_ENOUGH = 0.97
#: Where an RMSE search corrects the quantizer's share of the error (step_for_rmse), it aims the
#: occupied cells' RMSE at this fraction of the target: the middle of the window (CLOSE_ENOUGH to 1)
#: a round stops in, so that its rounds do not close in on the target from above.
CORRECTION_AIM = (1.0 + CLOSE_ENOUGH) / 2.0
#: Rate control stops raising the cutoff once a file is this much larger than the best.
GIVE_UP_FACTOR = 1.3
#: Quantizer steps tried per cutoff for a maximum-error target, as multiples of it; where the
#: coarsest gives a cutoff's smallest file, the step doubles while the file shrinks, up to
#: MAX_ERROR_STEP_FACTOR_LIMIT (see for_max_error) ...
MAX_ERROR_STEP_FACTORS = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
MAX_ERROR_STEP_FACTOR_LIMIT = 4096.0
#: ... at the cutoffs whose file is within this factor of the best one.
MAX_ERROR_EXTEND_WITHIN = 1.1
#: With a consistent fill, an RMSE target is searched again for a step up to
#: this much coarser than the one found with the smooth fill, ...
REFILL_STEP_RANGE = 1.25
#: ... in this many bisections (each a refill: about five transforms).
REFILL_STEP_ITERATIONS = 4
#: Share of rate control's time the first search takes (for progress display; the refill takes the rest).
FIRST_SEARCH_SHARE = 0.8
#: Bisections (geometric) on the bound of a residual layer that is to meet an RMSE target,
#: between the target and the map's largest error: 10 ** 5 apart become a factor 1.0002.
RMSE_BOUND_ITERATIONS = 16
#: ... held this fraction inside the target (see :func:`_coarsest_bound`).
RMSE_BOUND_MARGIN = 1e-9
#: The bisection's fast test sums cells by the multiple of the step they round to, up to this
#: many multiples (a search of that many edges in the sorted magnitudes, a fraction of one pass
#: over the cells); past them it sums cell by cell. Its sums lose about k**2 * 1e-16 of the
#: squared error of the cells at multiple k: near the answer that may pass the margin, and the
#: cell-by-cell test of the answer catches it (the bisection then runs cell by cell). Low-passed
#: maps at a coarse step have errors of hundreds of steps: below a thousand, the cell-by-cell
#: passes were most of the bound's time.
FAST_BOUND_MULTIPLES = 1 << 16
#: Steps (times the RMSE target) of the low-passed maps a residual layer may correct for an RMSE
#: target: the first at every cutoff, the others at the best (:func:`corrected_for_rmse`).
CORRECTED_STEP_FACTORS = (8.0, 4.0, 16.0)


#: How rate control finds its choice: ``'model'`` predicts it from the spectrum and verifies it
#: (:mod:`dftpcc.ratemodel`), falling back to ``'search'``, the trials of every candidate, where
#: the prediction misses; ``'search'`` alone is kept to compare the two (benchmarks/bench_ratecontrol.py).
METHODS = ("model", "search")
_METHOD: contextvars.ContextVar[str] = contextvars.ContextVar("dftpcc_rate_control", default="model")


@dataclass
class Tally:
    """What rate control did in a :func:`tally` block: choices it made (not those refused as out
    of reach), how many the model made (verified), and how many times it fell back to the search."""

    choices: int = 0
    modelled: int = 0
    fallbacks: int = 0


_TALLY: contextvars.ContextVar[Tally | None] = contextvars.ContextVar("dftpcc_rate_tally", default=None)


@contextlib.contextmanager
def method(name: str) -> Iterator[None]:
    """Rate control by ``name`` (one of :data:`METHODS`) inside the block, in this thread or task."""
    if name not in METHODS:
        raise InvalidInputError(f"rate control method must be one of {', '.join(METHODS)}, got {name!r}")
    token = _METHOD.set(name)
    try:
        yield
    finally:
        _METHOD.reset(token)


@contextlib.contextmanager
def tally() -> Iterator[Tally]:
    """Count rate control's choices inside the block (for benchmarks and tests)."""
    found = Tally()
    token = _TALLY.set(found)
    try:
        yield found
    finally:
        _TALLY.reset(token)


#: Told the fraction of a search done, in [0, 1] (progress display).
Progress = Callable[[float], None]


def _no_progress(_: float) -> None:
    pass


@dataclass
class Choice:
    """A candidate file's coded content: the trial, its COEF section and any residual layer."""

    analysis: Analysis
    trial: Trial
    coefs: bytes
    residual: np.ndarray | None = None
    residual_blob: bytes = b""
    #: The residual layer's bound (metres): every occupied cell within it. The file states it as
    #: its ``target_max_error``, also when the layer serves an RMSE target (:func:`corrected_for_rmse`).
    bound: float = 0.0

    @property
    def size(self) -> int:
        """Bytes of the coded sections that vary with the choice."""
        return len(self.coefs) + len(self.residual_blob)


def cutoffs(params: Params) -> tuple[float, ...]:
    """The cutoffs to try: the one given, else :data:`CUTOFF_CANDIDATES`."""
    return CUTOFF_CANDIDATES if params.cutoff is None else (params.cutoff,)


def step_for_rmse(an: Analysis, cutoff: float, target: float) -> Trial | None:
    """The coarsest step at ``cutoff`` whose rebuilt DEM is within ``target`` RMSE (occupied cells)."""
    exact = an.trial(cutoff, an.tiny_step())
    if exact.rmse > target:
        return None
    if an.params.storage != "quantized":
        return exact  # nothing to choose but the cutoff
    best = _calibrated(an, cutoff, target, exact, share=False)
    if best is exact:
        best = _calibrated(an, cutoff, target, exact, share=True)
    return best


def _calibrated(an: Analysis, cutoff: float, target: float, exact: Trial, *, share: bool) -> Trial:
    """:func:`step_for_rmse`'s rounds: a step bisected on the proxy (the whole grid's RMSE predicted in
    the coefficient domain) for a goal, then rebuilt and measured on the occupied cells, and the goal
    corrected, until a step meets the target within :data:`CLOSE_ENOUGH`; the coarsest step that met
    it (``exact``, the unquantized trial, where none did).

    The goal is corrected by the ratio measured (``share=False``), or (``share=True``) the quantizer's
    share of the error alone is: what the cutoff costs (``exact``'s RMSE, and the proxy's at that step)
    adds to it in quadrature, and the goal is aimed at :data:`CORRECTION_AIM` of the target. The ratio
    lands where the occupied cells and the proxy grow alike; where the cutoff's error is most of the
    target and the occupied cells gain error faster than the proxy, its rounds close in on the target
    from above, each a hair over, and leave no quantized step (a strip map in 256-cell tiles coded
    by its base layer alone: 62 kB where 5.3 kB met the target), and the share's rounds are run."""
    best = exact
    goal = target
    if share:  # what the cutoff alone costs, on the occupied cells and in the proxy
        floor, proxy_floor = exact.rmse, an.proxy_rmse(cutoff, an.tiny_step())
    aimed = CORRECTION_AIM * target
    for _ in range(CALIBRATION_ROUNDS):
        lo, hi = an.tiny_step(), max(target, 1e-9) * 1e4
        for _ in range(STEP_ITERATIONS):
            mid = math.sqrt(lo * hi)
            if an.proxy_rmse(cutoff, mid) <= goal:
                lo = mid
            else:
                hi = mid
        trial = an.trial(cutoff, lo)
        if trial.rmse <= target:
            if trial.step > best.step:
                best = trial
            if trial.rmse > CLOSE_ENOUGH * target:
                break
        # The proxy counts filled cells too: aim it where this step's proxy would have to be for
        # the occupied cells to meet the target. (Scaling the old goal instead fails when even the
        # finest step's proxy is far above it: the filled cells of a gappy map at a high cutoff can
        # hold more error than the whole target.)
        proxy = an.proxy_rmse(cutoff, lo)
        goal = target * proxy / max(trial.rmse, 1e-12)
        if share:
            measured, modelled = trial.rmse ** 2 - floor ** 2, proxy ** 2 - proxy_floor ** 2
            if measured > 0 and modelled > 0 and aimed > floor:
                goal = math.sqrt(proxy_floor ** 2 + (aimed ** 2 - floor ** 2) * modelled / measured)
    return best


def for_rmse(an: Analysis, params: Params, progress: Progress = _no_progress) -> Choice:
    """The smallest file whose DEM RMSE is at most ``params.target_rmse``."""
    best: Choice | None = None
    tried = cutoffs(params)
    for i, cutoff in enumerate(tried):
        progress(i / len(tried))
        trial = step_for_rmse(an, cutoff, params.target_rmse)
        if trial is None:
            continue
        blob = an.encode(trial, exhaustive=False)
        if best is None or len(blob) < best.size:
            best = Choice(an, trial, blob)
        elif len(blob) > GIVE_UP_FACTOR * best.size:
            break  # past the best cutoff: sizes only grow from here
    if best is None:
        raise InvalidInputError(_rmse_out_of_reach(an, params))
    return best


def _rmse_out_of_reach(an: Analysis, params: Params) -> str:
    """Why no cutoff tried meets the RMSE target, and what to change."""
    cutoff = min(cutoffs(params))
    floor = an.trial(cutoff, an.tiny_step()).rmse
    if params.cutoff is not None:
        return (f"target RMSE {params.target_rmse:g} m cannot be reached at cutoff {cutoff:g}: the low-pass alone "
                f"leaves {floor:.3g} m; lower the cutoff, leave it out so rate control chooses it, or ask for "
                f"at least {floor:.3g} m")
    return (f"target RMSE {params.target_rmse:g} m cannot be reached: even every coefficient at the finest step "
            f"leaves {floor:.3g} m ({params.storage} storage); ask for at least that")


def for_max_error(an: Analysis, params: Params, progress: Progress = _no_progress) -> Choice:
    """The smallest file, residual layer included, with every occupied cell within ``params.target_max_error``.

    Every cutoff is tried at the steps of :data:`MAX_ERROR_STEP_FACTORS`; then, at each cutoff
    whose smallest file came at the coarsest of them and lies within :data:`MAX_ERROR_EXTEND_WITHIN`
    of the best, the step doubles while the file shrinks (rough terrain, where the residual layer
    carries most of the map), up to :data:`MAX_ERROR_STEP_FACTOR_LIMIT`. The candidates' residual
    layers are sized without the predicted layout (the slowest to code); it is tried at the end, on
    the best candidate and on the map with no spectrum at all (every coefficient quantized to 0, at
    the highest cutoff tried): on rough terrain, predicting the heights from their neighbours beats
    any low-pass.
    """
    bound = params.target_max_error
    quantized = params.storage == "quantized"
    factors = MAX_ERROR_STEP_FACTORS if quantized else (0.0,)
    best: Choice | None = None

    def attempt(cutoff: float, factor: float) -> int | None:
        """The candidate's size, or None when its coefficients alone lose to the best file."""
        nonlocal best
        trial = an.trial(cutoff, bound * factor)
        coefs = an.encode(trial, exhaustive=False)
        if best is not None and len(coefs) >= best.size:
            return None  # not smaller even with an empty residual layer: no need to code one
        choice = _corrected(an, trial, coefs, params.coder, bound, predicted=False)
        if best is None or choice.size < best.size:
            best = choice
        return choice.size

    tried = cutoffs(params)
    at_coarsest: list[tuple[int, float]] = []  # (size, cutoff) where the coarsest step won
    for i, cutoff in enumerate(tried):
        progress(i / len(tried))
        sizes = [attempt(cutoff, f) for f in factors]
        known = [(size, k) for k, size in enumerate(sizes) if size is not None]
        if quantized and known and min(known)[1] == len(factors) - 1:
            at_coarsest.append((min(known)[0], cutoff))
    assert best is not None  # at least one cutoff and one step were tried
    for size, cutoff in sorted(at_coarsest):
        if size > MAX_ERROR_EXTEND_WITHIN * best.size:
            break
        factor, smallest = factors[-1], size
        while factor < MAX_ERROR_STEP_FACTOR_LIMIT:
            factor *= 2.0
            found = attempt(cutoff, factor)
            if found is None or found >= smallest:
                break
            smallest = found
    _try_predicted_layout(best, params.coder)
    spectrum_free = predicted_map(an, params, bound)
    if spectrum_free is not None and spectrum_free.size < best.size:
        best = spectrum_free
    return best


def _try_predicted_layout(choice: Choice, coder: str) -> None:
    """Give ``choice`` its residual layer in the predicted layout where that is shorter: the
    search sizes its candidates without it (the slowest to code) and tries it on the winner."""
    if choice.residual is None:
        return
    layer = predicted_residual(choice.residual, coder, choice.analysis.kept_cells)
    if layer is not None and len(layer) < len(choice.residual_blob):
        choice.residual_blob = layer


def _corrected(an: Analysis, trial: Trial, coefs: bytes, coder: str, bound: float, *,
               predicted: bool = True) -> Choice:
    """``trial`` with the residual layer that brings every occupied cell within ``bound``."""
    q = residual_integers(an.dem.heights, trial.heights, an.mask, an.kept_cells, bound)
    return Choice(an, trial, coefs, q, encode_residual(q, coder, an.kept_cells, predicted=predicted), bound)


def _spectrum_free(an: Analysis, params: Params) -> tuple[Analysis, Trial] | None:
    """The map with no spectrum and no plane (every coefficient quantized to 0, at the highest
    cutoff tried), whose residual is the heights themselves; None where the residual cannot
    carry the map: unquantized storage (no step to quantize to 0), or cells the file rebuilds
    without a measured height (``mask='footprint'``), which would all be rebuilt at 0."""
    if params.storage != "quantized" or np.count_nonzero(an.kept_cells) != np.count_nonzero(an.mask):
        return None
    on = an.untrended()
    cutoff = max(cutoffs(params))
    return on, on.trial(cutoff, _empty_step(an, cutoff))


def predicted_map(an: Analysis, params: Params, bound: float) -> Choice | None:
    """The map with no spectrum, every occupied cell within ``bound`` through its residual layer
    alone (predicted from decoded neighbours where that layout is the smallest): on rough terrain,
    and on scattered maps whose transform must code the empty cells too, this beats any low-pass.
    None where it does not apply (:func:`_spectrum_free`)."""
    found = _spectrum_free(an, params)
    if found is None:
        return None
    on, trial = found
    return _corrected(on, trial, on.encode(trial, exhaustive=False), params.coder, bound)


def corrected_for_rmse(an: Analysis, params: Params, first: Choice) -> Choice | None:
    """The smallest low-passed map with a residual layer that meets ``params.target_rmse``, or the
    map with no spectrum (:func:`_spectrum_free`) with one; None where neither applies.

    A layer at a bound E corrects only the cells whose error passes E, so a coarse step that
    leaves a few walls, ridges and gap edges far off the target, brought back by a sparse layer,
    can cost less than the step fine enough to meet the target everywhere (the fragmented coastal
    plain near the floor). The bases: the first of :data:`CORRECTED_STEP_FACTORS` times the target
    as the step, at each cutoff from ``first``'s (the low-pass alone's choice) up, until the file
    has grown twice in a row or is :data:`GIVE_UP_FACTOR` times the best, ``first`` included; then
    the other factors at the best cutoff. Each base gets the coarsest bound that meets the target
    (:func:`_coarsest_bound`). None on a tiled map,
    whose tiles would code their residuals against bases the map's trial only approximates (the
    RMSE a file states must be the one it has), and for unquantized storage.
    """
    if an.params.tile_size or params.storage != "quantized":
        return None
    target = params.target_rmse
    best: Choice | None = None

    def attempt(on: Analysis, trial: Trial, *, predicted: bool = False) -> int | None:
        """The candidate's size; None when ``trial`` needs no layer, or its coefficients alone
        lose to the best."""
        nonlocal best
        bound = _coarsest_bound(on, trial, target)
        if bound is None:
            return None  # the low-pass alone meets the target: for_rmse's search has seen it
        coefs = on.encode(trial, exhaustive=False)
        if best is not None and len(coefs) >= best.size:
            return None
        choice = _corrected(on, trial, coefs, params.coder, bound, predicted=predicted)
        if best is None or choice.size < best.size:
            best = choice
        return choice.size

    first_factor, *others = CORRECTED_STEP_FACTORS
    last, rises = None, 0
    for cutoff in (c for c in cutoffs(params) if c >= first.trial.cutoff):
        size = attempt(an, an.trial(cutoff, first_factor * target))
        if size is None:
            continue
        rises = rises + 1 if last is not None and size > last else 0
        last = size
        if rises == 2 or size > GIVE_UP_FACTOR * min(best.size, first.size):
            break  # past the best cutoff: the layer grows faster than the spectrum shrinks
    if best is not None:
        cutoff = best.trial.cutoff
        for factor in others:
            attempt(an, an.trial(cutoff, factor * target))
        _try_predicted_layout(best, params.coder)
    spectrum_free = _spectrum_free(an, params)
    if spectrum_free is not None:
        attempt(*spectrum_free, predicted=True)
    if best is not None:
        best.coefs = best.analysis.encode(best.trial)
    return best


def _coarsest_bound(an: Analysis, trial: Trial, target: float) -> float | None:
    """The coarsest residual bound (a bisection of :data:`RMSE_BOUND_ITERATIONS` between the
    target, which always meets it, and the trial's largest error, which does not) at which
    ``trial`` corrected by its residual layer is within ``target`` RMSE on the occupied cells;
    None when the trial alone is."""
    return coarsest_bound_of((an.dem.heights - trial.heights)[an.mask], target)


def coarsest_bound_of(err: np.ndarray, target: float) -> float | None:
    """:func:`_coarsest_bound` of the errors ``err`` (metres, one per cell counted)."""
    if float(np.sqrt(np.mean(err * err))) <= target:
        return None
    # Held a hair inside the target: the encoder rebuilds the corrected heights by another route
    # (residual()), whose rounding may differ in the last bit.
    goal = target * (1.0 - RMSE_BOUND_MARGIN)
    # Every bound tried is at least the target, so a cell within half of it rounds to 0 at every
    # step (residual_step(bound) / 2 > target / 2): its error is left as it is, summed once, and
    # each bisection looks only at the few cells a layer can correct.
    small = np.abs(err) < 0.5 * target
    kept_sum = dot(err[small], err[small])
    big = err[~small]

    def meets(bound: float) -> bool:
        step = residual_step(bound)
        left = big - np.round(big / step) * step
        return math.sqrt((kept_sum + dot(left, left)) / err.size) <= goal

    # The bisection asks sixteen times; sorted magnitudes and their running sums answer each in
    # a search of the few multiples of the step they span (the sum over the cells rounding to k
    # is S2 - 2 k step S1 + n (k step)^2). Its answer is checked by the exact sum at the end.
    mags = np.sort(np.abs(big))
    s1 = np.concatenate(([0.0], np.cumsum(mags)))
    s2 = np.concatenate(([0.0], np.cumsum(mags * mags)))

    def roughly_meets(bound: float) -> bool:
        step = residual_step(bound)
        top = int(round(float(mags[-1]) / step)) if mags.size else 0
        if top > FAST_BOUND_MULTIPLES:
            return meets(bound)
        k = np.arange(top + 1, dtype=np.float64)
        ends = np.searchsorted(mags, (k + 0.5) * step)
        starts = np.concatenate(([0], ends[:-1]))
        n = ends - starts
        one, two = s1[ends] - s1[starts], s2[ends] - s2[starts]
        left = float(np.sum(two - 2.0 * k * step * one + n * (k * step) ** 2))
        return math.sqrt(max(kept_sum + left, 0.0) / err.size) <= goal

    def bisect(test: Callable[[float], bool]) -> float:
        lo, hi = target, float(np.abs(err).max())
        for _ in range(RMSE_BOUND_ITERATIONS):
            if hi <= lo * (1.0 + 1e-6):
                break
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if test(mid) else (lo, mid)
        return lo

    found = bisect(roughly_meets)
    return found if found == target or meets(found) else bisect(meets)


def _empty_step(an: Analysis, cutoff: float) -> float:
    """A step at which every coefficient inside ``cutoff`` quantizes to 0 (or the coarsest a file
    can state, should the coefficients be larger than that)."""
    peak = float(np.abs(an.largest(cutoff)).max(initial=0.0))
    return max(4.0 * peak, an.tiny_step(), 1e-9)


def for_bpp(an: Analysis, params: Params, budget: int, progress: Progress = _no_progress) -> Choice:
    """The most accurate file whose COEF section fits in ``budget`` bytes."""
    best: Choice | None = None
    tried = cutoffs(params)
    for i, cutoff in enumerate(tried):
        progress(i / len(tried))
        if params.storage == "quantized":
            # Sizes only: the DEM is rebuilt once, for the step found.
            found = finest_step_within(an, cutoff, budget)
            if found is None:
                continue
            trial, blob = an.trial(cutoff, found[0]), found[1]
        else:
            trial = an.trial(cutoff, 0.0)
            blob = an.encode(trial, exhaustive=False)
            if len(blob) > budget:
                continue
        if best is None or trial.rmse < best.trial.rmse:
            best = Choice(an, trial, blob)
    if best is None:
        raise bpp_out_of_reach(params, budget)
    return best


def finest_step_within(an: Analysis, cutoff: float, budget: float) -> tuple[float, bytes] | None:
    """The finest step at ``cutoff`` whose COEF section, coded (``exhaustive=False``), takes at most
    ``budget`` bytes, bisected (log scale) by coding each step, and that section; None where no
    step tried fits."""
    lo, hi = an.tiny_step() * 1e3, 1e4
    found = None
    for _ in range(STEP_ITERATIONS):
        mid = math.sqrt(lo * hi)
        blob = an.encode_stream(an.quantized(cutoff, mid), exhaustive=False)
        if len(blob) <= budget:
            found, hi = (mid, blob), mid
        else:
            lo = mid
    return found


def coef_budget(params: Params, point_count: int, fixed_bytes: int) -> int:
    """Bytes a size target leaves the COEF section: the file's bits less ``fixed_bytes`` (the
    mask and header); :class:`InvalidInputError` where those alone pass the target."""
    budget = int(params.target_bpp * point_count / 8) - fixed_bytes
    if budget <= 0:
        raise InvalidInputError(
            f"target {params.target_bpp} bits/point cannot be reached: the occupancy mask and header (CRS "
            f"included) alone need {8 * fixed_bytes / point_count:.4f} bits/point")
    return budget


def bpp_out_of_reach(params: Params, budget: int) -> InvalidInputError:
    """The error of a size target no cutoff tried reaches."""
    where = f"at cutoff {params.cutoff:g}" if params.cutoff is not None else "at any cutoff"
    hint = ("raise the target, or leave the cutoff out so rate control may choose a higher one"
            if params.cutoff is not None else "raise the target")
    return InvalidInputError(f"target {params.target_bpp:g} bits/point cannot be reached {where}: the "
                             f"coefficients need more than the {budget:,} bytes left after the mask and "
                             f"header, even at the coarsest step; {hint}")


def _search(an: Analysis, params: Params, point_count: int, fixed_bytes: int,
            progress: Progress = _no_progress) -> Choice:
    """The choice for the target in ``params``, its COEF section coded with the best band layout per chunk."""
    if params.target_rmse > 0:
        choice = for_rmse(an, params, progress)
    elif params.target_max_error > 0:
        choice = for_max_error(an, params, progress)
    else:
        choice = for_bpp(an, params, coef_budget(params, point_count, fixed_bytes), progress)
    # The search sized candidates with one band layout; the file gets the best per chunk.
    choice.coefs = choice.analysis.encode(choice.trial)
    return choice


def search(an: Analysis, params: Params, point_count: int, fixed_bytes: int,
           progress: Progress = _no_progress) -> Choice:
    """:func:`choose` by trying every candidate: the cutoffs of :func:`cutoffs`, the steps at each
    (the fallback of the model, :mod:`dftpcc.ratemodel`)."""
    first = _search(an, params, point_count, fixed_bytes, lambda f: progress(FIRST_SEARCH_SHARE * f))
    progress(FIRST_SEARCH_SHARE)
    best = _refined(an, params, first, point_count, fixed_bytes) if an.refillable else first
    if params.target_rmse > 0:
        corrected = corrected_for_rmse(an, params, first)
        if corrected is not None and corrected.size < best.size:
            best = corrected
    return best


def _refined(an: Analysis, params: Params, first: Choice, point_count: int, fixed_bytes: int) -> Choice:
    """:func:`choose`'s second choice, at ``first``'s cutoff with the empty cells refilled, if better."""
    if params.target_rmse > 0:
        if params.storage != "quantized":
            return first  # no step to search
        other, trial = _refilled_for_rmse(an, first.trial, params.target_rmse)
        second = Choice(other, trial, other.encode(trial))
    else:
        other = an.refilled(first.trial)
        try:
            second = _search(other, params.replace(cutoff=first.trial.cutoff), point_count, fixed_bytes)
        except InvalidInputError:
            return first  # nothing at this cutoff meets the target with the new fill
    better = second.trial.rmse < first.trial.rmse if params.target_bpp > 0 else second.size < first.size
    return second if better else first


def _refilled_for_rmse(an: Analysis, first: Trial, target: float) -> tuple[Analysis, Trial]:
    """The coarsest step from ``first.step`` up to :data:`REFILL_STEP_RANGE` times it whose
    refilled map meets ``target`` (``first`` itself when even its own step does not)."""

    def attempt(base: Trial) -> tuple[Analysis, Trial]:
        other = an.refilled(base)
        return other, other.trial(base.cutoff, base.step)

    best = attempt(first)
    if best[1].rmse > target:
        return an, first
    lo, hi = first.step, first.step * REFILL_STEP_RANGE
    for _ in range(REFILL_STEP_ITERATIONS):
        mid = math.sqrt(lo * hi)
        found = attempt(an.trial(first.cutoff, mid))
        if found[1].rmse <= target:
            best, lo = found, mid
        else:
            hi = mid
    return best
