"""Applications on top of the core, msg_adapters and the node: what a user runs.

- ``cli``: the ``uncertain-facade-map`` command line (simulate, build, query, replay, plot,
  evaluate, benchmark);
- ``plots``: the paper's figures of a map and the benchmark's figure (matplotlib, headless);
- ``bench``: ``make bench``, throughput and memory of the hot paths;
- ``demo``: ``make demo``, the street drive mapped live by the node, queried, saved, drawn.

The only layer that may import all the others: the command line reads bags through
``msg_adapters`` and publishes through ``uncertain_facade_map_node.replay``.
"""
