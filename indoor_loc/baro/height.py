"""Pressure -> height (pure numpy): the barometric formula of the ICAO standard atmosphere.

In the troposphere, with a linear temperature lapse ``L`` (0.0065 K/m) from ``T0`` (288.15 K), the
hydrostatic equation integrates to ``h = (T0 / L) (1 - (p / p0)^(R L / (g M)))`` (ICAO Doc 7488;
``R L / (g M) = 0.190263``, ``T0 / L = 44330.77`` m). A phone's barometer is not calibrated to the
local sea-level pressure, and the weather moves it by about 1 hPa an hour, so the package never uses
the absolute altitude: :func:`height_change_m` is the height of a pressure relative to a reference
pressure (about 8.3 m per hPa near sea level), and :class:`~indoor_loc.baro.detector.FloorChangeDetector`
keeps the reference following the weather while the user stays on a floor.

Pressure is in pascals (``sensor_msgs/FluidPressure``, REP 145), heights in metres, up positive.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

#: ICAO standard atmosphere: sea-level pressure (Pa), T0 / L (m) and the exponent R L / (g M).
P0_PA = 101325.0
T0_OVER_L_M = 44330.77
EXPONENT = 0.190263
#: Pascals per hectopascal.
PA_PER_HPA = 100.0


def height_change_m(p_pa: ArrayLike, p_ref_pa: float = P0_PA) -> np.ndarray:
    """Height (m) of pressure ``p_pa`` relative to where the pressure is ``p_ref_pa`` (both Pa):
    ``(T0 / L) (1 - (p / p_ref)^0.190263)`` — positive above the reference."""
    p = np.asarray(p_pa, float)
    return T0_OVER_L_M * (1.0 - (p / float(p_ref_pa)) ** EXPONENT)


def pressure_at_height_pa(h_m: ArrayLike, p_ref_pa: ArrayLike = P0_PA) -> np.ndarray:
    """Inverse of :func:`height_change_m`: the pressure (Pa) ``h_m`` metres above ``p_ref_pa``."""
    h = np.asarray(h_m, float)
    return np.asarray(p_ref_pa, float) * (1.0 - h / T0_OVER_L_M) ** (1.0 / EXPONENT)


def metres_per_hpa(p_pa: float = P0_PA) -> float:
    """Height change of one hectopascal at pressure ``p_pa`` (m/hPa; 8.3 near sea level)."""
    return float(height_change_m(p_pa - PA_PER_HPA, p_pa))
