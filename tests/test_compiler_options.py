"""The trainers compile their programs on CPU without YNNPACK's elementwise fusions, with
YNNPACK's matmuls where the algorithm asks for them, and as XLA would where the user's
`XLA_FLAGS` choose YNNPACK's fusions themselves (cmat.runners.devices.compiler_options)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest
from jax.experimental.compilation_cache import compilation_cache

from cmat.config import TrainConfig
from cmat.resolve import load_config
from cmat.runners import devices
from cmat.runners.trainer import JaxTrainer

pytestmark = pytest.mark.quick_compiles


@pytest.fixture(autouse=True)
def fresh_options() -> Iterator[None]:
    devices._cpu_compiler_options.cache_clear()
    yield
    devices._cpu_compiler_options.cache_clear()


def compiled_text(lowered: jax.stages.Lowered) -> str:
    text = lowered.compile().as_text()
    assert text is not None
    return text


def ynn_fusions(text: str) -> list[set[str]]:
    """The HLO operations inside each of the compiled program's YNNPACK fusions."""
    fusions = []
    for name in re.findall(r'calls=(%[\w.\-]+)[^\n]*"kind":"__ynn_fusion"', text):
        body = re.search(re.escape(name) + r" \([^\n]*\{\n(.*?)\n\}", text, re.S)
        assert body is not None, name
        fusions.append(set(re.findall(r"= \S+ (\w[\w\-]*)\(", body.group(1))))
    return fusions


def small_config(algo: str) -> TrainConfig:
    return load_config(overrides=["env=matrix:fig1", f"algo={algo}", "num_envs=4",
                                  "rollout_length=4", "total_steps=32", "log_interval=2",
                                  "ppo.epochs=1", "network.n_embd=16"])


def training_program(algo: str) -> str:
    trainer = JaxTrainer(small_config(algo))
    text = trainer.compile_chunk(trainer.init()).as_text()
    assert text is not None
    return text


MATMUL_OPERATIONS = {"parameter", "bitcast", "copy", "transpose", "dot"}


@pytest.fixture
def xla_makes_ynn_fusions(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    elementwise = jax.jit(lambda x: jnp.tanh(2.0 * x + 1.0).sum(0))
    fusions = ynn_fusions(compiled_text(elementwise.lower(jnp.ones((256, 64)))))
    if not any(ops - MATMUL_OPERATIONS for ops in fusions):
        pytest.skip("this XLA makes no elementwise YNNPACK fusions by default")


@pytest.mark.usefixtures("xla_makes_ynn_fusions")
def test_mlp_training_program_has_no_ynnpack_fusions() -> None:
    program = training_program("mappo")
    assert "fusion" in program and ynn_fusions(program) == []


@pytest.mark.usefixtures("xla_makes_ynn_fusions")
def test_transformer_training_program_has_ynnpack_matmuls_only() -> None:
    fusions = ynn_fusions(training_program("cmat"))
    assert fusions and all("dot" in ops and ops <= MATMUL_OPERATIONS for ops in fusions), fusions


def test_users_xla_flags_choose_ynnpack_fusions(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_experimental_ynn_fusion_type=elementwise")
    assert devices.compiler_options() == devices.compiler_options(ynnpack_matmuls=True) == {}


def test_no_options_off_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert devices.compiler_options() == devices.compiler_options(ynnpack_matmuls=True) == {}


@pytest.fixture
def persistent_cache(tmp_path: Path) -> Iterator[Path]:
    """JAX's persistent compilation cache in `tmp_path` for one test, every program cached."""
    names = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")
    previous = {name: getattr(jax.config, name) for name in names}
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    compilation_cache.reset_cache()
    yield tmp_path
    for name, value in previous.items():
        jax.config.update(name, value)
    compilation_cache.reset_cache()


def test_compile_chunk_compiles_the_program_train_chunk_runs(persistent_cache: Path) -> None:
    trainer = JaxTrainer(small_config("cmat"))
    state = trainer.init()
    trainer.compile_chunk(state)
    cached = set(persistent_cache.iterdir())
    assert cached
    trainer.train_chunk(state)
    assert set(persistent_cache.iterdir()) == cached
