"""The ``facade_mapper`` ROS 2 node: a thin shell wiring :mod:`msg_adapters` to the core."""
