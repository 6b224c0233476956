"""The paper's motion model (section IV-D, E, equations 1-7), fitted online.

x(t) = A_x sin(ωt + φ_x) + δ_x(t),  y(t) = A_y sin(ωt + φ_y) + δ_y(t),
z(t) = A_z cos(ωt + φ_z) + A_z2 cos(2ωt + φ_z2) + δ_z(t)

over a sliding window of observations; the sway δ is a slow (linear in time) term; z also gets
the second harmonic (a body on a tether rises twice per swing). ω is estimated from the data:
the strongest peak of the horizontal velocity spectrum, refined every ``refit_s`` by a golden-
section search on the least-squares residual. Nothing about the wave condition is given.

Beyond the paper, two optional terms (the default predictor's harmonic part has both):
``second_xy``, the second harmonic horizontally too (drag is quadratic in the flow, and a
current makes it lopsided: a 35 cm sea swung a 9 cm cylinder with a 2ω term 11 % of its
swing), and ``half_omega``, a term at ω/2 on every axis: a buoyant body on a tether is a
pendulum whose restoring force the wave's vertical flow modulates at ω, and where its own
period is near twice the wave's it swings at ω/2 too (parametric resonance; a 14 cm sphere in
a 1.23 s sea: 23 mm at ω/2 beside 94 mm at ω, which the paper's model fitted with 17 mm RMS).
"""

from __future__ import annotations

from collections import deque

import numpy as np
from scipy.optimize import minimize_scalar

from wavegrasp.predictor.forecast import check_position


def spectral_omega(t: np.ndarray, p: np.ndarray, band_hz=(0.2, 3.0)) -> float | None:
    """ω (rad/s) of the strongest peak of the horizontal velocity spectrum, or None."""
    dt = 0.05
    grid = np.arange(t[0], t[-1], dt)
    if len(grid) < 40:
        return None
    v = np.diff(np.column_stack([np.interp(grid, t, p[:, i]) for i in range(2)]), axis=0) / dt
    v -= v.mean(axis=0)
    n = 8 * len(v)
    power = sum(np.abs(np.fft.rfft(v[:, i] * np.hanning(len(v)), n)) ** 2 for i in range(2))
    f = np.fft.rfftfreq(n, dt)
    band = (f >= band_hz[0]) & (f <= band_hz[1])
    if not band.any() or power[band].max() <= 0:
        return None
    return float(2 * np.pi * f[band][np.argmax(power[band])])


def design(tau: np.ndarray, omega: float, second: bool, half: bool = False) -> np.ndarray:
    """Columns 1, τ, sin ωτ, cos ωτ (and sin 2ωτ, cos 2ωτ; and sin ωτ/2, cos ωτ/2, last) for
    times ``tau`` (n,)."""
    cols = [np.ones_like(tau), tau, np.sin(omega * tau), np.cos(omega * tau)]
    if second:
        cols += [np.sin(2 * omega * tau), np.cos(2 * omega * tau)]
    if half:
        cols += [np.sin(omega / 2 * tau), np.cos(omega / 2 * tau)]
    return np.column_stack(cols)


