"""Run directory files: refusal to overwrite, atomic checksummed checkpoints, metric rows, plots."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from cmat import plots
from cmat.algorithms.cmat.options import CMATOptions
from cmat.cli import main
from cmat.config import AlgorithmOptions, TrainConfig
from cmat.configfile import field_names
from cmat.errors import CmatError
from cmat.plots import plot_runs, run_names
from cmat.rundir import COLUMNS, RunDir, Session


def snapshot(path: Path) -> dict[str, bytes]:
    """Every file under `path` with its bytes."""
    return {str(f.relative_to(path)): f.read_bytes() for f in path.rglob("*") if f.is_file()}


def eval_rows(steps: list[int], seeds: int, win_rate: bool) -> list[dict]:
    return [
        {"kind": "eval", "seed": seed, "env_steps": step, "episode_return": step / 100 + seed,
         "win_rate": seed / seeds if win_rate else math.nan}
        for step in steps for seed in range(seeds)
    ]


@pytest.mark.unit
def test_create_writes_config_that_reads_back(tmp_path: Path) -> None:
    config = TrainConfig(env="smax:3m", seeds=3, total_steps=1234, options=CMATOptions())
    run = RunDir.create(tmp_path / "a" / "b", config)
    assert run.config() == config
    bare = RunDir.create(tmp_path / "bare", replace(config, options=AlgorithmOptions()))
    assert bare.config() == config
    assert RunDir.open(run.path).config() == config


@pytest.mark.unit
@pytest.mark.parametrize("dropped", ["cmat.consensus_source", "network.n_block", "eval_episodes"])
def test_a_field_the_runs_config_lacks_is_marked_as_its_default_on_resume(
    tmp_path: Path, dropped: str
) -> None:
    config = TrainConfig(env="smax:3m", total_steps=1000, options=CMATOptions())
    sources = {name: "default" for name in field_names()} | {"env": "command line"}
    run = RunDir.create(tmp_path / "run", config, sources)
    section, _, key = dropped.rpartition(".")
    lines = run.config_path.read_text().splitlines(keepends=True)
    kept = [line for line in lines if not line.startswith(f"{'  ' if section else ''}{key}:")]
    assert len(kept) == len(lines) - 1
    run.config_path.write_text("".join(kept))

    resumed = run.resumed_sources(replace(config, total_steps=2000))

    assert resumed is not None
    assert resumed[dropped] == "default (not in this run's earlier config.yaml)"
    assert resumed["env"] == "command line"
    assert resumed["total_steps"] == "command line (--resume --steps)"
    run.write_config(config, resumed)
    assert run.sources()[dropped] == resumed[dropped]
    assert run.config() == config


@pytest.mark.parametrize(("existing", "message"), [
    ("config.yaml", "already holds a run; use --resume"),
    ("metrics.csv", "holds a metrics.csv but no config.yaml .* use another --out"),
])
@pytest.mark.unit
def test_create_refuses_a_directory_holding_a_run(
    tmp_path: Path, existing: str, message: str
) -> None:
    (tmp_path / existing).write_text("kept")
    (tmp_path / "other.txt").write_text("also kept")
    before = snapshot(tmp_path)
    with pytest.raises(CmatError, match=message):
        RunDir.create(tmp_path, TrainConfig())
    assert snapshot(tmp_path) == before


def test_runs_named_at_the_same_moment_get_directories_of_their_own(tmp_path: Path) -> None:
    base = tmp_path / "runs" / "smax_3m-20261202-150509"
    (base.parent / f"{base.name}-2").mkdir(parents=True)
    made = [RunDir.create_named(base, TrainConfig()).path for _ in range(3)]
    assert made == [base, base.with_name(f"{base.name}-3"), base.with_name(f"{base.name}-4")]
    assert all((path / "config.yaml").is_file() for path in made)


@contextmanager
def lock_held_elsewhere(run: Path) -> Iterator[int]:
    """Another process holding `run`'s training lock while the block runs; yields its pid."""
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from pathlib import Path; "
         "from cmat.rundir import RunDir\n"
         "with RunDir(Path(sys.argv[1])).training_lock():\n"
         "    print('held', flush=True); time.sleep(60)", str(run)],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        yield holder.pid
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.unit
def test_one_process_at_a_time_holds_a_runs_training_lock(tmp_path: Path) -> None:
    run = RunDir.create(tmp_path / "run", TrainConfig())
    with (lock_held_elsewhere(run.path) as pid,
          pytest.raises(CmatError, match=rf"in use by another cmat process \(pid {pid}\)"),
          run.training_lock()):
        pass
    with run.training_lock():
        assert run.lock_path.read_text() == f"{os.getpid()}\n"
    assert not run.lock_path.exists()
    with run.training_lock():
        pass


