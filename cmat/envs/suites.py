"""Suites: the environment-id prefixes cmat knows, each one `Suite` entry (how to build its
environments, its default settings, whether it runs on the host, how it is drawn), and those that
installed packages add (`registry`).

A suite's settings are the config layer between the dataclass defaults and the algorithm's
reference defaults (`cmat.resolve.resolve_config`): the reference MAT hyper-parameters of that
benchmark family (from the reference MAT implementation's train scripts) and the budget a user
of the suite expects. `cmat train --env mamujoco:HalfCheetah-6x1` therefore trains with MAT's
MA-MuJoCo settings without a `--set`; the run's config.yaml names the suite as the source of
each value it set.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from cmat.errors import CmatError, SuiteUnavailable
from cmat.plugins import with_plugins

PAPER_BUDGET = 10_000_000
"""Env steps per seed of every task in the paper's experiments (MAT's budget)."""

MATRIX_BUDGET = 4_000
"""Env steps per seed of a matrix game at 16 envs × 25 steps and 5 epochs: twice the least
budget measured to suffice. On matrix:fig1 every method ends at the optimum in 10 of 10 seeds at
2,000 steps, CMAT in 2 of 10 at 1,000 (benchmarks/matrix_optimum.py --steps N,
docs/suites.md)."""

SMAC_SETTINGS: dict[str, Any] = {
    "rollout_length": 100, "num_envs": 32,
    "ppo": {"lr": 5e-4, "adam_eps": 1e-5, "epochs": 15, "num_minibatches": 1, "clip_eps": 0.05,
            "ent_coef": 0.01, "max_grad_norm": 10.0},
}
"""MAT's SMAC column: 32 rollout threads × 100 steps, 15 epochs, one minibatch, lr 5e-4."""

MAVA_BUDGET = 1000 * 128 * 16 * 2
"""Env steps per seed of Mava's default Sable run (4,096,000): `num_updates` 1000 ×
`rollout_length` 128 × `num_envs` 16 × `update_batch_size` 2 (instadeepai/Mava
`mava/configs/system/sable/ff_sable.yaml` at b53e2de, the file the PPO settings below come
from; `mava/configs/arch/anakin.yaml` at 0258bb8). Mava's `ppo/ff_mappo.yaml` at 7d77035 runs
1220 updates; one budget serves every line of a suite, and the Sable comparison is what these
suites are for."""

MAVA_SETTINGS: dict[str, Any] = {
    "rollout_length": 128, "num_envs": 32, "total_steps": MAVA_BUDGET,
    "env_kwargs": {"agent_id": True},
    "ppo": {"lr": 2.5e-4, "adam_eps": 1e-5, "epochs": 4, "num_minibatches": 2, "clip_eps": 0.2,
            "ent_coef": 0.01, "value_coef": 0.5, "max_grad_norm": 0.5, "gamma": 0.99,
            "gae_lambda": 0.95},
}
"""Mava's PPO defaults, the same in its system configs `ppo/ff_mappo.yaml` (7d77035) and
`sable/ff_sable.yaml` (b53e2de), which it uses for RWARE, LBF and MABrax alike:
lr 2.5e-4 (Adam, eps 1e-5), 128 steps, 4 epochs of 2 minibatches, clip 0.2, entropy 0.01, value
coefficient 0.5, gradient norm 0.5; 16 envs × `update_batch_size` 2, whose gradients Mava
averages, are 32 envs here; agent ids on (`add_agent_id: True`)."""

