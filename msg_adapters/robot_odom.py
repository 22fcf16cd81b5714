"""A robot's ``nav_msgs/Odometry`` (topic ``odom``) -> :class:`~indoor_loc.odometry.increments.OdomIncrement`.

The one decoder every estimator uses for ``motion_source: odom`` (``tll_pf``, ``pdr_kf_node``,
``backend_node``): validation as for ``pdr/odom`` (:func:`msg_adapters.odom.odom_from_msg`: finite,
the contract's plausibility bounds, a unit quaternion, a symmetric PSD planar covariance — or
``covariance[0] = -1``, "not given", as robot drivers write it), the odometry-jump guard
(:class:`~msg_adapters.odom.OdomJumpGuard`), stamps strictly increasing, and the frames fixed by the
stream's first message (``header.frame_id`` / ``child_frame_id``, whatever the robot calls them: a
message in other frames is ``wrong_frame``); then the decimation into increments
(:class:`~indoor_loc.odometry.increments.IncrementAccumulator`). A refused message changes nothing.
"""
from __future__ import annotations

from nav_msgs.msg import Odometry

from indoor_loc.errors import InvalidMessageError
from indoor_loc.measurements import OdomPose
from indoor_loc.odometry.increments import IncrementAccumulator, OdomIncrement, OdomIncrementParams
from msg_adapters.odom import OdomJumpGuard, odom_from_msg


def robot_odom_from_msg(msg: Odometry) -> OdomPose:
    """Validate and unpack a robot's odometry message (see the module doc); a covariance "not
    given" (``-1``) comes back as zeros, which the increments read as "use the model"."""
    return odom_from_msg(msg, unknown_cov=True)


class RobotOdomReader:
    """Messages of one robot's ``odom`` stream -> increments (``read``), ``flush`` to close the open one."""

    def __init__(self, params: OdomIncrementParams | None = None) -> None:
        self.acc = IncrementAccumulator(params)
        self.guard = OdomJumpGuard()
        self.frames: tuple[str, str] | None = None
        self.messages = 0
        self.increments = 0
        self.from_message = 0          # increments whose covariance was the message's (else the model's)

    @property
    def last_stamp_ns(self) -> int | None:
        return self.acc.last_stamp_ns

    def read(self, msg: Odometry) -> tuple[OdomPose, OdomIncrement | None]:
        """Validate one message; returns it unpacked and the increment it closes (None while one is
        open). Raises :class:`InvalidMessageError` with the reader unchanged."""
        od = self.check(msg)
        return od, self.take(od)

    def check(self, msg: Odometry) -> OdomPose:
        """Validate one message against the contract and this stream (frames, stamps, jump) without
        taking it: nothing changes. Raises :class:`InvalidMessageError`."""
        od = robot_odom_from_msg(msg)
        frames = (od.frame_id, od.child_frame_id)
        if self.frames is not None and frames != self.frames:
            raise InvalidMessageError("wrong_frame", f"odom in frames {frames[0]!r} -> {frames[1]!r}, but this "
                                                     f"stream's are {self.frames[0]!r} -> {self.frames[1]!r}")
        last = self.acc.last_stamp_ns
        if last is not None and od.stamp_ns <= last:
            raise InvalidMessageError("non_monotonic_stamp", f"odom stamp {od.stamp_ns} <= previous {last}")
        self.guard.check(od)
        return od

    def take(self, od: OdomPose) -> OdomIncrement | None:
        """Take a pose :meth:`check` passed (nothing read since): the increment it closes, if any."""
        inc = self.acc.update(od.stamp_ns, od.x, od.y, od.yaw, od.cov)
        self.guard.accept(od)
        self.frames = (od.frame_id, od.child_frame_id)
        self.messages += 1
        return self._count(inc)

    def flush(self) -> OdomIncrement | None:
        """Close the open increment at the last message read (None if no time passed since it began)."""
        return self._count(self.acc.flush())

    def _count(self, inc: OdomIncrement | None) -> OdomIncrement | None:
        if inc is not None:
            self.increments += 1
            self.from_message += int(inc.from_message)
        return inc

    def diagnostics(self) -> dict[str, str]:
        return {"odom.messages": str(self.messages), "odom.increments": str(self.increments),
                "odom.increments_message_cov": str(self.from_message)}
