"""One-step cooperative matrix games for two agents.

Every step is a whole episode: both agents act once, the team receives `payoff[a1][a2]`, and the
episode ends. The game has no state (`state` is None) and all actions are always available.

Each agent observes only its one-hot agent id. The agents are otherwise indistinguishable, and the
id keeps the policy order independent: permuting the agents permutes their ids with them.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Iterable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from cmat.envs.protocol import EnvSpec, TimeStep
from cmat.envs.suites import choose
from cmat.errors import CmatError

FIG1_PAYOFF = ((1.0, 0.0), (-100.0, 100.0))
"""The paper's Fig. 1 game with actions A=0, B=1: (A,A)=1, (A,B)=0, (B,A)=-100, (B,B)=100."""


class MatrixGame:
    """A two-agent one-step game whose team reward is `payoff[a1][a2]`."""

    def __init__(self, env_id: str, payoff: Sequence[Sequence[float]]) -> None:
        try:
            table = np.asarray(payoff, dtype=np.float32)
        except (TypeError, ValueError):
            table = np.empty(0, dtype=np.float32)
        square = table.ndim == 2 and table.shape[0] == table.shape[1] >= 2
        if not (square and np.isfinite(table).all()):
            raise CmatError(
                f"malformed payoff for {env_id}: expected a square k x k list of finite numbers "
                f"with k >= 2, got {payoff!r}"
            )
        self.payoff = jnp.asarray(table)
        self.spec = EnvSpec(
            env_id=env_id,
            num_agents=2,
            obs_dim=2,
            action_dim=table.shape[0],
            discrete=True,
            max_episode_steps=1,
            has_win_rate=False,
        )

    def reset(self, key: jax.Array) -> tuple[None, TimeStep]:
        """Start an episode (the key is unused: the game is deterministic)."""
        return None, self._timestep(jnp.float32(0.0), done=False)

    def step(self, key: jax.Array, state: None, actions: jax.Array) -> tuple[None, TimeStep]:
        """Pay `payoff[actions[0], actions[1]]` and end the episode."""
        return None, self._timestep(self.payoff[actions[0], actions[1]], done=True)

    def _timestep(self, reward: jax.Array, done: bool) -> TimeStep:
        return TimeStep(
            obs=jnp.eye(2, dtype=jnp.float32),
            action_mask=jnp.ones((2, self.spec.action_dim), dtype=bool),
            reward=reward,
            done=jnp.asarray(done),
            won=jnp.asarray(False),
            alive=jnp.ones(2, dtype=bool),
            global_state=jnp.zeros(0, jnp.float32),
        )


def fig1(payoff: Sequence[Sequence[float]] = FIG1_PAYOFF) -> MatrixGame:
    """The paper's Fig. 1 game, or any square `payoff` given in its place."""
    return MatrixGame("matrix:fig1", payoff)


def penalty(k: float = -100.0) -> MatrixGame:
    """Claus & Boutilier's penalty game: [[10, 0, k], [0, 2, 0], [k, 0, 10]]. Raises
    CmatError where `k` is not a finite number."""
    if isinstance(k, bool) or not isinstance(k, (int, float)) or not np.isfinite(k):
        raise CmatError(f"matrix:penalty: k must be a finite number, got {k!r}")
    return MatrixGame("matrix:penalty", [[10.0, 0.0, k], [0.0, 2.0, 0.0], [k, 0.0, 10.0]])


GAMES: dict[str, Callable[..., MatrixGame]] = {"fig1": fig1, "penalty": penalty}
"""Matrix game name → factory; the factory's keyword arguments are the game's options."""


def build(env_id: str, name: str) -> tuple[Callable[..., MatrixGame], Iterable[str]]:
    """The suite's builder (cmat.envs.suites.Builder): the game NAME and its options."""
    factory = GAMES[choose("matrix game", name, GAMES)]
    return factory, inspect.signature(factory).parameters
