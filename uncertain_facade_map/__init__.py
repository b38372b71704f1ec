"""uncertain_facade_map: façade maps with a surface depth and a calibrated variance.

The package is the core of the project: numpy, scipy and scikit-learn only, arrays in and
arrays out, no ROS import anywhere (``test/test_core_imports.py`` enforces it). ROS message
conversion lives in the sibling package ``msg_adapters``.
"""

__version__ = '0.1.0'
__path__ = __import__('pkgutil').extend_path(__path__, __name__)
