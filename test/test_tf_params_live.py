"""The /tf parameters of the estimators: publish_tf false leaves /tf alone (pf/map_odom stays), a bad
transform_tolerance stops the start with a clear error (exit 2)."""
from __future__ import annotations

import sys

import pytest

from helpers_dds import Peer, child_env, ros_node, spin_until


@pytest.mark.timeout(120)
def test_publish_tf_false_and_bad_tolerance(ros_domain, tmp_path):
    bad = Peer([sys.executable, "-m", "indoor_loc.nodes.pdr_kf_node", "--ros-args", "-r", "__ns:=/alice",
                "-p", "transform_tolerance:=-1.0"], env=child_env())
    assert bad.wait(60) == 2
    assert "transform_tolerance" in bad.output() and "[0, 60]" in bad.output()
    quiet = Peer([sys.executable, "-m", "indoor_loc.nodes.pdr_kf_node", "--ros-args", "-r", "__ns:=/alice",
                  "-p", "publish_tf:=false"], env=child_env())
    loud = Peer([sys.executable, "-m", "indoor_loc.nodes.pdr_kf_node", "--ros-args", "-r", "__ns:=/bob",
                 "-p", "publish_tf:=true"], env=child_env())
    try:
        with ros_node("probe") as (node, ex):
            assert spin_until(ex, lambda: node.count_publishers("/bob/pdr_kf/map_odom") > 0
                              and node.count_publishers("/alice/pdr_kf/map_odom") > 0, 60), quiet.output()
            assert spin_until(ex, lambda: node.count_publishers("/tf") == 1, 20)     # bob's only
            assert spin_until(ex, lambda: {i.node_namespace for i in node.get_publishers_info_by_topic("/tf")}
                              == {"/bob"}, 20)          # (the publisher's node is known once discovery completes)
    finally:
        quiet.stop()
        loud.stop()


@pytest.mark.timeout(120)
def test_without_tf2_msgs_the_node_says_so_and_runs(ros_domain, tmp_path):
    """Where tf2_msgs could not be built, publish_tf says once that /tf is not published; the correction
    topic is still offered."""
    shadow = tmp_path / "tf2_msgs"
    shadow.mkdir()
    (shadow / "__init__.py").write_text("raise ImportError('tf2_msgs shadowed by the test')\n")
    env = child_env(PYTHONPATH=f"{tmp_path}:{child_env().get('PYTHONPATH', '')}")
    proc = Peer([sys.executable, "-m", "indoor_loc.nodes.pdr_kf_node", "--ros-args", "-r", "__ns:=/alice",
                 "-p", "publish_tf:=true"], env=env)
    try:
        assert proc.wait_seen(r"tf2_msgs is not installed .* NOT on /tf", 60), proc.output()
        with ros_node("probe") as (node, ex):
            assert spin_until(ex, lambda: node.count_publishers("/alice/pdr_kf/map_odom") > 0, 30)
            assert node.count_publishers("/tf") == 0
        assert proc.proc.poll() is None
    finally:
        proc.stop()
