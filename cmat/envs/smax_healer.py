"""SMAX with a healer: the Medivac, and SMAC's MMM and MMM2 scenarios built on JaxMARL's SMAX.

JaxMARL's SMAX has six unit types and none of them heals, so SMAC's MMM maps cannot be played in
it. `HealerSMAX` subclasses `SMAX` and adds the Medivac as unit type 6; `HeuristicEnemyHealerSMAX`
subclasses `HeuristicEnemySMAX` so that the scripted enemy team plays with one as well.

The Medivac
-----------
- It flies: it collides with no unit. (SC2's air units only drift apart softly; SMAX's hard
  push is kept for ground units, and the scenarios here have one flying unit a side.)
- It has no weapon. Its target actions point at its own team and heal instead of attack
  (SMAC's convention): target slot k of an ally Medivac is ally k; of an enemy Medivac, enemy
  `num_enemies - 1 - k` (SMAX counts the enemy team's targets in reverse, as its observations
  list them). Both teams' action spaces therefore have `max(num_allies, num_enemies)` target
  slots; in MMM and MMM2 the allies' action space is SMAX's usual `5 + num_enemies`.
- A heal slot is available (the action mask) when, as in SMAC's `get_avail_agent_actions`, the
  Medivac and the target are alive, the target is biological (not a Medivac, and not a stalker)
  and it is within heal range. SMAC does not mask full-health targets, and neither does this:
  healing a unit at full health is allowed and restores nothing.
- Each world step it restores `heal_rate * time_per_step` hit points to its target, never above
  the target's maximum and never to a unit that is dead (or killed in that same world step).
  Healing costs 1 energy per 3 hit points; energy regenerates and caps at 200, so a Medivac's
  initial 50 energy buys 150 hit points and then healing slows to the regeneration rate.
- Units that cannot hit air (marauders, zealots, zerglings) cannot target it.
- As in SMAC (`only_medivac_left`), a team left with no unit that can attack is out of the
  battle: its remaining Medivacs count as dead, so the other team wins.

Observations are SMAX's (health, relative position, last movement, last target, weapon cooldown,
unit-type one-hot); the unit-type one-hot gains a seventh bit, and for a Medivac the weapon
cooldown slot carries its energy / 200, as SMAC's global state does. The last-target feature of a
Medivac names the teammate it is healing, so a policy can see who heals whom.

Reward: SMAX (like SMAC) pays the absolute net health change of the opposing team, which would
pay a team for its enemy being healed. Here each unit counts only its net loss over a step.

Unit statistics
---------------
SMAX takes its units' hit points (+ shields), sight, attack range and radius from StarCraft II
unchanged, and speeds and weapon cooldowns in seconds of the "Faster" game speed (marine 3.15,
stalker 4.13, zealot 3.15; exceptions: the marauder's 2.25 and the stalker's 1.87 s are the
"Normal"-speed figures). Its damages are its own (a marine does 9, not SC2's 6) and armour is not
modelled. The Medivac follows the same rule, with StarCraft II (Legacy of the Void, Liquipedia
"Medivac (Legacy of the Void)" and "Heal") values at Faster speed:

=====================  =========  =====================================================
stat                   value      source
=====================  =========  =====================================================
hit points             150        SC2 (armour 1 not modelled, as for every SMAX unit)
speed                  3.5        SC2, Faster (2.5 at Normal); afterburners not modelled
heal rate              12.6 hp/s  SC2, Faster (9 hp/s at Normal)
heal range             4          SC2 (SMAC masks at its uniform shoot range 6; SMAX uses
                                  each unit's own SC2 range, so 4 here)
heal cost              1 / 3 hp   SC2: 1 energy per 3 hit points restored
energy                 50 / 200   SC2 starting / maximum energy
energy regeneration    0.7875/s   SC2 standard regeneration (0.5625/s Normal) at Faster
sight range            11         SC2
radius                 0.75       SC2 unit data
attack                 0          none (heals instead); weapon cooldown is unused
=====================  =========  =====================================================

Biological units (healable): marine, marauder, zealot, zergling, hydralisk. Units that hit air:
marine, stalker, hydralisk (SC2).

Scenarios (SMAC's unit order: marauders, then marines, then the Medivac):
`MMM` 2 marauders, 7 marines, 1 Medivac a side; `MMM2` the same 10 allies against 3 marauders,
8 marines and 1 Medivac. The enemy plays JaxMARL's heuristic, extended for healers: its Medivac
heals the most injured teammate in range, else flies towards the most injured one it sees, else
keeps with its team; its marauders ignore flying units they cannot shoot.

Rendering (`init_render`) is SMAX's and draws a heal as a shot at an enemy.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable
from functools import partial
from typing import Any, cast

import jax
import jax.numpy as jnp
import numpy as np
from flax.struct import dataclass
from jaxmarl.environments.smax import SMAX, HeuristicEnemySMAX, Scenario
from jaxmarl.environments.smax.heuristic_enemy import (
    HeuristicPolicyState,
    create_heuristic_policy,
)
from jaxmarl.environments.smax.heuristic_enemy_smax_env import State as EnemyState
from jaxmarl.environments.smax.smax_env import State

from cmat.envs.protocol import MarlEnv, TimeStep

__all__ = [
    "MEDIVAC",
    "SCENARIOS",
    "HealerSMAX",
    "HealerState",
    "HeuristicEnemyHealerSMAX",
    "first_episode_wins",
    "focus_fire_actions",
    "focus_fire_policy",
    "healer_heuristic_policy",
]

MARINE, MARAUDER, MEDIVAC = 0, 1, 6
"""Unit type indices: SMAX's marine and marauder, and the Medivac after SMAX's six types."""
STOP = 4
"""SMAX's stop action (0-3 move north, east, south, west; actions from 5 name targets)."""

