"""The strongest (image feature, model feature) pairings of an image, compiled.

The alignment pairs every image feature with every model feature of its kind
whose attributes lie within a gate (:func:`viewloc_core.align.align`), and
keeps the strongest pairings only: a model with many views in a busy photo
pairs millions of times (LM-O, 400x300 level: about 2.5 million, of which
40,000 are kept). The attributes are two numbers per feature and the gate
lets half of all pairs through, so a search tree saves little; what cost was
writing out millions of pairings and their weights only to select a few
percent of them (about 100 ms per LM-O photo).

Here the pairs are visited without storing them. A pass over a sample of
the image features estimates how strong the weakest kept pairing will be;
a pass over all of them histograms the strengths above that estimate, which
fixes the cut exactly; a last pass writes out only the pairings above the
cut. Passes above an estimate skip every image feature that is weaker than
it with any model feature, and the model features are sorted by their first
attribute, so only those within the gate on it are visited. Each pass is
shared by the two cores: the image features are cut in two runs of about
equal work, whose pairings laid end to end are those of one pass over all
(:func:`_halves`).

A pairing's strength is ``image_term[i] + model_term[j] - d² / 2``, with
``d`` the distance of the attributes in units of their pairing standard
deviations (:data:`viewloc_core.align.ATTR_SIGMA`): the log likelihood of the
attribute difference plus terms of either feature alone.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numba import njit
from numpy.typing import NDArray

from viewloc_core.both_cores import each_on_both

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Bins of the strength histogram: the kept pairings are those of the bins
#: at the top that hold ``max_pairings``, cut exactly among the last bin's.
HISTOGRAM_BINS = 4096

#: The cut is first estimated from every ``SAMPLE_STRIDE``-th image
#: feature's pairings, as the strength above which the sample holds
#: ``SAMPLE_MARGIN`` times its share of the pairings kept (a margin, so that
#: the full count rarely falls short and needs another pass).
SAMPLE_STRIDE = 8
SAMPLE_MARGIN = 1.5

#: Passes that visit at least this many (image, model) feature pairs are
#: shared by the two cores (:func:`_halves`); handing a run to the other
#: thread costs tens of microseconds, a visit a few nanoseconds. A
#: 400x300 textured photo visits millions.
MIN_SPLIT_VISITS = 100_000


@dataclass(frozen=True, slots=True)
class PairingSet:
    """The features of one kind, on either side, ready to pair.

    Attributes
    ----------
    image_rows, model_rows : (N,) and (M,) int64
        Rows of the features in the image's and the model's feature arrays.
    image_z, model_z : (N, D) and (M, D) float64
        Attributes in units of their pairing standard deviations.
    image_term, model_term : (N,) and (M,) float64
        Each feature's own part of the strength of its pairings.

    All finite. Model features sorted by their first attribute are used as
    they are (:func:`viewloc_core.align.build_index` stores them so), others
    are sorted on every use.
    """

    image_rows: I64
    model_rows: I64
    image_z: F64
    model_z: F64
    image_term: F64
    model_term: F64


@njit(cache=True, nogil=True)
def _pass(image_z: F64, model_z: F64, image_term: F64, model_term: F64, gate: float,
          lo: float, hi: float, hist: I64, min_bin: int, out_i: I64, out_j: I64,
          out_strength: F64, n_out: int, image_start: int, image_stop: int,
          image_stride: int) -> int:  # pragma: no cover
    """One pass over the pairs within the gate and at least ``lo`` strong.

    Counts their strengths in ``hist`` (bins spanning ``lo`` .. ``hi``, the
    last one holding everything above) and writes those falling in
    ``min_bin`` or above from row ``n_out`` on (none when ``min_bin`` is
    past the last bin); returns the next free row. Only every
    ``image_stride``-th image feature of ``image_start:image_stop`` is
    paired. ``model_z`` is sorted by its first column.
    """
    n_bins = hist.shape[0]
    inv_width = n_bins / max(hi - lo, 1e-9)
    gate_sq = gate * gate
    dims = image_z.shape[1]
    best_model = model_term.max()
    for i in range(image_start, image_stop, image_stride):
        a = image_term[i]
        if a + best_model < lo:
            continue  # weaker than lo with any model feature
        # The gate holds the first attribute within ``gate``.
        j0 = np.searchsorted(model_z[:, 0], image_z[i, 0] - gate)
        j1 = np.searchsorted(model_z[:, 0], image_z[i, 0] + gate, side="right")
        for j in range(j0, j1):
            d2 = 0.0
            for c in range(dims):
                diff = image_z[i, c] - model_z[j, c]
                d2 += diff * diff
            strength = a + model_term[j] - 0.5 * d2
            if d2 > gate_sq or strength < lo:
                continue
            b = min(int((strength - lo) * inv_width), n_bins - 1)
            hist[b] += 1
            if b >= min_bin:
                out_i[n_out] = i
                out_j[n_out] = j
                out_strength[n_out] = strength
                n_out += 1
    return n_out


#: A part of the image features of all sets: ``(set index, start, stop)``.
Span = tuple[int, int, int]


def _visits(sets: list[PairingSet], gate: float) -> list[I64]:
    """The model features within the gate of each image feature's first
    attribute, per set: what a pass visits for it."""
    return [np.searchsorted(s.model_z[:, 0], s.image_z[:, 0] + gate, side="right")
            - np.searchsorted(s.model_z[:, 0], s.image_z[:, 0] - gate) for s in sets]


def _halves(sets: list[PairingSet], visits: list[I64], lo: float = -np.inf) -> list[list[Span]]:
    """The sets' image features in two runs of about equal work, one per
    core; one run when there is too little work to share
    (:data:`MIN_SPLIT_VISITS`).

    The work of an image feature is its ``visits`` (:func:`_visits`), none
    when it is weaker than ``lo`` with any model feature (a pass skips it).
    The first run ends where the second begins, in the order of one pass
    over all, so the runs' pairings laid end to end are that pass's.
    """
    work = [v * (s.image_term + s.model_term.max() >= lo)
            for s, v in zip(sets, visits, strict=True)]
    total = int(sum(int(w.sum()) for w in work))
    if total < MIN_SPLIT_VISITS:
        return [[(k, 0, len(s.image_rows)) for k, s in enumerate(sets)]]
    cut = int(np.searchsorted(np.cumsum(np.concatenate(work)), total / 2))
    first: list[Span] = []
    second: list[Span] = []
    offset = 0
    for k, s in enumerate(sets):
        n = len(s.image_rows)
        m = min(max(cut - offset, 0), n)
        if m > 0:
            first.append((k, 0, m))
        if m < n:
            second.append((k, m, n))
        offset += n
    return [first, second]


def _first_of_stride(start: int, stride: int) -> int:
    """The first multiple of ``stride`` at or after ``start``: a run that
    begins inside a set samples the features one pass over all would."""
    return start + (-start) % stride


def _count(sets: list[PairingSet], runs: list[list[Span]], gate: float, lo: float, hi: float,
           image_stride: int = 1) -> list[I64]:
    """Histogram of the strengths at least ``lo`` (bins up to ``hi``) of
    each run, the runs on both cores."""
    none = np.zeros(0, np.int64)

    def count(run: list[Span]) -> I64:
        hist = np.zeros(HISTOGRAM_BINS, np.int64)
        for k, start, stop in run:
            s = sets[k]
            _pass(s.image_z, s.model_z, s.image_term, s.model_term, gate, lo, hi, hist,
                  HISTOGRAM_BINS, none, none, np.zeros(0), 0,
                  _first_of_stride(start, image_stride), stop, image_stride)
        return hist

    return each_on_both(count, runs)


def _first_kept_bin(hist: I64, wanted: float) -> int:
    """The first of the fewest top bins that hold ``wanted`` counts (0 when
    all of them hold fewer)."""
    from_top = np.cumsum(hist[::-1])
    return max(HISTOGRAM_BINS - int(np.searchsorted(from_top, wanted)) - 1, 0)


def strongest_pairings(sets: list[PairingSet], gate: float, max_pairings: int
                       ) -> tuple[I64, I64]:
    """The pairings within ``gate`` of all sets, the ``max_pairings``
    strongest when there are more.

    Parameters
    ----------
    sets : list of PairingSet
        One per feature kind (features of different kinds never pair).
    gate : float
        Largest attribute distance of a pairing, standard deviations.
    max_pairings : int
        Most pairings returned.

    Returns
    -------
    image_rows, model_rows : (N,) int64
        The pairings, ``N <= max_pairings``, in no particular order (ties at
        the cut broken arbitrarily, but the same on every call).
    """
    sets = [_sorted(s) for s in sets if len(s.image_rows) and len(s.model_rows)]
    if not sets:
        empty = np.zeros(0, np.int64)
        return empty, empty
    bottom = min(float(s.image_term.min() + s.model_term.min()) for s in sets) - 0.5 * gate**2
    top = max(float(s.image_term.max() + s.model_term.max()) for s in sets)
    visits = _visits(sets, gate)
    runs = _halves(sets, visits)
    # Where the cut will lie, from a sample of the image features: an image
    # feature weaker than it with every model feature is then passed over.
    sample = np.sum(_count(sets, runs, gate, bottom, top, SAMPLE_STRIDE), axis=0)
    sampled = sum(len(range(0, len(s.image_rows), SAMPLE_STRIDE)) for s in sets)
    share = sampled / sum(len(s.image_rows) for s in sets)
    lo = bottom + (_first_kept_bin(sample, SAMPLE_MARGIN * share * max_pairings)
                   * (top - bottom) / HISTOGRAM_BINS)
    while True:
        runs = _halves(sets, visits, lo)
        run_hists = _count(sets, runs, gate, lo, top)
        hist = np.sum(run_hists, axis=0)
        if hist.sum() >= max_pairings or lo <= bottom:
            break
        lo = max(bottom, lo - (top - lo))  # the sample misled: reach twice as far
    min_bin = _first_kept_bin(hist, max_pairings)

    def write(run: list[Span], run_hist: I64) -> tuple[I64, I64, F64]:
        """The run's pairings in the kept bins (as many as its histogram
        counts there), as feature rows, and their strengths."""
        n_kept = int(run_hist[min_bin:].sum())
        out_i = np.empty(n_kept, np.int64)
        out_j = np.empty(n_kept, np.int64)
        strength = np.empty(n_kept, np.float64)
        image_rows, model_rows = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
        n_out = 0
        for k, start, stop in run:
            s = sets[k]
            begin = n_out
            n_out = _pass(s.image_z, s.model_z, s.image_term, s.model_term, gate, lo, top,
                          np.zeros(HISTOGRAM_BINS, np.int64), min_bin, out_i, out_j, strength,
                          n_out, start, stop, 1)
            image_rows.append(s.image_rows[out_i[begin:n_out]])
            model_rows.append(s.model_rows[out_j[begin:n_out]])
        return np.concatenate(image_rows), np.concatenate(model_rows), strength[:n_out]

    parts = each_on_both(lambda r: write(*r), list(zip(runs, run_hists, strict=True)))
    rows_i = np.concatenate([p[0] for p in parts])
    rows_j = np.concatenate([p[1] for p in parts])
    strength = np.concatenate([p[2] for p in parts])
    if len(rows_i) > max_pairings:
        keep = np.argpartition(-strength, max_pairings)[:max_pairings]
        rows_i, rows_j = rows_i[keep], rows_j[keep]
    return rows_i, rows_j


def _sorted(s: PairingSet) -> PairingSet:
    """The set with its model features sorted by their first attribute
    (:func:`viewloc_core.align.build_index` stores them so)."""
    first = s.model_z[:, 0]
    if np.all(first[1:] >= first[:-1]):
        return s
    order = np.argsort(first, kind="stable")
    return replace(s, model_rows=s.model_rows[order],
                   model_z=np.ascontiguousarray(s.model_z[order]),
                   model_term=s.model_term[order])


def warm_up() -> None:
    """Compile (or load from numba's cache) for the types the alignment passes."""
    z = np.zeros((1, 2))
    term = np.zeros(1)
    strongest_pairings([PairingSet(np.zeros(1, np.int64), np.zeros(1, np.int64), z, z, term,
                                   term)], 1.0, 1)
