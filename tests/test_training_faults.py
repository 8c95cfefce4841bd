"""`dope-hope train` under faults: a time budget that is spent (idle, a load that starts or
stops, across a resume, after SIGKILL), huge budgets, non-finite starting weights, a length
changed at resume, SIGTERM, Ctrl-C inside a log row's averaging window, plots of NaN curves.

The time budget is checked twice: with the real clock through the CLI (the share of the budget
used is printed; run with -s to see it), and with an injected clock that advances by a fixed
profile of seconds per step, which makes the plans (and so the weights) reproducible: a run
killed with SIGKILL and resumed must end with the weights and the plans of an uninterrupted run.
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch
from test_cli_mistakes import TINY_SET, one_line_error, run_cli
from test_training_trainer import write_frames

from dope_hope.config import load_config
from dope_hope.model.checkpoint import load_checkpoint
from dope_hope.training.settings import TrainJob
from dope_hope.training.trainer import train

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parent.parent
TESTS = Path(__file__).resolve().parent
#: The tiny network of TINY_SET as nested overrides (the Python API's form).
TINY = {"input": {"size": [64, 64]},
        "model": {"stages": 1, "head": 50, "lite": {"width": 8, "feature_channels": 16, "stage_channels": 16}},
        "train": {"batch_size": 2, "workers": 0, "threads": 1, "log_every": 1, "time_limit_min": None,
                  "plots": False}}


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """41 frames: 40 training + 1 validation frame (lite's val_fraction 0.025), 20 steps per epoch
    at batch 2."""
    folder = tmp_path_factory.mktemp("faults")
    write_frames(folder, 41, seed=5)
    return folder


def _tiny(**train_values) -> dict:
    out = json.loads(json.dumps(TINY))
    out["train"].update(train_values)
    return out


def _rows(folder: Path) -> list[dict]:
    keep = ("event", "step", "epoch", "lr", "loss", "val_loss", "val_kp_acc")
    return [{k: r.get(k) for k in keep} for r in map(json.loads, (folder / "metrics.jsonl").read_text().splitlines())]


def _same_weights(a: Path, b: Path) -> bool:
    wa, wb = load_checkpoint(a)["model"], load_checkpoint(b)["model"]
    return wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


def _last_time(folder: Path) -> float:
    """The budget time of the last row of metrics.jsonl (0 before one; a line being appended is skipped)."""
    times = [0.0]
    with contextlib.suppress(OSError):
        for line in (folder / "metrics.jsonl").read_text().splitlines():
            with contextlib.suppress(ValueError):
                times.append(float(json.loads(line).get("time_s", 0.0)))
    return max(times)


def _checkpoint_step(path: Path) -> int:
    with contextlib.suppress(Exception):
        return int(load_checkpoint(path)["step"])
    return -1


# ============================================================================= an injected clock
def seconds_per_step(step: int) -> float:
    """The injected speed: 1/8 s per step, 1/2 s while a second job runs (steps 41-80: 4x
    slower), 1/8 s again after it stops (powers of two: the sums are exact)."""
    return 0.5 if 40 < step <= 80 else 0.125


class StepClock:
    """A clock that advances by :func:`seconds_per_step` when a step ends (validation and
    checkpoints take no time): a run's plans depend on its steps only."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def on_step(self, trainer, step: int) -> None:
        self.now += seconds_per_step(step)


#: 45 s of the injected clock, a checkpoint after every step.
CLOCKED = _tiny(time_limit_min=0.75, epochs=1000, checkpoint_every_steps=1, horizon_estimate_after=10, log_every=7)


def clocked_run(data: str, out: str, resume: str | None = None) -> dict:
    """A time-limited run on the injected clock (also the body of the killed subprocess)."""
    clock = StepClock()
    job = TrainJob([Path(data)], "Ketchup", Path(out), resume=Path(resume) if resume else None, progress=False,
                   overrides=CLOCKED if resume is None else {}, on_step=clock.on_step, clock=clock)
    return train(job, load_config("lite"))


def test_time_budget_replans_when_the_speed_changes_and_is_spent(data, tmp_path):
    """The speed drops 4x at step 41 and recovers at step 81: the run re-plans from the recent
    steps each time and ends between 97 % and 100 % of its budget (injected clock)."""
    out = clocked_run(str(data), str(tmp_path / "a"))
    plans = load_checkpoint(tmp_path / "a" / "last.pt")["extra"]["plans"]
    used = out["budget_used_s"] / 45.0
    print(f"\ninjected clock: {out['step']} steps, {100 * used:.1f} % of the budget, {len(plans)} plans: "
          + ", ".join(f"{p['step']}->{p['end']} ({p['why']})" for p in plans[:6]) + " ...")
    assert out["status"] == "time_limit" and out["step"] == plans[-1]["end"] == out["planned_steps"]
    assert 0.97 <= used <= 1.0, out
    ends = {p["step"]: p["end"] for p in plans}
    first = plans[0]
    assert first["why"] == "first" and first["per_step_s"] == 0.125
    slow = next(p for p in plans if p["step"] > 45)  # the first plan that measured the slow steps
    assert slow["end"] < first["end"]
    assert plans[-1]["end"] > min(ends.values())  # planned longer again once the load stopped
    lrs = [r["lr"] for r in _rows(tmp_path / "a") if r["event"] == "train"]
    assert lrs[-1] < 0.002 * 0.05  # the cosine (floor 2 %) is near its floor at the end


def test_sigkill_and_resume_follow_the_recorded_plans_bit_identically(data, tmp_path):
    """A run killed with SIGKILL in its slow phase (plans made before the kill, more after)
    and resumed ends with the uninterrupted run's weights, plans and metrics (injected clock)."""
    full = clocked_run(str(data), str(tmp_path / "full"))
    part = tmp_path / "part"
    code = f"import sys; sys.path.insert(0, {str(TESTS)!r}); import test_training_faults as t; " \
           f"t.clocked_run({str(data)!r}, {str(part)!r})"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while proc.poll() is None and time.monotonic() < deadline and _checkpoint_step(part / "last.pt") < 60:
        time.sleep(0.02)
    proc.kill()  # SIGKILL, maybe while last.pt is written
    proc.communicate()
    assert proc.returncode == -signal.SIGKILL, "the run ended before it could be killed"
    killed = load_checkpoint(part / "last.pt")
    assert 60 <= killed["step"] < full["step"] and len(killed["extra"]["plans"]) >= 2

    resumed = clocked_run(str(data), str(part), resume=str(part / "last.pt"))
    assert (resumed["status"], resumed["step"]) == (full["status"], full["step"])
    assert _same_weights(tmp_path / "full" / "last.pt", part / "last.pt")
    plans = [load_checkpoint(p / "last.pt")["extra"]["plans"] for p in (tmp_path / "full", part)]
    assert plans[0] == plans[1] and len(plans[0]) > len(killed["extra"]["plans"])
    assert _rows(part) == _rows(tmp_path / "full")
    assert not [p for p in part.iterdir() if ".tmp" in p.name]


def test_a_replan_bends_the_cosine_without_a_jump():
    from dope_hope.training.schedule import LrLambda

    f = LrLambda("cosine", horizon=100, warmup=10, min_factor=0.1)
    before = [f(s) for s in range(0, 60)]
    f.replan(50, 70)   # shorter: from f(50) down to the floor at 70
    assert [f(s) for s in range(0, 51)] == before[:51]
    assert f(70) == pytest.approx(0.1) and f(60) < before[59]
    f.replan(60, 200)  # longer again, from where it is
    g = LrLambda("cosine", horizon=100, warmup=10, min_factor=0.1)
    g.replan(50, 70)
    assert f(60) == g(60) and f(200) == pytest.approx(0.1) and f(61) < f(60)
    w = LrLambda("cosine", horizon=100, warmup=10, min_factor=0.1)
    w.replan(3, 40)    # during the warm-up: the ramp stays, the cosine spans 10..40
    assert w(3) == 0.4 and w(10) == 1.0 and w(40) == pytest.approx(0.1)


def test_a_warm_restart_climbs_from_the_floor_and_keeps_its_ramp_through_replans():
    from dope_hope.training.schedule import LrLambda

    f = LrLambda("cosine", horizon=100, warmup=10, min_factor=0.02)
    assert f.ended(100) and not f.ended(99) and f(100) == pytest.approx(0.02)
    f.restart(100, 300)
    assert [f(s) for s in range(100)] == [LrLambda("cosine", horizon=100, warmup=10, min_factor=0.02)(s)
                                          for s in range(100)]
    assert f(100) == pytest.approx(0.02 + 0.98 / 10) and f(109) == 1.0 and f(300) == pytest.approx(0.02)
    assert not f.ended(299) and f.ended(300)
    f.replan(105, 400)  # a time budget's re-plan during the ramp: the ramp goes on, the end moves
    assert f(109) == 1.0 and f(400) == pytest.approx(0.02) and f(250) > f(300) > f(399)
    old = LrLambda("cosine", horizon=100, warmup=10, min_factor=0.02)
    old.segments = [(50, 80, 0.9)]  # an older checkpoint's 3-field segment
    assert old(80) == pytest.approx(0.02) and old(50) == pytest.approx(0.9)


def test_continued_replans_follow_one_cosine_restarted_ones_stay_high():
    """A time budget re-plans its end some thirty times in 30 minutes (a step or two each way).
    ``continue``: the learning rate goes on along its cosine's phase, so it anneals as one cosine
    to the last end would, and a re-plan that keeps the end changes nothing. ``restart`` (the
    default, measured the better for a 30-minute model): each re-plan starts a cosine from its
    flat top, so the rate stays high until the last part of the run."""
    from dope_hope.training.schedule import LrLambda

    def replanned(mode: str) -> LrLambda:
        f = LrLambda("cosine", horizon=1500, warmup=10, min_factor=0.02, replan_mode=mode)  # first plan too long
        for i, step in enumerate(range(100, 1000, 30)):
            f.replan(step, 1000 + (3 if i % 2 else -3))
        return f

    one = LrLambda("cosine", horizon=1000, warmup=10, min_factor=0.02)
    same = LrLambda("cosine", horizon=1000, warmup=10, min_factor=0.02, replan_mode="continue")
    for step in range(50, 1000, 50):
        same.replan(step, 1000)
    assert max(abs(same(s) - one(s)) for s in range(1001)) < 1e-12
    cont, restart = replanned("continue"), replanned("restart")
    assert cont(920) == pytest.approx(one(920), abs=0.01) and cont(500) == pytest.approx(one(500), abs=0.05)
    assert restart(920) > 0.4 and restart(500) > 0.9
    assert cont(1003) == pytest.approx(0.02) and restart(1003) == pytest.approx(0.02)   # the last plan's end
    assert [cont(s) for s in range(100)] == [restart(s) for s in range(100)]            # before any re-plan


def test_wsd_holds_the_peak_until_its_decay_share_and_replans_cannot_flatten_it():
    """``wsd``: the peak rate until the last ``decay_share`` of the planned steps after the
    warm-up, then a straight line to the floor at the end. Re-plans in the stable part change
    nothing; a re-plan during the decay goes on from the factor reached, never jumping."""
    from dope_hope.training.schedule import LrLambda

    plain = LrLambda("wsd", horizon=1010, warmup=10, min_factor=0.02, decay_share=0.2)
    assert plain(0) == pytest.approx(0.1) and plain(10) == 1.0 and plain(809) == 1.0
    assert plain(810) == 1.0 and plain(910) == pytest.approx(0.51) and plain(1010) == pytest.approx(0.02)
    replanned = LrLambda("wsd", horizon=1500, warmup=10, min_factor=0.02, decay_share=0.2)
    for i, step in enumerate(range(100, 800, 30)):            # stable part: the end wobbles
        replanned.replan(step, 1010 + (3 if i % 2 else -3))
    replanned.replan(790, 1010)
    assert max(abs(replanned(s) - plain(s)) for s in range(1011)) < 1e-12
    late = LrLambda("wsd", horizon=1010, warmup=10, min_factor=0.02, decay_share=0.2)
    late.replan(910, 1510)                                     # the end moves out mid-decay
    factors = [late(s) for s in range(1511)]
    assert max(abs(a - b) for a, b in zip(factors[10:], factors[11:])) < 0.01   # no jump after the warm-up
    assert factors[1000] == pytest.approx(plain(910)) and factors[1510] == pytest.approx(0.02)
    assert LrLambda("wsd", horizon=1010, warmup=10, decay_share=0.0)(1009) == 1.0

def test_a_run_freezes_its_startup_objects_and_collects_at_each_validation(data, tmp_path, monkeypatch):
    """The garbage collector's full passes come at the validations, inside their timed cost (a
    pass landing at random doubled one validation in three, and a budget planning its final
    validation from their median overran); the run unfreezes what it froze."""
    import gc

    from dope_hope.training import trainer as trainer_module

    events: list[str] = []  # "step", "full pass", "validate", in order
    frozen: list[int] = []

    def on_step(trainer, step: int) -> None:
        events.append("step")
        frozen.append(gc.get_freeze_count())

    def count(phase: str, info: dict) -> None:
        if phase == "start" and info["generation"] == 2:
            events.append("full pass")

    validate = trainer_module.Trainer.validate
    monkeypatch.setattr(trainer_module.Trainer, "validate", lambda self: events.append("validate") or validate(self))
    before = gc.get_freeze_count()
    gc.callbacks.append(count)
    try:
        summary = train(TrainJob([data], "Ketchup", tmp_path / "o", progress=False,
                                 overrides=_tiny(epochs=3, val_every=1), on_step=on_step), load_config("lite"))
    finally:
        gc.callbacks.remove(count)
    assert summary["status"] == "completed" and summary["step"] == 60
    assert min(frozen) > before + 1000  # the model, the records and the modules are frozen out ...
    assert gc.get_freeze_count() == before  # ... and given back at the end
    at = [i for i, e in enumerate(events) if e == "validate"]
    assert len(at) == 3
    for i in at:  # a full pass since the last step, before each validation
        last_step = max(j for j in range(i) if events[j] == "step")
        assert "full pass" in events[last_step:i], events[last_step:i]


def test_a_calling_programs_own_freeze_is_left_to_it(data, tmp_path):
    """A program that froze its objects before training keeps them frozen after it (Python
    can only unfreeze all)."""
    import gc

    gc.freeze()
    try:
        mine = gc.get_freeze_count()
        assert mine > 0
        summary = train(TrainJob([data], "Ketchup", tmp_path / "o", progress=False,
                                 overrides=_tiny(epochs=1, val_every=1)), load_config("lite"))
        assert summary["status"] == "completed"
        assert gc.get_freeze_count() > mine // 2  # (frozen objects freed by reference counting leave it)
    finally:
        gc.unfreeze()


# ============================================================================= the real clock, through the CLI
BUDGET_MIN = 0.4  # 24 s


def _budgeted_argv(data: Path, out: Path, minutes: float = BUDGET_MIN, thresholds: bool = False) -> list:
    """A budgeted run; without the thresholds' choice at its end unless ``thresholds`` (its
    cost is estimated, not measured: the plans' own accuracy is what these tests check)."""
    return ["train", "--data", data, "--object", "Ketchup", "--out", out, "--no-progress",
            "--set", *TINY_SET, "train.epochs=100000", "train.log_every=50",
            f"train.calibrate_thresholds={str(thresholds).lower()}", "--time-budget", minutes]


def _burn(n: int) -> list[subprocess.Popen]:
    """``n`` processes that keep a CPU core busy (the second job of a shared machine)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _share(data: Path, out: Path, capfd, load_from: float | None = None, load_until: float | None = None,
           thresholds: bool = False) -> float:
    """Run a budgeted training through the CLI, with CPU burners from ``load_from`` to
    ``load_until`` (shares of the budget; None: from the start / to the end), ending with the
    thresholds' choice when ``thresholds``; returns the share of the budget the command took
    (wall clock)."""
    burners: list[subprocess.Popen] = []
    budget_s = BUDGET_MIN * 60.0

    def start() -> None:
        burners.extend(_burn(2))

    def stop() -> None:
        for p in burners:
            p.kill()

    timers = []
    if load_from is not None:
        timers.append(threading.Timer(load_from * budget_s, start))
    if load_until is not None:
        timers.append(threading.Timer(load_until * budget_s, stop))
    t0 = time.monotonic()
    for t in timers:
        t.start()
    try:
        code, stdout, err = run_cli(_budgeted_argv(data, out, thresholds=thresholds), capfd)
    finally:
        for t in timers:
            t.cancel()
        stop()
        for p in burners:
            p.wait()
    wall = time.monotonic() - t0
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "time_limit" and stdout.startswith("time_limit: step")
    print(f"\nbudget {budget_s:.0f} s, load {load_from}-{load_until}: command {wall:.2f} s ({100 * wall / budget_s:.1f} %), "
          f"budget used {summary['budget_used_s']} s, {summary['step']} steps, "
          f"{len(load_checkpoint(out / 'last.pt')['extra']['plans'])} plans; the last: "
          + "; ".join(", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in p.items())
                      for p in load_checkpoint(out / 'last.pt')['extra']['plans'][-3:]))
    return wall / budget_s


#: The command's own work outside the budget's clock (argument and folder checks, the summary).
TOLERANCE = 0.01


def test_time_budget_is_spent_on_an_idle_machine(data, tmp_path, capfd):
    share = _share(data, tmp_path / "o", capfd)
    assert 0.97 <= share <= 1.0 + TOLERANCE


def test_time_budget_holds_with_the_thresholds_choice_at_the_end(data, tmp_path, capfd):
    """The choice after the final validation is planned for (1.9 validations for one object): the run
    still ends inside its budget."""
    share = _share(data, tmp_path / "o", capfd, thresholds=True)
    assert 0.9 <= share <= 1.0 + TOLERANCE
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["min_score_frames"] > 0


def test_time_budget_holds_when_a_second_job_starts(data, tmp_path, capfd):
    """Two CPU burners start at 40 % of the budget: the run plans shorter and still ends in time
    (>= 97 % is not asked: a sudden slowdown near a plan's end may leave a little unused)."""
    share = _share(data, tmp_path / "o", capfd, load_from=0.4)
    assert 0.9 <= share <= 1.0 + TOLERANCE


def test_time_budget_is_spent_when_a_second_job_stops(data, tmp_path, capfd):
    """Two CPU burners run until 50 % of the budget: the run plans longer once they stop."""
    share = _share(data, tmp_path / "o", capfd, load_from=0.0, load_until=0.5)
    assert 0.97 <= share <= 1.0 + TOLERANCE


def test_time_budget_across_a_ctrl_c_and_resume(data, tmp_path, capfd):
    """Ctrl-C at ~40 % of the budget, then --resume: the two processes together use the
    budget (the resumed run plans with the time left, from its own speed)."""
    out = tmp_path / "o"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    argv = [sys.executable, "-m", "dope_hope.cli", *map(str, _budgeted_argv(data, out))]
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    started = time.monotonic()
    while proc.poll() is None and time.monotonic() - started < 60 and _last_time(out) < 0.4 * BUDGET_MIN * 60:
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    first = json.loads((out / "summary.json").read_text())
    assert first["status"] == "interrupted"
    t0 = time.monotonic()
    code, stdout, err = run_cli(["train", "--out", out, "--resume", "--no-progress"], capfd)
    second_wall = time.monotonic() - t0
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    share = summary["budget_used_s"] / (BUDGET_MIN * 60)
    total = (first["budget_used_s"] + second_wall) / (BUDGET_MIN * 60)
    print(f"\nresumed at {first['budget_used_s']} s: budget used {summary['budget_used_s']} s ({100 * share:.1f} %), "
          f"first process's budget + second command {100 * total:.1f} %")
    assert summary["status"] == "time_limit" and summary["step"] > first["step"]
    assert 0.97 <= share <= 1.0 + TOLERANCE
    assert total <= 1.0 + TOLERANCE


# ============================================================================= inputs and signals
def test_a_time_budget_beyond_a_year_is_one_line(data, tmp_path, capsys):
    base = ["train", "--data", data, "--object", "Ketchup", "--out", tmp_path / "o", "--no-progress", "--steps", "1"]
    line = one_line_error(*run_cli([*base, "--time-budget", "1e308", "--set", *TINY_SET], capsys)[::2], "train")
    assert "argument --time-budget: must be at most 525600 minutes" in line
    assert not (tmp_path / "o").exists()
    line = one_line_error(*run_cli([*base, "--set", *TINY_SET, "train.time_limit_min=1.0e+308"], capsys)[::2], "train")
    assert "train.time_limit_min must be at most 525600 minutes" in line
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").iterdir())  # nothing written


def test_init_from_non_finite_weights_is_refused(data, tmp_path, capsys):
    run = tmp_path / "run"
    code, _, err = run_cli(["train", "--data", data, "--object", "Ketchup", "--out", run, "--no-progress",
                            "--steps", "1", "--set", *TINY_SET], capsys)
    assert code == 0, err
    ck = torch.load(run / "last.pt", weights_only=True)
    name = next(k for k, v in ck["model"].items() if v.is_floating_point() and v.numel() > 1)
    ck["model"][name][0] = float("nan")
    torch.save(ck, tmp_path / "nan.pt")
    code, _, err = run_cli(["train", "--data", data, "--object", "Ketchup", "--out", tmp_path / "o", "--no-progress",
                            "--steps", "2", "--init", tmp_path / "nan.pt", "--set", *TINY_SET], capsys)
    line = [ln for ln in err.splitlines() if "error" in ln]
    assert code == 2 and len(line) == 1 and "Traceback" not in err, err
    assert f"{tmp_path / 'nan.pt'}: 1 weight tensor(s) hold NaN or inf values (e.g. {name})" in line[0]
    assert not (tmp_path / "o" / "last.pt").exists() and not (tmp_path / "o" / "metrics.jsonl").exists()


@pytest.mark.parametrize("budget", [None, 10])
def test_resume_with_more_steps_says_which_wins_and_runs_them(data, tmp_path, capsys, caplog, budget):
    run = tmp_path / "run"
    extra = [] if budget is None else ["--time-budget", budget]
    code, _, err = run_cli(["train", "--data", data, "--object", "Ketchup", "--out", run, "--no-progress",
                            "--steps", "4", "--set", *TINY_SET, *extra], capsys)
    assert code == 0 and json.loads((run / "summary.json").read_text())["step"] == 4, err
    code, out, err = run_cli(["train", "--out", run, "--resume", "--steps", "6", "--no-progress", *extra], capsys)
    assert code == 0, err
    said = [(r.levelname, r.getMessage()) for r in caplog.records if "given now" in r.getMessage()]
    tail = "" if budget is None else ", or earlier when the 10-min time budget is spent"
    assert said == [("WARNING", f"resume: train.steps 6 given now win(s) over the checkpoint's 4: the run "
                                f"ends at step 6{tail}; the run had ended: its learning rate restarts warm to "
                                "0.002 (SGDR)")]
    summary = json.loads((run / "summary.json").read_text())
    assert (summary["status"], summary["step"]) == ("completed", 6) and out.startswith("completed: step 6")


def test_a_finished_run_trained_longer_restarts_its_learning_rate_warm(data, tmp_path, capsys):
    """A run that reached its end sits at the cosine's floor; given more steps at --resume it
    warms up to the peak again and anneals to the new end (a re-plan from the floor kept the
    continued 30 -> 60 -> 120-minute Ketchup runs at 0.02 of the peak all along)."""
    run = tmp_path / "run"
    sets = ["--set", *TINY_SET, "train.warmup_steps=2", "train.lr=0.01"]
    code, _, err = run_cli(["train", "--data", data, "--object", "Ketchup", "--out", run, "--no-progress",
                            "--steps", "6", *sets], capsys)
    assert code == 0, err
    code, _, err = run_cli(["train", "--out", run, "--resume", "--steps", "16", "--no-progress"], capsys)
    assert code == 0, err
    lr = {r["step"]: r["lr"] for r in map(json.loads, (run / "metrics.jsonl").read_text().splitlines())
          if r["event"] == "train"}
    floor = 0.01 * 0.02  # lite's min_lr_factor
    assert lr[6] == pytest.approx(floor, rel=0.05)       # the first run's end
    assert lr[8] == pytest.approx(0.01, rel=0.05)        # two steps of warm-up later: the peak again
    assert floor < lr[12] < lr[8] and lr[16] == pytest.approx(floor, rel=0.05)


def test_a_run_that_spent_its_time_budget_restarts_warm_when_given_more(data, tmp_path, capsys, caplog):
    """A time budget's last re-plan leaves the schedule's end a step past the run's: the run's
    own end (its last plan) is what says it finished."""
    run = tmp_path / "run"
    code, _, err = run_cli(["train", "--data", data, "--object", "Ketchup", "--out", run, "--no-progress",
                            "--time-budget", "0.05", "--set", *TINY_SET, "train.epochs=1000"], capsys)
    assert code == 0 and json.loads((run / "summary.json").read_text())["status"] == "time_limit", err
    code, _, err = run_cli(["train", "--out", run, "--resume", "--time-budget", "0.1", "--no-progress"], capsys)
    assert code == 0, err
    said = [r.getMessage() for r in caplog.records if "given now" in r.getMessage()]
    assert len(said) == 1 and said[0].endswith("; the run had ended: its learning rate restarts warm to 0.002 (SGDR)")


@pytest.mark.parametrize("sig, code, status", [(signal.SIGTERM, 143, "terminated"), (signal.SIGINT, 130, "interrupted")])
def test_a_signal_during_training_exits_as_a_shell_expects(data, tmp_path, sig, code, status):
    out = tmp_path / "o"
    argv = [sys.executable, "-m", "dope_hope.cli", "train", "--data", str(data), "--object", "Ketchup",
            "--out", str(out), "--no-progress", "--set", *TINY_SET, "train.epochs=1000"]
    proc = subprocess.Popen(argv, env=dict(os.environ, PYTHONPATH=str(REPO)), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 90
    while proc.poll() is None and time.monotonic() < deadline and _checkpoint_step(out / "last.pt") < 0:
        time.sleep(0.05)
    proc.send_signal(sig)
    stdout, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err
    assert stdout.startswith(f"{status}: step") and "Traceback" not in err
    assert json.loads((out / "summary.json").read_text())["status"] == status
    assert _checkpoint_step(out / "last.pt") == json.loads((out / "summary.json").read_text())["step"]


def test_ctrl_c_inside_an_averaging_window_logs_as_an_uninterrupted_run(data, tmp_path, capsys):
    """A train row averages 20 steps; Ctrl-C lands inside a window: the resumed run's rows
    (the interrupted window's loss included) equal the uninterrupted run's."""
    args = ["--data", data, "--object", "Ketchup", "--no-progress", "--steps", "45",
            "--set", *TINY_SET, "train.log_every=20", "train.checkpoint_every_steps=1"]
    code, _, err = run_cli(["train", "--out", tmp_path / "full", *args], capsys)
    assert code == 0, err
    for attempt in range(3):  # a loaded machine may overshoot to a window's end: interrupt again
        part = tmp_path / f"part{attempt}"
        argv = [sys.executable, "-m", "dope_hope.cli", "train", "--out", str(part), *map(str, args)]
        proc = subprocess.Popen(argv, env=dict(os.environ, PYTHONPATH=str(REPO)), stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 90
        while proc.poll() is None and time.monotonic() < deadline and _checkpoint_step(part / "last.pt") < 22:
            time.sleep(0.01)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 130, err
        ck = load_checkpoint(part / "last.pt")
        if ck["extra"]["loss_window"][1] > 0:
            break
    assert 22 <= ck["step"] < 45 and ck["extra"]["loss_window"][1] > 0  # inside a window
    code, _, err = run_cli(["train", "--out", part, "--resume", "--no-progress"], capsys)
    assert code == 0, err
    assert _rows(part) == _rows(tmp_path / "full")


def test_plots_of_a_run_with_nan_curves_print_nothing(tmp_path, capfd):
    from dope_hope.training.metrics_log import MetricsLog
    from dope_hope.training.plots import plot_results

    log = MetricsLog(tmp_path, True)
    for step in (1, 2, 3, 4, 5):
        log.write("train", step=step, epoch=0, lr=1e-3, loss=float("nan"), images_per_s=10.0, time_s=step)
    log.write("val", step=5, epoch=0, time_s=5.0, val_loss=float("nan"), val_kp_acc=float("nan"),
              val_kp_acc_decoded=float("nan"))
    log.close()
    plot_results(tmp_path / "metrics.csv", tmp_path / "results.png")
    out, err = capfd.readouterr()
    assert (tmp_path / "results.png").stat().st_size > 0
    assert err == "" and out == ""
