"""Print a requirements.lock for the running environment.

The ros-jazzy-* wheels also ship egg-info metadata for the ROS packages inside them
(``rclpy``, ``sensor_msgs`` ...); those are not installable names, so only
``.dist-info`` distributions are pinned.
"""

import importlib.metadata as md

SKIP = {'pip', 'setuptools', 'wheel', 'uncertain-facade-map', 'uncertain_facade_map'}


def main() -> None:
    """Print one ``name==version`` line per installed distribution."""
    rows = set()
    for dist in md.distributions():
        name = dist.metadata['Name']
        if str(getattr(dist, '_path', '')).endswith('.dist-info') and name.lower() not in SKIP:
            rows.add(f'{name}=={dist.version}')
    print('# Pinned environment for uncertain_facade_map (make venv installs exactly this).')
    print('# Regenerate with: make lock   (after changing requirements.in)')
    print('\n'.join(sorted(rows, key=str.lower)))


if __name__ == '__main__':
    main()
