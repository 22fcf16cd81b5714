"""sensor_msgs/FluidPressure <-> a barometer sample (REP 145: pascals; ``variance`` Pa², 0 = unknown)."""
from __future__ import annotations

from typing import NamedTuple

from sensor_msgs.msg import FluidPressure

from msg_adapters.plausible import check
from msg_adapters.time import require_finite, stamp_from_ns, stamp_to_ns


class PressureSample(NamedTuple):
    """stamp_ns; pressure_pa (Pa); variance_pa2 (Pa², 0 = unknown); frame_id."""
    stamp_ns: int
    pressure_pa: float
    variance_pa2: float
    frame_id: str


def pressure_from_msg(msg: FluidPressure) -> PressureSample:
    """Validate and unpack a barometer message (``"nan"``, stamps; ``"out_of_range"``: a pressure
    outside ``BOUNDS["pressure"]`` — hPa or kPa instead of Pa; ``"bad_covariance"``: a variance
    outside ``BOUNDS["pressure_variance"]``)."""
    stamp = stamp_to_ns(msg.header.stamp)
    p, v = float(msg.fluid_pressure), float(msg.variance)
    require_finite("fluid_pressure", p)
    require_finite("variance", v)
    check("fluid_pressure", p, "pressure")
    check("variance", v, "pressure_variance")
    return PressureSample(stamp, p, v, msg.header.frame_id)


def pressure_to_msg(stamp_ns: int, frame_id: str, pressure_pa: float, variance_pa2: float = 0.0) -> FluidPressure:
    """A FluidPressure message: pressure (Pa) and its variance (Pa², 0 = unknown), validated as on
    input (``BOUNDS["pressure"]``, ``BOUNDS["pressure_variance"]``), so no writer makes one a node refuses."""
    require_finite("fluid_pressure", float(pressure_pa))
    require_finite("variance", float(variance_pa2))
    check("fluid_pressure", float(pressure_pa), "pressure")
    check("variance", float(variance_pa2), "pressure_variance")
    msg = FluidPressure()
    msg.header.stamp = stamp_from_ns(stamp_ns)
    msg.header.frame_id = frame_id
    msg.fluid_pressure = float(pressure_pa)
    msg.variance = float(variance_pa2)
    return msg
