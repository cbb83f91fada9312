"""The joining strategies, one module per family; :mod:`linear_slam_ros.joiner.registry` lists them."""
