"""Direct multi-step linear regression on lagged positions (the default model's core).

The observations are resampled onto a uniform grid (``dt``); the features at grid step k are
the last ``lags`` positions of all three axes and a constant; for each lead h = 1..H a separate
linear map predicts the displacement from step k to step k + h (direct, not iterated, so errors
do not compound). All maps share one design, so one regularised Gram matrix serves them all;
it and the cross terms are updated recursively with exponential forgetting (``memory`` steps),
and the maps are re-solved after each new grid step (a Cholesky solve of a small system).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from wavegrasp.predictor.forecast import check_position


class UniformGrid:
    """Resamples irregular observations onto steps ``dt`` apart.

    Between two observations the grid is interpolated linearly, unless frames were missed
    (the span is over 1.5 times the median of the recent intervals) and a ``guess`` of the
    path is given: then the guess, corrected to pass through both observations. A chord over
    a missed frame is far off a fast swing (0.3 m swinging at 2.5 s, a 0.4 s gap: 38 mm), and
    the regression learns from and predicts with those samples. A gap longer than
    ``max_gap_s`` (``max_fill_s`` when a guess bridges it), or time going backwards, restarts
    the grid: samples on both sides of it are never mixed in one feature vector.
    """

    def __init__(self, dt: float, max_gap_s: float, max_fill_s: float | None = None) -> None:
        self.dt, self.max_gap_s = dt, max_gap_s
        self.max_fill_s = max_gap_s if max_fill_s is None else max_fill_s
        self.intervals: deque[float] = deque(maxlen=21)
        self.reset()

    def reset(self) -> None:
        self.t_last: float | None = None
        self.p_last = np.zeros(3)
        self.next_t = 0.0
        self.samples: list[np.ndarray] = []
        self.t_latest = 0.0  # time of samples[-1]
        self.filled = 0  # grid samples taken from a guess over missed frames

    def add(self, t: float, p: np.ndarray,
            guess: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[int, bool]:
        """Take an observation; returns (new grid samples, whether the grid restarted).

        ``guess(times)``: positions (n, 3), metres, along the path at ``times`` (n,), seconds.
        """
        longest = self.max_gap_s if guess is None else max(self.max_gap_s, self.max_fill_s)
        restarted = self.t_last is None or not (0 < t - self.t_last <= longest)
        if restarted:
            self.samples, self.next_t = [], t
        times = []
        while self.next_t <= t + 1e-9:
            times.append(self.next_t)
            self.next_t += self.dt
        if times:
            if restarted:
                self.samples += [p] * len(times)
            else:
                self.samples += list(self._between(np.array(times), t, p, guess))
            self.t_latest = times[-1]
        if not restarted:
            self.intervals.append(t - self.t_last)
        self.t_last, self.p_last = t, p
        return len(times), restarted

    def _between(self, times: np.ndarray, t: float, p: np.ndarray,
                 guess: Callable[[np.ndarray], np.ndarray] | None) -> np.ndarray:
        """Grid positions (n, 3) at ``times`` between the last observation and (t, p)."""
        w = ((times - self.t_last) / (t - self.t_last))[:, None]
        missed = (len(self.intervals) >= 5
                  and t - self.t_last > 1.5 * float(np.median(self.intervals)))
        if guess is None or not missed:
            return self.p_last + w * (p - self.p_last)
        g = guess(np.concatenate([[self.t_last], times, [t]]))
        before, after = self.p_last - g[0], p - g[-1]
        self.filled += len(times)
        return g[1:-1] + before + w * (after - before)


class LagRegression:
    """Predicts displacements for leads 1..``horizon`` grid steps from ``lags`` past steps."""

    def __init__(self, dt: float = 0.1, lags: int = 16, horizon: int = 25,
                 memory: float = 400.0, ridge: float = 1e-7, max_gap_s: float = 0.5,
                 max_fill_s: float = 1.5) -> None:
        self.dt, self.lags, self.horizon = dt, lags, horizon
        self.forget, self.ridge = 1.0 - 1.0 / memory, ridge
        self.grid = UniformGrid(dt, max_gap_s, max_fill_s)
        n = 3 * lags + 1
        self.gram = np.zeros((n, n))
        self.cross = np.zeros((n, 3 * horizon))
        self.rows = 0
        self.weights: np.ndarray | None = None

    def reset(self) -> None:
        """Forget the stream (restart); the learnt maps stay valid and are kept."""
        self.grid.reset()

    def features(self, k: int) -> np.ndarray:
        """Lagged positions ending at grid sample k, relative to it, and a constant."""
        window = np.asarray(self.grid.samples[k - self.lags + 1:k + 1])
        return np.concatenate([(window - window[-1]).ravel(), [1.0]])

    def update(self, t: float, p: np.ndarray) -> None:
        new, _ = self.grid.add(t, check_position(p), self._path if self.warm else None)
        s = self.grid.samples
        for j in range(len(s) - new, len(s)):
            k = j - self.horizon  # the row whose every target is now known
            if k >= self.lags - 1:
                phi = self.features(k)
                targets = (np.asarray(s[k + 1:k + self.horizon + 1]) - s[k]).ravel()
                self.gram = self.forget * self.gram + np.outer(phi, phi)
                self.cross = self.forget * self.cross + np.outer(phi, targets)
                self.rows += 1
        keep = self.lags + self.horizon
        if len(s) > 4 * keep:
            del s[:len(s) - keep]
        if new and self.rows >= 3 * self.lags:
            reg = self.ridge * np.trace(self.gram) / len(self.gram)
            factor = cho_factor(self.gram + reg * np.eye(len(self.gram)))
            self.weights = cho_solve(factor, self.cross)

    @property
    def warm(self) -> bool:
        return self.weights is not None and len(self.grid.samples) >= self.lags

    def _path(self, times: np.ndarray) -> np.ndarray:
        """The forecast from the newest grid sample at ``times`` (n,), s: positions (n, 3)."""
        t0, positions = self.predict()
        leads = np.arange(len(positions)) * self.dt
        return np.column_stack([np.interp(times - t0, leads, positions[:, i]) for i in range(3)])

    def predict(self) -> tuple[float, np.ndarray] | None:
        """(time of the newest grid sample, positions (horizon + 1, 3) from it), or None."""
        if not self.warm:
            return None
        s = self.grid.samples
        disp = (self.features(len(s) - 1) @ self.weights).reshape(self.horizon, 3)
        return self.grid.t_latest, np.vstack([s[-1], s[-1] + disp])
