"""Exceptions of the core.

Every error a user can cause (a missing file, wrong fields, NaN, an empty cloud, a
malformed map file, a bad parameter) is raised as an :class:`InputError`, so that the
command line and the node can turn it into a one-line message instead of a traceback.
"""


class FacadeMapError(Exception):
    """Base class of the errors raised by uncertain_facade_map."""


class InputError(FacadeMapError, ValueError):
    """Input data, files or parameters that cannot be used, with the reason."""


# The keyword arguments of the transform errors have defaults so that the errors pickle
# (an exception is rebuilt from its message, then its attributes are restored).


class TransformError(InputError):
    """A transform that cannot be stored, or looked up, in a :class:`TransformBuffer`.

    Raised for malformed transforms (empty or equal frame names, NaN, a quaternion that is
    not a rotation, a frame given a second parent) and, through the subclasses, for
    lookups that cannot be answered.
    """


class UnknownFrameError(TransformError):
    """A lookup names a frame the buffer has never seen.

    Attributes:
        frame: the unknown frame's name.
        known: the frames the buffer knows, sorted.
    """

    def __init__(self, message: str, *, frame: str = '', known: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.frame = frame
        self.known = tuple(known)


class ConnectivityError(TransformError):
    """Both frames are known but lie in two separate trees: no chain joins them.

    Attributes:
        target, source: the frames of the lookup.
        target_root, source_root: the root (frame without parent) of each one's tree.
    """

    def __init__(self, message: str, *, target: str = '', source: str = '', target_root: str = '',
                 source_root: str = '') -> None:
        super().__init__(message)
        self.target, self.source = target, source
        self.target_root, self.source_root = target_root, source_root


class ExtrapolationError(TransformError):
    """A dynamic edge of the chain has no sample at or around the requested time.

    Attributes:
        frame: the child frame of the edge that lacks data.
        parent: that edge's parent frame.
        stamp_ns: the requested time, integer nanoseconds.
        first_ns, last_ns: the oldest and newest kept sample of the edge.
        future: True when ``stamp_ns`` is after the newest sample (waiting for more data can
            help); False when it is before the oldest kept sample (it never will).
    """

    def __init__(self, message: str, *, frame: str = '', parent: str = '', stamp_ns: int = 0, first_ns: int = 0,
                 last_ns: int = 0, future: bool = False) -> None:
        super().__init__(message)
        self.frame, self.parent = frame, parent
        self.stamp_ns, self.first_ns, self.last_ns = int(stamp_ns), int(first_ns), int(last_ns)
        self.future = bool(future)
