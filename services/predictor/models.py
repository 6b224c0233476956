"""The predictor's models behind one interface: ``update(t, position) -> Forecast | None``.

``linear``: constant velocity from the last ``window_s`` of observations (the paper's baseline).
``harmonic``: the paper's model (:mod:`.harmonic`). ``blend`` (the default): direct multi-step
lag regression (:mod:`.lagreg`) and the harmonic model, combined per lead time with weights
inverse to each one's recent squared error there. Every model's sigma is its own recently
measured error at each lead (:class:`~.forecast.ErrorTracker`).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from wavegrasp.predictor import MODELS
from wavegrasp.predictor.forecast import ErrorTracker, Forecast, check_position
from wavegrasp.predictor.harmonic import HarmonicModel
from wavegrasp.predictor.lagreg import LagRegression


class Predictor:
    """Bookkeeping shared by the models: time checks, restarts, error tracking.

    A model's ``_update`` marks its forecast warm when the model is ready to forecast; only
    those forecasts are measured (errors of a model still converging say nothing of the model
    it has become). A forecast is then warm once ``min_measured`` errors have been measured
    one period ahead.
    """

    name = "base"
    min_measured = 0

    def __init__(self, dt: float = 0.1, max_lead_s: float = 8.0, max_gap_s: float = 0.5) -> None:
        self.dt, self.max_gap_s = dt, max_gap_s
        self.leads = np.arange(int(round(max_lead_s / dt)) + 1) * dt
        self.tracker = ErrorTracker(dt, len(self.leads))
        self.t_last: float | None = None
        self.updates = 0
        self.observation_var = 0.0

    def update(self, t: float, p: np.ndarray, sigma: float | None = None) -> Forecast | None:
        """Take the observation ``p`` (shape (3,), metres, world) at ``t`` seconds, whose own
        uncertainty (1-sigma, metres) is ``sigma`` if the observer reports one.

        A duplicate or slightly out-of-order stamp is ignored (None); time running backwards
        by more than ``max_gap_s`` is a restart of the stream: the state is reset. A forecast's
        sigma is the error measured against later observations, plus the observations' own
        uncertainty (what the observer gets wrong consistently, no model can see).
        """
        p = check_position(p)
        if sigma is not None and np.isfinite(sigma):
            self.observation_var += 0.02 * (sigma**2 - self.observation_var)
        if self.t_last is not None and t <= self.t_last:
            if t > self.t_last - self.max_gap_s:
                return None
            self.restart()
        self.t_last = t
        self.updates += 1
        self.tracker.observe(t, p)
        forecast = self._update(t, p)
        if forecast is None:
            return None
        forecast.sigma = np.sqrt(self.tracker.sigma(forecast.leads) ** 2 + self.observation_var)
        if forecast.warm:
            self.tracker.keep(forecast)
            if self.min_measured:
                k = min(len(self.leads) - 1, int(round(forecast.period_s / self.dt)))
                forecast.warm = self.tracker.measured(self.leads[k]) >= self.min_measured
        return forecast

    def restart(self) -> None:
        self.tracker.reset()
        self.t_last = None

    def _update(self, t: float, p: np.ndarray) -> Forecast | None:
        raise NotImplementedError


class LinearPredictor(Predictor):
    """Constant velocity: least-squares slope of the last ``window_s`` of observations."""

    name = "linear"

    def __init__(self, window_s: float = 0.3, **kw: float) -> None:
        super().__init__(**kw)
        self.window_s = window_s
        self.recent: deque[tuple[float, np.ndarray]] = deque()
        self.periodic = HarmonicModel()  # only to report the motion's period

    def restart(self) -> None:
        super().restart()
        self.recent.clear()
        self.periodic.reset()

    def velocity(self) -> np.ndarray:
        ts = np.array([t for t, _ in self.recent])
        ps = np.array([p for _, p in self.recent])
        dt = ts - ts.mean()
        return (dt @ (ps - ps.mean(axis=0))) / (dt @ dt)

    def _update(self, t: float, p: np.ndarray) -> Forecast | None:
        if self.recent and t - self.recent[-1][0] > self.max_gap_s:
            self.recent.clear()
        self.recent.append((t, p))
        while self.recent[0][0] < t - self.window_s - 1e-9:
            self.recent.popleft()
        self.periodic.update(t, p)
        if len(self.recent) < 2:
            return None
        v = self.velocity()
        omega = self.periodic.omega
        return Forecast(t, self.leads, p + np.outer(self.leads, v), self.leads * np.nan,
                        2 * np.pi / omega if omega else np.nan,
                        {"vx": v[0], "vy": v[1], "vz": v[2]}, warm=omega is not None)


class HarmonicPredictor(Predictor):
    """The paper's harmonic model (equations 1-7), fitted online."""

    name = "harmonic"

    def __init__(self, **kw: float) -> None:
        super().__init__(**kw)
        self.model = HarmonicModel()

    def restart(self) -> None:
        super().restart()
        self.model.reset()

    def _update(self, t: float, p: np.ndarray) -> Forecast | None:
        self.model.update(t, p)
        positions = self.model.predict(self.leads)
        if positions is None:
            return None
        return Forecast(t, self.leads, positions, self.leads * np.nan,
                        2 * np.pi / self.model.omega, self.model.parameters(), self.model.warm)