def least_squares(A: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Coefficients minimising ||A c - y|| (A (n, k), y (n,) or (n, m)) by the normal
    equations: a few hundred rows of well-scaled columns, and about 3 times faster than the
    SVD of ``np.linalg.lstsq`` (13 against 36 µs for 120 x 8), which each refit calls
    dozens of times; the SVD where the columns are degenerate (too few or repeated stamps)."""
    try:
        return np.linalg.solve(A.T @ A, A.T @ y)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(A, y, rcond=None)[0]


class HarmonicModel:
    """Least-squares harmonic fit over the last ``window_s`` seconds of observations."""

    def __init__(self, window_s: float = 12.0, refit_s: float = 1.0,
                 min_periods: float = 3.0, half_omega: bool = False,
                 second_xy: bool = False) -> None:
        self.window_s, self.refit_s, self.min_periods = window_s, refit_s, min_periods
        self.half_omega, self.second_xy = half_omega, second_xy
        self.reset()

    def reset(self) -> None:
        self._t: deque[float] = deque()
        self._p: deque[np.ndarray] = deque()
        self.omega: float | None = None
        self._next_refit = -np.inf
        self.coef_xy: np.ndarray | None = None  # (4, 2)
        self.coef_z: np.ndarray | None = None  # (6,)
        self.t_now = 0.0

    def update(self, t: float, p: np.ndarray) -> None:
        self._t.append(t)
        self._p.append(check_position(p))
        while self._t[0] < t - self.window_s:
            self._t.popleft()
            self._p.popleft()
        self.t_now = t
        ts, ps = np.fromiter(self._t, float), np.array(self._p)
        if t >= self._next_refit or self.omega is None:
            # The spectrum again over the whole window, not only the first guess refined by
            # at most 10 % a refit: a first guess from two seconds of a 5 Hz camera (a 0.5 Hz
            # resolution) was a 6.3 s period for a 1.4 s swing, never left, never warm.
            fresh = spectral_omega(ts, ps)
            guesses = [w for w in (self.omega, fresh) if w is not None]
            if self.omega is not None and fresh is not None and (
                    abs(fresh - self.omega) <= 0.1 * self.omega):
                guesses = [self.omega]
            if guesses:
                refined = [self._refine(ts, ps, w) for w in guesses]
                self.omega = min(refined, key=lambda w: self._residual(ts, ps, w))
                self._next_refit = t + self.refit_s
        if self.omega is None or len(ts) < 12:
            self.coef_xy = self.coef_z = None
            return
        tau = ts - t
        self.coef_xy = least_squares(self._design(tau, self.omega, False), ps[:, :2])
        self.coef_z = least_squares(self._design(tau, self.omega, True), ps[:, 2])

    def _design(self, tau: np.ndarray, omega: float, z: bool) -> np.ndarray:
        """:func:`design` for the horizontal axes or for z, with this model's terms."""
        return design(tau, omega, z or self.second_xy, self.half_omega)

    def _residual(self, ts: np.ndarray, ps: np.ndarray, w: float) -> float:
        """The least-squares fit's sum of squared residuals, m², at ``w`` rad/s."""
        tau, r = ts - ts[-1], 0.0
        for cols, z in ((ps[:, :2], False), (ps[:, 2], True)):
            A = self._design(tau, w, z)
            r += float(np.sum((A @ least_squares(A, cols) - cols) ** 2))
        return r

    def _refine(self, ts: np.ndarray, ps: np.ndarray, omega: float) -> float:
        best = minimize_scalar(lambda w: self._residual(ts, ps, w),
                               bounds=(0.9 * omega, 1.1 * omega), method="bounded",
                               options={"xatol": 1e-4 * omega})
        return float(best.x)

    @property
    def warm(self) -> bool:
        return (self.coef_xy is not None and len(self._t) > 1
                and self._t[-1] - self._t[0] >= self.min_periods * 2 * np.pi / self.omega)

    def predict(self, leads: np.ndarray) -> np.ndarray | None:
        """Positions (m, 3) at ``leads`` seconds after the last observation, or None."""
        if self.coef_xy is None or self.coef_z is None:
            return None
        xy = self._design(leads, self.omega, False) @ self.coef_xy
        z = self._design(leads, self.omega, True) @ self.coef_z
        return np.column_stack([xy, z])

    def parameters(self) -> dict[str, float]:
        """ω, period, per-axis amplitude and phase (equations 1-3, t = 0 at the last
        observation), the z second harmonic, the sway (value and rate) per axis and, with
        ``second_xy`` and ``half_omega``, the amplitudes of the horizontal second harmonic
        (``A_x2``, ``A_y2``) and of the ω/2 term per axis (``A_half_x``...)."""
        if self.coef_xy is None or self.coef_z is None:
            return {}
        out = {"omega": self.omega, "period_s": 2 * np.pi / self.omega}
        for i, axis in enumerate("xy"):
            c0, c1, a, b = self.coef_xy[:4, i]  # a sin + b cos = A sin(ωt + φ)
            out |= {f"A_{axis}": float(np.hypot(a, b)), f"phi_{axis}": float(np.arctan2(b, a)),
                    f"sway_{axis}": float(c0), f"sway_rate_{axis}": float(c1)}
        c0, c1, a, b, a2, b2 = self.coef_z[:6]  # a sin + b cos = A cos(ωt + φ)
        out |= {"A_z": float(np.hypot(a, b)), "phi_z": float(np.arctan2(-a, b)),
                "A_z2": float(np.hypot(a2, b2)), "phi_z2": float(np.arctan2(-a2, b2)),
                "sway_z": float(c0), "sway_rate_z": float(c1)}
        if self.second_xy:
            out |= {f"A_{axis}2": float(np.hypot(*self.coef_xy[4:6, i]))
                    for i, axis in enumerate("xy")}
        if self.half_omega:  # the last two columns of every axis
            out |= {f"A_half_{axis}": float(np.hypot(*coef[-2:]))
                    for axis, coef in zip("xyz", (*self.coef_xy.T, self.coef_z), strict=True)}
        return out
