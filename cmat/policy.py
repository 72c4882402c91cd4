"""A trained team's policy, loaded from a run directory, to act in a user's own loop.

    policy = cmat.load_policy("runs/smax_3m", seed=0)
    env = policy.make_env()                   # the environment the run trained on
    actions = policy.greedy(obs, action_mask)  # obs [n, obs_dim] or [B, n, obs_dim]

    memory = policy.initial_memory()           # a recurrent policy (recurrent Sable): per step,
    actions, memory = policy.greedy_with_memory(memory, obs, action_mask, start=new_episode)

The actions are those `cmat eval` takes (greedy) or training samples (`act`), ready for the
environment's `step`: discrete ones are action indices, continuous ones are clipped to the
spec's range (host adapters map them onto each agent's Box).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np

from cmat.algorithms.base import initial_memories, is_recurrent, with_memory
from cmat.config import TrainConfig
from cmat.envs.protocol import EnvSpec
from cmat.errors import CmatError
from cmat.rundir import SAVED_POLICY_HEADER, Checkpoint, RunDir, sha256

if TYPE_CHECKING:
    from cmat.algorithms.base import Algorithm

SAVED_FORMAT = "cmat-policy 1"
"""`policy.json`'s `format`: the layout `Policy.save` writes and `load_policy` reads."""
SAVED_PARAMS = "policy.msgpack"


