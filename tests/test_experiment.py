"""`cmat experiment`: the shipped smoke grid end to end, killed and resumed, corrupt and partial
run directories redone, unavailable environments skipped, bad specs rejected, statistics."""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import fcntl
import io
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from rliable import metrics as rliable_metrics

from cmat.cli import main
from cmat.envs.host import grf
from cmat.errors import CmatError, SuiteUnavailable
from cmat.experiments import execute
from cmat.experiments.claims import CLAIMS, NO_DATA
from cmat.experiments.figures import panel_envs
from cmat.experiments.lines import (
    Line,
    drawn_suite_aggregates,
    load_suite_aggregates,
    matching_suite_aggregates,
)
from cmat.experiments.plan import FINISHED, cell_seed_groups, make_plan, schedule
from cmat.experiments.report import task_steps
from cmat.experiments.runner import run_experiment
from cmat.experiments.spec import load_spec, spec_names
from cmat.experiments.statistics import aggregate, improvement_probability, iqm
from cmat.resolve import load_config
from cmat.rundir import RunDir

pytestmark = pytest.mark.quick_compiles

REPO = Path(__file__).resolve().parents[1]
SMOKE = REPO / "cmat" / "experiments" / "specs" / "smoke.yaml"
CMAT_RUN = "runs/matrix_fig1/default/cmat-s0-1"
MAT_RUN = "runs/matrix_fig1/default/mat-s0-1"
STAGE_RUN = "runs/matrix_fig1/finetune_action/cmat-s0-1"


def one_error_line(stderr: str) -> str:
    assert "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cmat: error: "), stderr
    return lines[0]


def experiment(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cmat", "experiment", *args],
                          capture_output=True, text=True, timeout=1200, check=False)


def checkpoint_steps(run: Path) -> int:
    try:
        return RunDir(run).load_checkpoint()[1]
    except (CmatError, OSError):
        return -1


def group_alive(group: int) -> bool:
    try:
        os.killpg(group, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.fixture(scope="module")
def grid(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, bytes, str]:
    """The smoke grid killed (SIGKILL to the experiment process alone) once its first run is
    complete and its second half done, then run again to the end. The process group is stopped
    before each look into the checkpoint and stays stopped through the kill, so no run can move
    on between the look and the kill; until the run's metrics.csv exists (its first rows are the
    half-way chunk's, written just before that chunk's checkpoint) the runs go unstopped,
    watched by `stat` alone."""
    out = tmp_path_factory.mktemp("experiment") / "smoke"
    log = out.parent / "killed.log"
    with log.open("w") as file:
        process = subprocess.Popen(
            [sys.executable, "-m", "cmat", "experiment", str(SMOKE), "--out", str(out)],
            stdout=file, stderr=subprocess.STDOUT, start_new_session=True,
        )
    try:
        deadline = time.monotonic() + 900
        while not (out / MAT_RUN / "metrics.csv").exists():
            assert process.poll() is None, log.read_text()
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.005)
        while True:
            os.killpg(process.pid, signal.SIGSTOP)
            time.sleep(0.01)  # a process running on the other core stops within this
            if checkpoint_steps(out / MAT_RUN) == 500:
                break
            os.killpg(process.pid, signal.SIGCONT)
            assert process.poll() is None, log.read_text()
            assert time.monotonic() < deadline, log.read_text()
            time.sleep(0.02)
        os.kill(process.pid, signal.SIGKILL)
        process.wait()
        os.killpg(process.pid, signal.SIGCONT)  # the runs wake to their parent's death
        deadline = time.monotonic() + 30
        while group_alive(process.pid) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not group_alive(process.pid), "a run outlived the killed experiment"
    finally:
        if group_alive(process.pid):
            os.killpg(process.pid, signal.SIGKILL)
    assert checkpoint_steps(out / CMAT_RUN) == 1000
    finished = (out / CMAT_RUN / "checkpoints" / "latest.ckpt").read_bytes()
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["experiment", str(SMOKE), "--out", str(out)]) == 0
    return out, finished, printed.getvalue()


def test_killed_grid_resumes_without_redoing_finished_runs(grid: tuple[Path, bytes, str]) -> None:
    out, finished, stdout = grid
    assert f"reuse   {CMAT_RUN.removeprefix('runs/')}: complete at 1000 env steps" in stdout
    assert f"resume  {MAT_RUN.removeprefix('runs/')}: at 500 of 1000 env steps" in stdout
    assert f"[start] {CMAT_RUN.removeprefix('runs/')}" not in stdout
    assert (out / CMAT_RUN / "checkpoints" / "latest.ckpt").read_bytes() == finished
    for run in (CMAT_RUN, MAT_RUN):
        assert checkpoint_steps(out / run) == 1000
        rows = RunDir(out / run).read_metrics()
        keys = Counter((r["kind"], r["seed"], r["env_steps"]) for r in rows)
        assert set(keys.values()) == {1} and len(keys) == 2 * 2 * 2 + 2  # + absolute rows
    sessions = RunDir(out / MAT_RUN).sessions()
    spans = [(s["from_steps"], s["to_steps"]) for s in sessions]
    assert spans[-1] == (500, 1000) and spans[:-1] in ([], [(0, 500)])  # killed before or after
    assert all(s["backend"] == "cpu" and s["seconds"] > 0 for s in sessions)
    summary = json.loads((out / "results.json").read_text())
    cpus = sessions[0]["cpus"]
    where = f"cpu ({cpus} core{'' if cpus == 1 else 's'})"
    assert summary["compute"][where]["runs"] == 3
    assert summary["compute"][where]["hours"] * 3600 == pytest.approx(sum(
        s["seconds"] for run in (CMAT_RUN, MAT_RUN, STAGE_RUN)
        for s in RunDir(out / run).sessions()))
    assert checkpoint_steps(out / STAGE_RUN) == 500
    stage = RunDir(out / STAGE_RUN).config()
    assert stage.finetune == "action" and stage.finetune_from == str(out / CMAT_RUN)


def test_grid_writes_figures_table_and_statistics(grid: tuple[Path, bytes, str]) -> None:
    out, _, stdout = grid
    for name in ("figure_main", "figure_ablation"):
        png, pdf = out / f"{name}.png", out / f"{name}.pdf"
        assert png.read_bytes().startswith(b"\x89PNG") and pdf.read_bytes().startswith(b"%PDF")
        assert f"wrote {png}" in stdout and f"wrote {pdf}" in stdout
        from PIL import Image

        with Image.open(png) as image:  # the text width of a two-column paper, for print
            assert image.size[0] == 7 * 200 and round(image.info["dpi"][0]) == 200
    # the grid's progress: MAT resumed at 500 of 1,000 steps × 2 seeds, then the stage's 1,000
    assert "1/2 runs ended, 67% of 3,000 env steps" in stdout
    assert "2/2 runs ended, 100% of 3,000 env steps" in stdout
    table = (out / "results.md").read_text()
    assert "| task | metric | steps | CMAT | MAT | CMAT-finetune (action) |" in table
    assert "| Fig. 1 matrix game | episode return | 1,000 | " in table
    assert "| Fig. 1 matrix game | CMAT | 2 | mixture |" in table
    assert "Fine-tuning stage `finetune_action` ran 500 env steps after its base run" in table
    assert "| CMAT > MAT |" in table and "IQM [95% CI]" in table
    assert (out / "spec.yaml").read_text() == SMOKE.read_text()
    claims = {c["key"]: c for c in json.loads((out / "results.json").read_text())["claims"]}
    game = claims["e"]
    assert [c["tasks"] for c in game["comparisons"]] == [["matrix:fig1"]]
    assert game["verdict"] != NO_DATA
    assert f"| (e) {CLAIMS['e']} | {game['verdict']} | CMAT vs MAT: " in table
    assert claims["a"]["verdict"] == NO_DATA  # no task besides the matrix game


