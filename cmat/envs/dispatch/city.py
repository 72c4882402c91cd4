"""Cities of the dispatch suite: zones, travel times, repositioning neighbours and demand.

A city is static data (numpy arrays) that `cmat.envs.dispatch.env.DispatchEnv` turns into JAX
constants. Three cities exist:

- `grid_city`: a synthetic square grid of zones with demand hot spots, built from numbers alone;
  the default for tests and for users without the Manhattan table.
- `manhattan_city`: the 61 Manhattan taxi zones, with demand and travel times derived from the
  DIMACS ride-hailing challenge's data (PyPI `pyhailing` 0.0.9, Apache-2.0) by
  `scripts/dispatch_manhattan_table.py` into `data/manhattan.npz` (see `data/README.md`).
- `table_city`: an operator's own city from a table of the same format (`CITY_TABLE_KEYS`),
  the task `dispatch:custom-N-LEVEL` with `env_kwargs.city_file=PATH`.

Times are whole minutes (one environment step is one minute), demand is relative: the
environment scales it to the fleet's demand level (orders per vehicle-hour).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from cmat.errors import CmatError

MANHATTAN_TABLE = Path(__file__).parent / "data" / "manhattan.npz"
"""The derived Manhattan table shipped with the package (`data/README.md`)."""

CITY_TABLE_KEYS = ("demand", "travel_minutes", "coords")
"""The arrays of a city table (`np.savez(path, demand=..., travel_minutes=..., coords=...)`):
`demand` [S, Z, Z] relative order rates from origin to destination zone in each of S equal slots
of the day (S ≥ 1; 96 quarter hours for Manhattan), `travel_minutes` [H, Z, Z] driving minutes in
each of H equal parts of the day (H ≥ 1; rounded to whole minutes, at least 1), `coords` [Z, 2]
zone positions in [0, 1]², at least 5 zones."""

NEIGHBOURS = 4
"""Repositioning targets per zone: the 4 zones nearest by travel time (a grid zone's 4-
neighbourhood; fewer at a grid's edge, masked)."""


@dataclass(frozen=True)
class City:
    """Static description of a city of `Z` zones.

    Attributes:
        name: The city's name in task ids (`grid`, `manhattan`).
        travel_minutes: int32 [H, Z, Z], driving minutes from zone to zone in each of H equal
            parts of the day (H = 24 hours for Manhattan, 1 for the grid), at least 1.
        coords: float32 [Z, 2], zone positions in [0, 1]² (observations show them).
        neighbours: int32 [Z, NEIGHBOURS], repositioning targets of each zone.
        neighbour_mask: bool [Z, NEIGHBOURS], which targets exist.
        demand: float32 [S, Z, Z], relative order rates (origin, destination) in each of S equal
            slots of the day (S = 96 quarter hours for Manhattan, 1 for the grid).
    """

    name: str
    travel_minutes: np.ndarray
    coords: np.ndarray
    neighbours: np.ndarray
    neighbour_mask: np.ndarray
    demand: np.ndarray

    @property
    def num_zones(self) -> int:
        """Z."""
        return int(self.coords.shape[0])

    def mean_rate(self, start_minute: int, minutes: int) -> float:
        """Mean over the minutes [start_minute, start_minute + minutes) of the day of the
        total relative demand per slot (the environment's rate scale divides by it)."""
        slots = self.slot_of(np.arange(start_minute, start_minute + minutes))
        return float(self.demand.sum(axis=(1, 2))[slots].mean())

    def slot_of(self, minute_of_day: np.ndarray) -> np.ndarray:
        """Demand slot of each minute of the day (wrapping past midnight)."""
        return np.asarray((minute_of_day % 1440) * self.demand.shape[0] // 1440)

    def hour_of(self, minute_of_day: np.ndarray) -> np.ndarray:
        """Travel-time part of the day of each minute of the day (wrapping past midnight)."""
        return np.asarray((minute_of_day % 1440) * self.travel_minutes.shape[0] // 1440)


def nearest_neighbours(travel_minutes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The `NEIGHBOURS` other zones nearest to each zone by the day's mean travel time:
    (int32 [Z, NEIGHBOURS], bool [Z, NEIGHBOURS] all True)."""
    mean = travel_minutes.mean(axis=0).astype(np.float64)
    np.fill_diagonal(mean, np.inf)
    order = np.argsort(mean, axis=1, kind="stable")[:, :NEIGHBOURS]
    return order.astype(np.int32), np.ones(order.shape, dtype=bool)


def grid_city(size: int = 8, minutes_per_block: int = 2, hot_spots: int = 3,
              seed: int = 0) -> City:
    """A `size` × `size` grid of zones, `minutes_per_block` minutes between adjacent zones
    (Manhattan distance, at least 1 minute within a zone), with `hot_spots` demand hot spots.

    Origins and destinations are drawn from two different mixtures of Gaussian bumps (width
    size/5) placed by `seed` over a uniform floor of 10%, so that vehicles drift from the origin
    hot spots to the destination ones and repositioning pays. The demand does not change over the
    day (S = H = 1). Raises CmatError where a size is out of range."""
    if not 2 <= size <= 32:
        raise CmatError(f"dispatch grid size must be in [2, 32], got {size}")
    if not 1 <= minutes_per_block <= 30:
        raise CmatError(f"dispatch minutes_per_block must be in [1, 30], got {minutes_per_block}")
    if not 1 <= hot_spots <= 16:
        raise CmatError(f"dispatch hot_spots must be in [1, 16], got {hot_spots}")
    rows, cols = np.divmod(np.arange(size * size), size)
    blocks = np.abs(rows[:, None] - rows[None]) + np.abs(cols[:, None] - cols[None])
    travel = np.maximum(blocks * minutes_per_block, 1).astype(np.int32)[None]
    coords = (np.stack([cols, rows], axis=1) / max(size - 1, 1)).astype(np.float32)
    rng = np.random.default_rng(seed)

    def bumps() -> np.ndarray:
        centres = rng.uniform(0, size - 1, (hot_spots, 2))
        distance2 = ((np.stack([cols, rows], axis=1)[:, None] - centres[None]) ** 2).sum(-1)
        weight = np.exp(-distance2 / (2 * (size / 5) ** 2)).sum(axis=1)
        weight = 0.1 * weight.mean() + weight
        return np.asarray(weight / weight.sum())

    demand = np.outer(bumps(), bumps()).astype(np.float32)[None]
    steps = ((-1, 0), (1, 0), (0, -1), (0, 1))
    neighbours = np.zeros((size * size, NEIGHBOURS), dtype=np.int32)
    mask = np.zeros((size * size, NEIGHBOURS), dtype=bool)
    for k, (dr, dc) in enumerate(steps):
        r, c = rows + dr, cols + dc
        inside = (r >= 0) & (r < size) & (c >= 0) & (c < size)
        neighbours[:, k] = np.where(inside, r * size + c, np.arange(size * size))
        mask[:, k] = inside
    return City("grid", travel, coords, neighbours, mask, demand)


@cache
def manhattan_city(path: Path = MANHATTAN_TABLE) -> City:
    """The 61 Manhattan taxi zones from the derived table at `path` (`data/README.md`): demand
    by quarter hour of a weekday (the source has no weekend data), travel minutes by hour
    (rounded to whole minutes, at least 1), repositioning to the 4 zones nearest by travel time.

    Raises CmatError naming the file where it is missing, unreadable or malformed."""
    return table_city(path, "manhattan", "the Manhattan demand table",
                      "build it with python scripts/dispatch_manhattan_table.py, or use a grid "
                      "task")


def table_city(path: Path, name: str = "custom", what: str = "the city table",
               remedy: str = "give env_kwargs.city_file the path of an .npz with demand, "
                             "travel_minutes and coords (docs/dispatch.md)") -> City:
    """The city of the table at `path` (`CITY_TABLE_KEYS`), repositioning to the
    `NEIGHBOURS` zones nearest by the day's mean travel time.

    Raises CmatError naming the file (as `what`) where it is missing (with `remedy`),
    unreadable, or malformed: missing arrays, shapes that disagree on Z, fewer than 5 zones,
    negative, infinite or all-zero demand, travel minutes not above 0, positions outside
    [0, 1]²."""
    try:
        with np.load(path) as table:
            demand = np.asarray(table["demand"], dtype=np.float32)
            travel = np.asarray(table["travel_minutes"], dtype=np.float32)
            coords = np.asarray(table["coords"], dtype=np.float32)
    except FileNotFoundError:
        raise CmatError(f"{what} {path} is missing: {remedy}") from None
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise CmatError(f"{what} {path} is corrupt ({error})") from None
    zones = coords.shape[0] if coords.ndim == 2 else -1
    well_formed = (
        zones > NEIGHBOURS and coords.shape[1:] == (2,)
        and demand.ndim == 3 and demand.shape[0] > 0 and demand.shape[1:] == (zones, zones)
        and travel.ndim == 3 and travel.shape[0] > 0 and travel.shape[1:] == (zones, zones)
        and np.isfinite(demand).all() and (demand >= 0).all() and demand.sum() > 0
        and np.isfinite(travel).all() and (travel > 0).all()
        and np.isfinite(coords).all() and (coords >= 0).all() and (coords <= 1).all()
    )
    if not well_formed:
        raise CmatError(
            f"{what} {path} is corrupt (shapes demand {demand.shape}, travel_minutes "
            f"{travel.shape}, coords {coords.shape}, or values out of range: "
            f"{', '.join(CITY_TABLE_KEYS)} as [S, Z, Z], [H, Z, Z], [Z, 2] with Z >= "
            f"{NEIGHBOURS + 1}, demand >= 0 and not all 0, travel > 0, coords in [0, 1])"
        )
    minutes = np.maximum(np.rint(travel), 1).astype(np.int32)
    neighbours, mask = nearest_neighbours(minutes)
    return City(name, minutes, coords, neighbours, mask, demand)
