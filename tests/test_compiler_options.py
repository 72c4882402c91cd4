"""The trainers compile their programs on CPU without YNNPACK fusions, unless the user's
`XLA_FLAGS` choose YNNPACK's fusions themselves (cmat.runners.devices.compiler_options)."""

from __future__ import annotations

from collections.abc import Iterator

import jax
import jax.numpy as jnp
import pytest

from cmat.resolve import load_config
from cmat.runners import devices
from cmat.runners.trainer import JaxTrainer


@pytest.fixture(autouse=True)
def fresh_options() -> Iterator[None]:
    devices._cpu_compiler_options.cache_clear()
    yield
    devices._cpu_compiler_options.cache_clear()


def compiled_text(lowered: jax.stages.Lowered) -> str:
    text = lowered.compile().as_text()
    assert text is not None
    return text


def makes_ynn_fusions(text: str) -> bool:
    return "ynn_fusion" in text


def test_training_program_has_no_ynnpack_fusions(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    elementwise = jax.jit(lambda x: jnp.tanh(2.0 * x + 1.0).sum(0))
    if not makes_ynn_fusions(compiled_text(elementwise.lower(jnp.ones((256, 64))))):
        pytest.skip("this XLA makes no YNNPACK fusions by default")
    config = load_config(overrides=["env=matrix:fig1", "algo=mappo", "num_envs=4",
                                    "rollout_length=4", "total_steps=32", "log_interval=2",
                                    "ppo.epochs=1", "network.n_embd=16"])
    trainer = JaxTrainer(config)
    state = trainer.init()
    program = compiled_text(trainer._chunk.lower(state, jnp.int32(2)))
    assert devices.compiler_options() == dict(devices.CPU_COMPILER_OPTIONS)
    assert "fusion" in program and not makes_ynn_fusions(program)


def test_users_xla_flags_choose_ynnpack_fusions(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_experimental_ynn_fusion_type=elementwise")
    assert devices.compiler_options() == {}


def test_no_options_off_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert devices.compiler_options() == {}
