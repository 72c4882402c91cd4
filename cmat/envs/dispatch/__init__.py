"""The fleet dispatch suite: `dispatch:CITY-N-LEVEL`, ride-hailing order dispatch for a fleet of
N vehicles, one agent per vehicle (`cmat.envs.dispatch.env`).

- CITY: `grid` (a synthetic 8 × 8 grid with demand hot spots; needs no data), `manhattan`
  (the 61 Manhattan taxi zones, real demand and travel times; `city.manhattan_city`) or
  `custom` (an operator's own city: the table at `env_kwargs.city_file`, `city.table_city`).
- N: 1 to 5,000 vehicles; the named sizes are 100, 250, 500 and 1,000 (`SIZES`).
- LEVEL: the demand in orders per vehicle-hour (`DEMAND_LEVELS`).

Episodes are 60 one-minute steps starting between 08:00 and 10:00 (Manhattan: a weekday).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable
from functools import partial
from pathlib import Path
from typing import Any

from cmat.envs.dispatch.city import grid_city, manhattan_city, table_city
from cmat.envs.dispatch.env import METRICS, DispatchEnv, episode_metrics
from cmat.errors import CmatError

__all__ = ["DEMAND_LEVELS", "METRICS", "OPTIONS", "SIZES", "TASK", "DispatchEnv",
           "episode_metrics", "make_task"]

DEMAND_LEVELS = {"low": 1.5, "mid": 3.0, "high": 5.0}
"""Orders per vehicle-hour. A vehicle serves at most about 4 an hour in either city (a trip and
its pickup take 13–16 minutes): `low` leaves most of the fleet idle (coverage and repositioning
decide), `mid` is near capacity, `high` has more orders than the fleet can serve (which orders
to take decides)."""
SIZES = (100, 250, 500, 1000)
"""The fleet sizes the suite's documentation and experiments name."""
TASK = re.compile(r"(grid|manhattan|custom)-([1-9][0-9]*)-(low|mid|high)")
"""A task name: CITY-N-LEVEL."""
TASK_HELP = "CITY-N-LEVEL: CITY grid|manhattan|custom, N vehicles 1-5000, LEVEL low|mid|high"
CITY_OPTIONS: dict[str, tuple[str, ...]] = {
    "grid": ("grid_size", "hot_spots", "city_seed"), "manhattan": (), "custom": ("city_file",)}
ENV_OPTIONS = ("episode_minutes", "start_hour", "start_window", "patience", "candidates",
               "max_pickup", "fare_base", "fare_per_minute", "empty_cost", "expiry_penalty")
OPTIONS = (*ENV_OPTIONS, *(option for own in CITY_OPTIONS.values() for option in own))
"""Every option a dispatch task accepts (`env_kwargs`); a city's own only for that city."""


def make_task(name: str, **options: Any) -> DispatchEnv:
    """The task `name` (CITY-N-LEVEL) with `options` (`DispatchEnv`'s, and `grid_size`,
    `hot_spots`, `city_seed` for the grid, `city_file` for a custom city: the path of its
    table, `city.CITY_TABLE_KEYS`, relative to the working directory).

    Raises CmatError for a malformed name, a size out of range, an option of another city, a
    custom city without its `city_file`, or a missing or corrupt table."""
    match = TASK.fullmatch(name)
    if match is None:
        raise CmatError(f"unknown dispatch task {name!r}; tasks are {TASK_HELP}")
    city_name, size, level = match.group(1), int(match.group(2)), match.group(3)
    if size > 5000:
        raise CmatError(f"dispatch:{name}: at most 5000 vehicles, got {size}")
    for other, own in CITY_OPTIONS.items():
        wrong = sorted(set(options) & set(own))
        if other != city_name and wrong:
            raise CmatError(f"dispatch:{name}: option {wrong[0]!r} belongs to the {other} city")
    if city_name == "grid":
        city = grid_city(size=options.pop("grid_size", 8), hot_spots=options.pop("hot_spots", 3),
                         seed=options.pop("city_seed", 0))
    elif city_name == "custom":
        if not isinstance(options.get("city_file"), str):
            raise CmatError(f"dispatch:{name}: a custom city needs its table: --set "
                            f"env_kwargs.city_file=PATH (an .npz with demand, travel_minutes "
                            f"and coords; docs/dispatch.md)")
        city = table_city(Path(options.pop("city_file")))
    else:
        city = manhattan_city()
    return DispatchEnv(f"dispatch:{name}", city, size, DEMAND_LEVELS[level], **options)


def build(env_id: str, name: str) -> tuple[Callable[..., DispatchEnv], Iterable[str]]:
    """The dispatch suite's builder (cmat.envs.suites.Builder); `make_task` checks NAME."""
    return partial(make_task, name), OPTIONS
