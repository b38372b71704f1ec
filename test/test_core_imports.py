"""Dependencies point one way: apps -> node -> msg_adapters -> core.

The core (``uncertain_facade_map``) imports numerics only: no ROS package, no rosbags, and
none of the layers above it, neither at the top of a module nor inside a function
(``ast.walk`` sees every import statement, lazy ones included). ``msg_adapters`` imports
neither the node nor the applications; the node does not import the applications.
"""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
STDLIB = set(sys.stdlib_module_names)
#: What each layer may import besides the standard library and the layers below it.
LAYERS = {
    # laspy, pypcd4, lzf: file formats; octomap, threadpoolctl: baselines; matplotlib: the
    # evaluation report's figures; pypatchworkpp: ground removal of clouds without classes
    # (selection.building_points); pyarrow: Argoverse 2's feather files (io.av2) (each imported
    # inside the function that needs it); numba: compiled kernels of the hot paths (issue 27).
    'uncertain_facade_map': {'numpy', 'scipy', 'sklearn', 'yaml', 'plyfile', 'laspy', 'pypcd4', 'lzf',
                             'threadpoolctl', 'octomap', 'matplotlib', 'pypatchworkpp', 'pyarrow', 'numba',
                             'uncertain_facade_map'},
    'msg_adapters': {'numpy', 'rosbags', 'msg_adapters', 'uncertain_facade_map', 'builtin_interfaces',
                     'diagnostic_msgs', 'geometry_msgs', 'nav_msgs', 'sensor_msgs', 'std_msgs', 'tf2_msgs',
                     'visualization_msgs', 'rcl_interfaces'},
    'uncertain_facade_map_node': {'numpy', 'rclpy', 'msg_adapters', 'uncertain_facade_map', 'uncertain_facade_map_node',
                                  'builtin_interfaces', 'diagnostic_msgs', 'geometry_msgs', 'nav_msgs', 'sensor_msgs',
                                  'std_msgs', 'std_srvs', 'tf2_msgs', 'visualization_msgs', 'rcl_interfaces'},
}
#: The core's generated interfaces (``uncertain_facade_map.msg``/``.srv``) are ROS: only above the core.
ROS_OF_CORE = ('uncertain_facade_map.msg', 'uncertain_facade_map.srv')
BLOCKED = ['rclpy', 'rosbags', 'msg_adapters', 'uncertain_facade_map_node', 'uncertain_facade_map_apps', 'sensor_msgs',
           'std_msgs', 'builtin_interfaces', 'rosidl_runtime_py']


def imports_of(path: Path) -> list[tuple[int, str]]:
    """Every absolute module a file imports, at any depth, with its line."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out += [(node.lineno, node.module)]
            out += [(node.lineno, f'{node.module}.{a.name}') for a in node.names if node.module == 'uncertain_facade_map']
    return out


@pytest.mark.parametrize('layer', sorted(LAYERS))
def test_each_layer_imports_only_what_lies_below_it(layer):
    allowed = LAYERS[layer]
    wrong = []
    for path in sorted((REPO / layer).rglob('*.py')):
        for line, name in imports_of(path):
            root = name.split('.')[0]
            ros_of_core = layer == 'uncertain_facade_map' and name.startswith(ROS_OF_CORE)
            if (root not in STDLIB and root not in allowed) or ros_of_core:
                wrong.append(f'{path.relative_to(REPO)}:{line} imports {name}')
    assert not wrong, '\n'.join(wrong)


def test_the_checker_sees_imports_inside_functions(tmp_path):
    module = tmp_path / 'lazy.py'
    module.write_text('def f():\n    from uncertain_facade_map_node.replay import publish_scans\n'
                      '    import rclpy\n')
    assert [n for _, n in imports_of(module)] == ['uncertain_facade_map_node.replay', 'rclpy']


IMPORT_ALL = f'''
import importlib, importlib.abc, pkgutil, sys
BLOCKED = {BLOCKED!r}

class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in BLOCKED:
            raise ImportError('blocked for this test: ' + name)
        return None

sys.meta_path.insert(0, Block())
import uncertain_facade_map
names = [m.name for m in pkgutil.walk_packages(uncertain_facade_map.__path__, 'uncertain_facade_map.')
         if not m.name.startswith(('uncertain_facade_map.msg', 'uncertain_facade_map.srv'))]
for name in names:
    importlib.import_module(name)
loaded = sorted(m for m in sys.modules if m.split('.')[0] in BLOCKED)
assert not loaded, loaded
print(len(names))
'''


def test_every_core_module_imports_with_ros_and_the_upper_layers_blocked():
    result = subprocess.run([sys.executable, '-c', IMPORT_ALL], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert int(result.stdout.strip()) >= 25


def test_reading_a_cloud_does_not_load_the_model():
    """io and params are light: reading and selecting points loads neither the pipeline nor scikit-learn."""
    code = ('import sys\nfrom uncertain_facade_map.io.inputs import load_inputs, select_building_points\n'
            'from uncertain_facade_map.io.parameter_file import load_config\n'
            'print(sorted(m for m in sys.modules if m.startswith(("sklearn", "uncertain_facade_map.pipeline", '
            '"uncertain_facade_map.mapping"))))')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == '[]'
