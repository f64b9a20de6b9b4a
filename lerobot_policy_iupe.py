import lerobot_iupe  # noqa: F401  (LeRobot imports this module to discover the plugin)
