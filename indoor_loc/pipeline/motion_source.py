"""Which motion input an estimator stage takes: the package's PDR (``pdr/odom``) or a robot's own
odometry (``odom``, decoded into increments by :class:`msg_adapters.robot_odom.RobotOdomReader`).

Shared by ``tll_pf``, ``pdr_kf_node`` and ``backend_node`` (parameter ``motion_source``, the
``odom.*`` group): the stage subscribes to one of the two topics; a message on the other is
counted ``wrong_motion_source`` (offline runs and remapped topics may still deliver it).
"""
from __future__ import annotations

from indoor_loc.contract import MOTION_SOURCES, ODOM, Qos
from indoor_loc.errors import InvalidMessageError
from indoor_loc.pipeline.stage import Port

ODOMETRY_T = "nav_msgs/msg/Odometry"
PDR = "pdr/odom"
MOTION_DOC = ("motion input: pdr (pdr/odom, the package's pedestrian dead reckoning) or odom (a robot's "
              "nav_msgs/Odometry on odom: its increments, decimated by odom.*; docs/robot_odometry.md)")
ODOM_GROUP_DOC = "robot odometry increments for motion_source odom (odom.min_distance_m, odom.covariance, ...)"


def motion_topic(motion_source: str) -> str:
    return ODOM if motion_source == "odom" else PDR


def motion_port(motion_source: str) -> Port:
    """The stage's motion input port: required, a stream."""
    qos = Qos.SENSOR if motion_source == "odom" else Qos.RELIABLE
    return Port(motion_topic(motion_source), ODOMETRY_T, qos, required=True)


def require_source(motion_source: str, topic: str) -> None:
    """Refuse a message on the motion topic the stage does not take (``wrong_motion_source``)."""
    if topic != motion_topic(motion_source):
        raise InvalidMessageError("wrong_motion_source", f"{topic} received but motion_source is {motion_source} "
                                                         f"(the stage takes {motion_topic(motion_source)})")


def validate_source(owner: str, motion_source: str) -> None:
    from indoor_loc.params import require
    require(motion_source in MOTION_SOURCES, owner, "motion_source", f"one of {MOTION_SOURCES}", motion_source)
