"""`grf:SCENARIO`: Google Research Football academy scenarios through gfootball.

As the MAT and HARL GRF setups: the left team's first n players are the agents, each observes the
`simple115v2` vector (115 floats), picks one of the 19 default actions (all always available),
and the reward is `scoring,checkpoints` (the same for every agent, so the team reward, the mean,
equals it). An episode is won when the team scored in it (the sum of gfootball's
`info["score_reward"]` is positive): the win rate is GRF's score rate. Episodes end as the
scenario says (a goal, the ball lost or out, or its 400-step duration).

gfootball is not on PyPI as a wheel: `scripts/install_grf.sh` builds it (about 10 minutes on 2
cores). Keyword arguments go to `gfootball.env.create_environment` (e.g. `rewards="scoring"`).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np

from cmat.envs.host.protocol import AutoReset, simulator_call
from cmat.envs.protocol import EnvSpec
from cmat.errors import CmatError, SuiteUnavailable

SCENARIOS = {
    "academy_3_vs_1_with_keeper": 3,
    "academy_counterattack_easy": 4,
    "academy_pass_and_shoot_with_keeper": 2,
}
"""Scenarios and their number of controlled players (the MAT / HARL settings)."""

OBS_DIM = 115
NUM_ACTIONS = 19
EPISODE_STEPS = 400
"""`game_duration` of the academy scenarios."""


def import_gfootball() -> Any:
    """`gfootball.env`, or a CmatError saying how to install it."""
    try:
        import gfootball.env as football_env
    except ImportError as error:
        raise SuiteUnavailable(
            f"GRF needs gfootball ({error}); build it with scripts/install_grf.sh"
        ) from None
    return football_env


class GRFEnv(AutoReset):
    """One GRF academy game behind the host protocol (see the module docstring)."""

    def __init__(self, env_id: str, scenario: str, seed: int = 0, **kwargs: Any) -> None:
        if scenario not in SCENARIOS:
            raise CmatError(
                f"unknown GRF scenario {scenario!r}; available: {', '.join(SCENARIOS)}"
            )
        football_env = import_gfootball()
        self.num_agents = SCENARIOS[scenario]
        options = {
            "env_name": scenario,
            "stacked": False,
            "representation": "simple115v2",
            "rewards": "scoring,checkpoints",
            "write_goal_dumps": False,
            "write_full_episode_dumps": False,
            "render": False,
            "write_video": False,
            "dump_frequency": 0,
            "number_of_left_players_agent_controls": self.num_agents,
            "other_config_options": {"game_engine_random_seed": int(seed)},
            **kwargs,
        }
        try:
            self.env = football_env.create_environment(**options)
        except TypeError as error:
            raise CmatError(f"bad option for {env_id}: {error}") from None
        self.spec = EnvSpec(
            env_id=env_id,
            num_agents=self.num_agents,
            obs_dim=OBS_DIM,
            action_dim=NUM_ACTIONS,
            discrete=True,
            max_episode_steps=EPISODE_STEPS,
            has_win_rate=True,
        )
        self._mask = np.ones((self.num_agents, NUM_ACTIONS), bool)
        self._score = 0.0

    def close(self) -> None:
        """Close the game engine."""
        self.env.close()

    def _obs(self, obs: Any) -> np.ndarray:
        return np.asarray(obs, np.float32).reshape(self.num_agents, OBS_DIM)

    def _reset(self, seed: int | None) -> tuple[np.ndarray, np.ndarray]:
        with simulator_call(self.spec.env_id, "reset"):
            result = self.env.reset()
        obs = result[0] if isinstance(result, tuple) else result
        self._score = 0.0
        return self._obs(obs), self._mask

    def _step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, bool, bool]:
        with simulator_call(self.spec.env_id, "step"):
            result = self.env.step([int(a) for a in np.asarray(actions).reshape(-1)])
        if len(result) == 5:
            obs, reward, terminated, truncated, info = result
            done = bool(terminated or truncated)
        else:
            obs, reward, done, info = result
        self._score += float(info.get("score_reward", 0.0))
        won = bool(done) and self._score > 0
        return self._obs(obs), self._mask, float(np.mean(reward)), bool(done), won


def build(env_id: str, name: str) -> tuple[Callable[..., GRFEnv], None]:
    """The grf suite's builder (cmat.envs.suites.Builder): GRF takes its seed when built."""
    return partial(GRFEnv, env_id, name), None