def test_the_marl_eval_json_loads_in_marl_eval_with_the_numbers_of_results_json(
    grid: tuple[Path, bytes, str],
) -> None:
    pytest.importorskip("marl_eval")
    from marl_eval.utils.data_processing_utils import (
        create_matrices_for_rliable,
        data_process_pipeline,
    )

    out = grid[0]
    raw = json.loads((out / "marl_eval.json").read_text())
    summary = json.loads((out / "results.json").read_text())
    processed = data_process_pipeline(raw_data=raw, metrics_to_normalize=[])
    matrices, _ = create_matrices_for_rliable(
        data_dictionary=processed, environment_name="matrix", metrics_to_normalize=[])
    lines = summary["tasks"][0]["lines"]
    compared = {label for label in lines if "finetune" not in label}
    assert compared == set(raw["matrix"]["fig1"])
    assert set(matrices["mean_episode_return"]) == {label.lower() for label in compared}
    for label in compared:  # marl-eval lower-cases algorithm names
        line = lines[label]
        loaded = np.asarray(matrices["mean_episode_return"][label.lower()])[:, 0]
        np.testing.assert_allclose(sorted(loaded), sorted(line["finals"]))
        runs = raw["matrix"]["fig1"][label]
        assert len(runs) == 2
        steps = {value["step_count"] for run in runs.values()
                 for key, value in run.items() if key.startswith("step_")}
        assert steps == {500, 1000}


def copy_grid(grid: tuple[Path, bytes, str], tmp_path: Path) -> Path:
    return Path(
        shutil.copytree(grid[0], tmp_path / "smoke", ignore=shutil.ignore_patterns(".lock"))
    )


