"""Pure message <-> core-type functions (no Node, no rclpy.init).

Invalid input raises :class:`indoor_loc.errors.InvalidMessageError` with a stable ``reason``.
"""
