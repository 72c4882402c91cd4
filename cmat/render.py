"""Greedy episodes of a trained policy, drawn with each suite's own renderer into a GIF or MP4.

SMAX frames come from JaxMARL's SMAX renderer (`init_render`, one frame per env step: SMAX's
sub-steps are not expanded), MPE frames from JaxMARL's `MPEVisualizer`; MaMuJoCo and PettingZoo
environments draw themselves (`render_mode="rgb_array"`; MuJoCo headless through OSMesa,
scripts/install_render.sh). Every frame is titled with the episode, the step, the return so far,
and at the episode's last frame whether it was won. Matrix games have no picture: rendering
one is an error.
"""

from __future__ import annotations

import contextlib
import io
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from cmat.envs.suites import registry, suite_of
from cmat.errors import CmatError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from cmat.policy import Policy

FORMATS = (".gif", ".mp4")


@dataclass(frozen=True)
class Frame:
    """What one picture shows: the environment after `step` steps of an episode."""

    picture: Any
    """The suite's state (JaxMARL) or an RGB array (host environments)."""
    episode: int
    step: int
    episode_return: float
    outcome: str | None = None
    """'won', 'lost' or 'ended' on an episode's last frame, else None."""

    @property
    def title(self) -> str:
        text = f"episode {self.episode + 1} · step {self.step} · return {self.episode_return:.2f}"
        return text + (f" · {self.outcome}" if self.outcome else "")


def render_episodes(
    policy: Policy, out: Path, episodes: int = 1, seed: int = 0, fps: int = 8,
    max_steps: int | None = None,
) -> int:
    """Write `episodes` greedy episodes of `policy` to `out` (.gif or .mp4); the number of
    frames written (per episode, its steps + 1 for in-graph suites, its steps for host ones;
    an episode longer than `max_steps` is drawn up to there).

    Raises CmatError as `check_request` does, and for a host environment that cannot draw
    itself here."""
    from matplotlib import animation

    check_request(policy.config.env, out, episodes, fps)
    limit = policy.spec.max_episode_steps if max_steps is None else max_steps
    if limit <= 0:
        raise CmatError(f"--max-steps must be > 0, got {limit}")
    in_graph = suite_of(policy.config.env).renderer == "jaxmarl"
    played = (jaxmarl_frames if in_graph else host_frames)(policy, episodes, seed, limit)
    frames = list(tqdm(played, desc=f"playing {episodes} episode{'s' * (episodes > 1)}",
                       unit="frame", disable=None, leave=False))
    figure, draw = jaxmarl_drawing(policy, frames) if in_graph else picture_drawing(frames)
    writer = (animation.PillowWriter(fps=fps) if out.suffix.lower() == ".gif"
              else animation.FFMpegWriter(fps=fps))
    out.parent.mkdir(parents=True, exist_ok=True)
    with writer.saving(figure, str(out), dpi=80):
        for frame in tqdm(frames, desc=f"drawing {out.name}", unit="frame", disable=None,
                          leave=False):
            draw(frame)
            figure.suptitle(f"{policy.config.env} · {frame.title}", fontsize=9)
            writer.grab_frame()
    return len(frames)


def check_request(env_id: str, out: Path, episodes: int, fps: int) -> None:
    """Raise CmatError, before anything is loaded, for an environment without a renderer, a
    file type other than .gif or .mp4, an .mp4 without ffmpeg, or counts below 1."""
    from matplotlib import animation

    drawn = [prefix for prefix, suite in registry().items() if suite.renderer is not None]
    if env_id.partition(":")[0] not in drawn:
        raise CmatError(f"{env_id} has no renderer; cmat render draws "
                        f"{', '.join(drawn)} environments")
    if out.suffix.lower() not in FORMATS:
        raise CmatError(f"--out must end in {' or '.join(FORMATS)}, got {out.name!r}")
    if episodes <= 0 or fps <= 0:
        raise CmatError(f"--episodes and --fps must be > 0, got {episodes} and {fps}")
    if out.suffix.lower() == ".mp4" and not animation.writers.is_available("ffmpeg"):
        raise CmatError("writing an .mp4 needs ffmpeg on the PATH (apt-get install ffmpeg); "
                        "write a .gif instead")


def outcome(won: bool, has_win_rate: bool) -> str:
    return ("won" if won else "lost") if has_win_rate else "ended"


