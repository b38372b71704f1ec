"""Exceptions of the core.

Every error a user can cause (a missing file, wrong fields, NaN, an empty cloud, a
malformed map file, a bad parameter) is raised as an :class:`InputError`, so that the
command line and the node can turn it into a one-line message instead of a traceback.
"""


class FacadeMapError(Exception):
    """Base class of the errors raised by uncertain_facade_map."""


class InputError(FacadeMapError, ValueError):
    """Input data, files or parameters that cannot be used, with the reason."""
