"""The core imports without ROS: no rclpy, no rosbags, no message packages."""

import ast
import subprocess
import sys
from pathlib import Path

CORE = Path(__file__).resolve().parents[1] / 'uncertain_facade_map'
ALLOWED_TOP_LEVEL = {'numpy', 'scipy', 'sklearn', 'yaml', 'plyfile', 'uncertain_facade_map'}
BLOCKED = ['rclpy', 'rosbags', 'msg_adapters', 'sensor_msgs', 'std_msgs', 'builtin_interfaces', 'rosidl_runtime_py']

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
names = [m.name for m in pkgutil.walk_packages(uncertain_facade_map.__path__, 'uncertain_facade_map.')]
for name in names:
    importlib.import_module(name)
loaded = sorted(m for m in sys.modules if m.split('.')[0] in BLOCKED)
assert not loaded, loaded
print(len(names))
'''


def test_every_core_module_imports_with_ros_blocked():
    result = subprocess.run([sys.executable, '-c', IMPORT_ALL], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert int(result.stdout.strip()) >= 10


def test_core_modules_import_only_numerics_at_top_level():
    stdlib = set(sys.stdlib_module_names)
    for path in CORE.rglob('*.py'):
        tree = ast.parse(path.read_text())
        for node in tree.body:  # top level only; lazy imports inside functions are allowed
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module]
            for name in names:
                root = name.split('.')[0]
                assert root in stdlib or root in ALLOWED_TOP_LEVEL, f'{path.name} imports {name}'
