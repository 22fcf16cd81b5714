"""The node layer's names in one place, for ``from indoor_loc.nodes.base import X``.

Each concern lives in its own module: :mod:`~indoor_loc.nodes.qos` (profiles, depths, the QoS of
publishers and subscriptions), :mod:`~indoor_loc.nodes.process` (signals, spinning and draining,
``run_stage_node``, the start-up error report), :mod:`~indoor_loc.nodes.help` (``--help``, the
params-file arguments, ``run_option_node``), :mod:`~indoor_loc.nodes.liveness` (whether an input
flows, its restarts and losses), :mod:`~indoor_loc.nodes.inputs` (a node's subscriptions and how
their messages reach the stage) and :mod:`~indoor_loc.nodes.stage_node` (``StageNode``, a stage run as an rclpy
node).
"""
from __future__ import annotations

from indoor_loc.nodes.help import node_usage, params_file_args, run_option_node
from indoor_loc.nodes.liveness import SequenceGaps
from indoor_loc.nodes.process import (DRAIN_TIMEOUT_S, STARTUP_ERROR_ACK_S, STARTUP_ERROR_ALONE_S,
                                      STARTUP_ERROR_GRACE_S, STARTUP_ERROR_WAIT_S, check_stop, drain, exit_after,
                                      ignore_signals, raise_on_signals, report_startup_error, restore_signals,
                                      run_stage_node, spin_node, stop_requested, stop_time_ns)
from indoor_loc.nodes.qos import (PUB_DEPTH_RELIABLE, PUB_DEPTH_SENSOR, QOS_PROFILES, SENSOR_RELIABILITY_PARAM,
                                  SUB_DEPTH, SUB_DEPTH_REPLAY, publisher_qos, qos_profile, subscription_qos)
from indoor_loc.nodes.inputs import TAKE_MAX, _cdr_stamp_ns
from indoor_loc.nodes.stage_node import DIAGNOSTICS_PERIOD_S, DISCOVERY_PERIOD_S, FINISH_ACK_TIMEOUT_S, StageNode

__all__ = [
    "DIAGNOSTICS_PERIOD_S", "DISCOVERY_PERIOD_S", "DRAIN_TIMEOUT_S", "FINISH_ACK_TIMEOUT_S", "PUB_DEPTH_RELIABLE",
    "PUB_DEPTH_SENSOR", "QOS_PROFILES", "SENSOR_RELIABILITY_PARAM", "STARTUP_ERROR_ACK_S", "STARTUP_ERROR_ALONE_S",
    "STARTUP_ERROR_GRACE_S", "STARTUP_ERROR_WAIT_S", "SUB_DEPTH", "SUB_DEPTH_REPLAY", "TAKE_MAX", "SequenceGaps",
    "StageNode", "_cdr_stamp_ns", "check_stop", "drain", "exit_after", "ignore_signals", "node_usage",
    "params_file_args", "publisher_qos", "qos_profile", "raise_on_signals", "report_startup_error",
    "restore_signals", "run_option_node", "run_stage_node", "spin_node", "stop_requested", "stop_time_ns",
    "subscription_qos",
]
