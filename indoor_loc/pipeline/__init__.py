"""Stages: a node's message logic without rclpy.

A :class:`Stage` takes contract messages in and returns contract messages out. Live nodes
(``indoor_loc.nodes``) wrap a stage in an rclpy Node; ``indoor-loc run`` drives the very same
stage objects from bags in stamp order. That is how live and offline stay identical.
"""
