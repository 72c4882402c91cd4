"""A suite that is not cmat's: `coins:N`, N agents who each call heads (0) or tails (1) and
are paid the share of agents who called what the first agent called. Defined outside cmat and
found through the `cmat.suites` entry point that tests/test_plugins.py installs; nothing in
cmat names it."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from functools import partial
from typing import Any

from cmat.envs.protocol import EnvSpec, TimeStep
from cmat.envs.suites import Suite
from cmat.errors import CmatError

SUITE = Suite(
    ids="coins:N", builder="cmat_coins:build",
    settings={"total_steps": 2_000, "num_envs": 16, "rollout_length": 10, "ppo": {"epochs": 5}},
    source="the coins plugin's own settings",
)


class Coins:
    """N agents, one step: team reward = the share of agents whose call matches agent 0's."""

    def __init__(self, agents: int) -> None:
        self.spec = EnvSpec(env_id=f"coins:{agents}", num_agents=agents, obs_dim=1,
                            action_dim=2, discrete=True, max_episode_steps=1,
                            has_win_rate=False)

    def reset(self, key: Any) -> tuple[None, TimeStep]:
        import jax.numpy as jnp

        return None, self.timestep(jnp.float32(0.0), done=False)

    def step(self, key: Any, state: None, actions: Any) -> tuple[None, TimeStep]:
        import jax.numpy as jnp

        return None, self.timestep(jnp.mean(actions == actions[0]).astype(jnp.float32), True)

    def timestep(self, reward: Any, done: bool) -> TimeStep:
        import jax.numpy as jnp

        n = self.spec.num_agents
        return TimeStep(obs=jnp.ones((n, 1), jnp.float32),
                        action_mask=jnp.ones((n, 2), dtype=bool), reward=reward,
                        done=jnp.asarray(done), won=jnp.asarray(False),
                        alive=jnp.ones(n, dtype=bool), global_state=jnp.zeros(0, jnp.float32))


def build(env_id: str, name: str) -> tuple[Callable[..., Coins], Iterable[str]]:
    if not name.isdigit() or not 2 <= int(name) <= 64:
        raise CmatError(f"unknown coins task {name!r}; available: 2 to 64 agents")
    return partial(Coins, int(name)), ()
