"""The small scene's map of both its buildings, with sensor origins (built once per session)."""

import pytest


@pytest.fixture(scope='session')
def small_whole(scenes):
    return scenes.building_map('small', 0)
