"""The map folder: where the node's services may read and write maps (issue 38).

Any participant of the robot's DDS domain can call ``save_map`` and ``load_map``; ROS 2
without SROS2 authenticates nobody. So the services take their ``path`` inside one folder
(``persistence.map_dir``) and refuse, with a message naming the rule:

- a name that leads out of it: an absolute path elsewhere, ``..``, or a symbolic link (of
  the name or of a folder on its way) that points out; relative names are taken in the
  folder; ``persistence.allow_any_path`` lifts this rule, and only this one;
- a save over anything but a map file of this package (checked here and again just before
  the atomic rename, :func:`~uncertain_facade_map.io.map_file.save_map`), or under a name
  without the map suffix ``.npz``;
- a load of a map file, or a tiled map's manifest, larger than ``persistence.max_load_mb``
  on disk or unpacked (read from the zip's directory, before the file is read); a tiled map
  whose tiles' files lead out of its folder (through a symbolic link: the manifest itself
  refuses absolute and ``..`` names).

The command line is not confined: a user on the shell owns their files.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError
from .map_file import is_map_file, unpacked_bytes

__all__ = ['MAP_SUFFIX', 'DEFAULT_DIR', 'MapFolder', 'PathRefused']

#: The suffix of the map files ``save_map`` writes.
MAP_SUFFIX = '.npz'
#: The map folder under the working directory when neither ``persistence.map_dir`` nor
#: ``persistence.map_path`` names one.
DEFAULT_DIR = 'maps'


class PathRefused(InputError):
    """A path a service was given that the map folder's rules refuse (the message names the rule)."""


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


@dataclass(frozen=True)
class MapFolder:
    """The folder ``save_map`` and ``load_map`` resolve their paths in.

    Attributes:
        root: the folder, absolute (it need not exist yet: ``save_map`` creates it).
        allow_any: any path is accepted (``persistence.allow_any_path``); the other rules hold.
        max_load_bytes: largest map file or manifest a load reads, bytes.
    """

    root: Path
    allow_any: bool = False
    max_load_bytes: int = 4096 * 2**20

    @classmethod
    def of(cls, map_dir: str, map_path: str, allow_any: bool = False, max_load_mb: float = 4096.0,
           cwd: str | os.PathLike | None = None) -> MapFolder:
        """The folder of the node's ``persistence`` parameters: ``map_dir``, else the folder of
        ``map_path``, else :data:`DEFAULT_DIR`; relative ones under ``cwd`` (default: the
        working directory)."""
        base = Path(os.getcwd() if cwd is None else cwd)
        folder = Path(map_dir) if map_dir else Path(map_path).parent if map_path else Path(DEFAULT_DIR)
        return cls(Path(os.path.abspath(base / folder)), bool(allow_any), int(max_load_mb * 2**20))

    def resolve(self, name: str) -> Path:
        """The path a service's ``name`` stands for: absolute, links and ``..`` resolved.

        Raises:
            PathRefused: empty, or (unless :attr:`allow_any`) leading out of the folder.
        """
        if not isinstance(name, str) or not name.strip() or '\x00' in name:
            raise PathRefused(f'{name!r}: not a file name')
        target = Path(name) if os.path.isabs(name) else self.root / name
        real = Path(os.path.realpath(target))
        if not self.allow_any and not _inside(real, Path(os.path.realpath(self.root))):
            raise PathRefused(
                f'"{name}" leads outside the map folder {self.root} (persistence.map_dir): the services read and '
                'write maps only in it; names are taken in it; absolute paths, ".." and symbolic links that lead '
                'out are refused (persistence.allow_any_path lifts this rule)')
        return real

    def save_path(self, name: str) -> Path:
        """Where ``save_map`` may write the map it was asked to write to ``name``.

        Raises:
            PathRefused: out of the folder, no ``.npz`` suffix, a folder, or an existing
                file that is not a map file.
        """
        path = self.resolve(name)
        if path.suffix != MAP_SUFFIX:
            raise PathRefused(f'"{name}": save_map writes map files named *{MAP_SUFFIX} only')
        if path.is_dir():
            raise PathRefused(f'"{name}" is a folder; save_map writes a map file (*{MAP_SUFFIX})')
        if os.path.lexists(path) and not is_map_file(path):
            raise PathRefused(f'{path} exists and is not a map file of uncertain_facade_map: not replaced '
                              '(save_map replaces map files only)')
        return path

    def load_path(self, name: str) -> Path:
        """The map file or tiled map ``load_map`` may read for ``name``.

        Raises:
            PathRefused: out of the folder, larger than :attr:`max_load_bytes`, or a tiled
                map whose tiles lead out of its folder.
            InputError: a tiled map's manifest that cannot be read.
        """
        from ..tiling.manifest import is_tiled_map, manifest_path, read_manifest

        path = self.resolve(name)
        if is_tiled_map(path):
            manifest = manifest_path(path)
            self._check_size(manifest, manifest.stat().st_size, name)
            folder = Path(os.path.realpath(manifest.parent))
            for record in read_manifest(manifest).tiles.values():
                tile = Path(os.path.realpath(folder / record.file))
                if not _inside(tile, folder):
                    raise PathRefused(f'"{name}": tile {record.id}\'s file {record.file} leads outside the tiled '
                                      f'map\'s folder {folder}; a tiled map\'s tiles must lie in its folder')
        elif path.is_file():
            self._check_size(path, unpacked_bytes(path), name)
        return path

    def _check_size(self, path: Path, size: int, name: str) -> None:
        if size > self.max_load_bytes:
            raise PathRefused(f'"{name}": {path} holds {size / 2**20:.1f} MB, more than persistence.max_load_mb '
                              f'({self.max_load_bytes / 2**20:g} MB): not read')
