"""A sensor trajectory: where the sensor was at each time, for clouds without per-point origins.

A trajectory file is text, one pose per line: ``t x y z`` followed by anything (so the TUM
format ``t x y z qx qy qz qw`` is read as it is); values separated by spaces, tabs or
commas; empty lines, lines starting with ``#`` and a header line that is not numbers are
skipped. ``t`` is in seconds on the time base of the clouds' ``time`` field (a LAS file's
``gps_time``); ``x, y, z`` in metres in the clouds' own coordinates (the files' x, y, z,
georeferenced: a map origin is subtracted by the reader of the clouds, not by the user).

Each point's sensor origin is the trajectory's position at the point's time, linearly
interpolated between the two poses around it. A point more than ``tolerance`` seconds
outside the trajectory's time span is an error: its origin would be a guess.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ._files import PathLike, _existing_file

__all__ = ['Trajectory', 'read_trajectory']

_SEPARATORS = re.compile(r'[\s,;]+')


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Sensor positions over time.

    Attributes:
        time: (M,) float64 seconds, strictly increasing, M >= 1.
        position: (M, 3) float64 metres, the clouds' coordinates.
    """

    time: np.ndarray
    position: np.ndarray

    def __post_init__(self) -> None:
        time = np.asarray(self.time, dtype=np.float64)
        position = np.asarray(self.position, dtype=np.float64)
        if time.ndim != 1 or len(time) == 0 or position.shape != (len(time), 3):
            raise InputError(f'a trajectory needs M >= 1 times and (M, 3) positions, got {time.shape} and '
                             f'{position.shape}')
        if not (np.isfinite(time).all() and np.isfinite(position).all()):
            raise InputError('a trajectory holds NaN or infinite values')
        if len(time) > 1 and not (np.diff(time) > 0).all():
            at = int(np.flatnonzero(np.diff(time) <= 0)[0])
            raise InputError(f'trajectory times must increase strictly: pose {at + 2} at t={time[at + 1]!r} '
                             f'follows t={time[at]!r}')
        object.__setattr__(self, 'time', time)
        object.__setattr__(self, 'position', position)

    def __len__(self) -> int:
        return int(len(self.time))

    def positions_at(self, times: np.ndarray, tolerance: float = 0.1) -> np.ndarray:
        """The sensor's position at each time, linearly interpolated.

        Args:
            times: (N,) seconds, the trajectory's time base.
            tolerance: seconds a time may lie before the first or after the last pose (it
                then takes that pose's position).

        Returns:
            (N, 3) float64 metres, the trajectory's coordinates.

        Raises:
            InputError: a time that is not finite or lies more than ``tolerance`` outside
                the trajectory's span (the message says how many and the spans).
        """
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        if not np.isfinite(t).all():
            raise InputError(f'{int((~np.isfinite(t)).sum())} of {len(t)} point times are NaN or infinite')
        outside = (t < self.time[0] - tolerance) | (t > self.time[-1] + tolerance)
        if outside.any():
            raise InputError(f'{int(outside.sum())} of {len(t)} point times lie outside the trajectory '
                             f'({self.time[0]!r} to {self.time[-1]!r} s, tolerance {tolerance} s); points span '
                             f'{t.min()!r} to {t.max()!r} s: is the trajectory on the clouds\' time base?')
        return np.stack([np.interp(t, self.time, self.position[:, k]) for k in range(3)], axis=1)


def _numbers(fields: list[str]) -> list[float] | None:
    try:
        return [float(v) for v in fields]
    except ValueError:
        return None


def read_trajectory(path: PathLike) -> Trajectory:
    """Read a trajectory file (see the module's docstring for the format).

    Args:
        path: a text file, ``t x y z [...]`` per line.

    Returns:
        The trajectory in the file's order, which must be the time order.

    Raises:
        InputError: no such file; a line with fewer than four numbers (the message gives its
            number); no pose at all; times not strictly increasing; NaN or infinite values.
    """
    name = _existing_file(path)
    rows: list[list[float]] = []
    try:
        with open(name, encoding='utf-8') as f:
            for number, line in enumerate(f, start=1):
                text = line.strip()
                if not text or text.startswith('#'):
                    continue
                fields = [v for v in _SEPARATORS.split(text) if v]
                values = _numbers(fields[:4])
                if values is None and not rows and number == 1:
                    continue  # a header line
                if values is None or len(values) < 4:
                    raise InputError(f'{os.path.basename(name)} line {number}: expected t x y z, got {text[:80]!r}')
                rows.append(values)
    except UnicodeDecodeError as err:
        raise InputError(f'{name} is not a text trajectory file (t x y z per line)') from err
    if not rows:
        raise InputError(f'{name} holds no pose (t x y z per line)')
    data = np.array(rows, dtype=np.float64)
    try:
        return Trajectory(data[:, 0], data[:, 1:4])
    except InputError as err:
        raise InputError(f'{name}: {err}') from err
