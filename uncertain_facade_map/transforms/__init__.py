"""Frames and their timed transforms: what puts a cloud given in its own frame into the map.

Modules (numpy only, no ROS):

* :mod:`.rotations` -- vectorised quaternion helpers (ROS order ``(x, y, z, w)``):
  ``normalise``, ``to_matrix``, ``from_matrix``, ``multiply``, ``conjugate``, ``rotate``,
  ``slerp`` (Shoemake 1985).
* :mod:`.buffer` -- :class:`TransformBuffer`, a tree of static and timed transforms with
  tf2's BufferCore semantics (chain lookups, interpolation, time 0 = latest common time,
  extrapolation errors), and :class:`Rigid`, one rigid transform.
* :mod:`.scans` -- :func:`point_times` (per-point times of a cloud, by driver convention),
  :class:`ScanPose` and :func:`locate_scan` (one pose per cloud, or one per point time:
  motion compensation), :func:`place_scan` (the rule the node and replay share: exact,
  wait, hold within a tolerance, or one pose at the stamp).

Errors are :class:`uncertain_facade_map.errors.TransformError` and its subclasses
``UnknownFrameError``, ``ConnectivityError`` and ``ExtrapolationError`` (all InputErrors).
"""

from uncertain_facade_map.errors import ConnectivityError, ExtrapolationError, TransformError, UnknownFrameError

from . import rotations
from .buffer import Rigid, TransformBuffer
from .scans import Placement, ScanPose, locate_scan, place_scan, point_times

__all__ = [
    'ConnectivityError',
    'ExtrapolationError',
    'Placement',
    'Rigid',
    'ScanPose',
    'TransformBuffer',
    'TransformError',
    'UnknownFrameError',
    'locate_scan',
    'place_scan',
    'point_times',
    'rotations',
]
