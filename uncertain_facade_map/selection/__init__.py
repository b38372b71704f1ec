"""Building points of clouds that carry no class: ground removal, then tall vertical planes.

Most open lidar data has no building class; mapped as it is, ground, cars and trees
become "buildings" of their own. This sub-package picks the façade points of such a
cloud (numpy, scipy and, imported inside the function that needs it, ``pypatchworkpp``):

- ``building_points``: :func:`select_building_points`, (N, 3) points in, an (N,) mask of
  building points out, with :class:`Selection` saying what was found and why points were
  dropped, and :func:`selection_warning`, a one-line warning when a cloud kept too little;
  parameters in :class:`~uncertain_facade_map.params.SelectionConfig`;
- ``evaluation``: an independent wall picker and the selection's figures against it on
  real sweeps (``python -m uncertain_facade_map.selection.evaluation``).

:mod:`uncertain_facade_map.io.inputs` applies it to clouds without the class field
(``selection.mode``), for the command line and the node alike.
"""

from .building_points import DROP_RULES, Selection, select_building_points, selection_warning

__all__ = ['DROP_RULES', 'Selection', 'select_building_points', 'selection_warning']
