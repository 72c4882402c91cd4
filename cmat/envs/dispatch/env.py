"""`DispatchEnv`: ride-hailing order dispatch for a fleet, one agent per vehicle, in JAX.

Every step is one simulated minute. At each step every idle vehicle sees itself, the K open
orders nearest to it by pickup time and the zone-level supply/demand picture, and acts: stay
(action 0), take its k-th candidate order (actions 1..K) or drive empty to one of its zone's
repositioning neighbours (actions K+1..K+R; `cmat.envs.dispatch.city.NEIGHBOURS`). A busy
vehicle (on its way to a pickup, carrying a passenger or repositioning) may only stay. Each
vehicle carries one passenger group at a time (no pooling; its `seats` are its busy state).

Vehicles in one zone see the same K orders (the nearest to the zone), nearest first, equally
near ones in a vehicle-specific order (`DispatchEnv._observe`). The minute then runs in this
order:

1. Claims. Where several vehicles claim one order, the claimant with the shortest pickup time
   gets it, ties to the lower vehicle index; every other claim is a *conflict* (the paper's
   "redundant assignments", counted) and its vehicle stays idle this minute. A claim of an
   infeasible candidate (the action mask forbids it) is a stay.
2. Assignments. A winner drives to the pickup and then to the destination: it is busy for
   pickup + trip minutes, of which the pickup minutes are empty driving, and its zone becomes
   the destination. A repositioning vehicle is busy (empty) for the travel time to its target.
3. The minute passes: busy counters count down; every open order waits one minute more and
   expires when it has waited `patience` minutes (so an order is open for `patience` decisions).
4. New orders arrive: a Poisson number at the fleet's rate for the simulated time of day, each
   with an origin-destination pair drawn from the city's demand table for that time. They fill
   free order slots in slot order; arrivals beyond the free slots (or beyond the per-minute cap)
   are *dropped* and counted; the capacities are sized so that this is rare (`DispatchEnv`).

Rates: the city's relative demand (`City.demand`, the table's shape over the day) is scaled by
one factor per task so that the mean rate over the episode's window is `demand` orders per
vehicle-hour: a fleet of n vehicles has a market share of the city's demand, not all of it.

Reward (team, dollars per vehicle per step): fares of the orders taken, minus `empty_cost` per
empty-driving minute (charged when the pickup or repositioning is dispatched), minus
`expiry_penalty` per expired order, divided by the number of vehicles so that returns compare
across fleet sizes. The default weights follow the NYC TLC yellow-cab tariff (a $3.00 flag and
$0.70 per 1/5 mile, about $0.60 per minute at Manhattan's 9–11 mph), a driving cost of $0.20
per empty minute (fuel and wear at about $0.60 per mile at 20 mph) and a lost-customer penalty of
$2.00: chosen for this environment, not taken from a published dispatch benchmark.

Every quantity of the episode's service (orders generated, served, expired, dropped; revenue;
pickup waits; conflicts; empty and occupied driving minutes) is counted in the state's
`DispatchStats`, and `episode_metrics` turns them into the fleet operator's metrics.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from cmat.envs.autoreset import auto_reset
from cmat.envs.dispatch.city import City
from cmat.envs.protocol import EnvSpec, TimeStep
from cmat.errors import CmatError

OWN_FEATURES = 7
"""Per-vehicle features: zone position (2), idle, busy minutes / 30, time of day (sin, cos),
episode progress."""
ORDER_FEATURES = 7
"""Per-candidate features: feasible, pickup minutes / 10, trip minutes / 30, fare / 30, waited /
patience, destination position (2)."""
INT32_MAX = 2**31 - 1
UNREACHABLE = 1 << 12
"""Pickup minutes of an empty order slot in the candidate search (longer real pickups count as
one minute less; no city's travel times come near it)."""


class DispatchStats(NamedTuple):
    """Counts and sums of one episode so far (scalars unless stated)."""

    generated: jax.Array
    """Orders that arrived (placed or dropped)."""
    served: jax.Array
    expired: jax.Array
    dropped: jax.Array
    """Arrivals that found no free order slot."""
    revenue: jax.Array
    """Dollars of fares of the orders served."""
    wait_minutes: jax.Array
    """Sum over served orders of minutes from arrival to pickup."""
    wait_histogram: jax.Array
    """int32 [W]: served orders by whole minutes from arrival to pickup (the last bin holds
    longer waits)."""
    claims: jax.Array
    conflicts: jax.Array
    """Claims that lost their order to another vehicle."""
    empty_minutes: jax.Array
    """Vehicle-minutes driven without a passenger (to pickups, repositioning)."""
    occupied_minutes: jax.Array
    """Vehicle-minutes driven with a passenger."""


class DispatchState(NamedTuple):
    """The fleet, the order book and the episode's clock; n vehicles, O order slots, K
    candidates per vehicle."""

    minute: jax.Array
    """int32 []: minutes since the episode started."""
    start: jax.Array
    """int32 []: minute of the day at which the episode started."""
    zone: jax.Array
    """int32 [n]: each vehicle's zone (its destination while busy)."""
    busy: jax.Array
    """int32 [n]: minutes until the vehicle is free (0 = idle)."""
    empty_left: jax.Array
    """int32 [n]: of those, minutes still driven without a passenger."""
    order_valid: jax.Array
    """bool [O]: the slot holds an open order."""
    order_origin: jax.Array
    """int32 [O]."""
    order_destination: jax.Array
    """int32 [O]."""
    order_waited: jax.Array
    """int32 [O]: minutes since the order arrived."""
    order_trip: jax.Array
    """int32 [O]: driving minutes from origin to destination."""
    order_fare: jax.Array
    """float32 [O]: dollars."""
    candidates: jax.Array
    """int32 [n, K]: order slots of the K open orders nearest to each vehicle's zone, nearest
    first, ties in the vehicle's own cyclic order (what it observes)."""
    candidate_pickup: jax.Array
    """int32 [n, K]: their pickup minutes (`UNREACHABLE` for an empty slot)."""
    candidate_ok: jax.Array
    """bool [n, K]: the vehicle is idle and may take that candidate."""
    stats: DispatchStats


class DispatchEnv:
    """A fleet of `vehicles` in `city` serving `demand` orders per vehicle-hour (module
    docstring: dynamics, conflict rule, reward).

    Args:
        env_id: The task id (`dispatch:NAME`).
        city: Zones, travel times and demand.
        vehicles: Fleet size n (agents), 1 to 5,000.
        demand: Mean orders per vehicle-hour over the episode's window, in (0, 60].
        episode_minutes: Steps per episode, 1 to 1,440.
        start_hour: Hour of the day (0 to 24) at which episodes start; with `start_window`
            > 0 the start is drawn uniformly from [start_hour, start_hour + start_window) hours
            in whole minutes.
        start_window: Width of that window in hours, 0 to 24.
        patience: Minutes an order waits before it expires, 1 to 60.
        candidates: K, the open orders each vehicle sees and may take, 1 to 32.
        max_pickup: Longest pickup drive in minutes a vehicle may take an order for.
        fare_base, fare_per_minute: Fare = base + per_minute × trip minutes (dollars).
        empty_cost: Dollars per empty-driving minute.
        expiry_penalty: Dollars per expired order.

    Capacities: at most A = λ + 6√λ + 8 arrivals per minute (λ the peak rate per minute of the
    window) and O = max(1.5 × (patience + 1) × λ + A, K) order slots; arrivals beyond them are
    dropped and counted (`DispatchStats.dropped`).

    Raises CmatError for an option out of range.
    """

    def __init__(
        self, env_id: str, city: City, vehicles: int, demand: float, episode_minutes: int = 60,
        start_hour: float = 8.0, start_window: float = 2.0, patience: int = 5,
        candidates: int = 5, max_pickup: int = 15, fare_base: float = 3.0,
        fare_per_minute: float = 0.6, empty_cost: float = 0.2, expiry_penalty: float = 2.0,
    ) -> None:
        checks: list[tuple[str, Any, float, float]] = [
            ("vehicles", vehicles, 1, 5000), ("demand", demand, 1e-6, 60),
            ("episode_minutes", episode_minutes, 1, 1440), ("start_hour", start_hour, 0, 24),
            ("start_window", start_window, 0, 24), ("patience", patience, 1, 60),
            ("candidates", candidates, 1, 32), ("max_pickup", max_pickup, 1, 240),
            ("fare_base", fare_base, 0, 1e4), ("fare_per_minute", fare_per_minute, 0, 1e3),
            ("empty_cost", empty_cost, 0, 1e3), ("expiry_penalty", expiry_penalty, 0, 1e4),
        ]
        integers = {"vehicles", "episode_minutes", "patience", "candidates", "max_pickup"}
        for name, value, low, high in checks:
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            if not number or (name in integers and not isinstance(value, int)) or not (
                    low <= value <= high):
                kind = "an integer" if name in integers else "a number"
                raise CmatError(f"{env_id}: {name} must be {kind} in [{low:g}, {high:g}], "
                                f"got {value!r}")
        self.city = city
        self.vehicles = vehicles
        self.episode_minutes = episode_minutes
        self.start_minute = round(start_hour * 60)
        self.start_choices = max(round(start_window * 60), 1)
        self.patience = patience
        self.num_candidates = candidates
        self.max_pickup = max_pickup
        self.fare = (fare_base, fare_per_minute)
        self.empty_cost = empty_cost
        self.expiry_penalty = expiry_penalty

        window = self.start_choices + episode_minutes
        # orders per minute per unit of relative demand, so that the window's mean is `demand`
        self.rate_scale = demand * vehicles / 60 / city.mean_rate(self.start_minute, window)
        totals = city.demand.sum(axis=(1, 2))
        slots = city.slot_of(np.arange(self.start_minute, self.start_minute + window))
        peak = float(totals[slots].max() * self.rate_scale)
        self.max_arrivals = math.ceil(peak + 6 * math.sqrt(peak) + 8)
        self.num_orders = max(math.ceil(1.5 * (patience + 1) * peak) + self.max_arrivals,
                              candidates)
        if self.num_orders * UNREACHABLE > INT32_MAX:
            raise CmatError(f"{env_id}: {self.num_orders} order slots are too many to rank in "
                            f"int32; lower patience or the fleet size")
        cumulative = np.cumsum(city.demand.reshape(city.demand.shape[0], -1), axis=1,
                               dtype=np.float64)
        self._cdf = jnp.asarray(cumulative / np.maximum(cumulative[:, -1:], 1e-30), jnp.float32)
        self._slot_rate = jnp.asarray(totals * self.rate_scale, jnp.float32)
        self._travel = jnp.asarray(city.travel_minutes, jnp.int32)
        self._coords = jnp.asarray(city.coords, jnp.float32)
        self._neighbours = jnp.asarray(city.neighbours, jnp.int32)
        self._neighbour_mask = jnp.asarray(city.neighbour_mask)
        self.wait_bins = patience + max_pickup + 1
        zones = city.num_zones
        self.spec = EnvSpec(
            env_id=env_id,
            num_agents=vehicles,
            obs_dim=OWN_FEATURES + ORDER_FEATURES * candidates + 2 * zones,
            action_dim=1 + candidates + city.neighbours.shape[1],
            discrete=True,
            max_episode_steps=episode_minutes,
            has_win_rate=False,
            state_dim=3 * zones + 3,
            episode_metrics=METRICS,
        )

    def reset(self, key: jax.Array) -> tuple[DispatchState, TimeStep]:
        """Start an episode: vehicles idle, placed by the demand's origins at the start time;
        the order book holds the first minute's arrivals."""
        start_key, place_key, arrive_key = jax.random.split(key, 3)
        start = self.start_minute + jax.random.randint(start_key, (), 0, self.start_choices)
        slot = self._slot(start)
        origin_weight = jnp.asarray(self.city.demand.sum(axis=2))[slot]
        zone = jax.random.categorical(place_key, jnp.log(origin_weight + 1e-30),
                                      shape=(self.vehicles,)).astype(jnp.int32)
        n, orders = self.vehicles, self.num_orders
        zero_i, zero_f = jnp.int32(0), jnp.float32(0)
        stats = DispatchStats(
            generated=zero_i, served=zero_i, expired=zero_i, dropped=zero_i, revenue=zero_f,
            wait_minutes=zero_i, wait_histogram=jnp.zeros(self.wait_bins, jnp.int32),
            claims=zero_i, conflicts=zero_i, empty_minutes=zero_i, occupied_minutes=zero_i,
        )
        state = DispatchState(
            minute=zero_i, start=start.astype(jnp.int32), zone=zone,
            busy=jnp.zeros(n, jnp.int32), empty_left=jnp.zeros(n, jnp.int32),
            order_valid=jnp.zeros(orders, bool), order_origin=jnp.zeros(orders, jnp.int32),
            order_destination=jnp.zeros(orders, jnp.int32),
            order_waited=jnp.zeros(orders, jnp.int32), order_trip=jnp.zeros(orders, jnp.int32),
            order_fare=jnp.zeros(orders, jnp.float32),
            candidates=jnp.zeros((n, self.num_candidates), jnp.int32),
            candidate_pickup=jnp.zeros((n, self.num_candidates), jnp.int32),
            candidate_ok=jnp.zeros((n, self.num_candidates), bool), stats=stats,
        )
        state = self._observe(self._arrive(arrive_key, state))
        return state, self._timestep(state, jnp.float32(0), jnp.asarray(False))

    def step(self, key: jax.Array, state: DispatchState,
             actions: jax.Array) -> tuple[DispatchState, TimeStep]:
        """Take the fleet's `actions` [n]; on `done`, return the next episode's first state
        (the second key of `jax.random.split(key)` draws it)."""
        step_key, reset_key = jax.random.split(key)
        return auto_reset(*self.step_in_episode(step_key, state, actions), *self.reset(reset_key))

    def step_in_episode(self, key: jax.Array, state: DispatchState,
                        actions: jax.Array) -> tuple[DispatchState, TimeStep]:
        """One minute (module docstring, steps 1–4) without the automatic reset."""
        n, k_max, orders = self.vehicles, self.num_candidates, self.num_orders
        vehicle = jnp.arange(n, dtype=jnp.int32)
        action = actions.astype(jnp.int32)
        idle = state.busy == 0

        choice = jnp.clip(action - 1, 0, k_max - 1)[:, None]
        order = jnp.take_along_axis(state.candidates, choice, axis=1)[:, 0]
        pickup = jnp.take_along_axis(state.candidate_pickup, choice, axis=1)[:, 0]
        claim = (idle & (action >= 1) & (action <= k_max)
                 & jnp.take_along_axis(state.candidate_ok, choice, axis=1)[:, 0])
        priority = jnp.where(claim, pickup * n + vehicle, INT32_MAX)
        claimed = jnp.where(claim, order, orders)
        best = jax.ops.segment_min(priority, claimed, num_segments=orders + 1)
        win = claim & (priority == best[claimed])
        served = jnp.zeros(orders + 1, bool).at[jnp.where(win, order, orders)].set(True)[:orders]

        target_index = jnp.clip(action - 1 - k_max, 0, self._neighbours.shape[1] - 1)
        target = self._neighbours[state.zone, target_index]
        reposition = idle & (action > k_max) & self._neighbour_mask[state.zone, target_index]
        travel = self._travel[self._hour(state.start + state.minute)]
        drive = travel[state.zone, target]
        trip = state.order_trip[order]
        zone = jnp.where(win, state.order_destination[order],
                         jnp.where(reposition, target, state.zone))
        busy = jnp.where(win, pickup + trip, jnp.where(reposition, drive, state.busy))
        empty_left = jnp.where(win, pickup, jnp.where(reposition, drive, state.empty_left))
        empty_minutes = jnp.sum(empty_left > 0)
        occupied_minutes = jnp.sum((busy > 0) & (empty_left == 0))

        fares = jnp.sum(jnp.where(win, state.order_fare[order], 0.0))
        wait = state.order_waited[order] + pickup
        histogram = jnp.zeros(self.wait_bins, jnp.int32).at[
            jnp.minimum(wait, self.wait_bins - 1)].add(win.astype(jnp.int32))
        waited = state.order_waited + 1
        open_ = state.order_valid & ~served
        expired = open_ & (waited >= self.patience)
        dispatched_empty = jnp.sum(jnp.where(win, pickup, 0) + jnp.where(reposition, drive, 0))
        reward = (fares - self.empty_cost * dispatched_empty
                  - self.expiry_penalty * jnp.sum(expired)) / n

        stats = state.stats
        stats = stats._replace(
            served=stats.served + jnp.sum(win), expired=stats.expired + jnp.sum(expired),
            revenue=stats.revenue + fares,
            wait_minutes=stats.wait_minutes + jnp.sum(jnp.where(win, wait, 0)),
            wait_histogram=stats.wait_histogram + histogram,
            claims=stats.claims + jnp.sum(claim),
            conflicts=stats.conflicts + jnp.sum(claim & ~win),
            empty_minutes=stats.empty_minutes + empty_minutes,
            occupied_minutes=stats.occupied_minutes + occupied_minutes,
        )
        state = state._replace(
            minute=state.minute + 1, zone=zone, busy=jnp.maximum(busy - 1, 0),
            empty_left=jnp.maximum(empty_left - 1, 0), order_valid=open_ & ~expired,
            order_waited=waited, stats=stats,
        )
        state = self._observe(self._arrive(key, state))
        done = state.minute >= self.episode_minutes
        return state, self._timestep(state, reward.astype(jnp.float32), done)

    def _slot(self, minute_of_day: jax.Array) -> jax.Array:
        slots: int = self.city.demand.shape[0]
        slot: jax.Array = (minute_of_day % 1440) * slots // 1440
        return slot

    def _hour(self, minute_of_day: jax.Array) -> jax.Array:
        parts: int = self.city.travel_minutes.shape[0]
        hour: jax.Array = (minute_of_day % 1440) * parts // 1440
        return hour

    def _arrive(self, key: jax.Array, state: DispatchState) -> DispatchState:
        """Poisson arrivals for the state's minute placed into free order slots."""
        count_key, pair_key = jax.random.split(key)
        now = state.start + state.minute
        slot = self._slot(now)
        count = jax.random.poisson(count_key, self._slot_rate[slot]).astype(jnp.int32)
        drawn = jnp.minimum(count, self.max_arrivals)
        cdf = self._cdf[slot]
        pair = jnp.searchsorted(cdf, jax.random.uniform(pair_key, (self.max_arrivals,)),
                                side="right")
        pair = jnp.minimum(pair, cdf.shape[0] - 1).astype(jnp.int32)
        zones = self.city.num_zones
        free = ~state.order_valid
        rank = jnp.cumsum(free) - 1
        placed = free & (rank < drawn)
        new = jnp.clip(rank, 0, self.max_arrivals - 1)
        origin, destination = pair[new] // zones, pair[new] % zones
        trip = self._travel[self._hour(now)][origin, destination]
        fare = self.fare[0] + self.fare[1] * trip.astype(jnp.float32)
        stats = state.stats
        stats = stats._replace(generated=stats.generated + count,
                              dropped=stats.dropped + count - jnp.sum(placed))
        return state._replace(
            order_valid=state.order_valid | placed,
            order_origin=jnp.where(placed, origin, state.order_origin),
            order_destination=jnp.where(placed, destination, state.order_destination),
            order_waited=jnp.where(placed, 0, state.order_waited),
            order_trip=jnp.where(placed, trip, state.order_trip),
            order_fare=jnp.where(placed, fare, state.order_fare), stats=stats,
        )

    def _observe(self, state: DispatchState) -> DispatchState:
        """The state with each vehicle's candidates: the K open orders nearest to its zone
        (ties to the lower order slot), which all vehicles of a zone share, nearest first;
        orders equally near are listed in a cyclic order that starts at the zone list's
        position i mod K for vehicle i. A zone's vehicles thus see equally near orders in
        different orders, and a fleet that takes its first candidate spreads over them.
        Computed per zone ([Z, O] pickup minutes) and gathered per vehicle."""
        travel = self._travel[self._hour(state.start + state.minute)]
        orders, k_max = self.num_orders, self.num_candidates
        pickup = jnp.where(state.order_valid[None, :],
                           jnp.minimum(travel[:, state.order_origin], UNREACHABLE - 1),
                           UNREACHABLE)
        slots = jnp.arange(orders, dtype=jnp.int32)[None, :]
        score = pickup * orders + slots
        chosen = []
        for _ in range(k_max):  # K argmins: XLA's CPU top_k sorts every row
            best = jnp.argmin(score, axis=1)
            chosen.append(best)
            score = jnp.where(slots == best[:, None], INT32_MAX, score)
        zone_candidates = jnp.stack(chosen, axis=1).astype(jnp.int32)
        zone_pickup = jnp.take_along_axis(pickup, zone_candidates, axis=1)
        vehicle = jnp.arange(self.vehicles, dtype=jnp.int32)[:, None]
        rotation = (jnp.arange(k_max, dtype=jnp.int32)[None, :] - vehicle) % k_max
        position = jnp.argsort(zone_pickup[state.zone] * k_max + rotation, axis=1)
        candidates = jnp.take_along_axis(zone_candidates[state.zone], position, axis=1)
        candidate_pickup = jnp.take_along_axis(zone_pickup[state.zone], position, axis=1)
        ok = (state.busy == 0)[:, None] & (candidate_pickup <= self.max_pickup)
        return state._replace(candidates=candidates, candidate_pickup=candidate_pickup,
                              candidate_ok=ok)

    def _timestep(self, state: DispatchState, reward: jax.Array, done: jax.Array) -> TimeStep:
        n, zones = self.vehicles, self.city.num_zones
        idle = state.busy == 0
        per_zone = zones / n
        open_orders = jnp.zeros(zones).at[state.order_origin].add(state.order_valid) * per_zone
        idle_vehicles = jnp.zeros(zones).at[state.zone].add(idle) * per_zone
        busy_vehicles = jnp.zeros(zones).at[state.zone].add(~idle) * per_zone
        angle = 2 * jnp.pi * ((state.start + state.minute) % 1440) / 1440
        clock = jnp.stack([jnp.sin(angle), jnp.cos(angle),
                           state.minute / self.episode_minutes]).astype(jnp.float32)
        own = jnp.concatenate([
            self._coords[state.zone], idle[:, None], (state.busy / 30)[:, None],
            jnp.broadcast_to(clock, (n, 3)),
        ], axis=1)
        order = state.candidates
        shown = state.order_valid[order] & (state.candidate_pickup < UNREACHABLE)
        features = jnp.concatenate([
            jnp.stack([state.candidate_ok, state.candidate_pickup / 10,
                       state.order_trip[order] / 30, state.order_fare[order] / 30,
                       state.order_waited[order] / self.patience], axis=-1),
            self._coords[state.order_destination[order]],
        ], axis=-1)
        features = jnp.where(shown[..., None], features, 0.0).reshape(n, -1)
        picture = jnp.concatenate([open_orders, idle_vehicles])
        obs = jnp.concatenate([own, features, jnp.broadcast_to(picture, (n, 2 * zones))], axis=1)
        neighbour_ok = self._neighbour_mask[state.zone] & idle[:, None]
        mask = jnp.concatenate([jnp.ones((n, 1), bool), state.candidate_ok, neighbour_ok], axis=1)
        return TimeStep(
            obs=obs.astype(jnp.float32), action_mask=mask, reward=reward, done=done,
            won=jnp.asarray(False), alive=jnp.ones(n, bool),
            global_state=jnp.concatenate([picture, busy_vehicles, clock]).astype(jnp.float32),
            metrics=jnp.stack([value.astype(jnp.float32) for value in
                               episode_metrics(state.stats, state.minute).values()]),
        )


METRICS = ("service_rate", "revenue", "mean_wait", "p95_wait", "expired", "empty_share",
           "conflicts_per_step")
"""The fleet operator's metrics of an episode (`episode_metrics`; `EnvSpec.episode_metrics`)."""


def episode_metrics(stats: DispatchStats, steps: Any) -> dict[str, jax.Array]:
    """The operator's metrics, float32 with `stats`' leading batch axes, of episodes whose
    counters are `stats` after `steps` minutes: service rate (served / generated), revenue
    (dollars), mean and 95th-percentile minutes from arrival to pickup of the served orders
    (NaN where none was served; the percentile in whole minutes, the lowest bin whose
    cumulative count reaches 95%), expired orders, empty-driving share of the driven minutes
    (NaN where nothing drove), conflicts per step."""
    served = stats.served.astype(jnp.float32)
    cumulative = jnp.cumsum(stats.wait_histogram, axis=-1)
    p95 = jnp.argmax(cumulative >= 0.95 * cumulative[..., -1:], axis=-1)
    driven = (stats.empty_minutes + stats.occupied_minutes).astype(jnp.float32)
    return {
        "service_rate": served / jnp.maximum(stats.generated, 1),
        "revenue": stats.revenue.astype(jnp.float32),
        "mean_wait": jnp.where(served > 0, stats.wait_minutes / jnp.maximum(served, 1), jnp.nan),
        "p95_wait": jnp.where(served > 0, p95, jnp.nan),
        "expired": stats.expired.astype(jnp.float32),
        "empty_share": jnp.where(driven > 0, stats.empty_minutes / jnp.maximum(driven, 1),
                                 jnp.nan),
        "conflicts_per_step": stats.conflicts / jnp.maximum(jnp.asarray(steps, jnp.float32), 1),
    }