DISPATCH_SETTINGS: dict[str, Any] = {
    "rollout_length": 30, "num_envs": 4, "total_steps": 200_000, "eval_episodes": 8,
    "eval_actions": "sample", "sable": {"retention_chunk": 1},
    "ppo": {"lr": 5e-4, "adam_eps": 1e-5, "epochs": 5, "num_minibatches": 1, "clip_eps": 0.2,
            "ent_coef": 0.01, "max_grad_norm": 10.0},
}
"""The dispatch suite (`cmat.envs.dispatch`): 4 environments × 30 one-minute steps per update
(12,000 vehicle decisions at 100 vehicles), 5 epochs at clip 0.2. CMAT's consensus iterations
follow its large-team rule (`cmat.algorithms.cmat.options.LARGE_TEAM`: m = 2 for fleets of
more than 32 vehicles), which scored highest against m = 1, 5 (the CMAT authors' ride-sharing
code ran 1,000 vehicles with consensus length 5) and 10 on grid-100-mid (docs/dispatch.md);
the committed `dispatch` grid pins m = 5 in its spec, as it was trained. Measured
on dispatch:grid-100-mid (one seed each, docs/dispatch.md): at 24k steps, 4 × 30 reached a
greedy return of 22.1–22.4 with MAPPO and CMAT, where 8 × 60 (one whole episode per rollout)
was at 13–22 after 48k. The budget is per seed in environment steps (fleet minutes).
Evaluation samples the policy: greedy decoding sends every vehicle with the same observation to
the same choice, and on grid-100-mid after 24k steps (3 seeds × 16 episodes) it swung between
seeds and checkpoints (CMAT 16.4–21.7, MAPPO 9.0–23.3; service rate 52–96 %) where sampling
held CMAT at 19.0–22.4 and MAPPO at 20.2–21.4 (service rate 96–98 %).
Sable's training pass runs one timestep per chunk (`sable.retention_chunk`): its whole-rollout
pass (Mava's default) scores every vehicle of every step against every other, (31 · n)² per
head and environment, where chunks of one step score n² per step and carry the retention state
between them, the same numbers up to float rounding (tests/test_sable.py). On grid-100-mid
(2-core AMD EPYC, beside another run, 2026-12-07) one seed trained at 26 steps/s against
5.3 with the whole rollout in one pass (from the progress of 1,200- and 3,600-step runs)."""


Builder = Callable[[str, str], tuple[Callable[..., Any], Iterable[str] | None]]
"""A suite's builder: (env id, NAME after the prefix) -> (a factory that takes the environment's
options as keywords and returns it, the option names it accepts or None where the factory checks
them itself). Raises CmatError for a NAME the suite does not have."""


@dataclass(frozen=True)
class Suite:
    """One family of environments behind an id prefix (`PREFIX:NAME`): everything cmat knows of
    it, with no import of the suite's own code or of JAX (its builder is imported on first use).
    A package adds one by naming a `Suite` under the `cmat.suites` entry-point group, the entry
    point's name being the prefix (docs/own-environment.md)."""

    ids: str
    """The form of its ids, for help texts: `smax:SCENARIO`."""
    builder: str
    """`module:function` of its `Builder`; imported when an environment is built."""
    settings: dict[str, Any]
    """Config values (nested as in a config file) this suite's runs start from; a section
    named by an algorithm (`cmat: {consensus_iterations: 5}`) applies to that algorithm's runs
    only."""
    source: str
    """Where the settings come from (`cmat config` prints it under the fields, whose sources
    read `suite PREFIX`)."""
    host: bool = False
    """Stepped in Python by the host runner (cmat.runners.host), not inside the JAX program:
    its factory takes `seed` (the run's seed) besides the options."""
    requires: tuple[str, str] | None = None
    """(module, how to install it) where the suite needs a package cmat does not install:
    without it the suite is unavailable here (`SuiteUnavailable`), not wrong."""
    renderer: str | None = None
    """How `cmat render` draws it: 'jaxmarl' (JaxMARL's own renderers, in-graph) or 'rgb_array'
    (the simulator's `render()`), None where it cannot."""

    def unavailable(self, env_id: str) -> str | None:
        """Why `env_id` cannot be built on this machine (`requires` is not installed), else None;
        found without importing the suite or JAX."""
        if self.requires is not None and importlib.util.find_spec(self.requires[0]) is None:
            return f"{env_id} needs {self.requires[0]}, which is not installed: {self.requires[1]}"
        return None

    def build(self, env_id: str) -> tuple[Callable[..., Any], Iterable[str] | None]:
        """The factory and option names of `env_id` (its `Builder`'s answer).

        Raises SuiteUnavailable where `requires` is missing, CmatError for an unknown NAME."""
        if (why := self.unavailable(env_id)) is not None:
            raise SuiteUnavailable(why)
        module, _, function = self.builder.partition(":")
        builder: Builder = getattr(importlib.import_module(module), function)
        return builder(env_id, env_id.partition(":")[2])