_MEDIVAC_STATS: dict[str, Any] = {
    "unit_type_names": "medivac",
    "unit_type_shorthands": "V",
    "unit_type_velocities": 3.5,
    "unit_type_attacks": 0.0,
    "unit_type_attack_ranges": 4.0,  # heal range
    "unit_type_sight_ranges": 11.0,
    "unit_type_radiuses": 0.75,
    "unit_type_health": 150.0,
    "unit_type_weapon_cooldowns": 1.0,  # no weapon; keeps SMAX's cooldown features finite
}
"""The Medivac's entry in each of SMAX's per-unit-type arguments (see the module table)."""

# Per-unit-type tables in SMAX's order (marine, marauder, stalker, zealot, zergling, hydralisk),
# then the Medivac.
HEAL_RATES = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 12.6)
"""Hit points restored per second, by unit type."""
HEALABLE = (True, True, False, True, True, True, False)
"""Biological unit types (a Medivac heals only those)."""
HITS_AIR = (True, False, True, False, False, True, False)
"""Unit types whose weapon can hit flying units."""
FLYING = (False, False, False, False, False, False, True)
"""Flying unit types (they collide with nothing)."""
MAX_ENERGY = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 200.0)
"""Energy capacity (0: the unit has no energy)."""
START_ENERGY = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 50.0)
"""Energy at the start of an episode."""
ENERGY_REGEN = 0.7875
"""Energy per second (units with energy)."""
HP_PER_ENERGY = 3.0
"""Hit points a heal restores per energy spent."""


def _team(marauders: int, marines: int, medivacs: int) -> list[int]:
    return [MARAUDER] * marauders + [MARINE] * marines + [MEDIVAC] * medivacs


SCENARIOS = {
    "MMM": Scenario(
        jnp.array(_team(2, 7, 1) + _team(2, 7, 1), dtype=jnp.uint8), 10, 10, False, False
    ),
    "MMM2": Scenario(
        jnp.array(_team(2, 7, 1) + _team(3, 8, 1), dtype=jnp.uint8), 10, 12, False, False
    ),
}
"""SMAC's MMM maps, by name."""


