"""Rate control from a model: the choice predicted from one transform, verified by trials, coded once.

The search (:func:`dftpcc.ratecontrol.search`) rebuilds and entropy-codes every
candidate (cutoff, step). The spectrum already tells most of that: by Parseval
the whole grid's squared error at (cutoff, step) is the energy of the values
the cutoff drops plus the quantizer's error on the kept ones (:class:`Energy`),
and a candidate's bytes follow from its integers' probabilities under the
coder's own model (:func:`dftpcc.coding.estimated_size`, and for a residual
layer :func:`dftpcc.residual.estimated_size`), within 0.1 % (a few % for a
layer's map of nonzero cells) of the coded bytes. So no candidate is coded but
the one kept.

* An RMSE target: every cutoff's step from Parseval, ranked by estimated bytes;
  the best rebuilt and its step corrected from what the rebuilt map measures on
  the occupied cells (a ratio, then interpolation between trials) until it lands
  just inside the target; the consistent fill refilled from a trial at the step
  it is coded with; the files with a residual layer (a coarse low-pass with a
  sparse layer, the map with no spectrum) rebuilt and sized by estimates.
* A maximum-error target: a few pilot trials teach the model the residual
  layer's bytes as a function of the predicted RMSE over the bound; every
  (cutoff, step) is ranked by that and its estimated coefficients, and the
  one ranked smallest is rebuilt, teaching the model in turn, until it ranks
  none smaller than the smallest file found (the map with no spectrum's too).
* A size target: each cutoff's step that fills the budget by estimates, ranked
  by Parseval's error, the best few rebuilt to compare their occupied cells.

Every file keeps the search's guarantee: its error is measured on the map the
decoder rebuilds (a residual layer holds its bound by construction), its size
on the coded bytes. Where the model cannot verify a choice, :func:`choose`
returns None and rate control runs the search.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import coding, quantizer
from .analysis import Analysis, Trial
from .errors import InvalidInputError
from .params import Params
from .ratecontrol import (_METHOD, _TALLY, Progress, _no_progress, search, CLOSE_ENOUGH, CORRECTED_STEP_FACTORS, GIVE_UP_FACTOR, MAX_ERROR_STEP_FACTOR_LIMIT,
                          MAX_ERROR_STEP_FACTORS, REFILL_STEP_RANGE, Choice, coarsest_bound_of, _spectrum_free,
                          bpp_out_of_reach, coef_budget, cutoffs)
from .residual import (PREDICTED_SHARE, encode_residual, estimated_size, median_predicted_size, residual_integers,
                       sampled_rows)
from .sums import dot

__all__ = ["choose", "predict", "Energy"]

#: The first values of a cutoff's stream (the largest, lowest frequencies) enter the quantizer's
#: error exactly; the rest through an evenly strided sample of about :data:`ENERGY_SAMPLE` values,
#: whose error is scaled up: the file's error is measured on the rebuilt map anyway.
ENERGY_HEAD = 4096
ENERGY_SAMPLE = 32768
#: Bisections (geometric) of a step between brackets :data:`STEP_BRACKET` apart: 1 % apart at the end.
STEP_BRACKET = 4.0
STEP_BISECTIONS = 8
#: An RMSE a rebuilt map measures is aimed this far inside the target when the step is corrected
#: (the correction is a prediction too: a hair inside keeps it from landing a bit above).
AIM_INSIDE = 0.995
#: A trial whose RMSE is within this fraction of the target (below it) ends the correction ...
LANDING = 0.998
#: ... aimed at this fraction of it ...
AIM = 0.999
#: ... else at most this many trials (rebuilt maps) at a cutoff, and refills of a consistent fill.
VERIFY_TRIALS = 5
REFILL_TRIALS = 3
#: A size target's budget is aimed this far inside by the estimate (estimates are within 0.1 %
#: of the coded size on real maps; the coded file is checked, and coded again coarser on a miss).
BUDGET_INSIDE = 0.998
#: Where the coded file still passes the budget, the step is raised this much and the file coded
#: again, at most this many times, before the search takes over.
BUDGET_STEP_UP = 1.05
BUDGET_RETRIES = 6
#: A size target skips the cutoffs whose low-pass alone leaves this many times the (whole-grid)
#: error of the best file found at a lower one: their occupied cells would have to hold far less
#: of the error than the lower cutoff's do.
FLOOR_SKIP = 1.5
#: Cutoffs a size target rebuilds, best predicted first: a gappy map's empty cells hold another
#: share of each cutoff's error than its occupied ones.
VERIFIED_SIZE = 4
#: Secant iterations (log size against log step) that find a size target's step at a cutoff, and
#: how close (relative) to the budget they stop.
SIZE_ITERATIONS = 8
SIZE_TOLERANCE = 0.003


class Energy:
    """The whole grid's RMSE (metres) at one cutoff as a function of the quantizer step, from the
    coefficients alone (Parseval): the energy the cutoff drops plus the quantizer's error on the
    kept values, the first :data:`ENERGY_HEAD` exactly, the rest from a strided sample."""

    def __init__(self, an: Analysis, cutoff: float):
        kept, self.lost = an.energy_at(cutoff)
        self.count = kept.size
        self.head = kept[:ENERGY_HEAD]
        tail = kept[ENERGY_HEAD:]
        stride = max(1, tail.size // ENERGY_SAMPLE)
        self.tail = tail[::stride]
        self.weight = tail.size / self.tail.size if self.tail.size else 0.0
        self.parseval = an.parseval
        self.deadzone = an.params.deadzone

    def _quantizer_error(self, values: np.ndarray, step: float) -> float:
        err = values - quantizer.dequantize(quantizer.quantize(values, step, self.deadzone), step)
        return dot(err, err)

    def rmse(self, step: float) -> float:
        """Predicted RMSE over every cell of the grid at ``step`` (metres)."""
        total = self.lost + self._quantizer_error(self.head, step)
        if self.tail.size:
            total += self.weight * self._quantizer_error(self.tail, step)
        return math.sqrt(max(total, 0.0) * self.parseval)

    @property
    def floor(self) -> float:
        """The RMSE of the cutoff alone (every kept value exact)."""
        return math.sqrt(self.lost * self.parseval)

    def step_for(self, goal: float) -> float | None:
        """The coarsest step (to 1 %) whose predicted RMSE is at most ``goal``; None when the
        cutoff alone passes it."""
        if self.floor >= goal:
            return None
        # A uniform quantizer's error is about step**2 / 12 a value: the bracket starts there.
        budget = goal * goal / self.parseval - self.lost
        guess = math.sqrt(12.0 * budget / max(self.count, 1))
        lo, hi = guess / STEP_BRACKET, guess * STEP_BRACKET
        for _ in range(40):
            if self.rmse(lo) <= goal:
                break
            lo, hi = lo / STEP_BRACKET, lo
        else:
            return None
        for _ in range(40):
            if self.rmse(hi) > goal:
                break
            lo, hi = hi, hi * STEP_BRACKET
        for _ in range(STEP_BISECTIONS):
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if self.rmse(mid) <= goal else (lo, mid)
        return lo


@dataclass
class Candidate:
    """A (cutoff, step) the model ranks: its predicted whole-grid RMSE and estimated bytes."""

    cutoff: float
    step: float
    proxy: float
    size: float


def _estimate(an: Analysis, cutoff: float, step: float) -> float:
    """Estimated bytes of (cutoff, step) in the first band layout: to rank many candidates."""
    return an.estimate_stream(an.quantized(cutoff, step))


def _coded(an: Analysis, trial: Trial) -> float:
    """Estimated bytes of ``trial`` as the file codes it (each chunk's best band layout: on
    directional terrain a few % below the first layout's), to compare the few candidates left."""
    return an.estimate(trial, exhaustive=True)


class _OutOfReach(InvalidInputError):
    """A size target no cutoff reaches by the estimates: the search's error, not a miss of the model."""


def predict(an: Analysis, params: Params, point_count: int, fixed_bytes: int) -> Choice | None:
    """Rate control's choice for the target in ``params`` from the model, verified; None where the
    model does not apply or misses (:func:`choose` then searches)."""
    if params.storage != "quantized":
        return None  # no step to predict: the search tries the cutoffs alone
    budget = coef_budget(params, point_count, fixed_bytes) if params.target_bpp > 0 else 0
    try:
        if params.target_rmse > 0:
            choice = _for_rmse(an, params)
        elif params.target_max_error > 0:
            choice = _for_max_error(an, params)
        else:
            choice = _for_bpp(an, params, budget)
    except _OutOfReach as exc:
        raise InvalidInputError(str(exc)) from None
    except InvalidInputError:
        return None  # a step the model tried was refused (too fine for the map): the search decides
    if choice is not None and not choice.coefs:
        # Ranked by estimates of one band layout; the file gets the best per chunk.
        choice.coefs = choice.analysis.encode(choice.trial)
    return choice


# --- an RMSE target --------------------------------------------------------------------------------

def _ranked_for_rmse(an: Analysis, params: Params, goal: float) -> list[Candidate]:
    """Every cutoff that can meet the (whole-grid) ``goal``, with its step and estimated bytes,
    smallest first; from the highest cutoff down, stopping as the search does once the files
    only grow (:data:`GIVE_UP_FACTOR`)."""
    found: list[Candidate] = []
    for cutoff in sorted(cutoffs(params), reverse=True):
        energy = Energy(an, cutoff)
        step = energy.step_for(goal)
        if step is None:
            continue
        size = _estimate(an, cutoff, step)
        found.append(Candidate(cutoff, step, energy.rmse(step), size))
        if size > GIVE_UP_FACTOR * min(c.size for c in found):
            break
    return sorted(found, key=lambda c: c.size)


def _secant(tried: list[tuple[float, float]], goal: float) -> float | None:
    """The step where the measured RMSE crosses ``goal``, interpolated (log-log) between the coarsest
    trial below it and the finest above; None without such a pair. ``tried``: (step, rmse)."""
    below = [t for t in tried if t[1] <= goal]
    above = [t for t in tried if t[1] > goal]
    if not below or not above:
        return None
    (s0, r0), (s1, r1) = max(below), min(above)
    if not s0 < s1 or not r1 > r0 > 0:
        return math.sqrt(s0 * s1) if s0 < s1 else None
    at = (math.log(goal) - math.log(r0)) / (math.log(r1) - math.log(r0))
    return math.exp(math.log(s0) + at * (math.log(s1) - math.log(s0)))


def _verified_rmse(an: Analysis, cutoff: float, target: float, ratio: float) -> tuple[Trial | None, float]:
    """The trial at ``cutoff`` whose step the model predicts meets ``target`` on the occupied cells
    (the whole grid's predicted RMSE times ``ratio``), rebuilt and measured; then corrected, by the
    ratio measured or, once trials lie either side of the target, by interpolating them, until one
    lands within :data:`LANDING` of the target (at most :data:`VERIFY_TRIALS` trials: where the
    low-pass holds most of the error, the file's size moves much faster than its error). None
    where no trial meets the target. Also the last ratio measured (occupied cells' RMSE over the
    whole grid's prediction)."""
    energy = Energy(an, cutoff)
    best: Trial | None = None
    tried: list[tuple[float, float]] = []
    step = energy.step_for(AIM_INSIDE * target / ratio)
    for _ in range(VERIFY_TRIALS):
        if step is None or any(abs(step / s - 1.0) < 1e-6 for s, _ in tried):
            break
        trial = an.trial(cutoff, step)
        tried.append((trial.step, trial.rmse))
        predicted = energy.rmse(trial.step)
        ratio = trial.rmse / predicted if predicted > 0 else ratio
        if trial.rmse <= target:
            if best is None or trial.step > best.step:
                best = trial
            if trial.rmse >= LANDING * target:
                break
        step = _secant(tried, AIM * target)
        if step is None:
            step = energy.step_for(AIM * target / max(ratio, 1e-12))
    return best, ratio


def _for_rmse(an: Analysis, params: Params) -> Choice | None:
    target = params.target_rmse
    ranked = _ranked_for_rmse(an, params, target)
    if not ranked:
        return None
    first, ratio = _verified_rmse(an, ranked[0].cutoff, target, 1.0)
    if abs(ratio - 1.0) > 1.0 - CLOSE_ENOUGH:
        # The occupied cells hold another share of the error than the whole grid: rank again
        # with the measured share, and verify the new best where it moved.
        ranked = _ranked_for_rmse(an, params, target / ratio)
        if ranked and (first is None or ranked[0].cutoff != first.cutoff):
            other, _ = _verified_rmse(an, ranked[0].cutoff, target, ratio)
            if other is not None and (first is None or _coded(an, other) < _coded(an, first)):
                first = other
    if first is None:
        return None
    # The finalists are ranked by estimates, then coded: the file is the smallest as coded, so the
    # consistent fill and a residual layer are kept only where they are smaller, as the search keeps them.
    finalists = [Choice(an, first, b"")]
    if an.refillable:
        refilled = _refilled_for_rmse(an, first, target)
        if refilled is not None:
            finalists.append(Choice(*refilled, b""))
    estimates = [_coded(c.analysis, c.trial) for c in finalists]
    corrected = _corrected_for_rmse(an, params, first, min(estimates))
    # Only the finalists whose estimate is in reach of the smallest are coded (the estimates of a
    # stream are within 0.1 % of its bytes): where a residual layer wins by more, the file was
    # coded twice for nothing.
    smallest = min(estimates + ([corrected.size] if corrected is not None else []))
    coded = [c for c, e in zip(finalists, estimates) if e <= (1.0 + FINALIST_SLACK) * smallest]
    for choice in coded:
        choice.coefs = choice.analysis.encode(choice.trial)
    return min(coded + ([corrected] if corrected is not None else []), key=lambda c: c.size)


#: An RMSE target's finalists (the low-pass alone, refilled or not) are coded where their estimated
#: bytes are within this fraction of the smallest finalist's (a file with a residual layer: coded).
FINALIST_SLACK = 0.02


def _corrected_for_rmse(an: Analysis, params: Params, first: Trial, to_beat: float) -> Choice | None:
    """:func:`dftpcc.ratecontrol.corrected_for_rmse` with each candidate's bytes estimated, not
    coded: the smallest low-passed map with a residual layer that meets the RMSE target, or the map
    with no spectrum with one, where smaller than ``to_beat`` bytes; coded (None where none is).

    The map with no spectrum is sized after the walk's first base, whose size may rule it out at a
    glance (:func:`_free_loses`), and before the rest of the walk, whose bases it spares where their
    coefficients alone pass it, and the other steps where they cannot bring the walk's best below
    it: on rough terrain it wins by 7-30 %, and every base of the walk had lost to it. (The residual
    curve that guides a maximum-error target, :class:`_Guided`, ranks these bases poorly: the
    layer that brings a base to an RMSE grows from nothing just past the target, and it stopped
    short of the walk's file by 1-8 % on three maps of ../shared/data.)"""
    if an.params.tile_size or params.storage != "quantized":
        return None
    target, coder = params.target_rmse, params.coder
    # The walk's bases are sized from a quarter of the rows (their bound too), the one it keeps
    # again from all of them: a base's layer cost three times its rebuild to size.
    rows = sampled_rows(an.mask.shape[0])
    free_layer: _Layer | None = None
    walked: _Layer | None = None  # the walk's smallest base

    def beat() -> float:
        return min([to_beat] + [layer.size for layer in (free_layer, walked) if layer is not None])

    first_factor, *others = CORRECTED_STEP_FACTORS
    free = _spectrum_free(an, params)
    last, rises = None, 0
    for cutoff in (c for c in cutoffs(params) if c >= first.cutoff):
        found = _corrected_layer(an, cutoff, first_factor * target, target, coder, beat(), rows=rows)
        if free is not None:  # after the first base
            if not _free_loses(*free, target, coder, min(beat(), found.size if found else math.inf)):
                on, trial = free
                free_layer = _corrected_layer(on, trial.cutoff, trial.step, target, coder,
                                              min(beat(), found.size if found else math.inf), predicted=True)
            free = None
        if found is None:
            continue
        if walked is None or found.size < walked.size:
            walked = found
        rises = rises + 1 if last is not None and found.size > last else 0
        last = found.size
        # Against the walk's own files: the walk falls steeply at times, and by the map with no
        # spectrum's it stopped short of redrocks' smallest file at a 5 cm RMSE target (2.3 % larger).
        if rises == CORRECTED_RISES or found.size > GIVE_UP_FACTOR * min(walked.size, to_beat):
            break
    if walked is not None and walked.size < OTHERS_REACH * beat():
        for factor in others:
            found = _corrected_layer(an, walked.trial.cutoff, factor * target, target, coder, beat(), rows=rows)
            if found is not None and found.size < walked.size:
                walked = found
    if walked is not None and walked.q.size < np.count_nonzero(an.kept_cells):  # sized from the rows: now whole
        rival = min(to_beat, free_layer.size if free_layer else math.inf)
        walked = None if walked.size > SAMPLED_REACH * rival else \
            _corrected_layer(an, walked.trial.cutoff, walked.trial.step, target, coder, rival)
    if walked is not None:
        # The predicted layout must beat the chunked one and leave the file below the others.
        layout = _predicted_size(walked.q, coder, walked.analysis.kept_cells, beat() - walked.coefs)
        walked.resd = min(walked.resd, layout)
    best = min((layer for layer in (walked, free_layer) if layer is not None), key=lambda layer: layer.size,
               default=None)
    if best is None or best.size >= to_beat:
        return None
    return Choice(best.analysis, best.trial, best.analysis.encode(best.trial), best.q,
                  encode_residual(best.q, coder, best.analysis.kept_cells), best.bound)


#: A base sized from a quarter of the rows is sized again from all of them only where within this
#: factor of the file to beat (its size from the rows was within 1.5 % of the whole's on the dense
#: layers of ../shared/data; a sparse layer the rows miss is sized whole at once).
SAMPLED_REACH = 1.05
#: The other steps of :data:`~dftpcc.ratecontrol.CORRECTED_STEP_FACTORS` are tried at the walk's best
#: cutoff only where its file is within this factor of the one to beat: on ../shared/data they
#: brought it down by 39 % at most (to 0.61 of it), so further off they only cost two rebuilds.
OTHERS_REACH = 2.0
#: The walk of :func:`_corrected_for_rmse` up the cutoffs stops where the file has grown this many
#: times in a row, as the search's (:func:`dftpcc.ratecontrol.corrected_for_rmse`): at the first rise,
#: redrocks at a 5 cm RMSE target missed its smallest file by 2.3 %.
CORRECTED_RISES = 2


def _base(an: Analysis, cutoff: float, step: float, to_beat: float) -> tuple[float, Trial] | None:
    """A candidate's estimated COEF bytes (every band layout) and its rebuilt trial; None, without
    rebuilding it, where those bytes alone take ``to_beat`` or more (no residual layer can make it
    smaller): the start of sizing any candidate with a layer (:func:`_corrected_layer`, :func:`_layer`)."""
    coefs = an.estimate_stream(an.quantized(cutoff, step), exhaustive=True)
    return None if coefs >= to_beat else (coefs, an.trial(cutoff, step))


def _corrected_layer(on: Analysis, cutoff: float, step: float, target: float, coder: str, to_beat: float, *,
                     predicted: bool = False, rows: np.ndarray | None = None) -> _Layer | None:
    """A base of :func:`_corrected_for_rmse` rebuilt with the coarsest layer that brings it within
    the RMSE ``target`` (:func:`~dftpcc.ratecontrol.coarsest_bound_of`), sized by estimates (the
    predicted layout too with ``predicted``); None where its coefficients alone take ``to_beat``
    bytes or more (no need to rebuild it), or the low-pass alone meets the target. With ``rows``
    (a mask), the bound and the layer are those of these rows, its bytes scaled to the map's: a
    base to rank, not to code."""
    based = _base(on, cutoff, step, to_beat)
    if based is None:
        return None
    coefs, trial = based
    heights, rebuilt, mask, kept = on.dem.heights, trial.heights, on.mask, on.kept_cells
    if rows is not None:
        heights, rebuilt, mask, kept = heights[rows], rebuilt[rows], mask[rows], kept[rows]
    bound = coarsest_bound_of((heights - rebuilt)[mask], target)
    if bound is None and rows is not None:
        # The rows meet the target alone: the map's few cells past it lie elsewhere; sized whole.
        heights, rebuilt, mask, kept, rows = on.dem.heights, trial.heights, on.mask, on.kept_cells, None
        bound = coarsest_bound_of((heights - rebuilt)[mask], target)
    if bound is None:
        return None
    q = residual_integers(heights, rebuilt, mask, kept, bound)
    resd = estimated_size(q, coder, kept, predicted=False)
    if rows is not None:
        resd *= np.count_nonzero(on.kept_cells) / max(np.count_nonzero(kept), 1)
    if predicted:
        resd = min(resd, _predicted_size(q, coder, kept, to_beat - coefs))
    return _Layer(on, trial, coefs, resd, q, bound)


#: The map with no spectrum meets an RMSE target with a layer at a bound near sqrt(3) times the
#: target (nearly every cell corrected, its error then uniform within the bound); sized at this
#: many times the target, a coarser layer, its bytes are a floor of the file's (:func:`_free_loses`).
FREE_FLOOR_BOUND = 4.0


def _free_loses(on: Analysis, trial: Trial, target: float, coder: str, to_beat: float) -> bool:
    """Whether the map with no spectrum (:func:`~dftpcc.ratecontrol._spectrum_free`) surely loses to
    ``to_beat`` bytes at an RMSE ``target``: its layer at :data:`FREE_FLOOR_BOUND` times the target,
    coarser than the one it needs, takes that many bytes chunked, and the median predictor's share
    (:data:`~dftpcc.residual.PREDICTED_SHARE`) as many, whatever the layout. A few array passes
    instead of the bound's bisection and the predicted layout's fit, on maps it loses by a factor."""
    if not math.isfinite(to_beat):
        return False
    q = residual_integers(on.dem.heights, trial.heights, on.mask, on.kept_cells, FREE_FLOOR_BOUND * target)
    flat = np.zeros(q.size)
    coefs = on.estimate_stream(trial.stream)
    chunked = coding.estimated_size(q, radius=flat, angle=flat, coder=coder, exhaustive=False)
    if coefs + chunked < to_beat:
        return False
    return coder != "ans" or not q.size or coefs + PREDICTED_SHARE * median_predicted_size(q, on.kept_cells) >= to_beat


def _refilled_for_rmse(an: Analysis, first: Trial, target: float) -> tuple[Analysis, Trial] | None:
    """``first``'s cutoff with the empty cells refilled (a consistent fill) from a trial at the step
    it is coded with, as the search does: the coarsest such step up to :data:`REFILL_STEP_RANGE`
    times ``first``'s that meets ``target``, predicted from the map refilled at ``first`` and then
    found by interpolating the refills tried (at most :data:`REFILL_TRIALS`); None where even
    ``first``'s step refilled misses the target."""

    def attempt(step: float) -> tuple[Analysis, Trial]:
        other = an.refilled(an.trial(first.cutoff, step))
        return other, other.trial(first.cutoff, step)

    other, at_first = an.refilled(first), None
    at_first = other.trial(first.cutoff, first.step)
    if at_first.rmse > target:
        return None
    best = (other, at_first)
    tried = [(at_first.step, at_first.rmse)]
    # A map refilled from a trial holds coefficients near that trial's steps, so its own
    # quantizer error at that step says little of another: the first guess follows the
    # slope of the map before the refill (log RMSE against log step), then the refills tried.
    energy = Energy(an, first.cutoff)
    coarser, here = energy.rmse(first.step * 1.1), energy.rmse(first.step)
    # A map the step does not change (flat, or every coefficient far above it) has no slope to follow.
    slope = math.log(coarser / here) / math.log(1.1) if coarser > 0 and here > 0 else 0.0
    step = first.step * (AIM * target / at_first.rmse) ** (1.0 / slope) if slope > 0 and at_first.rmse > 0 else None
    top = REFILL_STEP_RANGE * first.step
    for _ in range(REFILL_TRIALS):
        if step is None or step <= best[1].step:
            break
        found = attempt(min(step, top))
        tried.append((found[1].step, found[1].rmse))
        if found[1].rmse <= target:
            best = found
            if found[1].rmse >= LANDING * target or found[1].step >= quantizer.short_step(top):
                break
        step = _secant(tried, AIM * target)
    return best


# --- a size target ---------------------------------------------------------------------------------

def _step_for_size(an: Analysis, cutoff: float, budget: float, energy: Energy,
                   guess: float | None = None) -> tuple[float, float] | None:
    """The finest step (and its estimated bytes) at ``cutoff`` whose estimated COEF section fits
    :data:`BUDGET_INSIDE` of ``budget`` bytes, by secant steps on log size against log step from
    ``guess`` (default: a step near the cutoff's own error); None where even the coarsest step
    tried does not fit."""
    guess = guess or energy.step_for(max(energy.floor * 1.5, 1e-9)) or an.tiny_step() * 1e6
    fits: tuple[float, float] | None = None  # (step, size) that fit: the finest one
    over: tuple[float, float] | None = None  # (step, size) that do not: the coarsest one
    budget = BUDGET_INSIDE * budget
    step = guess
    for _ in range(SIZE_ITERATIONS):
        size = _estimate(an, cutoff, step)
        if size <= budget:
            if fits is None or step < fits[0]:
                fits = (step, size)
            if size >= budget * (1.0 - SIZE_TOLERANCE):
                break
        elif over is None or step > over[0]:
            over = (step, size)
        if fits is not None and over is not None:
            (s0, z0), (s1, z1) = fits, over
            slope = (math.log(z1) - math.log(z0)) / (math.log(s1) - math.log(s0))
            step = math.exp(math.log(s0) + (math.log(budget) - math.log(z0)) / slope) if slope < 0 else \
                math.sqrt(s0 * s1)
            step = min(max(step, min(s0, s1) * 1.0001), max(s0, s1) / 1.0001)
        else:
            step = step * 4.0 if fits is None else step / 2.0
    return fits


#: A size target's step at a budget of a few hundred bytes is found again by coding, from this
#: factor of the estimate's either way (widened where the budget is not crossed), in this many halvings.
CODED_BRACKET = 1.1
CODED_HALVINGS = 5


def _coded_step(an: Analysis, cutoff: float, budget: int, step: float) -> float:
    """``step`` (an estimate's, aimed :data:`BUDGET_INSIDE` inside ``budget``) or, where ``budget``
    is a few hundred bytes, the finest step near it whose COEF section, coded, fits the budget
    itself: such a budget is met or missed by whole bytes, coarser than the estimate's tolerance,
    and a byte moves the error by several % (estimates stopped a few bytes short). Bisected
    between steps that fit and do not, from :data:`CODED_BRACKET` either way of ``step``; ``step``
    where no coarser step tried fits."""
    if budget * SIZE_TOLERANCE >= 1.0:
        return step

    def fits(s: float) -> bool:
        return len(an.encode_stream(an.quantized(cutoff, s), exhaustive=False)) <= budget

    coarse, fine = step * CODED_BRACKET, step / CODED_BRACKET
    for _ in range(4):
        if fits(coarse):
            break
        coarse *= CODED_BRACKET
    else:
        return step
    for _ in range(4):
        if not fits(fine):
            break
        coarse, fine = fine, fine / CODED_BRACKET
    else:
        return fine
    for _ in range(CODED_HALVINGS):
        mid = math.sqrt(coarse * fine)
        coarse, fine = (mid, fine) if fits(mid) else (coarse, mid)
    return coarse


def _for_bpp(an: Analysis, params: Params, budget: int) -> Choice | None:
    ranked = []
    guess = None
    for cutoff in sorted(cutoffs(params)):
        energy = Energy(an, cutoff)
        if ranked and energy.floor > FLOOR_SKIP * min(ranked)[0]:
            break  # the low-pass alone loses to a file found: so do the higher cutoffs
        # The step that fills the budget moves little from one cutoff to the next: the last one's first.
        found = _step_for_size(an, cutoff, budget, energy, guess)
        if found is not None:
            ranked.append((energy.rmse(found[0]), cutoff, found[0]))
            guess = found[0]
    if not ranked:
        # Estimates are within 0.1 % of the coded bytes, aimed BUDGET_INSIDE inside: as the search would.
        raise _OutOfReach(str(bpp_out_of_reach(params, budget)))
    ranked.sort()
    # The ranking is of the whole grid's error; the occupied cells decide: the best few rebuilt.
    trials = [an.trial(cutoff, _coded_step(an, cutoff, budget, step)) for _, cutoff, step in ranked[:VERIFIED_SIZE]]
    first = min(trials, key=lambda t: t.rmse)
    best = Choice(an, first, b"")
    if an.refillable:
        other = an.refilled(first)
        found = _step_for_size(other, first.cutoff, budget, Energy(other, first.cutoff))
        if found is not None:
            trial = other.trial(first.cutoff, _coded_step(other, first.cutoff, budget, found[0]))
            if trial.rmse < first.rmse:
                best = Choice(other, trial, b"")
    coefs = best.analysis.encode(best.trial)
    for _ in range(BUDGET_RETRIES):
        if len(coefs) <= budget:
            best.coefs = coefs
            return best
        # A short stream's estimate may miss by a few bytes: a little coarser, coded again.
        trial = best.analysis.trial(best.trial.cutoff, best.trial.step * BUDGET_STEP_UP)
        best, coefs = Choice(best.analysis, trial, b""), best.analysis.encode(trial)
    return None  # the estimate missed: the search sizes every step by coding it


# --- a maximum-error target ------------------------------------------------------------------------

#: Trials that teach the model a map's residual layer: (cutoff, step as a multiple of the bound).
#: Each gives the layer's bytes a cell at one ratio of the predicted RMSE to the bound; the layer's
#: cost at any other candidate is interpolated (log-log) between them.
PILOTS = ((0.8, 2.0), (0.8, 8.0), (0.95, 4.0), (0.6, 4.0))
#: A cutoff's smallest predicted file this many times in a row larger than the one before ends the
#: ranking's walk down the cutoffs (the files only grow from there).
RISES = 2
#: The step (times the bound) the ranking's walk over the steps starts from at the highest cutoff.
START_FACTOR = 4.0
#: Candidates rebuilt after the pilots, each the one the model (taught by every layer rebuilt
#: before it) ranks smallest, at most.
GUIDED = 10


@dataclass
class _Layer:
    """A rebuilt candidate for a maximum-error target: its trial, estimated COEF and RESD bytes."""

    analysis: Analysis
    trial: Trial
    coefs: float
    resd: float
    q: np.ndarray
    bound: float

    @property
    def size(self) -> float:
        return self.coefs + self.resd


def _layer(an: Analysis, cutoff: float, step: float, bound: float, coder: str,
           to_beat: float = math.inf) -> _Layer | None:
    """The candidate rebuilt and sized; None, without rebuilding it, where its coefficients alone
    take ``to_beat`` bytes or more (no residual layer can make it smaller)."""
    based = _base(an, cutoff, step, to_beat)
    if based is None:
        return None
    coefs, trial = based
    q = residual_integers(an.dem.heights, trial.heights, an.mask, an.kept_cells, bound)
    return _Layer(an, trial, coefs, estimated_size(q, coder, an.kept_cells, predicted=False), q, bound)


class _ResidualCurve:
    """The residual layer's bytes as a function of the predicted RMSE over the bound, learned from
    rebuilt candidates: log-log interpolation, and beyond them the nearest two's slope (a layer
    never shrinks as the ratio grows), so that the model ranks a candidate past the layers it
    has seen neither as cheap as the last one nor as dear as the first."""

    def __init__(self) -> None:
        self.points: list[tuple[float, float]] = []

    def add(self, ratio: float, size: float) -> None:
        self.points.append((math.log(max(ratio, 1e-12)), math.log(max(size, 1.0))))
        self.points.sort()

    def __call__(self, ratio: float) -> float:
        x = math.log(max(ratio, 1e-12))
        xs, ys = zip(*self.points)
        if xs[0] < x < xs[-1]:
            return math.exp(float(np.interp(x, xs, ys)))
        # Past an end, the slope from that end to the nearest point distinctly inside it.
        end = 0 if x <= xs[0] else len(xs) - 1
        inner = next((k for k in (range(1, len(xs)) if end == 0 else range(len(xs) - 2, -1, -1))
                      if abs(xs[k] - xs[end]) > CURVE_SPAN), None)
        slope = 0.0 if inner is None else (ys[inner] - ys[end]) / (xs[inner] - xs[end])
        slope = max(slope, 0.0 if end else CURVE_SLOPE_BELOW)
        return math.exp(ys[end] + slope * (x - xs[end]))


#: Ratios closer than this (log) are one point to the curve's extrapolation.
CURVE_SPAN = 0.01
#: Below the smallest ratio rebuilt, the curve falls at least this steeply (log-log): a layer
#: thins out fast as the errors sink below the bound (1.4-2.9 between rebuilt layers on
#: ../shared/data; a Gaussian error's share over the bound falls at 1.5 to 5 from ratio 1 to 0.5).
CURVE_SLOPE_BELOW = 2.0


def _factors(quantized: bool) -> list[float]:
    """The steps a maximum-error target tries, as multiples of the bound (the search's and the
    doublings after them)."""
    out = list(MAX_ERROR_STEP_FACTORS)
    while out[-1] * 2.0 <= MAX_ERROR_STEP_FACTOR_LIMIT:
        out.append(out[-1] * 2.0)
    return out


class _Guided:
    """A maximum-error target's candidates (a cutoff, a step as a multiple of the bound): each
    one's predicted file (estimated COEF bytes and the residual curve's RESD bytes, from estimates
    cached as they are asked for) and the layers rebuilt (:func:`_layer`), every one of which
    teaches the curve. :meth:`choose` rebuilds the candidate ranked smallest until none is ranked
    smaller than the smallest file found."""

    def __init__(self, an: Analysis, bound: float, coder: str, tried: list[float]):
        self.an, self.bound, self.coder = an, bound, coder
        self.tried, self.factors = sorted(tried), _factors(True)
        self.start = self.index(START_FACTOR)
        self.energies = {c: Energy(an, c) for c in self.tried}
        self.curve = _ResidualCurve()
        self.rebuilt: dict[tuple[float, int], _Layer | None] = {}
        self._coefs: dict[tuple[float, int], float] = {}
        self._ratio: dict[tuple[float, int], float] = {}
        # The layers' COEF bytes are estimated in every band layout, the ranking's in the first:
        # on directional terrain a few % apart, which the ranking scales by (the latest layer's).
        self.scale = 1.0
        #: Bytes of a file found another way (the map with no spectrum): a candidate's to beat too.
        self.ceiling = math.inf

    def index(self, factor: float) -> int:
        return min(range(len(self.factors)), key=lambda k: abs(math.log(self.factors[k] / factor)))

    def ratio(self, key: tuple[float, int]) -> float:
        if key not in self._ratio:
            self._ratio[key] = self.energies[key[0]].rmse(self.bound * self.factors[key[1]]) / self.bound
        return self._ratio[key]

    def predicted(self, key: tuple[float, int]) -> float:
        if key in self.rebuilt:
            layer = self.rebuilt[key]
            return math.inf if layer is None else layer.size
        if key not in self._coefs:
            self._coefs[key] = _estimate(self.an, key[0], self.bound * self.factors[key[1]])
        return self.scale * self._coefs[key] + self.curve(self.ratio(key)) if self.curve.points else \
            self.scale * self._coefs[key]

    def rebuild(self, cutoff: float, factor: float) -> None:
        key = (cutoff, self.index(factor))
        best = self.best()
        layer = _layer(self.an, cutoff, self.bound * self.factors[key[1]], self.bound, self.coder,
                       min(best.size if best is not None else math.inf, self.ceiling))
        self.rebuilt[key] = layer
        if layer is not None:
            self.curve.add(self.energies[cutoff].rmse(layer.trial.step) / self.bound, layer.resd)
            first = self._coefs.get(key)
            if first:
                self.scale = layer.coefs / first

    def best(self) -> _Layer | None:
        return min((layer for layer in self.rebuilt.values() if layer is not None), key=lambda layer: layer.size,
                   default=None)

    def ranked(self) -> list[tuple[float, tuple[float, int]]]:
        """The candidates the ranking looked at, not yet rebuilt, smallest predicted first. In the
        factor the predicted file falls to one low and rises from it (the spectrum shrinks, the
        layer grows), found by walking down from the last cutoff's (a few estimates a cutoff);
        the cutoffs from the highest down, until their lows have risen :data:`RISES` times."""
        seen: dict[tuple[float, int], float] = {}
        lows: list[float] = []
        at = self.start
        for cutoff in reversed(self.tried):
            def size_at(j: int) -> float:
                if (cutoff, j) not in seen:
                    seen[(cutoff, j)] = self.predicted((cutoff, j))
                return seen[(cutoff, j)]

            while True:
                near = [j for j in (at - 1, at + 1) if 0 <= j < len(self.factors)]
                nearer = min(near, key=size_at) if near else at
                if size_at(nearer) >= size_at(at):
                    break
                at = nearer
            lows.append(size_at(at))
            if len(lows) > RISES and all(lows[-k - 1] > lows[-k - 2] for k in range(RISES)):
                break
        return sorted((size, key) for key, size in seen.items() if key not in self.rebuilt)

    def choose(self) -> _Layer | None:
        """The candidate ranked smallest, rebuilt, until the model ranks none smaller than the
        smallest file found (at most :data:`GUIDED`): the curve learned from a few layers is
        coarse next to files a few % apart, and each layer rebuilt corrects it where the choice
        lies. The smallest layer rebuilt."""
        for _ in range(GUIDED):
            ranked = self.ranked()
            best = self.best()
            if not ranked or ranked[0][0] >= min(best.size if best is not None else math.inf, self.ceiling):
                break
            self.rebuild(ranked[0][1][0], self.factors[ranked[0][1][1]])
        return self.best()


def _for_max_error(an: Analysis, params: Params) -> Choice | None:
    bound, coder = params.target_max_error, params.coder
    tried = cutoffs(params)
    pilots = [(c, f) for c, f in PILOTS] if params.cutoff is None else [(params.cutoff, f) for f in (2.0, 8.0)]
    guided = _Guided(an, bound, coder, list(tried))
    for cutoff, factor in dict.fromkeys((min(tried, key=lambda t: abs(t - c)), f) for c, f in pilots):
        guided.rebuild(cutoff, factor)
    # The map with no spectrum, sized once the pilots give it a file to beat: on rough terrain it
    # wins, and no low-passed candidate whose coefficients alone pass it is rebuilt.
    free = _spectrum_free(an, params)
    if free is not None:
        on, trial = free
        free_q = residual_integers(on.dem.heights, trial.heights, on.mask, on.kept_cells, bound)
        coefs = _coded(on, trial)
        guided.ceiling = coefs + min(estimated_size(free_q, coder, on.kept_cells, predicted=False),
                                     _predicted_size(free_q, coder, on.kept_cells, guided.best().size - coefs))
    guided.choose()
    best = guided.best()
    if an.refillable:
        other = an.refilled(best.trial)
        factor = best.trial.step / bound
        # The step halved wins now and then on the refilled map (its fill follows the coded map, which a
        # finer step follows closer); doubled, it never won on ../shared/data (clouds at 1.5, 4 and 10
        # units): a rebuild saved.
        for f in (factor, factor / 2.0):
            layer = _layer(other, best.trial.cutoff, bound * f, bound, coder, min(best.size, guided.ceiling))
            if layer is not None and layer.size < best.size:
                best = layer
    choice = Choice(best.analysis, best.trial, b"", best.q, b"", bound)
    # The predicted layout, the slowest to code, is sized on the winner (and was on the map with no spectrum).
    predicted = _predicted_size(best.q, coder, best.analysis.kept_cells, min(best.resd, guided.ceiling - best.coefs))
    size = best.coefs + min(best.resd, predicted)
    if free is not None and guided.ceiling < size:
        choice = Choice(free[0], free[1], b"", free_q, b"", bound)
    choice.coefs = choice.analysis.encode(choice.trial)
    choice.residual_blob = encode_residual(choice.residual, coder, choice.analysis.kept_cells)
    return choice


def _predicted_size(q: np.ndarray, coder: str, kept: np.ndarray, to_beat: float = math.inf) -> float:
    """Estimated bytes of ``q`` in the predicted layout; inf where it does not apply or cannot
    come below ``to_beat`` bytes: where its estimate from a quarter of the rows
    (:func:`~dftpcc.residual.sampled_predicted_size`, within :data:`SAMPLED_OVER` of the whole's
    from above) passes ``to_beat``, or on a grid too small to sample, the median predictor's floor
    (:data:`~dftpcc.residual.PREDICTED_SHARE`) does; the model is fitted on every row only where
    it may win."""
    from .residual import _estimated_predicted, median_predicted_size, sampled_predicted_size

    if coder != "ans" or not q.size:
        return math.inf
    if math.isfinite(to_beat):
        sampled = sampled_predicted_size(q, kept)
        floor = PREDICTED_SHARE * median_predicted_size(q, kept) if sampled is None else sampled / SAMPLED_OVER
        if floor >= to_beat:
            return math.inf
    return _estimated_predicted(q, kept)


#: A predicted layout's estimate from a quarter of the rows over the whole grid's is at most this
#: (0.43-1.15 over the 52 layers rate control sized on ../shared/data at 0.75 and 2 units of RMSE
#: and 4 of maximum error, untiled; under 1 where few cells are not 0): below it, the layout cannot win.
SAMPLED_OVER = 1.25


def choose(an: Analysis, params: Params, point_count: int, fixed_bytes: int,
           progress: Progress = _no_progress) -> Choice:
    """Rate control (the model first, :func:`predict`; the search where it does not apply or misses,
    :func:`dftpcc.ratecontrol.search`, or always under ``ratecontrol.method("search")``), then (``fill='consistent'``) a second choice at the same cutoff, empty cells
    refilled; for an RMSE target, then the maps with a residual layer (:func:`corrected_for_rmse`).

    For an RMSE target the step is searched again upwards, refilling at each
    step tried: a fill consistent with the coded map lowers the error on the
    occupied cells, so a coarser step meets the target. For the other
    targets the search is repeated on the analysis refilled at the first
    choice. The better of the two is kept: the smaller file for an error
    target, the more accurate one for a size target.

    Parameters
    ----------
    point_count : int
        Points of the original cloud (for a bits-per-point target).
    fixed_bytes : int
        Bytes of the file besides its COEF section (for a bits-per-point target).
    progress : callable, optional
        Told the fraction done: the first search is 80 % of the work, the refill the rest.
    """
    counts = _TALLY.get()
    if _METHOD.get() == "model":
        found = predict(an, params, point_count, fixed_bytes)
        if found is not None:
            if counts is not None:
                counts.choices += 1
                counts.modelled += 1
            return found
        if counts is not None:
            counts.fallbacks += 1
    found = search(an, params, point_count, fixed_bytes, progress)
    if counts is not None:
        counts.choices += 1
    return found
