"""Adapters between ROS messages and the numpy records of :mod:`uncertain_facade_map`.

The adapters read message attributes and never check message classes, so the same code
serves rclpy's message classes and rosbags' typestore classes. This package imports
rosbags but never rclpy at import time (:func:`rclpy_types` imports the ROS 2 message
packages when called); the core package ``uncertain_facade_map`` imports neither.
"""

from .bag_io import BagClouds, list_topics, read_bag, read_bag_cloud, write_bag
from .pointcloud2 import (
    pointcloud2_fields,
    pointcloud2_from_structured,
    rclpy_types,
    rosbags_types,
    structured_from_pointcloud2,
)

__all__ = [
    'BagClouds',
    'list_topics',
    'pointcloud2_fields',
    'pointcloud2_from_structured',
    'rclpy_types',
    'read_bag',
    'read_bag_cloud',
    'rosbags_types',
    'structured_from_pointcloud2',
    'write_bag',
]
