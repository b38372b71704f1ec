"""Adapters between ROS messages and the numpy records of :mod:`uncertain_facade_map`.

The adapters read message attributes and never check message classes, so the same code
serves rclpy's message classes and rosbags' typestore classes. This package imports
rosbags but never rclpy at import time (:func:`rclpy_types` and :func:`rclpy_map_types`
import the ROS 2 message packages when called); the core package ``uncertain_facade_map``
imports neither.
"""

from .bag_io import BagClouds, list_topics, load_inputs, read_bag, read_bag_cloud, write_bag
from .map_messages import (
    diagnostic_array,
    facade_grid_array,
    facade_grid_msg,
    facade_msg,
    fill_query_response,
    occupancy_grid_msg,
    points_from_request,
    pose_from_frame,
    rclpy_map_types,
    rigid_from_pose,
    transform_points,
    triangle_marker_array,
)
from .pointcloud2 import (
    pointcloud2_fields,
    pointcloud2_from_structured,
    rclpy_types,
    rosbags_types,
    structured_from_pointcloud2,
)

__all__ = [
    'BagClouds',
    'diagnostic_array',
    'facade_grid_array',
    'facade_grid_msg',
    'facade_msg',
    'fill_query_response',
    'list_topics',
    'load_inputs',
    'occupancy_grid_msg',
    'pointcloud2_fields',
    'pointcloud2_from_structured',
    'points_from_request',
    'pose_from_frame',
    'rclpy_map_types',
    'rclpy_types',
    'read_bag',
    'read_bag_cloud',
    'rigid_from_pose',
    'rosbags_types',
    'structured_from_pointcloud2',
    'transform_points',
    'triangle_marker_array',
    'write_bag',
]