def _with_medivac() -> dict[str, Any]:
    """SMAX's default per-unit-type arguments with the Medivac appended."""
    defaults = inspect.signature(SMAX).parameters
    extended: dict[str, Any] = {}
    for name, medivac in _MEDIVAC_STATS.items():
        default = defaults[name].default
        extended[name] = (
            [*default, medivac] if isinstance(default, list) else jnp.append(default, medivac)
        )
    return extended


@dataclass
class HealerState(State):
    """SMAX's state plus each unit's energy (0 for units without energy)."""

    unit_energy: jax.Array


class HealerSMAX(SMAX):
    """SMAX with the Medivac (unit type 6); see the module docstring for the rules."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**{**_with_medivac(), **kwargs})
        self.unit_type_heal_rates = jnp.array(HEAL_RATES)
        self.unit_type_healable = jnp.array(HEALABLE)
        self.unit_type_hits_air = jnp.array(HITS_AIR)
        self.unit_type_flying = jnp.array(FLYING)
        self.unit_type_max_energy = jnp.array(MAX_ENERGY)
        self.unit_type_start_energy = jnp.array(START_ENERGY)
        num_slots = max(self.num_allies, self.num_enemies)
        self.num_ally_actions = self.num_enemy_actions = self.num_movement_actions + num_slots
        self.action_spaces = {
            agent: self._get_individual_action_space(i) for i, agent in enumerate(self.agents)
        }
        # [team, slot] -> the unit a target slot names (-1: none); team 1 counts in reverse.
        slots = np.arange(num_slots)
        na, ne, n = self.num_allies, self.num_enemies, self.num_agents
        self._enemy_slots = jnp.array(
            [np.where(slots < ne, na + slots, -1), np.where(slots < na, na - 1 - slots, -1)]
        )
        self._teammate_slots = jnp.array(
            [np.where(slots < na, slots, -1), np.where(slots < ne, n - 1 - slots, -1)]
        )

    # State: energy.

    @partial(jax.jit, static_argnums=(0,))
    def reset(self, key: jax.Array) -> tuple[dict[str, jax.Array], HealerState]:
        """SMAX's reset, with every unit at its starting energy."""
        obs, state = super().reset(key)
        fields = {field.name: getattr(state, field.name) for field in dataclasses.fields(state)}
        return obs, HealerState(**fields, unit_energy=self._energy(state))

    def _energy(self, state: State) -> jax.Array:
        """Each unit's energy. `SMAX.reset` observes the plain `State` it builds before `reset`
        adds energy: its units have their starting energy."""
        if isinstance(state, HealerState):
            return state.unit_energy
        return self.unit_type_start_energy[state.unit_types]

    def _energy_fraction(self, state: State) -> tuple[jax.Array, jax.Array]:
        """Each unit's energy / maximum, and whether it has energy at all."""
        max_energy = self.unit_type_max_energy[state.unit_types]
        has_energy = max_energy > 0
        return self._energy(state) / jnp.where(has_energy, max_energy, 1.0), has_energy

    # Targets: whom each unit's target actions name, and which are available.

    def _target_table(self, state: State) -> tuple[jax.Array, jax.Array, jax.Array]:
        """For each unit and target slot [num_agents, slots]: the unit it names, whether that
        unit exists, is alive and is of a kind the slot's owner may target, and whether it is in
        range. Healers' slots name teammates, everyone else's name enemies."""
        n = self.num_agents
        team = (jnp.arange(n) >= self.num_allies).astype(jnp.int32)
        types = state.unit_types
        healer = self.unit_type_heal_rates[types] > 0
        units = jnp.where(healer[:, None], self._teammate_slots[team], self._enemy_slots[team])
        exists = units >= 0
        units = jnp.maximum(units, 0)
        target_types = types[units]
        kind_ok = jnp.where(
            healer[:, None],
            self.unit_type_healable[target_types],
            self.unit_type_hits_air[types][:, None] | ~self.unit_type_flying[target_types],
        )
        targetable = exists & kind_ok & state.unit_alive[units]
        offsets = state.unit_positions[units] - state.unit_positions[:, None]
        in_range = jnp.linalg.norm(offsets, axis=-1) < self.unit_type_attack_ranges[types][:, None]
        return units, targetable, in_range

    @partial(jax.jit, static_argnums=(0,))
    def get_avail_actions(self, state: State) -> dict[str, jax.Array]:
        """Moves when alive, stop always, and the target slots `_target_table` allows."""
        _, targetable, in_range = self._target_table(state)
        alive = state.unit_alive[:, None]
        moves = jnp.broadcast_to(alive, (self.num_agents, self.num_movement_actions - 1))
        stop = jnp.ones((self.num_agents, 1), dtype=bool)
        masks = jnp.concatenate([moves, stop, targetable & in_range & alive], axis=-1)
        masks = masks.astype(jnp.uint8)
        return {agent: masks[i] for i, agent in enumerate(self.agents)}

    # Dynamics.

    @partial(jax.jit, static_argnums=(0,))
    def _world_step(
        self, key: jax.Array, state: HealerState, actions: tuple[jax.Array, jax.Array]
    ) -> HealerState:
        """SMAX's world step for the weapons, then the heals and energy."""
        movement, chosen = actions
        units, targetable, in_range = self._target_table(state)
        slot = jnp.maximum(chosen - self.num_movement_actions, 0)[:, None]
        target = jnp.take_along_axis(units, slot, axis=1)[:, 0]
        valid = (
            (chosen >= self.num_movement_actions)
            & jnp.take_along_axis(targetable & in_range, slot, axis=1)[:, 0]
            & state.unit_alive
        )
        healer = self.unit_type_heal_rates[state.unit_types] > 0
        # SMAX resolves every target action as an attack: hand it only valid weapon attacks.
        weapon_actions = jnp.where(valid & ~healer, chosen, 0)
        state = super()._world_step(key=key, state=state, actions=(movement, weapon_actions))

        types, health, energy = state.unit_types, state.unit_health, state.unit_energy
        max_health = self.unit_type_health[types]
        heal = valid & healer & (health[target] > 0)  # not a unit killed in this world step
        amount = jnp.minimum(
            self.unit_type_heal_rates[types] * self.time_per_step, energy * HP_PER_ENERGY
        )
        amount = jnp.where(heal, jnp.minimum(amount, max_health[target] - health[target]), 0.0)
        health = jnp.minimum(health.at[target].add(amount), max_health)
        regen = jnp.where(state.unit_alive, ENERGY_REGEN * self.time_per_step, 0.0)
        energy = jnp.clip(
            energy - amount / HP_PER_ENERGY + regen, 0.0, self.unit_type_max_energy[types]
        )
        return dataclasses.replace(state, unit_health=health, unit_energy=energy)

    def _update_dead_agents(self, state: State) -> State:
        """SMAX's deaths; a team with no unit left that can attack is out of the battle."""
        state = super()._update_dead_agents(state)
        fighting = state.unit_alive & (self.unit_type_attacks[state.unit_types] > 0)
        is_ally = jnp.arange(self.num_agents) < self.num_allies
        team_fights = jnp.where(
            is_ally, fighting[: self.num_allies].any(), fighting[self.num_allies :].any()
        )
        return dataclasses.replace(state, unit_alive=state.unit_alive & team_fights)

    def _push_units_away(self, state: State, firmness: float = 1.0) -> State:
        """SMAX's collisions between ground units; flying units collide with nothing (SMAX
        pushes only living units, so the pass counts them as dead)."""
        alive, flying = state.unit_alive, self.unit_type_flying[state.unit_types]
        pushed = dataclasses.replace(state, unit_alive=alive & ~flying)
        state = super()._push_units_away(pushed, firmness)
        return dataclasses.replace(state, unit_alive=alive)

    @partial(jax.jit, static_argnums=(0,))
    def compute_reward(
        self, state: State, health_before: jax.Array, health_after: jax.Array
    ) -> dict[str, jax.Array]:
        """SMAX's reward counting each unit's net health loss only (healing pays nothing)."""
        rewards: dict[str, jax.Array] = super().compute_reward(
            state, health_before, jnp.minimum(health_after, health_before)
        )
        return rewards

    # Observations: a Medivac's weapon cooldown slot shows its energy.

    @partial(jax.jit, static_argnums=(0,))
    def _observe_features(self, state: State, i: jax.Array, j_idx: jax.Array) -> jax.Array:
        features: jax.Array = super()._observe_features(state, i, j_idx)
        slot = self.unit_features.index("weapon_cooldown")
        energy, has_energy = self._energy_fraction(state)
        return features.at[slot].set(
            jnp.where(has_energy[j_idx], energy[j_idx], features[slot])
        )

    @partial(jax.jit, static_argnums=(0,))
    def _get_own_features(self, state: State, i: jax.Array) -> jax.Array:
        features: jax.Array = super()._get_own_features(state, i)
        slot = self.own_features.index("weapon_cooldown")
        energy, has_energy = self._energy_fraction(state)
        shown = has_energy[i] & state.unit_alive[i]
        return features.at[slot].set(jnp.where(shown, energy[i], features[slot]))

    def get_world_state(self, state: State) -> jax.Array:
        world = super().get_world_state(state)
        n, width = self.num_agents, len(self.own_features)
        units = world[: n * width].reshape(n, width)
        slot = self.own_features.index("weapon_cooldown")
        energy, has_energy = self._energy_fraction(state)
        shown = has_energy & state.unit_alive
        units = units.at[:, slot].set(jnp.where(shown, energy, units[:, slot]))
        return jnp.concatenate([units.reshape(-1), world[n * width :]])


