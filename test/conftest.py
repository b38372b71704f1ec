"""Fixtures shared by the whole test tree.

The simulated scenes are deterministic by seed and take seconds to build and scan, so each
is built once per test session and shared (read-only: tests that change a cloud copy it).
This folder is on ``sys.path`` (pytest's rootdir conftest), so tests import the helpers of
``support.py`` as ``from support import ...``.
"""

from __future__ import annotations

import numpy as np
import pytest

from uncertain_facade_map.mapping.facade_map import build_map
from uncertain_facade_map.simulation.campaign import simulate_campaign
from uncertain_facade_map.simulation.scenes import build_scene


class _Scenes:
    """Scenes and their campaigns, built on first use and kept for the session."""

    def __init__(self) -> None:
        self._scenes: dict = {}
        self._clouds: dict = {}

    def scene(self, name: str, seed: int = 0):
        """The scene ``name`` (``small``, ``street`` or ``zurich``) with ``seed``."""
        key = (name, seed)
        if key not in self._scenes:
            self._scenes[key] = build_scene(name, seed)
        return self._scenes[key]

    def campaign(self, name: str, index: int = 0, seed: int = 0):
        """Campaign ``index`` of the scene, with the scene's default sensor (a Cloud; do not modify)."""
        key = (name, seed, index)
        if key not in self._clouds:
            self._clouds[key] = simulate_campaign(self.scene(name, seed), index)
        return self._clouds[key]

    def building_points(self, name: str, index: int = 0, seed: int = 0):
        """The building points (class 1) of campaign ``index``: (N, 3) xyz, (N,) int64 building ids
        and (N, 3) sensor origins, metres, map frame (new arrays, free to change)."""
        pts = self.campaign(name, index, seed).points
        pts = pts[pts['class'] == 1]
        return (np.stack([pts['x'], pts['y'], pts['z']], 1), pts['building_id'].astype(np.int64),
                np.stack([pts['origin_x'], pts['origin_y'], pts['origin_z']], 1))

    def building_map(self, name: str, index: int = 0, map_origin=None, seed: int = 0):
        """A new map (default parameters) of campaign ``index``'s building points with their ids and
        sensor origins, georeferenced at ``map_origin`` (default: the campaign's)."""
        origin = self.campaign(name, index, seed).map_origin if map_origin is None else map_origin
        return build_map(*self.building_points(name, index, seed), map_origin=origin)


@pytest.fixture(scope='session')
def scenes() -> _Scenes:
    """Simulated scenes and campaigns, each built once per session: ``scenes.scene('small')``,
    ``scenes.campaign('street', 0)``."""
    return _Scenes()