@dataclass(frozen=True, eq=False)
class Policy:
    """One seed's trained parameters with its algorithm's acting functions, jitted."""

    spec: EnvSpec
    """The environment the policy expects: `num_agents`, `obs_dim`, `action_dim`, `discrete`."""
    config: TrainConfig
    """The run's config (config.yaml)."""
    seed: int
    """The seed of the run these parameters belong to (`config.seed + index`)."""
    env_steps: int
    """Env steps the parameters were trained for (below `config.budget_steps` if unfinished;
    from the best checkpoint, those of the seed's best evaluation)."""
    algorithm: Algorithm
    params: Any

    @property
    def complete(self) -> bool:
        """Whether the checkpoint is at the run's budget."""
        return self.env_steps == self.config.budget_steps

    @property
    def recurrent(self) -> bool:
        """Whether the policy acts from a state carried across an episode's steps; it then acts
        through `initial_memory` and `greedy_with_memory` only."""
        return is_recurrent(self.algorithm)

    def greedy(self, obs: Any, action_mask: Any = None) -> jax.Array:
        """The most likely actions: [n] ints or [n, A] floats for obs [n, obs_dim]; with a
        leading batch axis [B, ...] for obs [B, n, obs_dim]. `action_mask` [.., n, A] bool (True
        = available) defaults to every action.

        Raises CmatError if obs or action_mask do not have the spec's shapes, or if the policy
        is recurrent."""
        self._stateless("greedy")
        obs, action_mask = self._inputs(obs, action_mask)
        actions: jax.Array = _greedy_team(self, self.params, obs, action_mask)
        return actions

    def act(self, obs: Any, action_mask: Any = None, key: jax.Array | None = None) -> jax.Array:
        """Actions sampled as in training (shapes as `greedy`); `key` a jax PRNG key
        (default PRNGKey(0)), split over the batch.

        Raises CmatError if obs or action_mask do not have the spec's shapes, if `key` is not
        a PRNG key, or if the policy is recurrent."""
        self._stateless("act")
        obs, action_mask = self._inputs(obs, action_mask)
        key = jax.random.PRNGKey(0) if key is None else key
        if not isinstance(key, jax.Array) or not (
                jnp.issubdtype(key.dtype, jax.dtypes.prng_key)
                or (key.shape == (2,) and key.dtype == jnp.uint32)):
            raise CmatError(f"key must be a jax PRNG key (jax.random.PRNGKey(seed) or "
                            f"jax.random.key(seed)), got {type(key).__name__} {key!r}"[:200])
        actions: jax.Array = _sample_team(self, self.params, obs, action_mask, key)
        return actions

    def log_probs(self, obs: Any, action_mask: Any = None) -> jax.Array:
        """Each agent's log-probabilities of its actions, [n, A] for obs [n, obs_dim] (with a
        leading batch axis as `greedy`), -inf where `action_mask` rules an action out: the
        policy's decision for agents that decide independently given the team's observations
        (`cmat.algorithms.base.Factorised`: CMAT on its consensus, MAPPO, HAPPO, Triple-BERT).
        A joint decision under constraints between the agents scores them, as the dispatch
        tasks' conflict-free matching does (`cmat.envs.dispatch.matched`).

        Raises CmatError for MAT, PMAT and Sable (each agent's distribution depends on the
        actions decoded before it), for continuous actions, and for inputs of the wrong
        shape."""
        from cmat.algorithms.base import Factorised

        if not isinstance(self.algorithm, Factorised) or self.recurrent:
            raise CmatError(f"{self.config.algo} decodes its agents one after another, so it has "
                            f"no per-agent action distributions to score; CMAT, MAPPO, HAPPO and "
                            f"Triple-BERT have")
        if not self.spec.discrete:
            raise CmatError(f"log_probs needs discrete actions; {self.spec.env_id} has "
                            f"continuous ones")
        obs, action_mask = self._inputs(obs, action_mask)
        log_probs: jax.Array = _team_log_probs(self, self.params, obs, action_mask)
        return log_probs

    def save(self, path: str | Path) -> Path:
        """Write this policy to the new directory `path`, for `load_policy(path)` to act from
        without the run: `config.yaml` (the run's config), `policy.msgpack` (these parameters,
        flax msgpack; one seed, no optimiser state) and `policy.json` (`SAVED_FORMAT`, the cmat
        version, seed, env steps, the `EnvSpec`, the network the parameters belong to, and the
        SHA-256 of the three together: `bundle_digest`). CMAT's parameters for the 1,000-vehicle
        Manhattan fleet take 0.57 MB. Returns the directory.

        Raises CmatError where `path` is not a path, exists (nothing is replaced) or cannot be
        written; what a failure half-wrote, directories it created included, is removed."""
        from cmat.configfile import to_yaml
        from cmat.rundir import atomic_write, network_record
        from cmat.version import __version__

        if not isinstance(path, (str, os.PathLike)):
            raise CmatError(f"path must be a path, got {type(path).__name__}")
        target = Path(path)
        if target.exists() or target.is_symlink():
            raise CmatError(f"{target} already exists; a policy is saved to a new directory")
        data = flax.serialization.msgpack_serialize(
            flax.serialization.to_state_dict(jax.tree.map(np.asarray, self.params)))
        config_text = to_yaml(self.config, None).encode()
        header: dict[str, Any] = {
            "format": SAVED_FORMAT, "cmat": __version__, "algo": self.config.algo,
            "env": self.config.env, "seed": self.seed, "env_steps": self.env_steps,
            "spec": dataclasses.asdict(self.spec), "network": network_record(self.config),
            "size": len(data)}
        header["sha256"] = bundle_digest(header, config_text, data)
        created = [folder for folder in (target, *target.parents) if not folder.exists()]
        try:
            target.mkdir(parents=True)
            atomic_write(target / SAVED_PARAMS, data)
            atomic_write(target / "config.yaml", config_text)
            atomic_write(target / SAVED_POLICY_HEADER,
                         (json.dumps(header, indent=1) + "\n").encode())
        except BaseException as error:
            shutil.rmtree(target, ignore_errors=True)
            for folder in created[1:]:
                with contextlib.suppress(OSError):
                    folder.rmdir()
            if isinstance(error, OSError):
                raise CmatError(f"cannot write {error.filename or target}: "
                                f"{error.strerror or error}") from None
            raise
        return target

    def initial_memory(self, batch: int | None = None) -> Any:
        """The state before an episode's first step (() for a feed-forward policy); with
        `batch`, one per team of a batch [batch, ...]."""
        return initial_memories(self.algorithm, *(() if batch is None else (batch,)))

    def greedy_with_memory(
        self, memory: Any, obs: Any, action_mask: Any = None, start: Any = False,
    ) -> tuple[jax.Array, Any]:
        """`greedy` for any policy, recurrent ones included: the most likely actions from
        `memory`, the state the previous call of the same episode returned (`initial_memory()`
        at the first), reset first where `start` ([] or [B] bool) says `obs` begins a new
        episode. Returns the actions (shapes as `greedy`) and the state for the next step.

        Raises CmatError if obs or action_mask do not have the spec's shapes."""
        obs, action_mask = self._inputs(obs, action_mask)
        start = jnp.broadcast_to(jnp.asarray(start, bool), obs.shape[:-2])
        actions, memory = _greedy_team_with_memory(self, self.params, memory, obs, action_mask,
                                                   start)
        return actions, memory

    def _stateless(self, method: str) -> None:
        if self.recurrent:
            raise CmatError(
                f"this {self.config.algo} policy is recurrent: it acts "
                f"from a state carried across an episode's steps; use "
                f"policy.greedy_with_memory(policy.initial_memory(), obs, ...) instead of "
                f"policy.{method}")

    def make_env(self) -> Any:
        """A new instance of the environment the run trained on, with its `env_kwargs`: an
        in-graph `MarlEnv` (jax `reset(key)` / `step(key, state, actions)`) or, for host
        suites, a `HostEnv` (numpy `reset(seed)` / `step(actions)`)."""
        from cmat.envs import make_env
        from cmat.envs.host import is_host_env, make_host_env

        if is_host_env(self.config.env):
            return make_host_env(self.config.env, seed=self.seed, **self.config.env_kwargs)
        return make_env(self.config.env, **self.config.env_kwargs)

    def _inputs(self, obs: Any, action_mask: Any) -> tuple[jax.Array, jax.Array]:
        spec = self.spec
        obs = jnp.asarray(obs, jnp.float32)
        team = (spec.num_agents, spec.obs_dim)
        if obs.ndim not in (2, 3) or obs.shape[-2:] != team:
            raise CmatError(f"obs must have shape {team} or (batch, *{team}) for "
                            f"{spec.env_id}, got {tuple(obs.shape)}")
        finite = np.isfinite(np.asarray(obs))
        if not finite.all():
            where = tuple(int(i) for i in np.argwhere(~finite)[0][:-1])
            raise CmatError(f"obs holds a NaN or infinite value (team member {where})")
        mask_shape = (*obs.shape[:-1], spec.action_dim)
        if action_mask is None:
            return obs, jnp.ones(mask_shape, bool)
        action_mask = jnp.asarray(action_mask, bool)
        if action_mask.shape != mask_shape:
            raise CmatError(f"action_mask must have shape {mask_shape} for obs of shape "
                            f"{tuple(obs.shape)}, got {tuple(action_mask.shape)}")
        allowed = np.asarray(action_mask).any(-1)
        if spec.discrete and not allowed.all():
            where = tuple(int(i) for i in np.argwhere(~allowed)[0])
            raise CmatError(f"action_mask allows no action for team member {where} (a dead "
                            f"agent allows its no-op)")
        return obs, action_mask