def jaxmarl_frames(policy: Policy, episodes: int, seed: int, limit: int) -> Iterator[Frame]:
    """Frames of greedy episodes in an in-graph JaxMARL environment (SMAX, MPE); each holds
    (key, JaxMARL state, actions of every unit) for the suite's renderer."""
    import jax

    env = policy.make_env()
    reset = jax.jit(env.reset)
    step = jax.jit(env.step_in_episode)
    key = jax.random.PRNGKey(seed)
    for episode in range(episodes):
        key, reset_key = jax.random.split(key)
        state, timestep = reset(reset_key)
        total, memory = 0.0, policy.initial_memory()
        for t in range(limit):
            key, step_key = jax.random.split(key)
            actions, memory = policy.greedy_with_memory(memory, timestep.obs,
                                                        timestep.action_mask)
            yield Frame((step_key, state, actions), episode, t, total)
            state, timestep = step(step_key, state, actions)
            total += float(timestep.reward)
            if bool(timestep.done):
                yield Frame((step_key, state, actions), episode, t + 1, total,
                            outcome(bool(timestep.won), policy.spec.has_win_rate))
                break


def jaxmarl_drawing(policy: Policy, frames: list[Frame]) -> tuple[Figure, Callable[[Frame], None]]:
    """The figure and per-frame drawing of JaxMARL's own renderers."""
    import matplotlib.pyplot as plt

    env = policy.make_env().env
    if policy.config.env.startswith("smax:"):
        figure, axes = plt.subplots(1, 1, figsize=(5, 5))

        def draw_smax(frame: Frame) -> None:
            key, state, _ = frame.picture
            units = state.state
            attacks = {agent: units.prev_attack_actions[index]
                       for index, agent in enumerate(env.all_agents)}
            env.init_render(axes, (key, units, attacks), 0, frame.step)
            axes.set_title("")

        return figure, draw_smax
    from jaxmarl.environments.mpe.mpe_visualizer import MPEVisualizer

    with contextlib.redirect_stdout(io.StringIO()):  # it prints whether agents communicate
        visualiser = MPEVisualizer(env, [frame.picture[1] for frame in frames])
    index = {id(frame): position for position, frame in enumerate(frames)}
    return visualiser.fig, lambda frame: visualiser.update(index[id(frame)])


def host_frames(policy: Policy, episodes: int, seed: int, limit: int) -> Iterator[Frame]:
    """Frames of greedy episodes in a host environment built with `render_mode="rgb_array"`,
    each an RGB array from the simulator's own `render()`."""
    if policy.config.env.startswith("mamujoco:"):
        os.environ.setdefault("MUJOCO_GL", "osmesa")
        os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
    from cmat.envs.host import make_host_env

    try:
        env = make_host_env(policy.config.env, seed=seed,
                            **{**policy.config.env_kwargs, "render_mode": "rgb_array"})
    except (CmatError, TypeError) as error:
        raise CmatError(f"{policy.config.env} cannot draw itself (it does not take "
                        f"render_mode='rgb_array'): {error}") from None
    simulator = env
    while not hasattr(simulator, "render") and hasattr(simulator, "env"):
        simulator = simulator.env
    try:
        for episode in range(episodes):
            timestep, total = env.reset(seed=seed + episode), 0.0
            memory = policy.initial_memory()
            for t in range(limit):
                picture = draw_host(simulator, policy.config.env)
                chosen, memory = policy.greedy_with_memory(memory, timestep.obs,
                                                           timestep.action_mask)
                timestep = env.step(np.asarray(chosen))
                total += float(timestep.reward)
                last = ("stopped at --max-steps" if not timestep.done and t + 1 == limit
                        else outcome(timestep.won, policy.spec.has_win_rate) if timestep.done
                        else None)
                yield Frame(picture, episode, t, total, last)
                if last:
                    break
    finally:
        env.close()


def draw_host(simulator: Any, env_id: str) -> np.ndarray:
    """One RGB frame [H, W, 3] from a host simulator's `render()`; CmatError naming what is
    missing where it cannot draw."""
    try:
        picture = simulator.render()
    except Exception as error:  # each simulator's GL stack fails in its own way
        missing = ("an OpenGL context for MuJoCo: install OSMesa with scripts/install_render.sh "
                   "(or set MUJOCO_GL=egl on a GPU machine)") if env_id.startswith("mamujoco:") \
            else "a working render()"
        raise CmatError(f"{env_id} cannot draw here: it needs {missing} "
                        f"({type(error).__name__}: {error})") from None
    if not isinstance(picture, np.ndarray):
        got = "None" if picture is None else f"a {type(picture).__name__}"
    elif picture.ndim != 3 or picture.shape[2] not in (3, 4):
        got = f"an array of shape {picture.shape} and dtype {picture.dtype}"
    else:
        return picture
    raise CmatError(f"{env_id}: render() returned no RGB array (got {got}); expected an "
                    f"(H, W, 3) uint8 array, as render_mode='rgb_array' gives")


def picture_drawing(frames: list[Frame]) -> tuple[Figure, Callable[[Frame], None]]:
    """A figure that shows each frame's RGB array."""
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 1, figsize=(5, 5))
    axes.set_axis_off()
    image = axes.imshow(frames[0].picture)
    return figure, lambda frame: image.set_data(frame.picture)
