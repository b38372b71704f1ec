"""ROS 2 parameters <-> the declarations of :mod:`uncertain_facade_map.params`.

:func:`parameter_descriptor` turns a parameter's declaration into a read-only
``rcl_interfaces/ParameterDescriptor``: its description with unit and allowed values, the
relations it takes part in as ``additional_constraints``, and its interval as an integer
or floating-point range. ROS ranges are closed, so an open end is advertised as the
nearest value inside it (:meth:`~uncertain_facade_map.params.Interval.closed_range`):
every advertised value is accepted, and the exact interval is in the description.

:func:`parameter_value` turns a value as rclpy returns it (lists for arrays) into the
value the declarations check (tuples).
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from uncertain_facade_map.params import ParameterInfo

__all__ = ['parameter_descriptor', 'parameter_value', 'rclpy_parameter_types']


def rclpy_parameter_types() -> SimpleNamespace:
    """rclpy's ``ParameterDescriptor``, ``IntegerRange`` and ``FloatingPointRange`` classes.

    Raises:
        ImportError: rcl_interfaces is not installed.
    """
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

    return SimpleNamespace(ParameterDescriptor=ParameterDescriptor, IntegerRange=IntegerRange,
                           FloatingPointRange=FloatingPointRange)


def parameter_descriptor(info: ParameterInfo, types: Any, read_only: bool = True) -> Any:
    """A ``ParameterDescriptor`` message for one parameter.

    Args:
        info: the parameter (:func:`uncertain_facade_map.params.parameters`).
        types: a namespace with ``ParameterDescriptor``, ``IntegerRange`` and
            ``FloatingPointRange`` classes (:func:`rclpy_parameter_types`).
        read_only: the node reads its parameters once, at start.

    Returns:
        The descriptor: ``name``, ``description`` (description (unit; allowed values)),
        ``additional_constraints`` (allowed values and relations), ``read_only`` and, for an
        interval, ``integer_range`` or ``floating_point_range`` (step 0).
    """
    spec = info.spec
    extra = spec.constraint_text()
    constraints = [str(spec.allowed)] if spec.allowed is not None else []
    constraints += [f'need {rel.text}' for rel in info.relations]
    d = types.ParameterDescriptor(name=info.name, description=spec.description + (f' ({extra})' if extra else ''),
                                  additional_constraints='; '.join(constraints), read_only=read_only)
    bounds = info.closed_range()
    if bounds is not None:
        if info.type is int:
            d.integer_range = [types.IntegerRange(from_value=int(bounds[0]), to_value=int(bounds[1]), step=0)]
        else:
            d.floating_point_range = [types.FloatingPointRange(from_value=float(bounds[0]), to_value=float(bounds[1]),
                                                               step=0.0)]
    return d


def parameter_value(value: Any) -> Any:
    """A parameter value as the declarations check it: arrays (lists, ``array.array``) as tuples."""
    if isinstance(value, (str, bytes)) or not hasattr(value, '__len__'):
        return value
    return tuple(value)
