"""Python packaging for uncertain_facade_map.

The project's own environment installs it with ``pip install -e .`` in setuptools' compat
mode (``make venv``; the ROS interfaces are built by CMake, see the Makefile); in a colcon
workspace CMakeLists.txt installs the same Python packages next to the generated interfaces.
"""

from setuptools import find_packages, setup

PACKAGE = 'uncertain_facade_map'

setup(
    name=PACKAGE,
    version='0.1.0',
    description='Façade maps with calibrated uncertainty: GMM depth layers + local GP blocks (ROS 2 Jazzy)',
    license='MIT',
    python_requires='==3.11.*',
    packages=find_packages(include=[PACKAGE, f'{PACKAGE}.*', 'msg_adapters', 'msg_adapters.*',
                                    'uncertain_facade_map_node', 'uncertain_facade_map_node.*',
                                    'uncertain_facade_map_apps', 'uncertain_facade_map_apps.*']),
    package_data={PACKAGE: ['py.typed'],
                  # the zurich scene's CityJSON (cjio test data, MIT) with its licence and README
                  f'{PACKAGE}.simulation': ['data/*.json', 'data/*.txt', 'data/*.md']},
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/config', ['config/facade_mapper.yaml', 'config/facade_localizer.yaml']),
    ],
    install_requires=['numpy', 'scipy', 'scikit-learn', 'rosbags', 'pyyaml', 'plyfile', 'tqdm'],
    entry_points={
        'console_scripts': [
            'uncertain-facade-map = uncertain_facade_map_apps.cli:main',
            'facade_mapper = uncertain_facade_map_node.node:main',
            'facade_localizer = uncertain_facade_map_node.localizer:main',
        ],
    },
)
