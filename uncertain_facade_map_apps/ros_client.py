"""A ROS 2 process beside the facade_mapper node: its own context, node and spinning thread.

The soak suite (:mod:`uncertain_facade_map_apps.soak`) and the node's tests drive the node
from another process as a localisation node would; both build on :class:`SpinningClient`,
and both ask and read ``query_points`` with :func:`query_request` and :func:`answers_of`.
"""

from __future__ import annotations

import concurrent.futures
import queue
import threading
from typing import Any, Callable

import numpy as np

__all__ = ['ANSWER_KEYS', 'SpinningClient', 'answers_of', 'list_tiles_request', 'query_request', 'tiles_of']

#: The per-point answers of ``query_points``, in the response's order.
ANSWER_KEYS = ('facade', 'mean_depth', 'variance', 'noise_variance', 'signed_distance', 'p_occupied')


class SpinningClient:
    """An rclpy context of its own (domain ``domain``), one node in it, and a thread that
    spins its executor. A subclass creates its publishers and subscriptions in its
    ``__init__`` and then calls :meth:`_start`; afterwards entities are created and
    destroyed only through :meth:`on_spin_thread`.

    Args:
        name: the node's name.
        domain: ROS_DOMAIN_ID of the context.
        num_threads: threads of the executor (None: rclpy's default).
    """

    def __init__(self, name: str, domain: int, num_threads: int | None = None) -> None:
        import rclpy
        from rclpy.executors import MultiThreadedExecutor

        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = MultiThreadedExecutor(num_threads=num_threads, context=self.context)
        self.executor.add_node(self.node)
        self._stopping = False
        self._between_turns: queue.SimpleQueue = queue.SimpleQueue()
        self.thread = threading.Thread(target=self._spin, daemon=True, name=name)

    def _start(self) -> None:
        """Start spinning (after the subclass has created its entities)."""
        self.thread.start()

    def _spin(self) -> None:
        # A short timeout: entities created between turns join the wait set at the next turn.
        while not self._stopping and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)
            while True:
                try:
                    fn, future = self._between_turns.get_nowait()
                except queue.Empty:
                    break
                try:
                    future.set_result(fn())
                except Exception as exc:  # noqa: BLE001 - handed to the waiting thread
                    future.set_exception(exc)

    def on_spin_thread(self, fn: Callable[[], Any], timeout: float = 30.0) -> Any:
        """Run ``fn`` on the executor's thread between two turns and return its result.

        Entities (subscriptions, clients) must not be created or destroyed from another
        thread while the executor builds its wait set: rclpy raises InvalidHandle in the
        spinning thread, which then dies and the client hears nothing more.
        """
        future: concurrent.futures.Future = concurrent.futures.Future()
        self._between_turns.put((fn, future))
        return future.result(timeout)

    def close(self) -> None:
        """Stop spinning, destroy the node and shut the context down."""
        self._stopping = True
        self.thread.join(5)
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


def query_request(xyz: np.ndarray, resolution: float = 0.0, flat: bool = False) -> Any:
    """A ``QueryPoints`` request for (N, 3) map-frame points, metres (resolution 0: the node's
    default); ``flat``: in the request's ``xyz`` field, 3 numbers per point (no message per
    point: the fast way for large batches), else as ``geometry_msgs/Point`` messages."""
    from uncertain_facade_map.srv import QueryPoints

    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    request = QueryPoints.Request()
    if flat:
        from msg_adapters.map_messages import encode_array

        request.xyz = encode_array(xyz, 'd')
    else:
        from geometry_msgs.msg import Point

        request.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in xyz]
    request.resolution = float(resolution)
    return request


def answers_of(response: Any) -> dict[str, np.ndarray]:
    """The per-point answers of a ``QueryPoints`` response, as arrays by :data:`ANSWER_KEYS`,
    and ``normal`` as (N, 3) when the response carries it."""
    out = {k: np.asarray(getattr(response, k)) for k in ANSWER_KEYS}
    normal = getattr(response, 'normal', None)
    if normal is not None and len(normal) == 3 * len(out['facade']):
        out['normal'] = np.asarray(normal, dtype=np.float64).reshape(-1, 3)
    return out


def list_tiles_request(x: float, y: float, radius: float = 0.0) -> Any:
    """A ``ListTiles`` request: the tiles of the node's tiled map within ``radius`` metres
    (0: the node's ``tiles.radius``) of the map-frame position (``x``, ``y``), metres."""
    from uncertain_facade_map.srv import ListTiles

    return ListTiles.Request(x=float(x), y=float(y), radius=float(radius))


def tiles_of(response: Any) -> dict[str, Any]:
    """The tiles of a ``ListTiles`` response: ``ids``, ``bounds`` (K, 4: min_x, min_y, max_x,
    max_y, metres, map frame), ``files`` (absolute paths) and ``loaded`` (K,) bool
    (:func:`msg_adapters.map_messages.tiles_of_response`)."""
    from msg_adapters.map_messages import tiles_of_response

    return tiles_of_response(response)
