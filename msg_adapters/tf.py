"""Planar transforms <-> ``geometry_msgs/TransformStamped`` and ``tf2_msgs/TFMessage`` (``/tf``).

``tf2_msgs`` has no wheel: ``make venv`` builds it into the venv (``indoor_loc/tools/build_tf2_msgs.py``).
Where it could not be built :func:`tf_message_class` returns None and the nodes publish the
corrections on their ``TransformStamped`` topics only (``pf/map_odom`` etc.), saying so once.
"""
from __future__ import annotations

from typing import Any

from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped

from msg_adapters.odom import quat_to_yaw, yaw_to_quat
from msg_adapters.time import require_finite, stamp_from_ns, stamp_to_ns


def transform_to_msg(stamp_ns: int, frame_id: str, child_frame_id: str, x: float, y: float,
                     yaw: float) -> TransformStamped:
    """The planar transform ``frame_id -> child_frame_id`` (translation x, y m; rotation yaw rad about z)."""
    require_finite("transform", [x, y, yaw])
    t = TransformStamped()
    t.header.stamp = stamp_from_ns(stamp_ns)
    t.header.frame_id = frame_id
    t.child_frame_id = child_frame_id
    t.transform.translation.x = float(x)
    t.transform.translation.y = float(y)
    t.transform.rotation = yaw_to_quat(float(yaw))
    return t


def transform_from_msg(t: TransformStamped) -> tuple[int, str, str, tuple[float, float, float]]:
    """``(stamp_ns, frame_id, child_frame_id, (x, y, yaw))`` of a planar TransformStamped (validated)."""
    tr = t.transform.translation
    require_finite("transform.translation", [tr.x, tr.y, tr.z])
    yaw = quat_to_yaw(t.transform.rotation, "transform.rotation")
    return stamp_to_ns(t.header.stamp), t.header.frame_id, t.child_frame_id, (float(tr.x), float(tr.y), yaw)


def pose_yaw_var(msg: PoseWithCovarianceStamped) -> tuple[int, str, tuple[float, float, float], float]:
    """``(stamp_ns, frame_id, (x, y, yaw), yaw variance)`` of an estimate."""
    p = msg.pose.pose.position
    require_finite("pose.position", [p.x, p.y])
    yaw = quat_to_yaw(msg.pose.pose.orientation, "pose.orientation")
    return (stamp_to_ns(msg.header.stamp), msg.header.frame_id, (float(p.x), float(p.y), yaw),
            float(msg.pose.covariance[35]))


def tf_message_class() -> Any | None:
    """``tf2_msgs.msg.TFMessage``, or None where tf2_msgs is not installed (see the module doc)."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        return None
    return TFMessage


def tf_message(transforms: list[TransformStamped], future_dating_ns: int = 0) -> Any:
    """A ``TFMessage`` of copies of ``transforms``, each stamp moved ``future_dating_ns`` later (nav2_amcl's
    ``transform_tolerance``: the transform stays usable that long after its stamp)."""
    cls = tf_message_class()
    if cls is None:
        raise ImportError("tf2_msgs is not installed (make venv builds it: indoor_loc/tools/build_tf2_msgs.py)")
    out = []
    for t in transforms:
        c = TransformStamped()
        c.header.frame_id = t.header.frame_id
        c.header.stamp = stamp_from_ns(stamp_to_ns(t.header.stamp) + int(future_dating_ns))
        c.child_frame_id = t.child_frame_id
        c.transform = t.transform
        out.append(c)
    return cls(transforms=out)
