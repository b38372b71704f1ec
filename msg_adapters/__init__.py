"""Adapters between ROS messages and the numpy records of :mod:`uncertain_facade_map`.

The adapters read message attributes and never check message classes, so the same code
serves rclpy's message classes and rosbags' typestore classes. This package imports
rosbags but never rclpy at import time (:func:`rclpy_types` and :func:`rclpy_map_types`
import the ROS 2 message packages when called); the core package ``uncertain_facade_map``
imports neither.

Modules: ``pointcloud2`` (PointCloud2 <-> structured arrays), ``transforms`` (TFMessage,
TransformStamped, Odometry <-> :class:`~msg_adapters.transforms.StampedTransform` <-> the
core's transform buffer), ``map_messages`` (the published maps, services, diagnostics),
``bag_io`` (bags: clouds with their frames and poses), ``parameters`` (ROS parameter
descriptors), ``published_maps``.
"""

from .bag_io import BagClouds, list_topics, load_inputs, read_bag, read_bag_cloud, write_bag
from .map_messages import (
    diagnostic_array,
    facade_grid_array,
    facade_grid_msg,
    facade_msg,
    fill_list_tiles_response,
    fill_query_response,
    occupancy_grid_msg,
    points_from_request,
    pose_from_frame,
    rclpy_map_types,
    rigid_from_pose,
    tiles_of_response,
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
from .transforms import (
    StampedTransform,
    feed,
    header_stamp_ns,
    odometry_msg,
    pose_stamped_msg,
    stamped_transforms,
    tf_message,
    transform_arrays,
    transform_stamped_msg,
    transform_types_rclpy,
    transform_types_rosbags,
)

__all__ = [
    'BagClouds',
    'StampedTransform',
    'diagnostic_array',
    'facade_grid_array',
    'facade_grid_msg',
    'facade_msg',
    'feed',
    'fill_list_tiles_response',
    'fill_query_response',
    'header_stamp_ns',
    'list_topics',
    'load_inputs',
    'occupancy_grid_msg',
    'odometry_msg',
    'pointcloud2_fields',
    'pointcloud2_from_structured',
    'points_from_request',
    'pose_from_frame',
    'pose_stamped_msg',
    'rclpy_map_types',
    'rclpy_types',
    'read_bag',
    'read_bag_cloud',
    'rigid_from_pose',
    'rosbags_types',
    'stamped_transforms',
    'structured_from_pointcloud2',
    'tf_message',
    'tiles_of_response',
    'transform_arrays',
    'transform_points',
    'transform_stamped_msg',
    'transform_types_rclpy',
    'transform_types_rosbags',
    'triangle_marker_array',
    'write_bag',
]