@pytest.mark.unit
def test_open_of_a_file_names_the_mistake(tmp_path: Path) -> None:
    run = RunDir.create(tmp_path / "run", TrainConfig())
    with pytest.raises(CmatError, match=r"config.yaml is a file; give the run's directory"):
        RunDir.open(run.config_path)


@pytest.mark.unit
def test_create_accepts_an_existing_directory_without_a_run(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("x")
    RunDir.create(tmp_path, TrainConfig())
    assert (tmp_path / "config.yaml").is_file()


@pytest.mark.unit
def test_open_without_config_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(CmatError, match="holds no run"):
        RunDir.open(tmp_path)


@pytest.mark.unit
def test_checkpoint_round_trip_leaves_no_temporary_files(tmp_path: Path) -> None:
    run = RunDir.create(tmp_path, TrainConfig())
    with pytest.raises(CmatError, match=f"no checkpoint in {tmp_path}"):
        run.load_checkpoint()
    run.save_checkpoint(b"first", 10)
    payload = bytes(range(256)) * 50
    run.save_checkpoint(payload, 20)
    assert run.load_checkpoint() == (payload, 20)
    assert [p.name for p in run.checkpoint_path.parent.iterdir()] == ["latest.ckpt"]


@pytest.mark.unit
def test_failed_checkpoint_write_keeps_the_previous_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = RunDir.create(tmp_path, TrainConfig())
    run.save_checkpoint(b"old", 5)

    def crash(*_: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(KeyboardInterrupt):
        run.save_checkpoint(b"new" * 1000, 10)
    monkeypatch.undo()
    assert run.load_checkpoint() == (b"old", 5)
    assert [p.name for p in run.checkpoint_path.parent.iterdir()] == ["latest.ckpt"]


@pytest.mark.parametrize(
    ("damage", "reason"),
    [
        (lambda raw: raw[:-7], "truncated"),
        (lambda raw: raw[:-7] + b"garbage", "checksum mismatch"),
        (lambda raw: raw[:10], "not a cmat checkpoint"),
        (lambda raw: b"", "not a cmat checkpoint"),
        (lambda raw: raw.replace(b'"size"', b'"sise"'), "unreadable header"),
    ],
)
@pytest.mark.unit
def test_damaged_checkpoint_is_reported(tmp_path: Path, damage, reason: str) -> None:
    run = RunDir.create(tmp_path, TrainConfig())
    run.save_checkpoint(b"state bytes" * 100, 42)
    run.checkpoint_path.write_bytes(damage(run.checkpoint_path.read_bytes()))
    with pytest.raises(CmatError, match=f"corrupt checkpoint: {run.checkpoint_path} \\({reason}"):
        run.load_checkpoint()


@pytest.mark.unit
def test_metrics_rows_append_with_nan_as_nan(tmp_path: Path) -> None:
    run = RunDir.create(tmp_path, TrainConfig())
    run.append_metrics([{"kind": "train", "seed": 0, "env_steps": 100, "episode_return": math.nan,
                         "win_rate": 0.5, "policy_loss": 0.25, "grad_norm": 3.0}])
    run.append_metrics(eval_rows([100], 2, win_rate=False))
    text = run.metrics_path.read_text()
    assert text.splitlines()[0] == ",".join([*COLUMNS, "grad_norm"])
    assert text.count("kind,") == 1
    rows = run.read_metrics()
    assert [(r["kind"], r["seed"]) for r in rows] == [("train", "0"), ("eval", "0"), ("eval", "1")]
    assert rows[0]["episode_return"] == "nan" and rows[0]["policy_loss"] == "0.25"
    assert rows[0]["grad_norm"] == "3.0" and rows[1]["grad_norm"] == ""
    assert rows[1]["win_rate"] == "nan" and rows[1]["value_loss"] == ""


@pytest.mark.unit
def test_truncate_drops_rows_past_the_checkpoint_and_keeps_earlier_bytes(tmp_path: Path) -> None:
    run = RunDir.create(tmp_path, TrainConfig())
    run.append_metrics(eval_rows([100, 200], 2, win_rate=True))
    kept = run.metrics_path.read_bytes()
    run.truncate_metrics(200)
    assert run.metrics_path.read_bytes() == kept
    run.append_metrics(eval_rows([300], 2, win_rate=True))
    with run.metrics_path.open("a") as file:
        file.write("eval,0,400,1.")
    run.truncate_metrics(200)
    assert run.metrics_path.read_bytes() == kept
    run.truncate_metrics(100)
    assert {r["env_steps"] for r in run.read_metrics()} == {"100"}
    assert kept.startswith(run.metrics_path.read_bytes())


@pytest.mark.unit
def test_truncate_reports_a_garbled_row(tmp_path: Path) -> None:
    run = RunDir.create(tmp_path, TrainConfig())
    run.append_metrics(eval_rows([100], 1, win_rate=True))
    with run.metrics_path.open("a") as file:
        file.write("eval,0,lots,1\n")
    with pytest.raises(CmatError, match="line 3"):
        run.truncate_metrics(100)


def replace_cell(text: str, line: int, column: str, value: str) -> str:
    """`text` (a metrics.csv) with the cell of `column` on 1-based `line` set to `value`."""
    lines = text.split("\n")
    cells = lines[line - 1].split(",")
    cells[lines[0].split(",").index(column)] = value
    lines[line - 1] = ",".join(cells)
    return "\n".join(lines)


DAMAGED_METRICS = {
    "a word for a number": (lambda t: replace_cell(t, 3, "episode_return", "lots").encode(),
                            "line 3: episode_return 'lots' is not a number"),
    "a fraction of a step": (lambda t: replace_cell(t, 4, "env_steps", "2.5").encode(),
                             "line 4: env_steps '2.5' is not a whole number"),
    "an unknown kind": (lambda t: replace_cell(t, 2, "kind", "test").encode(),
                        "line 2: kind 'test' is none of train, eval, absolute"),
    "a cell too many": (lambda t: replace_cell(t, 5, "seed", "0,0").encode(),
                        f"line 5: {len(COLUMNS) + 1} cells under {len(COLUMNS)} columns"),
    "a header without seeds": (lambda t: t.replace("seed,", "seeds,", 1).encode(),
                               "line 1: no seed column"),
    "a byte that is not UTF-8": (lambda t: b"\xfe" + t.encode()[1:],
                                 "is not UTF-8 text \\(byte 0\\)"),
}


@pytest.mark.parametrize("damage", DAMAGED_METRICS)
@pytest.mark.parametrize("diagnostics", [[], ["--diagnostics"]])
def test_a_damaged_metrics_file_is_one_error_line_naming_file_and_line(
    damage: str, diagnostics: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = RunDir.create(tmp_path / "run", TrainConfig(env="smax:3m", seeds=2))
    run.append_metrics([{**row, "kind": "train", "policy_loss": 0.5}
                        for row in eval_rows([100], 2, win_rate=True)])
    run.append_metrics(eval_rows([100, 200], 2, win_rate=True))
    assert len(run.read_metrics()) == 6
    make, message = DAMAGED_METRICS[damage]
    run.metrics_path.write_bytes(make(run.metrics_path.read_text()))
    with pytest.raises(CmatError, match=message):
        run.read_metrics()
    assert main(["plot", str(run.path), "--out", str(tmp_path / "x.png"), *diagnostics]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(run.metrics_path) in err[0]
    assert not (tmp_path / "x.png").exists()


@pytest.mark.unit
def test_a_last_row_cut_short_is_left_out_of_the_rows_read(tmp_path: Path) -> None:
    run = RunDir.create(tmp_path, TrainConfig())
    run.append_metrics(eval_rows([100], 2, win_rate=True))
    with run.metrics_path.open("a") as file:
        file.write("eval,0,200,1.")
    assert [r["env_steps"] for r in run.read_metrics()] == ["100", "100"]


def test_plot_draws_a_win_rate_panel_only_where_a_run_defines_it(tmp_path: Path) -> None:
    no_win = RunDir.create(tmp_path / "mpe", TrainConfig(env="mpe:simple_spread", seeds=2))
    no_win.append_metrics(eval_rows([100, 200, 300], 2, win_rate=False))
    with_win = RunDir.create(tmp_path / "smax", TrainConfig(env="smax:3m", seeds=3))
    with_win.append_metrics(eval_rows([100, 300], 3, win_rate=True))

    plot_runs([no_win.path], tmp_path / "one.png")
    plot_runs([no_win.path, with_win.path], tmp_path / "out" / "two.png")
    one, two = imread(tmp_path / "one.png"), imread(tmp_path / "out" / "two.png")
    # a panel is a paper's column wide; two take its text width
    assert (one.shape[1], two.shape[1]) == (round(plots.COLUMN_INCHES * plots.PRINT_DPI),
                                            round(plots.TEXT_INCHES * plots.PRINT_DPI))


@pytest.mark.parametrize(("label_length", "rows"), [(6, 1), (40, 5), (90, 10)])
def test_the_legend_under_a_figure_fits_its_width(label_length: int, rows: int) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    figure = plots.new_figure(figsize=(5.2, 4), layout="constrained")
    axes = figure.subplots()
    labels = [f"{index}{'x' * (label_length - 1)}" for index in range(5)]
    handles = [axes.plot([0, 1], [0, index])[0] for index in range(5)]
    plots.legend_below(figure, handles, labels)
    (legend,) = figure.legends
    renderer = FigureCanvasAgg(figure).get_renderer()
    assert legend.get_window_extent(renderer).width <= figure.bbox.width
    texts = [text.get_text() for text in legend.get_texts()]
    assert [text.replace("\n", "") for text in texts] == labels
    assert sum(text.count("\n") + 1 for text in texts) // legend._ncols == rows


def test_runs_with_the_same_directory_name_get_labels_that_tell_them_apart(
    tmp_path: Path
) -> None:
    assert run_names([tmp_path / "grid/a/cmat-s0-2", tmp_path / "grid/b/cmat-s0-2"]) == [
        "a/cmat-s0-2", "b/cmat-s0-2"]
    assert run_names([tmp_path / "one", tmp_path / "two"]) == ["one", "two"]
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "grid/a/cmat-s0-2")
    assert run_names([link, tmp_path / "grid/a/cmat-s0-2"]) == ["link", "cmat-s0-2"]


def test_plot_of_a_run_without_evaluations_is_an_error(tmp_path: Path) -> None:
    run = RunDir.create(tmp_path / "empty", TrainConfig())
    with pytest.raises(CmatError, match="no evaluation results"):
        plot_runs([run.path], tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("diagnostics", [[], ["--diagnostics"]])
@pytest.mark.parametrize(("name", "message"), [
    ("curve.txt", "unknown format 'txt'"),
    ("curve.PNGG", "unknown format 'pngg'"),
    ("curve", "no file suffix"),
    ("folder.png", "it is a directory"),
])
def test_a_figure_path_matplotlib_cannot_write_is_one_error_line_before_any_work(
    name: str, message: str, diagnostics: list[str], tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    (tmp_path / "folder.png").mkdir()
    missing_run = tmp_path / "no-such-run"
    assert main(["plot", str(missing_run), "--out", str(tmp_path / name), *diagnostics]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"cannot write a figure to {tmp_path / name}: {message}" in err[0]
    assert (".png" in err[0] and ".pdf" in err[0]) or message == "it is a directory"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.png"]


def test_a_curve_of_one_evaluation_is_drawn(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    run = RunDir.create(tmp_path / "one", TrainConfig(env="mpe:simple_spread", seeds=2))
    run.append_metrics(eval_rows([100], 2, win_rate=False))
    plot_runs([run.path], tmp_path / "marked.png")
    monkeypatch.setattr(plots, "FEW_POINTS", 0)
    plot_runs([run.path], tmp_path / "line-only.png")
    assert not np.array_equal(imread(tmp_path / "marked.png"), imread(tmp_path / "line-only.png"))


@pytest.mark.unit
def test_sessions_append_after_earlier_ones_and_skip_unreadable_lines(tmp_path: Path) -> None:
    run = RunDir.create(tmp_path / "run", TrainConfig())
    run.sessions_path.write_text('{"from_steps": 0, "to_steps": 64, "seconds": 2.0}\n'
                                 "half a line from a crash\n[1, 2]\n")
    session = Session(run, 64)
    session.record(128)
    session.record(192)
    sessions = run.sessions()
    assert [(s["from_steps"], s["to_steps"]) for s in sessions] == [(0, 64), (64, 192)]
    assert sessions[1]["backend"] == "cpu" and sessions[1]["cpus"] >= 1
    assert sessions[1]["seconds"] >= 0


def test_an_exported_copy_has_results_and_the_checkpoint_header_not_its_bytes(
    tmp_path: Path,
) -> None:
    run = RunDir.create(tmp_path / "run", TrainConfig())
    run.append_metrics(eval_rows([100], 2, win_rate=True))
    run.save_checkpoint(b"trainer bytes", 100)
    copy = run.export(tmp_path / "copy")
    assert not copy.checkpoint_path.exists() and copy.checkpoint_steps() == (100, False)
    assert copy.read_metrics() == run.read_metrics() and copy.config() == run.config()
    again = copy.export(tmp_path / "again")
    assert again.header_path.read_text() == copy.header_path.read_text()
    with pytest.raises(CmatError, match="an exported copy"):
        copy.load_checkpoint()
    copy.header_path.write_text("{}")
    with pytest.raises(CmatError, match="corrupt checkpoint header"):
        copy.checkpoint_steps()
    assert run.checkpoint_steps() == (100, True)
