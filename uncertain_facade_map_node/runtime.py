"""What every node of the package shares: parameters declared from their one declaration,
callbacks no exception escapes, the look for other nodes offering the same services, and
the executor's run until Ctrl-C."""

from __future__ import annotations

import difflib
import functools
import sys
from typing import Any, Callable

from rclpy.exceptions import ParameterException

from msg_adapters import parameters as mp_params
from uncertain_facade_map.errors import FacadeMapError, InputError
from uncertain_facade_map.params import Config, config_from_parameters, node_sections, parameters

__all__ = ['ServiceCheck', 'declare_config', 'failed', 'guarded', 'spin']

#: Parameters every rclpy node has, besides the declared ones.
_BUILTIN_PARAMETERS = frozenset({'use_sim_time', 'start_type_description_service'})
#: Seconds between the looks for other nodes offering a node's services, after start.
SERVICE_CHECK_DELAY = 3.0
#: How many looks (discovery may take several seconds; a warning ends them).
SERVICE_CHECKS = 20


def declare_config(node: Any, sections: tuple[str, ...] | None = None) -> Config:
    """Declare every parameter of ``sections`` (default: the mapper's, :func:`node_sections`) on
    ``node`` (read-only, with its descriptor) and read the configuration (the other
    sections at their defaults).

    The node's parameter path: each parameter's default, description, unit, range and
    relations come from its declaration (:mod:`uncertain_facade_map.params`); rclpy checks
    the advertised range of a ``-p`` or parameter-file override, then the declarations
    check everything (open ends, relations).

    Raises:
        InputError: a parameter of the wrong type, out of its range or breaking a relation,
            with a message naming it.
    """
    types = mp_params.rclpy_parameter_types()
    values = {}
    for info in parameters(sections=node_sections() if sections is None else sections):
        default = list(info.value) if info.is_list else info.value
        try:
            node.declare_parameter(info.name, default, mp_params.parameter_descriptor(info, types))
        except ParameterException as exc:
            raise InputError(f'parameter {info.name}: {" ".join(str(exc).split())} '
                             f'(allowed: {info.spec.constraint_text() or "any " + info.type.__name__})') from exc
        values[info.name] = mp_params.parameter_value(node.get_parameter(info.name).value)
    _refuse_unknown_overrides(node, set(values))
    return config_from_parameters(values)


def _refuse_unknown_overrides(node: Any, declared: set[str]) -> None:
    """Raise InputError for a ``-p`` or parameter-file override that names no parameter
    (rclpy would ignore it silently), with the closest declared names."""
    overrides = getattr(node, '_parameter_overrides', None) or {}
    unknown = sorted(set(overrides) - declared - _BUILTIN_PARAMETERS)
    if unknown:
        name = unknown[0]
        close = difflib.get_close_matches(name, sorted(declared), n=3, cutoff=0.6)
        hint = f'; did you mean {" or ".join(close)}?' if close else ''
        more = f' (and {", ".join(unknown[1:])})' if len(unknown) > 1 else ''
        raise InputError(f'unknown parameter {name}{more}{hint}')


def failed(node: Any, accounts: Any, name: str, exc: Exception) -> bool:
    """Log and count (``callback_errors``) that ``name`` failed with ``exc`` in ``node``;
    False, and nothing logged, while the node stops (``node.stopping``, or its context is
    shut down by Ctrl-C: publishers and helper processes are going, not broken)."""
    if getattr(node, 'stopping', False) or not node.context.ok():
        return False
    accounts.event('callback_error', f'{name} failed: {type(exc).__name__}: {exc}')
    node.get_logger().error(f'{name} failed: {type(exc).__name__}: {exc}', throttle_duration_sec=5.0)
    return True


def guarded(callback: Callable[..., Any]) -> Callable[..., Any]:
    """No exception escapes ``callback``, a method of a node with ``accounts`` and ``stopping``
    (it would end the executor, and the node): it is logged and counted, and a service
    answers ``success = False`` with the reason."""
    @functools.wraps(callback)
    def run(self: Any, *args: Any) -> Any:
        try:
            return callback(self, *args)
        except Exception as exc:  # noqa: BLE001 - the node must live on
            response = args[1] if len(args) == 2 else None
            if not failed(self, self.accounts, callback.__name__, exc):
                return response
            if response is not None and hasattr(response, 'success'):
                response.success = False
                if hasattr(response, 'message'):
                    response.message = f'internal error: {type(exc).__name__}: {exc}'
            return response
    return run


class ServiceCheck:
    """For the first minute after start: warn (once) when another node offers one of
    ``node``'s services (``names``, relative), or is called as it is."""

    def __init__(self, node: Any, names: tuple[str, ...], group: Any) -> None:
        self._node = node
        self._names = names
        self._looks = 0
        self._timer = node.create_timer(SERVICE_CHECK_DELAY, self.check_callback, callback_group=group)

    def check_callback(self) -> None:
        node = self._node
        self._looks += 1
        if self._looks >= SERVICE_CHECKS:
            self._timer.cancel()
        try:
            mine = {node.resolve_service_name(n) for n in self._names}
            me = (node.get_name(), node.get_namespace())
            advice = ('clients may reach either node. Give each mapper its own namespace '
                      '(--ros-args -r __ns:=/robot1) or remap the services')
            nodes = node.get_node_names_and_namespaces()
            if nodes.count(me) > 1:  # a twin: same name, hence the same services
                self._timer.cancel()
                node.get_logger().warning(f'another node is called {node.get_fully_qualified_name()} and offers '
                                          f'the same services: {advice}')
            for name, namespace in set(nodes) - {me}:
                offered = {s for s, _ in node.get_service_names_and_types_by_node(name, namespace)}
                shared = sorted(mine & offered)
                if shared:
                    self._timer.cancel()
                    full = namespace.rstrip('/') + '/' + name
                    node.get_logger().warning(f'node {full} offers {", ".join(shared)} too: {advice}')
        except Exception as exc:  # noqa: BLE001 - a check, not a duty
            node.get_logger().debug(f'service check skipped: {exc}')


def spin(factory: Callable[[], Any], name: str, args: list[str] | None = None, threads: int = 4) -> None:
    """Start rclpy, run the node ``factory()`` on a multi-threaded executor until Ctrl-C or
    shutdown, and clean up; a :class:`FacadeMapError` (bad parameters, say) ends the process
    with its message and status 2."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor

    rclpy.init(args=args)
    node = None
    try:
        node = factory()
        executor = MultiThreadedExecutor(num_threads=threads)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except FacadeMapError as exc:
        print(f'{name}: {exc}', file=sys.stderr)
        raise SystemExit(2) from None
    finally:
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