# The scripted enemy.


def _move_towards(offset: jax.Array, stop_within: float = 0.0) -> jax.Array:
    """The move action (0 north, 1 east, 2 south, 3 west) best aligned with `offset`, or stop (4)
    when `offset` is shorter than `stop_within`."""
    directions = jnp.array([[0.0, 1.0], [1.0, 0.0], [0.0, -1.0], [-1.0, 0.0]])
    move = jnp.argmax(directions @ offset)
    return jnp.where(jnp.linalg.norm(offset) < stop_within, STOP, move)


def healer_heuristic_policy(
    world: HealerSMAX, team: int, shoot: bool = True, attack_mode: str = "closest"
) -> Callable[..., tuple[jax.Array, HeuristicPolicyState]]:
    """JaxMARL's heuristic for `team`, extended for healers and units that cannot hit air.

    The returned `policy(key, policy_state, obs, slot)` needs the unit's `slot`: its own
    position in its team's target-slot order (ally i: i; the enemy of global index i:
    `num_agents - 1 - i`), which the observation does not reveal. A healer heals the most
    injured teammate in range, else moves towards the most injured teammate it sees, else
    towards the teammates it sees, else (alone) as the heuristic moves. Other units play
    JaxMARL's heuristic, blind to flying units they cannot shoot.
    """
    fighter = create_heuristic_policy(world, team, shoot=shoot, attack_mode=attack_mode)
    mover = create_heuristic_policy(world, team, shoot=False)
    width, bits = len(world.unit_features), world.unit_type_bits
    others = world.num_agents - 1
    teammates = (world.num_allies if team == 0 else world.num_enemies) - 1

    def heal_action(
        blocks: jax.Array, own_type: jax.Array, slot: jax.Array
    ) -> tuple[jax.Array, jax.Array]:
        """A healer's action, and whether it sees any teammate."""
        mates = blocks[:teammates]
        health = mates[:, 0]  # 0 when dead or out of sight
        offsets = mates[:, 1:3] * world.unit_type_sight_ranges[own_type]
        mate_types = jnp.argmax(mates[:, width - bits :], axis=-1)
        seen = health > 0
        injured = seen & world.unit_type_healable[mate_types] & (health < 1.0)
        in_range = injured & (
            jnp.linalg.norm(offsets, axis=-1) < world.unit_type_attack_ranges[own_type]
        )
        patient = jnp.argmin(jnp.where(in_range, health, jnp.inf))
        heal = world.num_movement_actions + patient + (patient >= slot)
        neediest = jnp.argmin(jnp.where(injured, health, jnp.inf))
        centre = jnp.sum(offsets * seen[:, None], axis=0) / jnp.maximum(seen.sum(), 1)
        follow = jnp.where(
            injured.any(), _move_towards(offsets[neediest]), _move_towards(centre, 1.0)
        )
        return jnp.where(in_range.any(), heal, follow), seen.any()

    def policy(
        key: jax.Array, state: HeuristicPolicyState, obs: jax.Array, slot: jax.Array
    ) -> tuple[jax.Array, HeuristicPolicyState]:
        blocks = obs[: others * width].reshape(others, width)
        block_types = jnp.argmax(blocks[:, width - bits :], axis=-1)
        own_type = jnp.argmax(obs[-bits:])
        hidden = world.unit_type_flying[block_types] & ~world.unit_type_hits_air[own_type]
        fighter_obs = jnp.concatenate(
            [jnp.where(hidden[:, None], 0.0, blocks).reshape(-1), obs[others * width :]]
        )
        fight, fight_state = fighter(key, state, fighter_obs)
        move, move_state = mover(key, state, obs)
        heal, has_company = heal_action(blocks, own_type, slot)
        is_healer = world.unit_type_heal_rates[own_type] > 0
        action = jnp.where(is_healer, jnp.where(has_company, heal, move), fight)
        new_state = jax.tree.map(
            lambda m, f: jnp.where(is_healer, m, f), move_state, fight_state
        )
        return action, new_state

    return policy


