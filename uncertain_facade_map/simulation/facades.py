"""Façade detail generator: windows, balconies, oriels, sloped parts, round bays, columns.

A façade is laid out as floors (along ``v``) and bays (along ``u``). Every bay of every
floor gets a window recess unless a larger feature takes the bay; special features are
asked for by a :class:`FacadeStyle`. All sizes are metres in the façade frame; the
ranges follow the project's issue: recesses 5 to 30 cm deep, balconies and oriels 0.3 to
1.5 m out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .scene import Block, Feature, Recess, Round, Slope

#: Distance kept free of detail at both ends of a wall, metres (corners stay solid).
END_MARGIN = 0.8


@dataclass(frozen=True)
class FacadeStyle:
    """Which special features a façade gets (windows are always there).

    Attributes:
        balconies: balconies on some bays of the upper floors.
        oriel: one box oriel over two bays and up to three upper floors.
        slope: a sloped plinth (wedge) in front of the ground floor of some bays.
        round_bay: a round bay (cylinder) over two bays of the upper floors.
        columns: half-columns on the ground floor between bays.
        windows: window and door recesses.
    """

    balconies: bool = False
    oriel: bool = False
    slope: bool = False
    round_bay: bool = False
    columns: bool = False
    windows: bool = True


def decorate(length: float, height: float, style: FacadeStyle, rng: np.random.Generator) -> tuple[Feature, ...]:
    """Lay out the detail of one façade.

    Args:
        length: wall length, metres.
        height: wall height, metres.
        style: special features wanted.
        rng: random source (the only source of variation).

    Returns:
        Features in the façade frame; none overlap except balconies in front of windows.
    """
    floor_h = float(rng.uniform(3.0, 3.5))
    n_floors = max(1, int(height // floor_h))
    bay_w = float(rng.uniform(2.4, 3.2))
    usable = length - 2 * END_MARGIN
    n_bays = int(usable // bay_w)
    if n_bays < 1:
        return ()
    bay_w = usable / n_bays
    centres = END_MARGIN + bay_w * (np.arange(n_bays) + 0.5)
    depth = float(rng.uniform(0.05, 0.30))
    taken: set[tuple[int, int]] = set()  # (bay, floor) cells given to a big feature
    features: list[Feature] = []
    upper = list(range(1, n_floors))

    def free_run(width: int, floors: list[int]) -> int | None:
        starts = [b for b in range(n_bays - width + 1)
                  if all((b + k, f) not in taken for k in range(width) for f in floors)]
        return int(rng.choice(starts)) if starts else None

    if style.oriel and upper and n_bays >= 3:
        floors = upper[:3]
        b = free_run(2, floors)
        if b is not None:
            features.append(Block(centres[b] - 0.45 * bay_w, centres[b + 1] + 0.45 * bay_w,
                                  floors[0] * floor_h - 0.3, (floors[-1] + 1) * floor_h - 0.2,
                                  float(rng.uniform(0.3, 1.0)), kind='oriel'))
            taken.update((b + k, f) for k in range(2) for f in floors)
    if style.round_bay and upper and n_bays >= 3:
        floors = upper[:3]
        b = free_run(2, floors)
        if b is not None:
            radius = float(rng.uniform(0.9, 1.4))
            out = float(rng.uniform(0.5, min(1.2, radius)))
            features.append(Round(0.5 * (centres[b] + centres[b + 1]), out - radius, radius,
                                  floors[0] * floor_h - 0.3, (floors[-1] + 1) * floor_h - 0.2, kind='bay'))
            taken.update((b + k, f) for k in range(2) for f in floors)
    if style.slope and n_bays >= 2:
        width = min(n_bays, 2 + int(rng.integers(0, 2)))
        b = free_run(width, [0])
        if b is not None:
            features.append(Slope(centres[b] - 0.5 * bay_w, centres[b + width - 1] + 0.5 * bay_w, 0.0,
                                  float(rng.uniform(1.5, min(3.0, floor_h))), float(rng.uniform(0.3, 0.8)), 0.0))
            taken.update((b + k, 0) for k in range(width))
    if style.balconies and upper:
        free_bays = [b for b in range(n_bays) if not any((b, f) in taken for f in upper)]
        chosen = [b for b in free_bays if rng.random() < 0.5] or free_bays[:1]
        out = float(rng.uniform(1.0, 1.5))
        for b in chosen:
            half = float(rng.uniform(0.35, 0.48)) * bay_w
            for f in upper:
                features.append(Block(centres[b] - half, centres[b] + half, f * floor_h - 0.15,
                                      f * floor_h + 1.05, out, kind='balcony'))
    if style.columns and n_bays >= 2:
        radius = float(rng.uniform(0.2, 0.3))
        for k in range(1, n_bays):
            if (k - 1, 0) not in taken and (k, 0) not in taken:
                features.append(Round(END_MARGIN + k * bay_w, 0.0, radius, 0.0, floor_h, kind='column'))
    if style.windows:
        for b in range(n_bays):
            for f in range(n_floors):
                if (b, f) in taken:
                    continue
                d = float(np.clip(depth + rng.normal(0.0, 0.02), 0.05, 0.30))
                if f == 0:
                    half = float(rng.uniform(0.30, 0.38)) * bay_w
                    v0 = 0.0 if rng.random() < 0.3 else 0.4  # door or shop window
                    features.append(Recess(centres[b] - half, centres[b] + half, v0, min(2.6, floor_h - 0.3), d))
                else:
                    half = float(rng.uniform(0.2, 0.27)) * bay_w
                    top = min(f * floor_h + 2.5, height - 0.3)
                    if top - (f * floor_h + 0.9) > 0.5:
                        features.append(Recess(centres[b] - half, centres[b] + half, f * floor_h + 0.9, top, d))
    return tuple(features)
