"""The ROS 2 nodes: wiring of :mod:`msg_adapters` and the core.

- ``node``: ``facade_mapper``, wiring of the parts (docs/node.md, "The node's parts");
- ``listener``: :class:`PoseListener`, the pose topics into one transform buffer;
- ``publisher``: :class:`MapPublisher`, the latched map products;
- ``runtime``: parameters declared, guarded callbacks, the service check, the executor's run;
- ``localizer``: ``facade_localizer``, scans localised against the mapper's queries;
- ``replay``: recorded scans published to a running node.
"""