class BlendPredictor(Predictor):
    """Lag regression and harmonic model, weighted per lead by their recent errors; beyond
    ``lag_lead_s`` the harmonic model alone. A regression learns from a row only once its
    farthest lead has been observed: leads of 8 s would hold back its first forecast, and
    every change it learns, by 4 s more."""

    name = "blend"
    min_measured = 20

    def __init__(self, lag_lead_s: float = 4.0, **kw: float) -> None:
        super().__init__(**kw)
        self.lag = LagRegression(dt=self.dt, max_gap_s=self.max_gap_s,
                                 horizon=min(len(self.leads) - 1, int(round(lag_lead_s / self.dt))))
        self.harmonic = HarmonicModel(half_omega=True, second_xy=True)
        # Short memory: the weights follow which model is better now.
        self.lag_errors = ErrorTracker(self.dt, len(self.leads), memory=20)
        self.harmonic_errors = ErrorTracker(self.dt, len(self.leads), memory=20)

    def restart(self) -> None:
        super().restart()
        self.lag.reset()  # the learnt regression stays: only the stream restarts
        self.harmonic.reset()
        self.lag_errors.reset()
        self.harmonic_errors.reset()

    def _update(self, t: float, p: np.ndarray) -> Forecast | None:
        self.lag_errors.observe(t, p)
        self.harmonic_errors.observe(t, p)
        self.lag.update(t, p)
        self.harmonic.update(t, p)
        lag = self.lag.predict()
        t0 = lag[0] if lag is not None else t
        harmonic = self.harmonic.predict(t0 - t + self.leads)
        if lag is not None and len(lag[1]) < len(self.leads):
            lag = (t0, self._beyond(lag[1], harmonic))
        if harmonic is not None:
            self.harmonic_errors.keep(Forecast(t0, self.leads, harmonic, self.leads * np.nan, 0))
        if lag is not None:
            self.lag_errors.keep(Forecast(t0, self.leads, lag[1], self.leads * np.nan, 0))
        if lag is None and harmonic is None:
            return None
        if lag is None or harmonic is None:
            positions, w_lag = (harmonic, np.zeros(len(self.leads))) if lag is None else (
                lag[1], np.ones(len(self.leads)))
        else:
            mse_lag = self.lag_errors.recent(self.leads) ** 2
            mse_h = self.harmonic_errors.recent(self.leads) ** 2
            w_lag = np.where(np.isnan(mse_lag) | np.isnan(mse_h), 0.5,
                             mse_h / np.maximum(mse_lag + mse_h, 1e-12))
            w_lag = np.nan_to_num(w_lag, nan=0.5)
            positions = w_lag[:, None] * lag[1] + (1 - w_lag[:, None]) * harmonic
        omega = self.harmonic.omega
        period = 2 * np.pi / omega if omega else np.nan
        params = self.harmonic.parameters()
        k = min(len(self.leads) - 1, int(round(period / self.dt))) if omega else 0
        params["lag_weight_at_period"] = float(w_lag[k])
        # Either model alone may forecast: the lag regression needs about 9 s without a gap
        # over max_gap_s, which a slow camera or a perception that misses frames may never
        # give it; the harmonic model fits whatever it is given.
        ready = bool(omega) and (self.lag.warm or self.harmonic.warm)
        return Forecast(t0, self.leads, positions, self.leads * np.nan, period, params, ready)

    def _beyond(self, lag: np.ndarray, harmonic: np.ndarray | None) -> np.ndarray:
        """The lag regression's positions (k, 3) on every lead (n, 3): the harmonic model's
        beyond its own leads (its last position while there is none: no period is known
        then, and nothing is published)."""
        rest = harmonic[len(lag):] if harmonic is not None else np.repeat(
            lag[-1:], len(self.leads) - len(lag), axis=0)
        return np.vstack([lag, rest])


def make_predictor(name: str, **kw: float) -> Predictor:
    """A model by name: one of :data:`MODELS`."""
    classes = {"blend": BlendPredictor, "harmonic": HarmonicPredictor,
               "linear": LinearPredictor}
    if name not in classes:
        raise ValueError(f"unknown predictor model {name!r}: choose one of {', '.join(MODELS)}")
    return classes[name](**kw)
