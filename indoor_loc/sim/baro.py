"""A phone barometer for the simulator (pure numpy): the pressure at the device's height with
weather drift, door/ventilation spikes, white sensor noise and the sensor's quantisation.

``p(t) = p_site(t) · (1 − h(t) / 44330.77)^(1/0.190263) + spikes(t) + noise``, rounded to
``quantum_hpa``: ``h`` the device height (m, map frame), ``p_site`` the weather at height 0 — a
linear trend of ``drift_hpa_per_h`` (about 1 hPa/h on a changing day) plus a slow oscillation.
Spikes are trapezoids of ``spike_hpa`` amplitude (either sign) held ``spike_s`` seconds, at random
times (Poisson, ``spikes_per_min``): a door between rooms of different ventilation pressure opening
and closing. Noise: phone barometers (Bosch BMP280/BMP380, ST LPS22HB) give 0.01–0.1 hPa of
noise per sample at 1–25 Hz and report hundredths of a hectopascal.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from indoor_loc.baro.height import PA_PER_HPA, pressure_at_height_pa
from indoor_loc.errors import ConfigError


@dataclass(frozen=True)
class BaroSimParams:
    """The simulated barometer and weather."""
    rate_hz: float = 10.0             # sample rate, Hz
    noise_hpa: float = 0.08           # white noise per sample (std), hPa
    quantum_hpa: float = 0.01         # the sensor's resolution, hPa (0 = none)
    p0_hpa: float = 1013.25           # mean weather pressure at height 0, hPa
    drift_hpa_per_h: float = 1.0      # magnitude of the weather trend, hPa/h (its sign is drawn)
    wave_hpa: float = 0.15            # amplitude of a slow weather oscillation, hPa
    wave_period_s: float = 1800.0     # its period, s
    spikes_per_min: float = 0.5       # door/ventilation spikes per minute (Poisson)
    spike_hpa: tuple[float, float] = (0.05, 0.25)   # spike amplitude range, hPa (either sign)
    spike_s: tuple[float, float] = (0.5, 3.0)       # spike hold range, s
    spike_ramp_s: float = 0.3         # rise and fall time of a spike, s

    def validate(self) -> None:
        if not 0.5 <= self.rate_hz <= 200.0:
            raise ConfigError(f"BaroSimParams.rate_hz: expected 0.5..200 Hz, got {self.rate_hz}")
        if self.noise_hpa < 0 or self.quantum_hpa < 0 or self.spikes_per_min < 0:
            raise ConfigError("BaroSimParams: noise_hpa, quantum_hpa and spikes_per_min must be >= 0")


@dataclass
class BaroData:
    t_ns: np.ndarray           # (K,) relative to the run start
    pressure_pa: np.ndarray    # (K,) Pa
    spikes: np.ndarray         # (S, 3) start s, hold s, amplitude hPa


def simulate_pressure(t_s: np.ndarray, height_m: np.ndarray, duration_s: float, params: BaroSimParams,
                      rng: np.random.Generator) -> BaroData:
    """Barometer samples over [0, duration_s] of a device whose height is ``height_m`` at ``t_s``
    (interpolated); the sample grid starts at a random phase."""
    params.validate()
    dt = 1.0 / params.rate_hz
    t = np.arange(float(rng.uniform(0.0, dt)), duration_s, dt)
    h = np.interp(t, t_s, height_m)
    sign = 1.0 if rng.random() < 0.5 else -1.0
    phase = float(rng.uniform(0, 2 * np.pi))
    weather = (params.p0_hpa + sign * params.drift_hpa_per_h * t / 3600.0
               + params.wave_hpa * np.sin(2 * np.pi * t / params.wave_period_s + phase))
    p = pressure_at_height_pa(h, weather * PA_PER_HPA)
    n_sp = int(rng.poisson(params.spikes_per_min * duration_s / 60.0))
    spikes = np.column_stack([rng.uniform(0, duration_s, n_sp), rng.uniform(*params.spike_s, n_sp),
                              rng.uniform(*params.spike_hpa, n_sp) * np.where(rng.random(n_sp) < 0.5, -1, 1)])
    r = params.spike_ramp_s
    for t0, hold, amp in spikes:
        shape = np.clip(np.minimum((t - t0) / r + 1.0, (t0 + hold + r - t) / r), 0.0, 1.0)
        p += amp * PA_PER_HPA * shape
    p += rng.normal(0.0, params.noise_hpa * PA_PER_HPA, len(t))
    if params.quantum_hpa > 0:
        q = params.quantum_hpa * PA_PER_HPA
        p = np.round(p / q) * q
    return BaroData(np.round(t * 1e9).astype(np.int64), p, spikes.reshape(-1, 3))