def test_report_only_reports_the_runs_on_disk_and_starts_none(
    grid: tuple[Path, bytes, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = copy_grid(grid, tmp_path)
    shutil.rmtree(out / MAT_RUN)
    (out / "results.md").unlink()
    assert main(["experiment", str(SMOKE), "--out", str(out), "--report-only"]) == 0
    assert not (out / MAT_RUN).exists()
    table = (out / "results.md").read_text()
    assert "| task | metric | steps | CMAT | CMAT-finetune (action) |" in table
    assert f"| {MAT_RUN.removeprefix('runs/')} | new | — |" in table
    assert main(["experiment", str(SMOKE), "--out", str(tmp_path / "none"), "--report-only"]) == 2
    assert "--report-only: no experiment directory" in one_error_line(capsys.readouterr().err)


def test_a_score_window_reports_mean_evaluations_and_the_verdicts_from_last_ones(
    grid: tuple[Path, bytes, str], tmp_path: Path
) -> None:
    out = copy_grid(grid, tmp_path)
    spec = yaml.safe_load(SMOKE.read_text())
    spec["score_window"] = 0.6
    path = tmp_path / "window.yaml"
    path.write_text(yaml.safe_dump(spec))
    before = {run: (out / run / "metrics.csv").read_bytes() for run in (CMAT_RUN, MAT_RUN)}
    assert main(["experiment", str(path), "--out", str(out), "--report-only"]) == 0
    summary = json.loads((out / "results.json").read_text())
    lines = summary["tasks"][0]["lines"]
    for run, label in ((CMAT_RUN, "CMAT"), (MAT_RUN, "MAT")):
        assert (out / run / "metrics.csv").read_bytes() == before[run]
        evaluations: dict[str, list[tuple[int, float]]] = {}
        with (out / run / "metrics.csv").open() as file:
            for row in csv.DictReader(file):
                if row["kind"] == "eval":
                    evaluations.setdefault(row["seed"], []).append(
                        (int(row["env_steps"]), float(row["episode_return"])))
        window = [np.mean([v for steps, v in rows if steps >= 0.4 * max(s for s, _ in rows)])
                  for _, rows in sorted(evaluations.items())]
        last = [max(rows)[1] for _, rows in sorted(evaluations.items())]
        assert len(window) == 2 and any(len(rows) > 1 for rows in evaluations.values())
        np.testing.assert_allclose(lines[label]["scores"], window)
        np.testing.assert_allclose(lines[label]["finals"], last)
        assert lines[label]["mean"] == pytest.approx(np.mean(window))
    table = (out / "results.md").read_text()
    assert "mean greedy evaluation over the last 60% of its env steps" in table
    assert "verdict from last evaluations |" in table
    assert [c["statement"] for c in summary["claims_from_finals"]] == [
        c["statement"] for c in summary["claims"]]


def test_an_export_keeps_results_not_checkpoints_and_continues_the_grid_elsewhere(
    grid: tuple[Path, bytes, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = copy_grid(grid, tmp_path)
    exported = tmp_path / "committed"
    assert main(["experiment", str(SMOKE), "--out", str(out), "--report-only",
                 "--export", str(exported)]) == 0
    assert not list(exported.rglob("*.ckpt")) and (exported / "spec.yaml").is_file()
    for run in (CMAT_RUN, MAT_RUN, STAGE_RUN):
        metrics = (exported / run / "metrics.csv").read_bytes()
        assert metrics == (out / run / "metrics.csv").read_bytes()
        assert RunDir(exported / run).sessions() == RunDir(out / run).sessions()
        header = json.loads((exported / run / "checkpoints" / "latest.json").read_text())
        data, steps = RunDir(out / run).load_checkpoint()
        assert header["env_steps"] == steps and header["size"] == len(data)
    assert ((exported / "results.md").read_text().split("## Runs")[0]
            == (out / "results.md").read_text().split("## Runs")[0])

    elsewhere = Path(shutil.copytree(exported, tmp_path / "elsewhere"))
    shutil.rmtree(elsewhere / STAGE_RUN)
    capsys.readouterr()
    assert main(["experiment", str(SMOKE), "--out", str(elsewhere)]) == 0
    done = capsys.readouterr().out
    cmat, mat, stage = (run.removeprefix("runs/") for run in (CMAT_RUN, MAT_RUN, STAGE_RUN))
    assert f"redo    {cmat}: exported without its checkpoint, which {stage} needs" in done
    assert f"reuse   {mat}: complete at 1000 env steps (exported" in done
    assert done.index(f"[start] {cmat}") < done.index(f"[start] {stage}")
    retrained = RunDir(elsewhere / CMAT_RUN).read_metrics()
    assert [row["episode_return"] for row in retrained] == [
        row["episode_return"] for row in RunDir(out / CMAT_RUN).read_metrics()]
    assert checkpoint_steps(elsewhere / STAGE_RUN) == 500

    capsys.readouterr()
    assert main(["train", "--resume", str(exported / CMAT_RUN), "--steps", "2000"]) == 2
    assert "an exported copy" in one_error_line(capsys.readouterr().err)
    assert main(["experiment", str(SMOKE), "--out", str(out), "--export", str(out)]) == 2
    assert "is the experiment directory itself" in one_error_line(capsys.readouterr().err)


def test_a_carried_export_continues_partial_runs_and_stages_without_retraining(
    grid: tuple[Path, bytes, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = copy_grid(grid, tmp_path)
    shutil.rmtree(out / STAGE_RUN)
    longer = tmp_path / "longer.yaml"
    longer.write_text(yaml.safe_dump({**yaml.safe_load(SMOKE.read_text()), "steps": 2000}))
    finished_mat = Path(shutil.copytree(out / MAT_RUN, tmp_path / "finished_mat"))
    just_started = RunDir(out / MAT_RUN)
    just_started.metrics_path.unlink()
    just_started.save_checkpoint(just_started.load_checkpoint()[0], 0)
    moved = tmp_path / "moved"
    assert main(["experiment", str(longer), "--out", str(out), "--report-only",
                 "--export", str(moved), "--carry"]) == 0
    assert ((moved / CMAT_RUN / "checkpoints" / "latest.ckpt").read_bytes()
            == (out / CMAT_RUN / "checkpoints" / "latest.ckpt").read_bytes())
    assert not (moved / MAT_RUN).exists()
    assert "carried 1 runs with their checkpoints" in capsys.readouterr().out
    assert main(["experiment", str(longer), "--out", str(moved), "--dry-run"]) == 0
    planned = capsys.readouterr().out
    assert f"resume  {CMAT_RUN.removeprefix('runs/')}: at 1000 of 2000" in planned
    shutil.rmtree(out / MAT_RUN)
    shutil.copytree(finished_mat, out / MAT_RUN)

    committed = tmp_path / "committed"
    assert main(["experiment", str(SMOKE), "--out", str(out), "--report-only",
                 "--export", str(committed), "--carry"]) == 0
    assert (committed / CMAT_RUN / "checkpoints" / "latest.ckpt").is_file()
    assert not (committed / MAT_RUN / "checkpoints" / "latest.ckpt").exists()
    elsewhere = Path(shutil.copytree(committed, tmp_path / "elsewhere"))
    capsys.readouterr()
    assert main(["experiment", str(SMOKE), "--out", str(elsewhere), "--export", str(committed),
                 "--carry"]) == 0
    done = capsys.readouterr().out
    assert f"[start] {CMAT_RUN.removeprefix('runs/')}" not in done
    assert checkpoint_steps(elsewhere / STAGE_RUN) == 500
    assert not list(committed.rglob("*.ckpt")) and "carried 0 runs" in done

    assert main(["experiment", str(SMOKE), "--out", str(out), "--carry"]) == 2
    assert "--carry applies to --export only" in one_error_line(capsys.readouterr().err)


def test_partial_runs_start_first_and_stages_after_their_base(
    grid: tuple[Path, bytes, str], tmp_path: Path
) -> None:
    out = copy_grid(grid, tmp_path)
    shutil.rmtree(out / CMAT_RUN)
    longer = tmp_path / "longer.yaml"
    longer.write_text(yaml.safe_dump({**yaml.safe_load(SMOKE.read_text()), "steps": 2000}))
    plan = make_plan(load_spec(longer), out)
    status = {run.name: run.status for run in plan.runs}
    cmat, mat, stage = (run.removeprefix("runs/") for run in (CMAT_RUN, MAT_RUN, STAGE_RUN))
    assert (status[cmat], status[mat], status[stage]) == ("new", "resume", "redo")
    order = [run.name for run in schedule(plan.runs)]
    assert order[0] == mat and order.index(cmat) < order.index(stage)
    assert [name for name in order if name != mat] == [
        run.name for run in plan.runs if run.name != mat]


@pytest.mark.parametrize("nearer", ["cmat", "mat"])
def test_the_partial_run_nearest_its_budget_starts_first(
    grid: tuple[Path, bytes, str], tmp_path: Path, nearer: str
) -> None:
    out = copy_grid(grid, tmp_path)
    longer = tmp_path / "longer.yaml"
    longer.write_text(yaml.safe_dump({**yaml.safe_load(SMOKE.read_text()), "steps": 2000}))
    plan = make_plan(load_spec(longer), out)
    partial = {run.algo: run for run in plan.runs if run.status == "resume"}
    assert sorted(partial) == ["cmat", "mat"]
    near = partial[nearer]
    assert near.config is not None
    near.config = dataclasses.replace(near.config, total_steps=1500)

    order = [run.name for run in schedule(plan.runs)]

    far = partial["mat" if nearer == "cmat" else "cmat"]
    assert order[:2] == [near.name, far.name]


def test_corrupt_and_partial_run_directories_are_reported_and_redone(
    grid: tuple[Path, bytes, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = copy_grid(grid, tmp_path)
    checkpoint = out / MAT_RUN / "checkpoints" / "latest.ckpt"
    raw = checkpoint.read_bytes()
    checkpoint.write_bytes(raw[: len(raw) // 2] + bytes(b ^ 0xFF for b in raw[len(raw) // 2:]))
    shutil.rmtree(out / STAGE_RUN / "checkpoints")
    reused = (out / CMAT_RUN / "checkpoints" / "latest.ckpt").read_bytes()

    assert main(["experiment", str(SMOKE), "--out", str(out)]) == 0
    done = capsys.readouterr().out
    mat, stage = MAT_RUN.removeprefix("runs/"), STAGE_RUN.removeprefix("runs/")
    assert f"redo    {mat}: corrupt checkpoint: {checkpoint} (checksum mismatch)" in done
    assert f"redo    {stage}: no checkpoint in {out / STAGE_RUN}" in done
    assert f"[start] {mat} (redo" in done and f"[start] {stage} (redo" in done
    assert len(list((out / "discarded").iterdir())) == 2
    assert checkpoint_steps(out / MAT_RUN) == 1000 and checkpoint_steps(out / STAGE_RUN) == 500
    assert (out / CMAT_RUN / "checkpoints" / "latest.ckpt").read_bytes() == reused
    assert "corrupt checkpoint" in (out / "results.md").read_text()


def test_plan_changes_are_detected_without_running(
    grid: tuple[Path, bytes, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = copy_grid(grid, tmp_path)
    (out / STAGE_RUN / "metrics.csv").unlink()
    spec = yaml.safe_load(SMOKE.read_text())
    longer = tmp_path / "longer.yaml"
    longer.write_text(yaml.safe_dump({**spec, "steps": 2000}))
    assert main(["experiment", str(longer), "--out", str(out), "--dry-run"]) == 0
    planned = capsys.readouterr().out
    assert f"resume  {CMAT_RUN.removeprefix('runs/')}: at 1000 of 2000 env steps" in planned
    assert (f"redo    {STAGE_RUN.removeprefix('runs/')}: its base run is not complete yet"
            in planned)
    spec["set"]["ppo"]["epochs"] = 3
    changed = tmp_path / "changed.yaml"
    changed.write_text(yaml.safe_dump(spec))
    assert main(["experiment", str(changed), "--out", str(out), "--dry-run"]) == 0
    planned = capsys.readouterr().out
    assert (f"redo    {MAT_RUN.removeprefix('runs/')}: config differs from the spec "
            f"(ppo.epochs: 2, spec 3)") in planned
    assert not (out / "discarded").exists()

    assert main(["experiment", str(SMOKE), "--out", str(out), "--dry-run"]) == 0
    planned = capsys.readouterr().out
    assert (f"redo    {STAGE_RUN.removeprefix('runs/')}: metrics.csv lacks the eval rows of its "
            f"checkpoint at 500 env steps") in planned

    metrics = out / MAT_RUN / "metrics.csv"
    lines = metrics.read_text().split("\n")
    lines[2] = lines[2].replace(",", ",word,", 1).rsplit(",", 1)[0]
    metrics.write_text("\n".join(lines))
    assert main(["experiment", str(SMOKE), "--out", str(out), "--dry-run"]) == 0
    planned = capsys.readouterr().out
    assert (f"redo    {MAT_RUN.removeprefix('runs/')}: unreadable {metrics}, line 3: seed 'word' "
            f"is not a whole number") in planned


def test_unavailable_environments_are_reported_and_skipped(
    grid: tuple[Path, bytes, str], tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def missing_suite() -> None:
        raise SuiteUnavailable("GRF needs gfootball (No module named 'gfootball')")

    monkeypatch.setattr(grf, "import_gfootball", missing_suite)
    out = copy_grid(grid, tmp_path)
    spec = yaml.safe_load(SMOKE.read_text())
    spec["envs"] += ["grf:academy_3_vs_1_with_keeper",
                     {"id": "smax:3m", "unavailable": "left out on purpose"}]
    path = tmp_path / "more.yaml"
    path.write_text(yaml.safe_dump(spec))
    assert main(["experiment", str(path), "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert ("skip    grf:academy_3_vs_1_with_keeper: unavailable: GRF needs gfootball"
            in stdout)
    assert "skip    smax:3m: unavailable: marked unavailable in the spec: left out on purpose" \
        in stdout
    assert "[start]" not in stdout
    table = (out / "results.md").read_text()
    assert "| smax:3m | — | 1,000 | unavailable: marked unavailable in the spec" in table
    assert "unavailable: marked unavailable in the spec: left out on purpose" in table
    assert (out / "figure_main.png").read_bytes().startswith(b"\x89PNG")


@pytest.mark.parametrize(
    ("env", "message"),
    [
        ("nope:x", "unknown environment prefix 'nope'"),
        ("smax:3s5zz", "unknown SMAX scenario '3s5zz'"),
        ({"id": "matrix:penalty", "set": ["env_kwargs.k=abc"]},
         "matrix:penalty: k must be a finite number, got 'abc'"),
        ({"id": "smax:3m", "set": ["env_kwargs.see_enemy=true"]}, "unknown option 'see_enemy'"),
        ("jax:cmat_no_such_user_module:make", "cannot import 'cmat_no_such_user_module'"),
    ],
)
def test_a_task_that_names_no_environment_is_an_error_not_a_skip(
    env: str | dict, message: str, grid: tuple[Path, bytes, str], tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = copy_grid(grid, tmp_path)
    before = {path: path.read_bytes() for path in out.rglob("*") if path.is_file()}
    spec = yaml.safe_load(SMOKE.read_text())
    spec["envs"].append(env)
    path = tmp_path / "typo.yaml"
    path.write_text(yaml.safe_dump(spec))
    assert main(["experiment", str(path), "--out", str(out)]) == 2
    error = one_error_line(capsys.readouterr().err)
    assert f"{path}: task " in error and message in error
    assert {path: path.read_bytes() for path in out.rglob("*") if path.is_file()} == before


def test_another_experiments_directory_is_refused_and_left_as_it_was(
    grid: tuple[Path, bytes, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = copy_grid(grid, tmp_path)
    before = {path: path.read_bytes() for path in out.rglob("*") if path.is_file()}
    other = yaml.safe_load(SMOKE.read_text())
    other["name"] = "another"
    path = tmp_path / "another.yaml"
    path.write_text(yaml.safe_dump(other))
    for options in (["--out", str(out), "--report-only"], ["--out", str(out), "--dry-run"],
                    ["--out", str(tmp_path / "new"), "--export", str(out)]):
        assert main(["experiment", str(path), *options]) == 2
        assert (f"{out} holds the experiment 'smoke', not 'another'"
                in one_error_line(capsys.readouterr().err))
    assert {path: path.read_bytes() for path in out.rglob("*") if path.is_file()} == before
    (out / "results.json").unlink()
    assert main(["experiment", str(path), "--out", str(out), "--report-only"]) == 2
    assert "holds the experiment 'smoke'" in one_error_line(capsys.readouterr().err)


def test_one_experiment_at_a_time(grid: tuple[Path, bytes, str], tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    out = copy_grid(grid, tmp_path)
    with (out / ".lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        assert main(["experiment", str(SMOKE), "--out", str(out)]) == 2
    assert "another cmat experiment is running in" in one_error_line(capsys.readouterr().err)


SPEC = {"steps": 100, "envs": ["matrix:fig1"], "algos": ["cmat"]}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"stpes": 5}, "unknown key 'stpes'; allowed:"),
        ({"algos": ["cmat", "nope"]}, "algos: unknown algorithm 'nope'"),
        ({"envs": []}, "envs must be a non-empty list"),
        ({"envs": ["fig1"]}, "envs[0]: id must look like PREFIX:NAME"),
        ({"steps": 0}, "steps must be > 0, got 0"),
        ({"seeds": "many"}, "seeds must be an integer, got 'many'"),
        ({"set": ["ppo.nope=1"]},
         "matrix:fig1 / default / cmat: invalid config: unknown key ppo.nope"),
        ({"set": {"cmat": {"consensus_iterations": "3n"}}}, "must be >= 0, got '3n'"),
        ({"set": {"mat": {"inducing_points": 4}}},
         "set: mat.inducing_points is an option of mat, and none of the runs it applies to "
         "trains mat"),
        ({"algos": ["cmat", "mat"],
          "variants": {"a": {"algos": ["cmat"]},
                       "b": {"algos": ["cmat"], "set": ["mat.inducing_points=2"]}}},
         "variants.b.set: mat.inducing_points is an option of mat, and none of the runs"),
        ({"algos": ["cmat", "mat"],
          "envs": ["matrix:fig1", {"id": "matrix:penalty", "set": {"mat": {"inducing_points": 2}}}],
          "variants": {"a": {"algos": ["cmat"]},
                       "b": {"algos": ["mat"], "envs": ["matrix:fig1"]}}},
         "envs[1].set: mat.inducing_points is an option of mat, and none of the runs"),
        ({"variants": {"ft": {"finetune": "action"}}}, "needs both 'from' (a variant) and"),
        ({"variants": {"a": {}, "ft": {"from": "b", "finetune": "action"}}},
         "from names no variant: 'b'"),
        ({"variants": {"a": {"algos": ["mat"]}, "ft": {"from": "a", "finetune": "action"}}},
         "variant 'a' it starts from has no cmat runs"),
        ({"variants": {"a": {}, "ft": {"from": "a", "finetune": "action", "algos": ["mat"]}}},
         "fine-tuning stage 'action' freezes CMAT's blocks and is supported only for algo cmat"),
        ({"variants": {"a": {"from": "b", "finetune": "action"},
                       "b": {"from": "a", "finetune": "consensus"}}}, "form a cycle"),
        ({"variants": {"a": {"figure": "fig3"}}}, "figure must be one or a list of"),
        ({"baselines": ["hungarian"]},
         "baselines: baselines apply to dispatch tasks, and this spec has none"),
        ({"envs": ["dispatch:grid-8-mid"], "baselines": ["auction"]},
         "baselines: unknown baseline 'auction'; available: random, greedy, hungarian"),
        ({"envs": ["dispatch:grid-8-mid"], "baselines": ["greedy", "greedy"]},
         "baselines: lists 'greedy' twice"),
        ({"score_window": 1}, "score_window must be a number in [0, 1), got 1"),
        ({"score_window": -0.2}, "score_window must be a number in [0, 1), got -0.2"),
        ({"score_window": "last 10"}, "score_window must be a number in [0, 1), got 'last 10'"),
        ({"score_window": float("nan")}, "score_window must be a number in [0, 1), got nan"),
        ({"variants": {"a": {"envs": ["matrix:penalty"]}}},
         "variants.a: envs names 'matrix:penalty', which is not one of the spec's envs"),
        ({"envs": ["matrix:fig1", "matrix:penalty"],
          "variants": {"a": {"envs": ["matrix:fig1"]}}}, "no variant runs on 'matrix:penalty'"),
        ({"envs": ["matrix:fig1", "matrix:penalty"],
          "variants": {"a": {"envs": ["matrix:penalty"]}, "b": {"envs": ["matrix:fig1"]},
                       "ft": {"from": "a", "finetune": "action"}}},
         "variant 'a' it starts from does not run on every environment this stage runs on"),
    ],
)
def test_bad_specs_are_one_error_line(
    change: dict, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({**SPEC, **change}))
    assert main(["experiment", str(path), "--out", str(tmp_path / "out")]) == 2
    assert message in one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


def test_unreadable_specs_and_options_are_one_error_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["experiment", str(tmp_path / "missing.yaml")]) == 2
    assert "experiment spec not found" in one_error_line(capsys.readouterr().err)
    path = tmp_path / "broken.yaml"
    path.write_text("envs: [unclosed\n")
    assert main(["experiment", str(path)]) == 2
    assert "is not valid YAML" in one_error_line(capsys.readouterr().err)
    path.write_text(yaml.safe_dump(SPEC))
    assert main(["experiment", str(path), "--parallel", "0"]) == 2
    assert "--parallel must be > 0" in one_error_line(capsys.readouterr().err)


def test_only_runs_the_matching_runs_and_reports_every_complete_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "two.yaml"
    smoke = yaml.safe_load(SMOKE.read_text())  # the smoke MAT program: cached after `grid`
    path.write_text(yaml.safe_dump({**SPEC, "steps": 500, "algos": ["cmat", "mat"],
                                    "seeds": smoke["seeds"], "set": smoke["set"]}))
    out = tmp_path / "out"
    assert main(["experiment", str(path), "--out", str(out), "--only", "*/mat-*",
                 "--parallel", "2"]) == 0
    assert "--only */mat-*: 1 of 2 runs: matrix_fig1/default/mat-s0-1" in capsys.readouterr().out
    assert checkpoint_steps(out / "runs/matrix_fig1/default/mat-s0-1") == 500
    cores = len(os.sched_getaffinity(0))
    sessions = RunDir(out / "runs/matrix_fig1/default/mat-s0-1").sessions()
    first_group = execute.core_groups(2)[0] if cores >= 2 else range(cores)
    assert [s["cpus"] for s in sessions] == [len(first_group)]
    assert not (out / "runs/matrix_fig1/default/cmat-s0-1").exists()
    assert "| MAT |" in (out / "results.md").read_text()
    assert main(["experiment", str(path), "--out", str(out), "--only", "smax_3m/*"]) == 2
    assert "--only 'smax_3m/*' matches no run of the grid" in one_error_line(
        capsys.readouterr().err)


@pytest.mark.unit
def test_a_cells_runs_on_disk_keep_their_seeds_and_the_others_follow_seeds_per_run(
        tmp_path: Path) -> None:
    """Random folders of run directories (this algorithm's, in and out of the spec's seeds,
    overlapping; another algorithm's; a file): the groups cover the spec's seeds exactly once,
    each run on disk within them is kept unless one at least as large overlaps it, and the other
    seeds go in consecutive groups of `seeds_per_run`, each full but the last of a stretch."""
    rng = np.random.default_rng(0)
    smoke = load_spec(SMOKE)
    for trial in range(300):
        first_seed, seeds = int(rng.integers(0, 3)), int(rng.integers(1, 7))
        per_run = int(rng.integers(1, seeds + 1))
        spec = dataclasses.replace(smoke, seed=first_seed, seeds=seeds, seeds_per_run=per_run)
        wanted = set(range(first_seed, first_seed + seeds))
        folder = tmp_path / str(trial)
        folder.mkdir()
        on_disk = set()
        for _ in range(int(rng.integers(0, 4))):
            first, count = int(rng.integers(0, 8)), int(rng.integers(1, 4))
            last = first + count - 1
            (folder / (f"mat-s{first}" + (f"-{last}" if count > 1 else ""))).mkdir(exist_ok=True)
            on_disk.add((first, count))
        (folder / "cmat-s0-99").mkdir()
        (folder / "mat-s0-99.txt").touch()
        groups = cell_seed_groups(spec, folder, "mat")
        assert sorted(s for first, n in groups for s in range(first, first + n)) == sorted(wanted)
        assert groups == sorted(groups)
        kept = [group for group in groups if group in on_disk]
        for first, count in on_disk - set(kept):
            members = set(range(first, first + count))
            assert not members <= wanted or any(
                n >= count and members & set(range(f, f + n)) for f, n in kept), (trial, groups)
        new = [group for group in groups if group not in on_disk]
        assert all(n <= per_run for _, n in new)
        for (first, n), (following, _) in itertools.pairwise(new):
            assert first + n < following or n == per_run, (trial, groups)
    spec = dataclasses.replace(smoke, seed=0, seeds=5, seeds_per_run=2)
    assert cell_seed_groups(spec, tmp_path / "none", "mat") == [(0, 2), (2, 2), (4, 1)]


def test_seeds_per_run_finishes_a_cell_one_seed_at_a_time_and_keeps_the_runs_on_disk(
        grid: tuple[Path, bytes, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert main(["experiment", str(SMOKE), "--out", str(out), "--seeds-per-run", "1",
                 "--only", "*/default/mat-s1"]) == 0
    assert checkpoint_steps(out / "runs/matrix_fig1/default/mat-s1") == 1000
    assert "(n=1)" in (out / "results.md").read_text()
    mat = [run for run in make_plan(load_spec(SMOKE), out).runs if run.algo == "mat"]
    assert [(run.name, run.status) for run in mat] == [
        ("matrix_fig1/default/mat-s0", "new"), ("matrix_fig1/default/mat-s1", FINISHED)]
    whole = run_experiment(SMOKE, out=copy_grid(grid, tmp_path), seeds_per_run=1, dry_run=True)
    assert [(run.name, run.status) for run in whole.runs] == [
        (name.removeprefix("runs/"), FINISHED) for name in (CMAT_RUN, MAT_RUN, STAGE_RUN)]
    capsys.readouterr()
    assert main(["experiment", str(SMOKE), "--out", str(out), "--seeds-per-run", "0"]) == 2
    assert "--seeds-per-run must be > 0, got 0" in one_error_line(capsys.readouterr().err)


@pytest.mark.parametrize(
    ("cores", "slots", "groups"),
    [
        ({0, 1}, 2, [[0], [1]]),
        ({0, 1, 2, 3, 4}, 2, [[0, 1, 2], [3, 4]]),
        ({2, 5, 7, 9}, 3, [[2, 5], [7], [9]]),
        ({0, 1, 2, 3}, 1, []),
        ({0, 1}, 3, []),
    ],
)
def test_parallel_runs_get_disjoint_core_groups_covering_the_cores(
    cores: set[int], slots: int, groups: list[list[int]], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: cores)
    assert execute.core_groups(slots) == groups


def test_a_finished_runs_cores_go_to_the_next_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    class Finished:
        def __init__(self, argv: list[str], env: dict[str, str], **_: object) -> None:
            self.cores = env.get("CMAT_CORES")

        def poll(self) -> int:
            return 0

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    monkeypatch.setattr(execute.subprocess, "Popen", Finished)
    executor = execute.LocalExecutor(tmp_path / "cache", slots=2)
    first = executor.submit(["train"], tmp_path / "a.log")
    second = executor.submit(["train"], tmp_path / "b.log")
    assert (first.cores, second.cores) == ("0,1", "2,3")
    assert executor.wait([first]) == (first, 0)
    assert executor.submit(["train"], tmp_path / "c.log").cores == "0,1"


@pytest.mark.parametrize("name", spec_names())
def test_shipped_specs_plan_by_name(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["experiment", name, "--out", str(tmp_path / "x"), "--dry-run"]) == 0
    assert "runs in" in capsys.readouterr().out


def test_unknown_spec_name_lists_the_shipped_ones(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["experiment", "dispatchh", "--dry-run"]) == 2
    assert "smoke" in one_error_line(capsys.readouterr().err)


def test_specs_name_cmats_paper_setting_or_its_default(tmp_path: Path) -> None:
    """paper_main runs the paper's CMAT (`preset: paper`); the speed study's CMAT lines name
    their clip and tau, so they keep their meaning whatever CMAT's default is."""
    from cmat.experiments.plan import make_plan

    paper = make_plan(load_spec("paper_main"), tmp_path / "a")
    cmat_runs = [run.config for run in paper.runs if run.algo == "cmat" and run.config]
    assert cmat_runs and all(
        (c.preset, c.options.joint_clip, c.ppo.target_tau, c.num_envs) == ("paper", "joint", 0.1, 8)
        for c in cmat_runs
    )
    study = make_plan(load_spec("cmat_speed_study"), tmp_path / "b")
    lines = {run.variant.name: (run.config.options.joint_clip, run.config.ppo.target_tau)
             for run in study.runs if run.algo == "cmat" and run.config}
    assert lines == {
        "per_agent_clip_tau_one": ("per_agent", 1.0), "paper_clip_and_tau": ("joint", 0.1),
        "per_agent_clip": ("per_agent", 0.1), "tau_one": ("joint", 1.0),
    }
    default = load_config(overrides=["env=smax:6h_vs_8z"])
    assert (default.options.joint_clip, default.ppo.target_tau) == lines["per_agent_clip_tau_one"]


def test_a_variant_restricted_to_some_envs_plans_and_aggregates_only_there(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "restricted.yaml"
    path.write_text(yaml.safe_dump({
        "steps": 100, "envs": ["matrix:fig1", "matrix:penalty"], "algos": ["cmat", "mat"],
        "variants": {"default": {}, "probe": {"algos": ["cmat"], "envs": ["matrix:penalty"]}},
    }))
    assert main(["experiment", str(path), "--out", str(tmp_path / "x"), "--dry-run"]) == 0
    planned = [line.split()[1] for line in capsys.readouterr().out.splitlines()
               if line.startswith("  new")]
    assert sorted(planned) == sorted([
        "matrix_fig1/default/cmat-s0", "matrix_fig1/default/mat-s0",
        "matrix_penalty/default/cmat-s0", "matrix_penalty/default/mat-s0",
        "matrix_penalty/probe/cmat-s0",
    ])

    def line(label: str, variant: str, wins: list[float]) -> Line:
        rows = [{"kind": "eval", "seed": str(seed), "env_steps": "100", "win_rate": str(win)}
                for seed, win in enumerate(wins)]
        return Line(label, variant, "cmat", ("main",), [], rows)

    spec = load_spec(path)
    lines = {"matrix:fig1": [line("CMAT", "default", [1.0, 0.0]),
                             line("MAT", "default", [0.0, 0.0])],
             "matrix:penalty": [line("CMAT", "default", [1.0, 1.0]),
                                line("MAT", "default", [0.0, 1.0]),
                                line("probe", "probe", [1.0, 1.0])]}
    metrics = {"matrix:fig1": "win_rate", "matrix:penalty": "win_rate"}
    result = aggregate(lines, metrics, spec)
    assert result is not None
    assert result["tasks"] == ["matrix:fig1", "matrix:penalty"]
    assert list(result["lines"]) == ["CMAT", "MAT"]
    assert result["lines"]["CMAT"]["mean"] == pytest.approx(0.75)
    assert result["lines"]["MAT"]["mean"] == pytest.approx(0.25)
    lines["smax:3m"] = [line("CMAT", "default", [1.0, 0.5]), line("MAT", "default", [0.0, 0.5])]
    metrics["smax:3m"] = "win_rate"
    beside_a_benchmark = aggregate(lines, metrics, spec)
    assert beside_a_benchmark is not None and beside_a_benchmark["tasks"] == ["smax:3m"]
    assert beside_a_benchmark["lines"]["MAT"]["mean"] == pytest.approx(0.25)


def test_a_tasks_row_states_the_budget_of_its_lines_not_of_a_longer_variant(
    tmp_path: Path,
) -> None:
    path = tmp_path / "long.yaml"
    path.write_text(yaml.safe_dump({
        "steps": 100, "envs": ["matrix:fig1", "matrix:penalty"], "algos": ["cmat", "mat"],
        "variants": {"default": {}, "long": {"algos": ["mat"], "steps": 400},
                     "stage": {"algos": ["cmat"], "from": "default", "finetune": "consensus",
                               "steps": 50}},
    }))
    spec = load_spec(path)
    fig1, penalty = spec.envs

    def line(variant: str, budgets: list[int]) -> Line:
        runs = [SimpleNamespace(config=SimpleNamespace(budget_steps=b)) for b in budgets]
        return Line(variant, variant, "mat", ("main",), runs, [])  # type: ignore[arg-type]

    assert task_steps(fig1, [line("default", [128, 128]), line("long", [512]),
                             line("stage", [64])], spec) == 128
    assert task_steps(penalty, [line("long", [512])], spec) == 100
    assert task_steps(penalty, [], spec) == 100


def test_an_algorithms_options_in_a_shared_set_apply_to_its_runs_alone(tmp_path: Path) -> None:
    path = tmp_path / "scoped.yaml"
    path.write_text(yaml.safe_dump({
        "steps": 100, "envs": ["matrix:fig1", {"id": "matrix:penalty",
                                               "set": {"mat": {"inducing_points": 2}}}],
        "algos": ["cmat", "mat"],
        "set": {"cmat": {"consensus_iterations": 1}, "ppo": {"epochs": 3}},
        "variants": {"default": {},
                     "m0": {"algos": ["cmat"], "set": ["cmat.consensus_iterations=0"]}},
    }))
    runs = {run.name: run.config for run in make_plan(load_spec(path), tmp_path / "out").runs}
    assert all(config is not None and config.ppo.epochs == 3 for config in runs.values())
    cmat_m = {name: config.options.consensus_iterations for name, config in runs.items()
              if config is not None and config.algo == "cmat"}
    assert cmat_m == {"matrix_fig1/default/cmat-s0": 1, "matrix_penalty/default/cmat-s0": 1,
                      "matrix_fig1/m0/cmat-s0": 0, "matrix_penalty/m0/cmat-s0": 0}
    mat_points = {name: config.options.inducing_points for name, config in runs.items()
                  if config is not None and config.algo == "mat"}
    assert mat_points == {"matrix_fig1/default/mat-s0": 0, "matrix_penalty/default/mat-s0": 2}


def test_the_ablation_draws_the_tasks_its_variants_are_compared_on(tmp_path: Path) -> None:
    path = tmp_path / "panels.yaml"
    envs = ["matrix:fig1", "matrix:penalty", "matrix:climbing"]
    path.write_text(yaml.safe_dump({
        "steps": 100, "envs": envs, "algos": ["cmat", "mat"],
        "variants": {
            "default": {"figure": ["main", "ablation"]},
            "m0": {"algos": ["cmat"], "figure": "ablation", "envs": ["matrix:penalty"],
                   "set": {"cmat": {"consensus_iterations": 0}}},
            "last": {"algos": ["cmat"], "figure": "ablation",
                     "envs": ["matrix:penalty", "matrix:climbing"],
                     "set": {"cmat": {"consensus_source": "last"}}},
            "mat_only": {"algos": ["mat"], "figure": "ablation", "envs": ["matrix:fig1"]},
        },
    }))
    spec = load_spec(path)
    assert [env.id for env in panel_envs(spec, "ablation")] == envs[1:]
    assert [env.id for env in panel_envs(spec, "main")] == envs
    path.write_text(yaml.safe_dump({
        "steps": 100, "envs": envs, "algos": ["cmat"],
        "variants": {"a": {"envs": ["matrix:fig1"]}, "b": {"envs": ["matrix:penalty"]},
                     "c": {"envs": ["matrix:climbing"]}},
    }))
    assert [env.id for env in panel_envs(load_spec(path), "main")] == envs
    path.write_text(yaml.safe_dump({
        "steps": 100, "envs": envs, "algos": ["cmat"],
        "variants": {"default": {}, "long": {"envs": ["matrix:fig1"], "steps": 200}},
    }))
    assert [env.id for env in panel_envs(load_spec(path), "main")] == envs


def test_a_spec_names_the_paper_preset_or_the_defaults(tmp_path: Path) -> None:
    path = tmp_path / "presets.yaml"
    path.write_text(yaml.safe_dump({
        "steps": 100, "envs": ["matrix:fig1"], "algos": ["cmat"],
        "variants": {"default": {}, "paper": {"set": {"preset": "paper"}}},
    }))
    plan = run_experiment(path, out=tmp_path / "x", dry_run=True)
    configs = {run.variant.name: run.config for run in plan.runs}
    assert configs["paper"].preset == "paper" and configs["default"].preset is None
    assert (configs["paper"].num_envs, configs["default"].num_envs) == (8, 16)  # matrix suite
    assert configs["paper"].ppo == load_config(overrides=["preset=paper"]).ppo


def test_published_suite_means_are_listed_for_a_suites_tasks_and_drawn_only_on_its_scale(
    tmp_path: Path,
) -> None:
    """Two invented tasks ids under the LBF and RWARE prefixes pick up their suites' rows; an
    unrelated task none; only rows whose `drawn_on` is the task's metric are drawn, one per
    algorithm, the one nearest the budget."""
    rows = load_suite_aggregates()
    assert rows and all(0.0 <= row["value"] <= 1.0 and row["env_steps"] > 0 and row["source"]
                        for row in rows)
    lbf = matching_suite_aggregates(rows, ["jumanji:lbf-99x99-9p-9f"])
    assert lbf and {row["suite"] for row in lbf} == {"Level-Based Foraging"}
    both = matching_suite_aggregates(rows, ["jumanji:lbf-x", "jumanji:rware-x", "matrix:fig1"])
    assert {row["suite"] for row in both} == {"Level-Based Foraging", "Robot Warehouse"}
    assert matching_suite_aggregates(rows, ["matrix:fig1", "mpe:simple_spread"]) == []
    drawn = drawn_suite_aggregates(rows, "jumanji:lbf-x", "episode_return", 700_000)
    assert sorted(row["algorithm"] for row in drawn) == ["MAPPO", "MAT", "Sable"]
    assert {row["env_steps"] for row in drawn} == {1_000_000}
    assert {row["env_steps"] for row in
            drawn_suite_aggregates(rows, "jumanji:lbf-x", "episode_return", 30_000_000)} == {
        20_000_000}
    assert drawn_suite_aggregates(rows, "jumanji:lbf-x", "win_rate", 700_000) == []
    assert drawn_suite_aggregates(rows, "jumanji:rware-x", "episode_return", 700_000) == []


@pytest.mark.parametrize("seed", range(5))
def test_a_seeds_score_is_its_mean_evaluation_over_the_last_part_of_its_steps(seed: int) -> None:
    rng = np.random.default_rng(seed)
    window = float(rng.uniform(0.05, 0.95))
    rows: list[dict[str, str]] = []
    expected_last, expected_window = [], []
    for run_seed in rng.permutation(4):
        count, interval = int(rng.integers(1, 15)), int(rng.integers(1, 5)) * 1000
        steps = interval * np.arange(1, count + 1)
        values = rng.random(count)
        if run_seed == 2:  # a NaN before the window is harmless, one inside drops the seed
            values[0] = np.nan
        inside = steps >= (1 - window) * steps[-1]
        if not np.isnan(values[inside]).any():
            expected_window.append((run_seed, values[inside].mean()))
        if not np.isnan(values[-1]):
            expected_last.append((run_seed, values[-1]))
        for step, value in zip(steps, values, strict=True):
            common = {"seed": str(run_seed), "env_steps": str(step)}
            rows.append({**common, "kind": "eval", "win_rate": repr(float(value))})
            rows.append({**common, "kind": "train", "win_rate": "1.0"})
        rows.append({"seed": str(run_seed), "env_steps": str(steps[-1] * 2), "kind": "eval",
                     "win_rate": ""})
    rows = [rows[i] for i in rng.permutation(len(rows))]
    line = Line("X", "default", "cmat", ("main",), [], rows)
    np.testing.assert_allclose(line.scores("win_rate"), [v for _, v in sorted(expected_last)])
    np.testing.assert_allclose(line.scores("win_rate", window),
                               [v for _, v in sorted(expected_window)])
    assert line.scores("episode_return", window) == []


def test_statistics_equal_rliables() -> None:
    rng = np.random.default_rng(3)
    x = rng.integers(0, 4, size=(5, 3)).astype(float)
    y = rng.integers(0, 4, size=(4, 3)).astype(float)
    assert iqm(x) == pytest.approx(rliable_metrics.aggregate_iqm(x))
    assert improvement_probability(x, y) == pytest.approx(
        rliable_metrics.probability_of_improvement(x, y)
    )
    batched = improvement_probability(np.stack([x, x[::-1]]), np.stack([y, y]))
    assert batched == pytest.approx([rliable_metrics.probability_of_improvement(x, y)] * 2)


@pytest.mark.slow
def test_ray_runs_a_grid_on_a_local_cluster(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    spec = yaml.safe_load(SMOKE.read_text())
    spec.update(steps=500, seeds=1, algos=["cmat"])
    spec["variants"]["finetune_action"]["steps"] = 500
    path = tmp_path / "ray.yaml"
    path.write_text(yaml.safe_dump(spec))
    done = experiment(str(path), "--out", str(tmp_path / "out"), "--ray", "local")
    assert done.returncode == 0, done.stdout + done.stderr
    assert checkpoint_steps(tmp_path / "out" / "runs/matrix_fig1/finetune_action/cmat-s0") == 500


def test_ray_address_without_ray_is_one_error_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(SPEC))
    for dry_run in ([], ["--dry-run"]):
        assert main(["experiment", str(path), "--out", str(tmp_path / "out"), "--ray", "auto",
                     *dry_run]) == 2
        assert "--ray needs Ray: pip install 'ray>=2.40,<3'" in one_error_line(
            capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("flag", "options"), [
    ("--out", []), ("--out", ["--dry-run"]), ("--export", ["--report-only"]), ("--export", []),
])
def test_a_file_where_a_directory_is_needed_is_one_error_line_before_any_work(
    flag: str, options: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(SPEC))
    file = tmp_path / "notes.txt"
    file.write_text("mine")
    out = ["--out", str(tmp_path / "out")] if flag == "--export" else []
    for target, message in ((file, f"{flag} {file} is a file, not a directory"),
                            (file / "grid", f"{flag} {file / 'grid'}: its parent {file} is a "
                                            "file, not a directory")):
        before = sorted(tmp_path.iterdir())
        assert main(["experiment", str(path), *out, flag, str(target), *options]) == 2
        assert message in one_error_line(capsys.readouterr().err)
        assert sorted(tmp_path.iterdir()) == before and file.read_text() == "mine"


def test_the_documented_spec_example_plans(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """docs/experiments.md's spec-format block is a valid spec: it loads with the values its
    comments state, and `--dry-run` plans every cell (the unavailable env skipped) without an
    error."""
    readme = (REPO / "docs" / "experiments.md").read_text()
    after = readme[readme.index("A spec is one YAML file"):]
    block = after[after.index("```yaml\n") + 8:after.index("\n```", after.index("```yaml"))]
    path = tmp_path / "readme_spec.yaml"
    path.write_text(block + "\n")
    spec = load_spec(path)
    assert (spec.name, spec.seeds, spec.seeds_per_run, spec.score_window) == ("my_grid", 3, 3, 0.1)
    assert [env.steps for env in spec.envs] == [200000, 500000, 200000]
    assert [v.name for v in spec.variants] == ["default", "last", "m_half", "finetune_action"]
    assert spec.variant("finetune_action").base == "default"
    assert main(["experiment", str(path), "--out", str(tmp_path / "out"), "--dry-run"]) == 0
    planned = capsys.readouterr().out
    assert "new     smax_2s3z/finetune_action/cmat-s0-2" in planned, planned
    assert "new     smax_3m/m_half" not in planned and "unavailable" in planned, planned


def test_claims_are_judged_only_where_the_spec_asks(tmp_path: Path) -> None:
    path = tmp_path / "claims.yaml"
    base = {"steps": 100, "envs": ["matrix:fig1"], "algos": ["cmat"]}
    path.write_text(yaml.safe_dump(base))
    assert load_spec(path).claims is False
    path.write_text(yaml.safe_dump({**base, "claims": True}))
    assert load_spec(path).claims is True
    path.write_text(yaml.safe_dump({**base, "claims": "yes"}))
    with pytest.raises(CmatError, match="claims must be true or false"):
        load_spec(path)
    assert {name for name in spec_names() if load_spec(name).claims} == {
        "paper_main", "paper_ablation", "smax_benchmark", "sable_comparison", "mini_repro",
        "smoke"}


def test_bands_stay_in_the_metric_range() -> None:
    from matplotlib.figure import Figure

    from cmat.plots import band

    axes = Figure().subplots()
    steps, mean, std = np.arange(3.0), np.array([0.05, 0.5, 0.95]), np.full(3, 0.2)
    band(axes, steps, mean, std, "win_rate")
    low, high = axes.collections[0].get_paths()[0].vertices[:, 1].min(), \
        axes.collections[0].get_paths()[0].vertices[:, 1].max()
    assert (low, high) == (0.0, 1.0)
    band(axes, steps, mean, std, "episode_return")
    assert axes.collections[1].get_paths()[0].vertices[:, 1].min() == pytest.approx(-0.15)


def test_sable_lines_are_named_as_their_authors_name_them() -> None:
    """"Sable" is the Sable paper's recurrent Sable; the feed-forward one says so."""
    spec = load_spec("sable_comparison")
    plan = make_plan(spec, Path("unused"))
    labels = {run.algo: run.variant.line_label(run.algo) for run in plan.runs}
    assert labels == {"cmat": "CMAT", "sable": "Sable", "ff_sable": "Sable (feed-forward)",
                      "mat": "MAT"}
