"""What every motion model returns, and how its uncertainty is measured.

Times are seconds on the recording's clock relative to the predictor's epoch; positions metres
in ``world``. A forecast's sigma is not a model covariance: it is the RMS of the errors this
model actually made, recently, at the same lead time (:class:`ErrorTracker`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from wavegrasp.schemas.path import interpolate_path, path_spline


def check_position(p: np.ndarray) -> np.ndarray:
    """position : array, shape (3,), metres, finite; ValueError naming the problem otherwise."""
    p = np.asarray(p, dtype=float)
    if p.shape != (3,):
        raise ValueError(f"position must have shape (3,), got {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"position has NaN or inf: {p}")
    return p


@dataclass
class Forecast:
    """t0 : seconds; leads : array, shape (m,), seconds after t0 (leads[0] = 0: now);
    positions : array, shape (m, 3), metres, world; sigma : array, shape (m,), metres (NaN
    while no error has been measured at that lead); period_s : the motion's period."""

    t0: float
    leads: np.ndarray
    positions: np.ndarray
    sigma: np.ndarray
    period_s: float
    parameters: dict[str, float] = field(default_factory=dict)
    warm: bool = False

    def at(self, t: float) -> np.ndarray:
        """Position at time ``t`` (cubic between samples, as every reader of a prediction
        reads it: :mod:`wavegrasp.schemas.path`), shape (3,)."""
        return interpolate_path(self.leads, self.positions, t - self.t0)


class ErrorTracker:
    """Recent RMS of a model's 3-D error per lead time, measured against later observations.

    Every forecast is kept until its last lead has passed; each new observation is compared
    with what each kept forecast said for that moment, and the squared error goes into an
    exponential average for its lead bin (``dt`` wide), a fast one (``memory`` samples per bin)
    and a slow one (three times longer); sigma is the larger, so it rises as soon as errors grow
    and does not drop after a few lucky forecasts; :meth:`recent` is the fast one alone.
    Until a bin has as many samples as an average's memory, that average is the plain mean of
    them (an exponential average started at its first sample would weigh that one sample
    most for hundreds more). Forecasts must share the lead grid ``k * dt``, k = 0..n_leads-1.
    """

    def __init__(self, dt: float, n_leads: int, memory: int = 60) -> None:
        self.dt, self.n_leads = dt, n_leads
        self.alphas = np.array([1.0 / memory, 1.0 / (3 * memory)])
        self.mse = np.full((n_leads, 2), np.nan)
        self.count = np.zeros(n_leads, dtype=int)
        # A spline's coefficients are linear in the sampled positions: on the fixed lead
        # grid, one product with the spline of each unit sample gives them.
        leads = np.arange(n_leads) * dt
        self._basis = path_spline(leads, np.eye(n_leads)).c  # (4, n_leads - 1, n_leads)
        self.reset()

    def reset(self) -> None:
        """Forget the kept forecasts (a restart); the measured errors stay."""
        # Kept forecasts, oldest first, in rows start:end of arrays that grow by doubling: a
        # slice of them is a view, where a deque had to be copied at every observation.
        self._t0 = np.empty(16)
        self._splines = np.empty((16, *self._basis.shape[:2], 3))
        self._start = self._end = 0

    def observe(self, t: float, p: np.ndarray) -> None:
        horizon = (self.n_leads - 1) * self.dt
        while self._start < self._end and t - self._t0[self._start] > horizon - 1e-9:
            self._start += 1
        if self._start == self._end:
            return
        x = (t - self._t0[self._start:self._end]) / self.dt
        rows = self._start + np.flatnonzero(x > 1e-6)
        x = x[rows - self._start]
        i = np.minimum(np.floor(x).astype(int), self.n_leads - 2)
        s = ((x - i) * self.dt)[:, None]
        c = self._splines[rows, :, i]  # (k, 4, 3): the cubic piece each forecast is in
        predicted = ((c[:, 0] * s + c[:, 1]) * s + c[:, 2]) * s + c[:, 3]
        err2 = np.sum((predicted - p) ** 2, axis=1)
        bins = np.round(x).astype(int)
        # Each bin's errors in order, as they came: one vectorised round per repeat of a
        # bin (a camera faster than dt puts several forecasts in a bin; at 30 Hz a loop over
        # them took 6 ms an observation).
        for sel in repeats(bins):
            b = bins[sel]
            self.count[b] += 1
            alpha = np.maximum(self.alphas, 1.0 / self.count[b][:, None])
            old = np.nan_to_num(self.mse[b])
            self.mse[b] = old + alpha * (err2[sel][:, None] - old)

    def keep(self, forecast: Forecast) -> None:
        """Measure ``forecast`` against the observations to come, read between its samples
        as every reader reads a prediction (cubic)."""
        if self._end == len(self._t0):  # full: move the live rows to the front, grow if needed
            live = slice(self._start, self._end)
            size = max(16, 2 * (self._end - self._start))
            t0, splines = np.empty(size), np.empty((size, *self._splines.shape[1:]))
            n = self._end - self._start
            t0[:n], splines[:n] = self._t0[live], self._splines[live]
            self._t0, self._splines, self._start, self._end = t0, splines, 0, n
        self._t0[self._end] = forecast.t0
        self._splines[self._end] = self._basis @ forecast.positions
        self._end += 1

    def _bins(self, leads: np.ndarray) -> np.ndarray:
        return np.clip(np.round(leads / self.dt).astype(int), 1, self.n_leads - 1)

    def _between(self, values: np.ndarray) -> np.ndarray:
        """``values`` (shape (n_leads,) or (n_leads, c)) with the bins no observation has
        fallen in yet filled linearly from the measured bins either side, those before the
        first like it (left as they are after the last: nothing was measured that far). A
        camera slower than 1 / dt hits only some lead bins: at 5 Hz and dt 0.1 s, only the
        even ones."""
        measured = np.flatnonzero(self.count)
        if not len(measured):
            return values
        out = values.astype(float, copy=True)
        inner = np.arange(1, measured[-1] + 1)
        cols = out[:, None] if out.ndim == 1 else out
        for c in range(cols.shape[1]):
            cols[inner, c] = np.interp(inner, measured, cols[measured, c])
        return out

    def sigma(self, leads: np.ndarray) -> np.ndarray:
        """RMS error at ``leads`` (seconds), NaN where nothing was measured yet."""
        return np.sqrt(self._between(self.mse)[self._bins(leads)].max(axis=1))

    def recent(self, leads: np.ndarray) -> np.ndarray:
        """The fast average alone: how good the model is now (for weighting models)."""
        return np.sqrt(self._between(self.mse)[self._bins(leads), 0])

    def measured(self, lead: float) -> float:
        """How many errors were measured at ``lead`` (seconds); a bin no observation can fall
        in (see :meth:`_between`) counts as its measured neighbours do."""
        return float(self._between(self.count)[self._bins(np.array([lead]))[0]])


def repeats(values: np.ndarray) -> list[np.ndarray]:
    """Indices of ``values`` (k,) in rounds: the first of each distinct value, then the
    second of those that repeat, and so on; within a round each value once, in order."""
    if len(values) == 0:
        return []
    order = np.argsort(values, kind="stable")
    ranked = values[order]
    starts = np.flatnonzero(np.r_[True, ranked[1:] != ranked[:-1]])
    run = np.arange(len(values)) - np.repeat(starts, np.diff(np.r_[starts, len(values)]))
    occurrence = np.empty_like(run)
    occurrence[order] = run
    return [np.flatnonzero(occurrence == r) for r in range(int(occurrence.max()) + 1)]
