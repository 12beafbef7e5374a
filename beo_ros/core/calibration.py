"""Calibration of the completion's per-voxel occupancy probabilities.

A class model gives an unknown voxel P(occupied) = Phi((m - 0.5) / s) from its linear-Gaussian
predictive mean m and standard deviation s (``InferenceEngine.predictive``). Those
probabilities are far too sure of themselves: on fold-0 views of ModelNet10 (class models
fitted without them), the unknown voxels given 0.1 were occupied 42 % of the time and those
given 0.01, 14 %. ``OccupancyCalibration`` learns a monotone map from the model's probability
to the observed frequency: isotonic regression on out-of-fold views, binned on the logit
scale, applied by linear interpolation between the knots.
"""
from __future__ import annotations

import numpy as np

from .grid import check_count

# the probabilities are binned on the logit scale in [-LOGIT_RANGE, LOGIT_RANGE]: the model's
# probabilities reach 1e-8 and below, where the observed frequencies still differ
LOGIT_RANGE = 20.0
ARRAY_KEYS = ('probability', 'frequency', 'counts')


def _check_inputs(p, occupied):
    p = np.asarray(p, dtype=np.float64).ravel()
    occupied = np.asarray(occupied).ravel()
    if p.shape != occupied.shape:
        raise ValueError(f'p and occupied must have the same size, got {p.size} and '
                         f'{occupied.size}')
    if not np.all(np.isfinite(p)) or (p.size and (p.min() < 0 or p.max() > 1)):
        raise ValueError('p must be finite probabilities in [0, 1]')
    if occupied.dtype != bool and not np.all((occupied == 0) | (occupied == 1)):
        raise ValueError('occupied must be boolean or 0/1')
    return p, occupied.astype(bool)


def check_bin_count(bins):
    """Raise ValueError unless ``bins`` (of an equal-width binning of probabilities) is an
    integer >= 1."""
    check_count('bins', bins, 1)


class OccupancyCalibration:
    """Isotonic calibration of occupancy probabilities, scikit-learn style.

    Args:
        bins: number of logit-scale bins the training probabilities are counted in.

    Learned attributes: ``counts_`` (bins, 3): per bin the sum of the probabilities, the
    number of occupied voxels and the number of voxels; ``probability_`` and ``frequency_``
    (K,): the knots of the map, increasing in ``probability_``, non-decreasing in
    ``frequency_``.
    """

    def __init__(self, bins=800):
        self.bins = bins

    def _bin(self, p):
        lo = np.log(np.clip(p, 1e-300, None)) - np.log(np.clip(1 - p, 1e-300, None))
        u = (np.clip(lo, -LOGIT_RANGE, LOGIT_RANGE) + LOGIT_RANGE) / (2 * LOGIT_RANGE)
        return np.minimum((u * self.bins).astype(np.int64), self.bins - 1)

    def fit(self, p, occupied):
        """p: probabilities (any shape), occupied: the truth of the same voxels. Returns self."""
        for name in ('counts_', 'probability_', 'frequency_'):   # no map of an earlier fit
            self.__dict__.pop(name, None)
        return self.partial_fit(p, occupied)

    def partial_fit(self, p, occupied):
        """Add voxels to the counts and refit the map (a batch of views at a time: each call
        refits). Returns self."""
        if isinstance(self.bins, (bool, np.bool_)) or not isinstance(self.bins, (int, np.integer)) \
                or self.bins < 2:
            raise ValueError(f'bins must be an integer >= 2, got {self.bins!r}')
        p, occupied = _check_inputs(p, occupied)
        counts = getattr(self, 'counts_', None)
        if counts is None:
            counts = np.zeros((self.bins, 3))
        elif counts.shape != (self.bins, 3):   # bins changed: refused, not counted anew
            raise ValueError(f'bins is {self.bins}, the voxels counted so far are in '
                             f'{len(counts)} bins: fit() starts again with the new bins')
        b = self._bin(p)
        # new counts, not added in place: the earlier counts_ may be an array the caller holds
        # (from_arrays' input, an arrays_ taken before)
        counts = counts + np.stack([np.bincount(b, weights=p, minlength=self.bins),
                                    np.bincount(b, weights=occupied, minlength=self.bins),
                                    np.bincount(b, minlength=self.bins)], axis=1)
        self.counts_ = counts
        seen = counts[:, 2] > 0
        if seen.sum() >= 2:
            from sklearn.isotonic import IsotonicRegression
            ir = IsotonicRegression(y_min=0.0, y_max=1.0, out_of_bounds='clip').fit(
                counts[seen, 0] / counts[seen, 2], counts[seen, 1] / counts[seen, 2],
                sample_weight=counts[seen, 2])
            self.probability_ = np.asarray(ir.X_thresholds_, dtype=np.float64)
            self.frequency_ = np.asarray(ir.y_thresholds_, dtype=np.float64)
        return self

    def predict(self, p):
        """Calibrated probabilities, float32, the shape of ``p``."""
        if not hasattr(self, 'probability_'):
            raise ValueError('OccupancyCalibration is not fitted (it needs voxels in at least '
                             f'two of its {self.bins} bins, each {2 * LOGIT_RANGE / self.bins:g} '
                             'wide in logit)')
        p = np.asarray(p)
        return np.interp(p.astype(np.float64).ravel(), self.probability_,
                         self.frequency_).astype(np.float32).reshape(p.shape)

    @property
    def arrays_(self):
        """The arrays a model directory stores (``calibration.npz``), copies of the fitted
        state."""
        return dict(probability=self.probability_.copy(), frequency=self.frequency_.copy(),
                    counts=self.counts_.copy())

    @classmethod
    def from_arrays(cls, arrays):
        """The calibration stored as ``arrays`` (checked with :func:`check_arrays` first), with
        copies of them."""
        cal = cls(bins=len(arrays['counts']))
        cal.counts_ = np.array(arrays['counts'], dtype=np.float64)
        cal.probability_ = np.array(arrays['probability'], dtype=np.float64)
        cal.frequency_ = np.array(arrays['frequency'], dtype=np.float64)
        return cal


