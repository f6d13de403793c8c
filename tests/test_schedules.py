"""Learning-rate schedules (kpd6d.schedules) against closed-form values."""

import math

import pytest
import torch

from kpd6d import schedules
from kpd6d.schedules import WarmupCosine, parse_max_time


def test_step_cosine_values():
    f = WarmupCosine(warmup_steps=10, min_factor=0.1, total_steps=100)
    assert f(0) == pytest.approx(0.1 * 1.0 * 1.0)  # warm-up 1/10 of the cosine's start (1.0)
    assert f(9) == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 0.09)))
    assert f(50) == pytest.approx(0.1 + 0.9 * 0.5)
    assert f(100) == pytest.approx(0.1) and f(500) == pytest.approx(0.1)


def test_time_cosine_follows_the_clock_and_resumes_without_the_gap(monkeypatch):
    now = [1000.0]
    monkeypatch.setattr(schedules.time, "monotonic", lambda: now[0])
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, WarmupCosine(0, 0.0, budget_s=100.0))
    assert opt.param_groups[0]["lr"] == pytest.approx(1.0)
    now[0] += 50.0
    sched.step()
    assert opt.param_groups[0]["lr"] == pytest.approx(0.5)  # half the budget: cos(pi/2)
    state = sched.state_dict()
    assert state["lr_lambdas"][0]["elapsed_s"] == pytest.approx(50.0)
    assert "_last" not in state["lr_lambdas"][0]
    # a resumed run, an hour later: the stopped time does not count
    now[0] += 3600.0
    opt2 = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    sched2 = torch.optim.lr_scheduler.LambdaLR(opt2, WarmupCosine(0, 0.0, budget_s=100.0))
    sched2.load_state_dict(state)
    sched2.step()  # first reading after resuming: starts the clock again
    now[0] += 25.0
    sched2.step()
    assert opt2.param_groups[0]["lr"] == pytest.approx(0.5 * (1 + math.cos(math.pi * 0.75)))


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="exactly one"):
        WarmupCosine(total_steps=10, budget_s=5.0)
    with pytest.raises(ValueError, match="budget_s"):
        WarmupCosine(budget_s=0)
    assert parse_max_time("00:01:02:03") == 3723.0
    assert parse_max_time({"minutes": 2}) == 120.0
    assert parse_max_time(None) is None
    with pytest.raises(ValueError, match="DD:HH:MM:SS"):
        parse_max_time("15 minutes")