@functools.partial(jax.jit, static_argnums=0)
def _greedy_team(policy: Policy, params: Any, obs: jax.Array, mask: jax.Array) -> jax.Array:
    from cmat.runners.collector import env_actions

    act = policy.algorithm.greedy
    actions = act(params, obs, mask) if obs.ndim == 2 else jax.vmap(act, (None, 0, 0))(
        params, obs, mask)
    return env_actions(policy.spec, actions)


@functools.partial(jax.jit, static_argnums=0)
def _team_log_probs(policy: Policy, params: Any, obs: jax.Array, mask: jax.Array) -> jax.Array:
    logits = policy.algorithm.action_logits  # type: ignore[attr-defined]
    if obs.ndim == 3:
        logits = jax.vmap(logits, (None, 0, 0))
    log_probs = jax.nn.log_softmax(logits(params, obs, mask), axis=-1)
    return jnp.where(mask, log_probs, -jnp.inf)


@functools.partial(jax.jit, static_argnums=0)
def _greedy_team_with_memory(
    policy: Policy, params: Any, memory: Any, obs: jax.Array, mask: jax.Array, start: jax.Array,
) -> tuple[jax.Array, Any]:
    from cmat.runners.collector import env_actions

    act = with_memory(policy.algorithm).greedy_with_memory
    if obs.ndim == 2:
        actions, memory = act(params, memory, obs, mask, start)
    else:
        actions, memory = jax.vmap(act, (None, 0, 0, 0, 0))(params, memory, obs, mask, start)
    return env_actions(policy.spec, actions), memory