class HeuristicEnemyHealerSMAX(HeuristicEnemySMAX):
    """`HeuristicEnemySMAX` on `HealerSMAX`, with `healer_heuristic_policy` for the enemy."""

    def __init__(
        self, enemy_shoots: bool = True, attack_mode: str = "closest", **env_kwargs: Any
    ) -> None:
        super().__init__(enemy_shoots=enemy_shoots, attack_mode=attack_mode, **env_kwargs)
        # EnemySMAX builds a plain SMAX: put the healer world in its place, and rebuild what
        # was derived from it.
        self._env = HealerSMAX(**env_kwargs)
        self.observation_spaces = {a: self._env.observation_spaces[a] for a in self.agents}
        self.action_spaces = {a: self._env.action_spaces[a] for a in self.agents}
        self.heuristic_policy = healer_heuristic_policy(
            self._env, 1, shoot=enemy_shoots, attack_mode=attack_mode
        )

    @property
    def world(self) -> HealerSMAX:
        """The two-team SMAX world the enemy heuristic plays in."""
        return cast(HealerSMAX, self._env)  # set in __init__; the base class declares SMAX

    def get_enemy_actions(
        self, key: jax.Array, policy_state: HeuristicPolicyState, enemy_obs: jax.Array
    ) -> tuple[dict[str, jax.Array], HeuristicPolicyState]:
        keys = jax.random.split(key, self.num_enemies)
        slots = self.num_enemies - 1 - jnp.arange(self.num_enemies)
        actions, policy_state = jax.vmap(self.heuristic_policy)(
            keys, policy_state, enemy_obs, slots
        )
        return {agent: actions[e] for e, agent in enumerate(self.enemy_agents)}, policy_state


