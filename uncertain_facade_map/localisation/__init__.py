"""Localisation against the uncertain map (issue 28): the 6-DoF pose of a scan from a prior
and the map's answers, weighted by the map's variance.

Modules (numpy and scipy only):

* :mod:`.se3` -- exp/log of SO(3) and SE(3), their left Jacobians, ``skew``, ``compose``.
* :mod:`.solver` -- :func:`localise` and :class:`PoseEstimate` (the model, the rounds of map
  queries and Levenberg-Marquardt, the covariance: see its docstring).
* :mod:`.queries` -- :func:`map_query`, a map's ``query`` with surface normals.
* :mod:`.poses` -- poses from x, y, z, roll, pitch, yaw and back, prior covariances from
  standard deviations.
"""

from .poses import covariance_from_std, pose_from_xyzrpy, xyzrpy_from_pose
from .queries import map_query
from .solver import PoseEstimate, localise

__all__ = ['PoseEstimate', 'covariance_from_std', 'localise', 'map_query', 'pose_from_xyzrpy', 'xyzrpy_from_pose']
