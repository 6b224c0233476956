"""Linear (Airy) wave kinematics in finite depth, and the tank's sea states.

Frame ``world``: origin on the seabed, z up, the still-water surface at ``z = depth``; waves
travel along +x. Every component follows the dispersion relation ω² = g k tanh(k h); orbital
velocity and acceleration decay with depth as cosh(k z)/sinh(k h) and sinh(k z)/sinh(k h).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import brentq

from wavegrasp.checks import check_positive

G = 9.81  # m/s²
RHO = 1000.0  # kg/m³, fresh water as in the tank


def wavenumber(omega: float, depth: float) -> float:
    """k in rad/m solving ω² = g k tanh(k h) for ``omega`` rad/s in water ``depth`` metres."""
    check_positive("omega", omega)
    check_positive("depth", depth)
    deep = omega**2 / G
    return float(brentq(lambda k: omega**2 - G * k * np.tanh(k * depth), deep * 0.5,
                        max(deep, omega / np.sqrt(G * depth)) * 1.5, xtol=1e-12))


@dataclass(frozen=True)
class WaveCondition:
    """One row of the paper's Table I: regular wave height and period, and the measured maxima."""

    number: int
    height_m: float
    period_s: float
    max_horizontal_mps: float
    max_vertical_mps: float


TABLE_I = {
    1: WaveCondition(1, 0.25, 1.25, 0.2218, 0.2157),
    2: WaveCondition(2, 0.135, 1.08, 0.1036, 0.0894),
    3: WaveCondition(3, 0.15, 1.2, 0.0523, 0.0012),
}


def orbital_amplitudes(height: float, period: float, depth: float, z: float) -> tuple[float, float]:
    """Peak horizontal and vertical orbital speed (m/s) at height ``z`` above the seabed."""
    omega = 2 * np.pi / period
    k = wavenumber(omega, depth)
    a = height / 2
    return (a * omega * np.cosh(k * z) / np.sinh(k * depth),
            a * omega * np.sinh(k * z) / np.sinh(k * depth))