def check_arrays(arrays, where='calibration'):
    """Why ``arrays`` are not a valid stored calibration, or '' when they are."""
    missing = [k for k in ARRAY_KEYS if k not in arrays]
    if missing:
        return f'{where}: missing array(s) {missing}'
    x, f, c = (np.asarray(arrays[k]) for k in ARRAY_KEYS)
    if x.ndim != 1 or f.shape != x.shape or len(x) < 2:
        return (f'{where}: probability and frequency must be two 1-D arrays of the same length '
                f'>= 2, got shapes {x.shape} and {f.shape}')
    if not (np.issubdtype(x.dtype, np.floating) and np.issubdtype(f.dtype, np.floating)):
        return f'{where}: probability and frequency must be floating point'
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(f))):
        return f'{where}: probability and frequency must be finite'
    if x.min() < 0 or x.max() > 1 or f.min() < 0 or f.max() > 1:
        return f'{where}: probability and frequency must lie in [0, 1]'
    if np.any(np.diff(x) <= 0) or np.any(np.diff(f) < 0):
        return (f'{where}: the map must be increasing in probability and non-decreasing in '
                'frequency')
    if c.ndim != 2 or c.shape[1] != 3 or len(c) < 2 or not np.issubdtype(c.dtype, np.number) \
            or not np.all(np.isfinite(c)) or c.min() < 0:
        return f'{where}: counts must be a finite, non-negative (bins >= 2, 3) array'
    # per bin: the sum of the probabilities, the occupied voxels, the voxels (see partial_fit)
    if np.any(c[:, 1:] != np.round(c[:, 1:])):
        return f'{where}: counts of occupied voxels and of voxels must be whole numbers'
    # a sum of probabilities <= 1 each is <= their number in floating point too (monotone
    # rounding, whole numbers exact): no tolerance
    if np.any(c[:, 0] > c[:, 2]) or np.any(c[:, 1] > c[:, 2]):
        return (f'{where}: counts: the sum of probabilities and the occupied voxels of a bin '
                'cannot exceed its voxels')
    return ''


def calibration_sums(p, occupied, bins=10):
    """What :func:`metrics_from_sums` needs of one set of voxels (JSON-ready): their number, the
    sums of their squared errors and log losses, and per equal-width probability bin the sums
    of the probabilities and of the truths and the count."""
    check_bin_count(bins)   # else numpy's errors ('list' argument must have no negative ...)
    p, occupied = _check_inputs(p, occupied)
    t = occupied.astype(np.float64)
    q = np.clip(p, 1e-6, 1 - 1e-6)
    b = np.minimum((p * bins).astype(np.int64), bins - 1)
    table = np.stack([np.bincount(b, weights=p, minlength=bins),
                      np.bincount(b, weights=t, minlength=bins),
                      np.bincount(b, minlength=bins)], axis=1)
    return dict(voxels=int(p.size), brier_sum=float(np.sum((p - t) ** 2)),
                log_loss_sum=float(-np.sum(t * np.log(q) + (1 - t) * np.log(1 - q))),
                bins=table.tolist())


def metrics_from_sums(sums):
    """Brier score, log loss and expected calibration error (over the equal-width bins) of the
    voxels behind a list of :func:`calibration_sums`; NaN for no voxels."""
    n = sum(s['voxels'] for s in sums)
    if not n:
        return dict(voxels=0, brier=float('nan'), log_loss=float('nan'), ece=float('nan'))
    table = np.sum([np.asarray(s['bins'], dtype=np.float64) for s in sums], axis=0)
    return dict(voxels=int(n), brier=sum(s['brier_sum'] for s in sums) / n,
                log_loss=sum(s['log_loss_sum'] for s in sums) / n,
                ece=float(np.abs(table[:, 0] - table[:, 1]).sum() / n))


def calibration_metrics(p, occupied, bins=10):
    """Brier score, log loss and expected calibration error (``bins`` equal-width bins) of
    probabilities ``p`` for the truth ``occupied``; NaN for no voxels."""
    return metrics_from_sums([calibration_sums(p, occupied, bins)])
