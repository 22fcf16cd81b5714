"""rclpy nodes: thin wrappers around pipeline stages. The only package that imports rclpy."""