# A scripted team, the sanity check that the units fight as designed.


def focus_fire_actions(env: HeuristicEnemyHealerSMAX, state: EnemyState) -> jax.Array:
    """Scripted ally actions [num_allies]: focus fire, with the Medivac healing.

    A fighter shoots the enemy with the fewest hit points in its range, else moves towards the
    nearest enemy it can shoot. A healer heals the most injured (by fraction) teammate in range,
    else moves towards the most injured teammate, else keeps with its team's fighters. Every
    action chosen is available under the action mask.
    """
    world, units = env.world, state.state
    named, targetable, in_range = world._target_table(units)
    types, health, alive = units.unit_types, units.unit_health, units.unit_alive
    healer = (world.unit_type_heal_rates[types] > 0)[:, None]
    fraction = health / world.unit_type_health[types]
    offsets = units.unit_positions[named] - units.unit_positions[:, None]

    # Fighters want every enemy they can shoot, fewest hit points first; healers want injured
    # teammates, lowest fraction first.
    wanted = targetable & (~healer | (fraction[named] < 1.0))
    priority = jnp.where(healer, fraction[named], health[named])
    in_reach = wanted & in_range
    target = jnp.argmin(jnp.where(in_reach, priority, jnp.inf), axis=1)
    # Out of reach, fighters close in on the nearest, healers on the neediest.
    closeness = jnp.where(healer, priority, jnp.linalg.norm(offsets, axis=-1))
    chase = jnp.argmin(jnp.where(wanted, closeness, jnp.inf), axis=1)
    chase_move = jax.vmap(_move_towards)(offsets[jnp.arange(world.num_agents), chase])
    # With nobody to heal, a healer keeps with its team's fighters.
    fighters = (jnp.arange(world.num_agents) < world.num_allies) & alive & ~healer[:, 0]
    centre = (units.unit_positions * fighters[:, None]).sum(0) / jnp.maximum(fighters.sum(), 1)
    keep_with_team = jax.vmap(partial(_move_towards, stop_within=1.0))(
        centre - units.unit_positions
    )

    idle = jnp.where(healer[:, 0], keep_with_team, STOP)
    move = jnp.where(wanted.any(axis=1), chase_move, idle)
    actions = jnp.where(in_reach.any(axis=1), world.num_movement_actions + target, move)
    return jnp.where(alive, actions, STOP)[: world.num_allies]


