"""indoor_loc: indoor localisation from WiFi RSS and IMU on a graph of the building.

Layers (imports flow one way, checked by test/test_architecture.py):
  core      indoor_loc.{imu,wifi,eval,...}  pure numpy/scipy, no ROS imports
  adapters  msg_adapters         pure message <-> core-type functions
  stages    indoor_loc.pipeline             a node's message logic without rclpy (used live and offline)
  nodes     indoor_loc.nodes                the only code that imports rclpy
"""
__version__ = "0.1.0"