SUITES: dict[str, Suite] = {
    "matrix": Suite(
        "matrix:NAME", "cmat.envs.matrix:build",
        {"total_steps": MATRIX_BUDGET, "num_envs": 16, "rollout_length": 25, "ppo": {"epochs": 5}},
        "matrix games: the budget they need, measured (MATRIX_BUDGET)",
    ),
    "smax": Suite("smax:SCENARIO", "cmat.envs.jaxmarl_envs:build_smax",
                  {**SMAC_SETTINGS, "total_steps": PAPER_BUDGET},
                  "MAT's SMAC scripts; the paper's 1e7 steps", renderer="jaxmarl"),
    "mpe": Suite("mpe:NAME", "cmat.envs.jaxmarl_envs:build_mpe",
                 {**SMAC_SETTINGS, "total_steps": PAPER_BUDGET},
                 "no MAT reference for MPE: its SMAC settings; the paper's 1e7 steps",
                 renderer="jaxmarl"),
    "jumanji": Suite("jumanji:TASK", "cmat.envs.jumanji_envs:build", MAVA_SETTINGS,
                     "Mava's ff_mappo/ff_sable defaults for Jumanji RWARE and LBF; its budget"),
    "mabrax": Suite("mabrax:TASK", "cmat.envs.mabrax_envs:build", MAVA_SETTINGS,
                    "Mava's ff_mappo/ff_sable defaults, which it runs MABrax with; its budget",
                    requires=("brax", "pip install 'brax>=0.14.2,<0.15' (cmat's mabrax extra)")),
    "dispatch": Suite("dispatch:CITY-N-LEVEL (e.g. dispatch:grid-100-mid)",
                      "cmat.envs.dispatch:build", DISPATCH_SETTINGS,
                      "cmat's dispatch suite: half an episode per rollout; budget and PPO "
                      "settings measured (DISPATCH_SETTINGS)"),
    "jax": Suite("jax:package.module:factory (your own)", "cmat.envs.user_jax:build",
                 {"total_steps": PAPER_BUDGET},
                 "a user's JAX env: the dataclass defaults; the paper's 1e7 steps"),
    "mamujoco": Suite(
        "mamujoco:SCENARIO-CONF", "cmat.envs.host.mamujoco:build",
        {"num_envs": 40, "rollout_length": 100, "total_steps": PAPER_BUDGET, "eval_episodes": 8,
         "env_kwargs": {"agent_id": True},
         "ppo": {"lr": 5e-5, "adam_eps": 1e-5, "epochs": 10, "num_minibatches": 40,
                 "clip_eps": 0.05, "ent_coef": 0.001, "max_grad_norm": 0.5}},
        "MAT's MA-MuJoCo scripts (agent ids: the agents are different joints); the paper's 1e7",
        host=True, renderer="rgb_array",
    ),
    "grf": Suite(
        "grf:SCENARIO", "cmat.envs.host.grf:build",
        {"num_envs": 20, "rollout_length": 200, "total_steps": PAPER_BUDGET,
         "ppo": {"lr": 5e-4, "adam_eps": 1e-5, "epochs": 10, "num_minibatches": 1,
                 "clip_eps": 0.05, "ent_coef": 0.01, "max_grad_norm": 0.5}},
        "MAT's GRF scripts; the paper's 1e7 steps",
        host=True,
    ),
    "pettingzoo": Suite("pettingzoo:package.module:factory (your own)",
                        "cmat.envs.host.pettingzoo_env:build", {"total_steps": PAPER_BUDGET},
                        "a user's ParallelEnv: the paper's 1e7 steps", host=True,
                        renderer="rgb_array"),
}
"""The suites cmat ships: prefix -> Suite, in the order help texts list them."""

ENTRY_POINTS = "cmat.suites"
"""The entry-point group where installed packages name their suites."""


@functools.cache
def registry() -> dict[str, Suite]:
    """Every suite: cmat's own (`SUITES`), then those installed packages add under
    `ENTRY_POINTS` (cmat.plugins: a broken one is skipped with a one-line warning)."""
    return with_plugins(SUITES, ENTRY_POINTS, Suite, "suite")


def suite_of(env_id: str) -> Suite:
    """The suite of `env_id` (PREFIX:NAME); CmatError for an unknown prefix."""
    prefix = env_id.partition(":")[0]
    suites = registry()
    if prefix not in suites:
        raise CmatError(f"unknown environment prefix {prefix!r} in {env_id!r} (ids are "
                        f"PREFIX:NAME); available: {', '.join(suites)}")
    return suites[prefix]


def is_host_env(env_id: str) -> bool:
    """Whether `env_id` names an environment of a host suite (an unknown prefix: False)."""
    suite = registry().get(env_id.partition(":")[0])
    return suite is not None and suite.host


def choose(kind: str, name: str, available: Iterable[str], also: str = "") -> str:
    """`name`, where it is one of `available`; else CmatError listing them (and `also`)."""
    if name not in available:
        listed = ", ".join([*available, *([also] if also else [])])
        raise CmatError(f"unknown {kind} {name!r}; available: {listed}")
    return name
