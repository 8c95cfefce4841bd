"""The trainer's parts on their own (no network, no data): the time budget fed step timings,
the run progress a checkpoint records, the stop requests, the thresholds' gate, and the
typed recipe a run trains with (checked once, read as attributes)."""
from __future__ import annotations

import pickle

import pytest

from dope_hope.config import load_config
from dope_hope.errors import ConfigError
from dope_hope.synth.settings import SynthSettings, load_synth_config
from dope_hope.training.calibration import RunThresholds
from dope_hope.training.resume import RunProgress
from dope_hope.training.settings import TrainConfig, TrainJob, run_recipe, with_train_values
from dope_hope.training.stopping import StopControl
from dope_hope.training.time_budget import BudgetShape, TimeBudget, after_run_validations


class Clock:
    """An injected clock: the test moves it."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _shape(**changes) -> BudgetShape:
    values = dict(limit_s=100.0, sets_horizon=True, nominal_steps=10_000, steps_per_epoch=50, val_every=1,
                  val_batches=2, val_area_ratio=3.0, first_window_steps=1, horizon_estimate_after=10,
                  after_run_validations=None)
    values.update(changes)
    return BudgetShape(**values)


def _steps(budget: TimeBudget, clock: Clock, first: int, last: int, seconds: float) -> list[int | None]:
    ends = []
    for step in range(first, last + 1):
        clock.now += seconds
        budget.stepped()
        ends.append(budget.decide_end(step, validated=False))
    return ends


def test_the_budget_plans_its_end_from_the_step_timings_it_is_fed():
    """1 s per step, 100 s: the first plan comes once the window holds horizon_estimate_after
    steps and ends the run where its steps and validations (2 batches x 3 steps each) fit."""
    clock = Clock()
    budget = TimeBudget(_shape(), clock, started=0.0)
    budget.begin_steps()
    ends = _steps(budget, clock, 1, 11, 1.0)
    assert ends[:10] == [None] * 10 and ends[10] is not None
    first = budget.plan.last
    assert first["why"] == "first" and first["per_step_s"] == 1.0 and budget.planned_steps == ends[10]
    assert budget.plan.run_cost(11, ends[10], 1.0, 6.0, 50) <= 100.0 - budget.used()
    assert budget.state()["plans"] == budget.plan.plans and budget.state()["time_used_s"] == 11.0


def test_a_budget_spent_before_its_first_plan_ends_the_run_at_once():
    clock = Clock()
    budget = TimeBudget(_shape(limit_s=5.0), clock, started=0.0)
    budget.begin_steps()
    assert _steps(budget, clock, 1, 5, 1.0) == [None] * 4 + [5]  # 5 s used of 5: the run ends at step 5
    assert budget.plan.last["why"] == "budget spent before a plan" and budget.planned_steps == 5


def test_an_end_planned_on_an_estimated_validation_moves_once_the_validation_is_measured():
    """Slow first steps (a loader decoding every frame once: 10 s each) make the estimated
    validation (2 batches x 3 steps x 10 s, and the thresholds' choice after it) fill the whole
    budget: the first plan ends the run at once. The final validation then takes 2 s; planned
    again from that measurement, at the steps' later speed, the run goes on."""
    clock = Clock()
    budget = TimeBudget(_shape(limit_s=200.0, after_run_validations=1.9, horizon_estimate_after=2), clock,
                        started=0.0)
    budget.begin_steps()
    ends = _steps(budget, clock, 1, 15, 10.0)
    assert ends[-1] == 15 and budget.end_rests_on_estimate
    clock.now += 2.0
    budget.validated(2.0)
    end = budget.decide_end(15, validated=True)
    assert end is not None and end > 15 and not budget.end_rests_on_estimate
    assert budget.plan.last["why"] == "validation" and budget.plan.last["val_measured"]


def test_the_thresholds_choice_is_counted_in_validations():
    assert after_run_validations(False, 3) is None
    assert after_run_validations(True, 1) == pytest.approx(1.9) and after_run_validations(True, 6) > 3.5


def test_a_budget_keeps_the_time_of_earlier_processes():
    clock = Clock()
    budget = TimeBudget(_shape(limit_s=None), clock, started=2.0)
    budget.restore({"time_used_s": 30.0, "other_s": 4.0, "last_val_s": 1.5, "val_steps": [3.0]})
    clock.now = 7.0
    budget.begin_steps()
    budget.validated(0.5)
    assert budget.plan is None and budget.planned_steps is None
    assert (budget.elapsed(), budget.used(), budget.other_time()) == (5.0, 35.0, 9.5)


def test_run_progress_round_trips_through_a_checkpoint_extra():
    progress = RunProgress(batch_in_epoch=3, best_acc=0.25, val_done_epoch=2, last_val={"val_loss": 0.5, "x": "y"},
                           loss_window=[1.5, 2])
    extra = progress.extra(metrics_rows=7)
    back = RunProgress.from_extra(extra, epoch=1, steps_per_epoch=5)
    assert back == RunProgress(3, 0.25, 2, {"val_loss": 0.5}, [1.5, 2], 7)
    # stopped mid-epoch after that epoch's validation: it validates again at the epoch's end
    assert RunProgress.from_extra(extra, epoch=2, steps_per_epoch=5).val_done_epoch == -1


def test_the_first_stop_reason_stays():
    stop = StopControl(distributed=False, device="cpu")
    assert not stop.agree()
    stop.request("terminated")
    stop.request("interrupted")
    assert stop.agree() and stop.reason == "terminated"


def test_the_thresholds_are_chosen_only_with_validation_frames(tmp_path):
    job = TrainJob([tmp_path], "Ketchup", tmp_path)
    assert RunThresholds(True, 1, job, tmp_path, "cpu").calibrates(10)
    assert not RunThresholds(True, 1, job, tmp_path, "cpu").calibrates(0)
    assert not RunThresholds(True, 0, job, tmp_path, "cpu").calibrates(10)
    assert not RunThresholds(False, 1, job, tmp_path, "cpu").calibrates(10)


def test_a_run_recipe_is_checked_once_and_read_as_attributes():
    recipe = run_recipe(load_config("lite"), {"train": {"lr": 0.01}})
    assert isinstance(recipe, TrainConfig) and recipe.train.lr == 0.01 and recipe.model.arch == "lite"
    assert run_recipe(recipe) is recipe  # settings already checked pass through
    resumed = run_recipe({}, {"train": {"steps": 5}}, recorded=recipe.to_dict())
    assert resumed.train.steps == 5 and resumed.train.lr == 0.01  # the recorded recipe, not the given one
    with pytest.raises(ConfigError, match="train.lrr"):
        run_recipe(load_config("lite"), {"train": {"lrr": 1}})
    assert with_train_values(recipe, epochs=3).train.epochs == 3
    with pytest.raises(ConfigError, match="train.epochs"):
        with_train_values(recipe, epochs=0)


def test_synth_settings_are_attributes_and_pickle_to_the_workers():
    cfg = load_synth_config("demo", ["target.count=[0,2]"])
    assert isinstance(cfg, SynthSettings) and cfg.target.count == [0, 2]
    assert load_synth_config(cfg) is cfg
    assert pickle.loads(pickle.dumps(cfg)) == cfg
    assert type(cfg.background.clutter).__name__ == "SynthBackgroundClutterSettings"
