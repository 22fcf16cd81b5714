"""Barometer samples <-> sensor_msgs/FluidPressure (``baro/pressure``, REP 145: Pascals).

``fluid_pressure`` in Pa, ``variance`` in Pa² (0 = unknown, the message's own convention). Rejected:
a non-finite value (``nan``), a pressure outside ``BOUNDS['pressure']`` or a negative variance
(``out_of_range``)."""
from __future__ import annotations

from sensor_msgs.msg import FluidPressure

from indoor_loc.errors import InvalidMessageError
from msg_adapters.plausible import check
from msg_adapters.time import require_finite, stamp_from_ns, stamp_to_ns


def pressure_to_msg(stamp_ns: int, frame_id: str, pressure_pa: float, variance_pa2: float = 0.0) -> FluidPressure:
    """A FluidPressure message (validated like on input)."""
    require_finite("fluid_pressure", [pressure_pa, variance_pa2])
    check("fluid_pressure", float(pressure_pa), "pressure")
    if variance_pa2 < 0:
        raise InvalidMessageError("out_of_range", f"variance = {variance_pa2} Pa^2 is negative")
    msg = FluidPressure()
    msg.header.stamp = stamp_from_ns(int(stamp_ns))
    msg.header.frame_id = frame_id
    msg.fluid_pressure = float(pressure_pa)
    msg.variance = float(variance_pa2)
    return msg


def pressure_from_msg(msg: FluidPressure) -> tuple[int, float, float]:
    """(stamp ns, pressure Pa, variance Pa² (0 = unknown)) of a validated message."""
    stamp = stamp_to_ns(msg.header.stamp)
    require_finite("fluid_pressure", [msg.fluid_pressure, msg.variance])
    check("fluid_pressure", float(msg.fluid_pressure), "pressure")
    if msg.variance < 0:
        raise InvalidMessageError("out_of_range", f"variance = {msg.variance} Pa^2 is negative")
    return stamp, float(msg.fluid_pressure), float(msg.variance)