@functools.partial(jax.jit, static_argnums=0)
def _sample_team(
    policy: Policy, params: Any, obs: jax.Array, mask: jax.Array, key: jax.Array
) -> jax.Array:
    from cmat.runners.collector import env_actions

    state = jnp.zeros(policy.spec.state_dim)

    def one(obs: jax.Array, mask: jax.Array, key: jax.Array) -> jax.Array:
        return policy.algorithm.act(params, obs, mask, key, state).actions

    if obs.ndim == 2:
        actions = one(obs, mask, key)
    else:
        actions = jax.vmap(one)(obs, mask, jax.random.split(key, obs.shape[0]))
    return env_actions(policy.spec, actions)


def load_policy(
    run_dir: str | Path, seed: int | None = None, checkpoint: Checkpoint = "latest"
) -> Policy:
    """The policy of seed `seed` (default: the run's first, `config.seed`) from checkpoint
    `checkpoint` of the run directory `run_dir`: `latest` (which may be unfinished, see
    `Policy.complete`), `best` (the seed's parameters at its best evaluation; `env_steps` says
    when) or the env steps of a periodic one (cmat.runners.checkpoints). `run_dir` may also be
    a policy saved by `Policy.save` (its one seed and checkpoint: `seed` and `checkpoint` left
    at their defaults, or naming that seed).

    Raises CmatError for a `run_dir` that is not a path or holds no run or checkpoint, a corrupt
    checkpoint, a seed that is not an int or that the run did not train, or a run whose files
    this version of cmat cannot read."""
    from cmat.runners import build_trainer
    from cmat.runners.base import restore_run

    if not isinstance(run_dir, (str, os.PathLike)):
        raise CmatError(f"run_dir must be a path, got {type(run_dir).__name__}")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer))):
        raise CmatError(f"seed must be an int, got {type(seed).__name__} {seed!r}")
    if not (checkpoint in ("latest", "best") or (
            isinstance(checkpoint, int) and not isinstance(checkpoint, bool) and checkpoint >= 0)):
        raise CmatError(f"checkpoint must be 'latest', 'best' or the env steps of a kept "
                        f"checkpoint (an int), got {checkpoint!r}")
    if RunDir(Path(run_dir)).is_saved_policy:
        return load_saved(Path(run_dir), seed, checkpoint)
    run = RunDir.open(Path(run_dir))
    config = run.config()
    seed = config.seed if seed is None else int(seed)
    index = seed - config.seed
    if not 0 <= index < config.seeds:
        seeds = f"{config.seed}..{config.seed + config.seeds - 1}"
        raise CmatError(f"{run.path} trained seeds {seeds}; there is no seed {seed}")
    trainer = build_trainer(config)
    state, env_steps = restore_run(run, trainer, checkpoint)
    if checkpoint == "best":
        env_steps = int((run.checkpoint_header("best") or {})["best"]["env_steps"][index])
    params = jax.tree.map(lambda leaf: np.asarray(leaf)[index], state.learner.params)
    trainer.close()
    return Policy(trainer.env_spec, config, seed, env_steps, trainer.learner_setup.algorithm,
                  jax.tree.map(jnp.asarray, params))


def bundle_digest(header: dict[str, Any], config_text: bytes, params: bytes) -> str:
    """SHA-256 of a saved policy's three parts together: `policy.json` without its `sha256`
    (canonical JSON), `config.yaml` and `policy.msgpack`. An edit to any one of them, or parts
    of two saved policies put together, no longer matches the digest `policy.json` records."""
    fields = json.dumps({k: v for k, v in header.items() if k != "sha256"}, sort_keys=True)
    return sha256(b"\0".join((fields.encode(), config_text, params)))


