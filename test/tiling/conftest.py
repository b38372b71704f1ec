"""The small scene's map of both its buildings, with sensor origins (built once per session)."""

import numpy as np
import pytest

from uncertain_facade_map.mapping.facade_map import build_map


@pytest.fixture(scope='session')
def small_whole(scenes):
    cloud = scenes.campaign('small', 0)
    pts = cloud.points[cloud.points['class'] == 1]
    xyz = np.stack([pts['x'], pts['y'], pts['z']], 1)
    origins = np.stack([pts['origin_x'], pts['origin_y'], pts['origin_z']], 1)
    return build_map(xyz, pts['building_id'], origins, map_origin=cloud.map_origin)
