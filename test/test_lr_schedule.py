"""The learning-rate phases of `vlocnetpp train` (`--lr`, `--lr-end`): the cosine curve and how a resume continues
it."""

from __future__ import annotations

import math

import pytest

from vlocnetpp_core.training.lr_schedule import LearningRatePhase


def test_a_constant_phase_keeps_its_rate():
    phase = LearningRatePhase(start=0, lr=1e-3, end=None, total=100)
    assert {phase.at(s) for s in (0, 50, 99, 150)} == {1e-3}


def test_the_cosine_starts_at_lr_falls_monotonically_and_reaches_the_end_at_total():
    phase = LearningRatePhase(start=200, lr=1e-3, end=1e-5, total=1200)
    rates = [phase.at(s) for s in range(200, 1201)]
    assert rates[0] == pytest.approx(1e-3) and rates[-1] == pytest.approx(1e-5)
    assert all(b < a for a, b in zip(rates[:-1], rates[1:], strict=True))
    assert phase.at(700) == pytest.approx(1e-5 + (1e-3 - 1e-5) * 0.5)  # half way: the mean of the two rates
    assert phase.at(450) == pytest.approx(1e-5 + (1e-3 - 1e-5) * 0.5 * (1 + math.cos(math.pi / 4)))
    assert phase.at(5000) == pytest.approx(
        1e-5
    )  # past the end (a run trained on with another --steps starts a new phase)


def test_a_resume_with_the_same_rates_and_end_continues_the_saved_curve():
    saved = LearningRatePhase(start=0, lr=1e-3, end=1e-5, total=1000).to_dict()
    resumed = LearningRatePhase(start=400, lr=1e-3, end=1e-5, total=1000).continues(saved)
    assert resumed.start == 0 and resumed.at(400) == LearningRatePhase(0, 1e-3, 1e-5, 1000).at(400)
    for other in (
        LearningRatePhase(400, 1e-4, 1e-5, 1000),
        LearningRatePhase(400, 1e-3, None, 1000),
        LearningRatePhase(400, 1e-3, 1e-5, 2000),
    ):
        assert other.continues(saved) == other  # another rate, end or length: a new phase from the resumed step
    assert LearningRatePhase(400, 1e-3, 1e-5, 1000).continues(None).start == 400  # a run saved before phases existed
