"""starleth-demo: the trotting demo over ROS 2, the headless drop test and the terrain courses."""
