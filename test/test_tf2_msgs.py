"""tf2_msgs, built into the venv by ``make venv`` (indoor_loc/tools/build_tf2_msgs.py): the type
imports, serialises, and a message crosses DDS between two processes."""
from __future__ import annotations

import subprocess
import sys

import pytest
from geometry_msgs.msg import TransformStamped
from rclpy.serialization import deserialize_message, serialize_message

from helpers_dds import python_peer, ros_node, spin_until


def test_tfmessage_serialises_round_trip():
    from tf2_msgs.msg import TFMessage   # built by make venv: an ImportError here means the build failed
    t = TransformStamped(child_frame_id="alice/odom")
    t.header.frame_id = "map"
    t.transform.translation.y = -2.25
    t.transform.rotation.z = 0.6
    t.transform.rotation.w = 0.8
    back = deserialize_message(serialize_message(TFMessage(transforms=[t, t])), TFMessage)
    assert len(back.transforms) == 2
    assert back.transforms[1].child_frame_id == "alice/odom"
    assert back.transforms[0].transform.translation.y == -2.25
    assert back.transforms[0].transform.rotation.z == pytest.approx(0.6)


def test_build_is_idempotent():
    r = subprocess.run([sys.executable, "-m", "indoor_loc.tools.build_tf2_msgs"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "already built" in r.stdout


def test_tfmessage_crosses_dds(ros_domain):
    from tf2_msgs.msg import TFMessage
    got: list = []
    with ros_node("tf_listener") as (node, ex):
        node.create_subscription(TFMessage, "/tf", got.append, 100)
        peer = python_peer("tf_sender.py", "robot1/odom")
        try:
            assert spin_until(ex, lambda: bool(got), 20.0), peer.output()
        finally:
            peer.stop()
    t = got[0].transforms[0]
    assert (t.header.frame_id, t.child_frame_id, t.header.stamp.sec) == ("map", "robot1/odom", 42)
    assert t.transform.translation.x == 1.5