@dataclass(frozen=True)
class Sway:
    """Slow flow that sways the oscillation plane: mean current, seiche, transverse circulation.

    All velocities m/s, uniform over depth; periods in seconds; phases radians.
    """

    mean_current: tuple[float, float] = (0.0, 0.0)
    seiche_mps: float = 0.0
    seiche_period_s: float = 69.0
    transverse_mps: float = 0.0
    transverse_period_s: float = 23.0
    plane_deg: float = 0.0
    plane_period_s: float = 40.0
    phases: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def plane_angle(self, t: float) -> float:
        """Slow rotation of the orbital plane about z, radians."""
        return np.deg2rad(self.plane_deg) * np.sin(
            2 * np.pi * t / self.plane_period_s + self.phases[2])

    def velocity_acceleration(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        ws, wt = 2 * np.pi / self.seiche_period_s, 2 * np.pi / self.transverse_period_s
        ps, pt = ws * t + self.phases[0], wt * t + self.phases[1]
        u = np.array([self.mean_current[0] + self.seiche_mps * np.sin(ps),
                      self.mean_current[1] + self.transverse_mps * np.sin(pt), 0.0])
        a = np.array([self.seiche_mps * ws * np.cos(ps), self.transverse_mps * wt * np.cos(pt),
                      0.0])
        return u, a


@dataclass
class Sea:
    """A sum of linear wave components plus slow sway, in water ``depth`` metres deep.

    amplitudes : array, shape (n,), metres; omegas : rad/s; directions : rad from +x;
    phases : rad. ``modulation`` = (depth 0..1, period s): slow amplitude modulation.
    """

    depth: float
    amplitudes: np.ndarray
    omegas: np.ndarray
    directions: np.ndarray
    phases: np.ndarray
    modulation: tuple[float, float] = (0.0, 30.0)
    sway: Sway = field(default_factory=Sway)

    def __post_init__(self) -> None:
        check_positive("depth", self.depth)
        self.ks = np.array([wavenumber(w, self.depth) for w in self.omegas])
        self._cos_b, self._sin_b = np.cos(self.directions), np.sin(self.directions)
        self._sinh_kh = np.sinh(self.ks * self.depth)
        self._a_omega = self.amplitudes * self.omegas

    def _theta(self, t: float, x: float, y: float) -> np.ndarray:
        return self.ks * (x * self._cos_b + y * self._sin_b) - self.omegas * t + self.phases

    def _gain(self, t: float) -> float:
        m, period = self.modulation
        return 1.0 + m * np.sin(2 * np.pi * t / period)

    def elevation(self, t: float, x: float = 0.0, y: float = 0.0) -> float:
        """Free-surface elevation above still water, metres."""
        return float(self._gain(t) * np.sum(self.amplitudes * np.cos(self._theta(t, x, y))))

    def kinematics(self, t: float, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Water velocity (m/s) and acceleration (m/s²) at ``p`` (shape (3,), metres, world).

        Above the still-water surface the flow is taken at the surface (no stretching).
        """
        z = min(max(float(p[2]), 0.0), self.depth)
        th = self._theta(t, float(p[0]), float(p[1]))
        cos_th, sin_th = np.cos(th), np.sin(th)
        aw = self._gain(t) * self._a_omega
        ch = aw * np.cosh(self.ks * z) / self._sinh_kh
        sh = aw * np.sinh(self.ks * z) / self._sinh_kh
        uh, duh = ch * cos_th, ch * self.omegas * sin_th
        u = np.array([uh @ self._cos_b, uh @ self._sin_b, sh @ sin_th])
        a = np.array([duh @ self._cos_b, duh @ self._sin_b, -(sh * self.omegas) @ cos_th])
        c, s = np.cos(self.sway.plane_angle(t)), np.sin(self.sway.plane_angle(t))
        turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        su, sa = self.sway.velocity_acceleration(t)
        return turn @ u + su, turn @ a + sa


def default_sway(rng: np.random.Generator, current: tuple[float, float] = (0.01, 20.0)) -> Sway:
    """The tank's slow flow: a mean ``current`` (m/s, degrees from the waves' direction; 1 cm/s
    at 20° in the tank), a 1 cm/s longitudinal seiche (period 2·104 m/√(g·0.93 m) ≈ 69 s for a
    104 m flume), a 0.8 cm/s transverse circulation of 23 s, and the orbital plane swaying ±3°
    over 40 s; random phases."""
    speed, angle = current[0], np.deg2rad(current[1])
    return Sway(mean_current=(speed * np.cos(angle), speed * np.sin(angle)), seiche_mps=0.01,
                transverse_mps=0.008, plane_deg=3.0, phases=tuple(rng.uniform(0, 2 * np.pi, 3)))


def regular_sea(cond: WaveCondition, depth: float, rng: np.random.Generator,
                reflection: float = 0.08, modulation: float = 0.05,
                current: tuple[float, float] = (0.01, 20.0)) -> Sea:
    """The paper's regular wave, a ``reflection`` fraction travelling back from the beach,
    slow amplitude modulation and sway."""
    a = cond.height_m / 2
    w = 2 * np.pi / cond.period_s
    return Sea(depth=depth, amplitudes=np.array([a, reflection * a]), omegas=np.array([w, w]),
               directions=np.array([0.0, np.pi]), phases=rng.uniform(0, 2 * np.pi, 2),
               modulation=(modulation, float(rng.uniform(25.0, 40.0))),
               sway=default_sway(rng, current))


def jonswap_spectrum(f: np.ndarray, hs: float, tp: float, gamma: float = 3.3) -> np.ndarray:
    """JONSWAP variance density S(f), m²/Hz, scaled so that 4·sqrt(∫S df) = ``hs``."""
    fp = 1.0 / tp
    sigma = np.where(f <= fp, 0.07, 0.09)
    shape = f**-5.0 * np.exp(-1.25 * (fp / f) ** 4) * gamma ** np.exp(
        -((f - fp) ** 2) / (2 * sigma**2 * fp**2))
    fine = np.linspace(0.3 * fp, 6 * fp, 4000)
    fs = np.where(fine <= fp, 0.07, 0.09)
    m0 = np.trapezoid(fine**-5.0 * np.exp(-1.25 * (fp / fine) ** 4) * gamma ** np.exp(
        -((fine - fp) ** 2) / (2 * fs**2 * fp**2)), fine)
    return shape * (hs / 4) ** 2 / m0


def jonswap_sea(cond: WaveCondition, depth: float, rng: np.random.Generator,
                n: int = 64, current: tuple[float, float] = (0.01, 20.0)) -> Sea:
    """Irregular sea with Hs = the condition's height and Tp = its period (γ = 3.3), ``n``
    components between 0.6 fp and 2.5 fp at jittered frequencies, random phases, and sway."""
    fp = 1.0 / cond.period_s
    edges = np.linspace(0.6 * fp, 2.5 * fp, n + 1)
    f = edges[:-1] + rng.uniform(0.0, 1.0, n) * np.diff(edges)
    amps = np.sqrt(2 * jonswap_spectrum(f, cond.height_m, cond.period_s) * np.diff(edges))
    return Sea(depth=depth, amplitudes=amps, omegas=2 * np.pi * f,
               directions=rng.normal(0.0, np.deg2rad(5.0), n),
               phases=rng.uniform(0, 2 * np.pi, n), sway=default_sway(rng, current))