def focus_fire_policy(
    env: HeuristicEnemyHealerSMAX,
) -> Callable[[jax.Array, EnemyState, TimeStep], jax.Array]:
    """`focus_fire_actions` as a `first_episode_wins` policy of the adapter wrapping `env`."""
    return lambda key, state, timestep: jax.vmap(partial(focus_fire_actions, env))(state)


def first_episode_wins(
    env: MarlEnv,
    policy: Callable[[jax.Array, Any, TimeStep], jax.Array],
    num_envs: int,
) -> Callable[[jax.Array], jax.Array]:
    """A function playing one whole episode in each of `num_envs` envs, returning whether each
    was won [num_envs]. `policy(key, states, timesteps)` sees all envs at once and returns
    their actions [num_envs, num_agents].

    Every env's first episode counts, however long it lasts, so short episodes are not
    over-represented as they are in win rates counted over a fixed number of steps.
    """

    Carry = tuple[Any, TimeStep, jax.Array, jax.Array]

    def one_step(carry: Carry, key: jax.Array) -> tuple[Carry, None]:
        state, timestep, finished, won = carry
        action_key, step_key = jax.random.split(key)
        actions = policy(action_key, state, timestep)
        state, timestep = jax.vmap(env.step)(jax.random.split(step_key, num_envs), state, actions)
        won = jnp.where(finished, won, timestep.won)
        return (state, timestep, finished | timestep.done, won), None

    def run(key: jax.Array) -> jax.Array:
        reset_key, scan_key = jax.random.split(key)
        state, timestep = jax.vmap(env.reset)(jax.random.split(reset_key, num_envs))
        false = jnp.zeros((num_envs,), dtype=bool)
        steps = jax.random.split(scan_key, env.spec.max_episode_steps)
        (_, _, _, won), _ = jax.lax.scan(one_step, (state, timestep, false, false), steps)
        return won

    return run