def load_saved(path: Path, seed: int | None, checkpoint: Checkpoint) -> Policy:
    """The policy `Policy.save` wrote to `path`. CmatError where `seed` or `checkpoint` ask
    for another than it holds; where a file is missing or unreadable; where the three files do
    not match the digest `policy.json` records (an edit, damage, or parts of two saved
    policies); and where a header field has the wrong type, the parameters are not the
    float32 arrays of the network `config.yaml` describes, or are not finite."""
    from cmat.algorithms import build_algorithm, check_config
    from cmat.configfile import from_yaml

    header_file, config_file, params_file = (path / SAVED_POLICY_HEADER, path / "config.yaml",
                                             path / SAVED_PARAMS)
    try:
        header = json.loads(header_file.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        raise CmatError(f"corrupt saved policy header: {header_file}") from None
    if not isinstance(header, dict):
        raise CmatError(f"corrupt saved policy header: {header_file}")
    if header.get("format") != SAVED_FORMAT:
        raise CmatError(f"{header_file}: format {header.get('format')!r} is not "
                        f"{SAVED_FORMAT!r}")
    parts = []
    for file in (config_file, params_file):
        try:
            parts.append(file.read_bytes())
        except OSError:
            raise CmatError(f"cannot read {file}") from None
    config_text, data = parts
    if bundle_digest(header, config_text, data) != header.get("sha256"):
        raise CmatError(f"corrupt saved policy {path}: policy.json, config.yaml and "
                        f"policy.msgpack are not the files saved together (their SHA-256 "
                        f"differs from the one policy.json records)")
    saved_seed, env_steps, spec = saved_fields(header, header_file)
    if seed is not None and int(seed) != saved_seed:
        raise CmatError(f"{path} is the saved policy of seed {saved_seed}; there is no seed "
                        f"{seed}")
    if checkpoint != "latest":
        raise CmatError(f"{path} is a saved policy, one checkpoint (env step {env_steps}); "
                        f"checkpoint {checkpoint!r} is the run directory's choice")
    try:
        config = check_config(from_yaml(config_text.decode()))
    except CmatError as error:
        raise CmatError(f"{config_file}: {error}") from None
    except UnicodeDecodeError:
        raise CmatError(f"cannot read {config_file}") from None
    if (config.algo, config.env) != (header.get("algo"), header.get("env")):
        raise CmatError(f"{config_file} is a {config.algo} run on {config.env}, and "
                        f"{header_file} a {header.get('algo')} policy on {header.get('env')}")
    algorithm = build_algorithm(config.algo, config.network, spec, config.ppo, config.options)
    template = jax.eval_shape(algorithm.init, jax.random.PRNGKey(0),
                              jnp.zeros((spec.num_agents, spec.obs_dim), jnp.float32),
                              jnp.ones((spec.num_agents, spec.action_dim), bool))
    try:
        params = flax.serialization.from_state_dict(
            template, flax.serialization.msgpack_restore(data))
        fits = all(isinstance(leaf, np.ndarray) and leaf.shape == expected.shape
                   and leaf.dtype == expected.dtype for leaf, expected in
                   zip(jax.tree.leaves(params), jax.tree.leaves(template), strict=True))
    except Exception:  # msgpack and flax raise many kinds for foreign bytes
        fits = False
    if not fits:
        raise CmatError(f"{params_file} does not fit the {config.algo} network of {config_file}")
    if not all(np.isfinite(leaf).all() for leaf in jax.tree.leaves(params)):
        raise CmatError(f"{params_file} holds NaN or infinite parameters")
    return Policy(spec, config, saved_seed, env_steps, algorithm,
                  jax.tree.map(jnp.asarray, params))


def saved_fields(header: dict[str, Any], header_file: Path) -> tuple[int, int, EnvSpec]:
    """The seed, env steps and `EnvSpec` a saved policy's header records, each checked for its
    type and range (CmatError naming the field)."""
    def integer(value: Any, name: str, least: int | None) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or (
                least is not None and value < least):
            bound = "" if least is None else f" >= {least}"
            raise CmatError(f"{header_file}: {name} must be an integer{bound}, got {value!r}")
        return int(value)

    spec_fields = header.get("spec")
    names = {field.name: field for field in dataclasses.fields(EnvSpec)}
    if not isinstance(spec_fields, dict) or set(spec_fields) != set(names):
        raise CmatError(f"{header_file}: spec must hold exactly the fields of an EnvSpec "
                        f"({', '.join(names)})")
    checked: dict[str, Any] = {}
    for name, value in spec_fields.items():
        kind = str(names[name].type)
        if kind == "int":
            checked[name] = integer(value, f"spec.{name}", 0 if name == "state_dim" else 1)
        elif kind == "bool" and isinstance(value, bool):
            checked[name] = value
        elif kind == "float" and isinstance(value, (int, float)) and not isinstance(value, bool):
            checked[name] = float(value)
        elif kind == "str" and isinstance(value, str):
            checked[name] = value
        elif kind.startswith("tuple") and isinstance(value, list) and all(
                isinstance(item, str) for item in value):
            checked[name] = tuple(value)
        else:
            raise CmatError(f"{header_file}: spec.{name} must be {kind}, got {value!r}")
    return (integer(header.get("seed"), "seed", None),
            integer(header.get("env_steps"), "env_steps", 0), EnvSpec(**checked))
