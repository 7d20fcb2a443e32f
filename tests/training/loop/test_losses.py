"""Training losses: values on known inputs."""

import math

import pytest
import torch

from neumip.training.loop.losses import comb2, log_space, log_weighted_mse, mse, relative_mse, training_loss
from neumip.training.loop.config import TrainConfig


def test_comb2_known_values():
    pred = torch.tensor([[math.e - 1, 0.0, 0.0]])
    target = torch.zeros(1, 3)
    # log1p(e - 1) = 1: one difference of 1 in three channels -> MSE 1/3, L1 1/3
    assert float(comb2(pred, target, 0.1)) == pytest.approx(1 / 3 + 0.1 / 3, rel=1e-6)
    assert float(comb2(pred, target, 0.0)) == pytest.approx(1 / 3, rel=1e-6)
    assert float(comb2(target, target)) == 0.0


def test_comb2_weighs_a_glint_like_a_few_times_brighter_value():
    """A 100x highlight error costs ~log(101)^2 under comb2, not 100^2 as under MSE."""
    target = torch.full((1, 3), 0.0)
    glint = torch.full((1, 3), 100.0)
    assert float(comb2(glint, target, 0.0)) == pytest.approx(math.log(101) ** 2, rel=1e-5)
    assert float(mse(glint, target)) == pytest.approx(1e4)


def test_log_space_floor_keeps_slightly_negative_outputs_finite():
    x = torch.tensor([[-5.0, -0.1, 0.0]])
    assert torch.equal(log_space(x)[0, 0], log_space(x)[0, 1])
    assert torch.isfinite(log_space(x)).all()


def test_training_loss_follows_the_config():
    pred, target = torch.tensor([[2.0, 0.0, 0.0]]), torch.zeros(1, 3)
    assert float(training_loss(pred, target, TrainConfig(loss="mse"))) == pytest.approx(4 / 3)
    assert float(training_loss(pred, target, TrainConfig(loss="comb2", l1_weight=0.0))) == pytest.approx(
        math.log(3) ** 2 / 3, rel=1e-6)


def _fitted_constant(loss, targets: torch.Tensor) -> float:
    """The constant prediction that `loss` settles on for these noisy targets (Adam from 1)."""
    value = torch.ones(1, 3, requires_grad=True)
    optimiser = torch.optim.Adam([value], lr=0.01)
    for _ in range(1500):
        optimiser.zero_grad()
        loss(value.expand_as(targets), targets).backward()
        optimiser.step()
    return float(value.mean())


def test_relative_mse_is_unbiased_under_noise_where_the_log_loss_is_not():
    """Noisy targets of mean 2 (an exponential spread, like few-sample highlights): the relative MSE's
    minimiser is their mean; comb2's is darker."""
    torch.manual_seed(0)
    targets = torch.distributions.Exponential(torch.tensor(0.5)).sample((4096, 3))
    mean = float(targets.mean())
    assert _fitted_constant(relative_mse, targets) == pytest.approx(mean, rel=0.02)
    assert _fitted_constant(lambda p, t: comb2(p, t, 0.1), targets) < 0.8 * mean


def test_relative_mse_weighs_errors_relative_to_the_prediction():
    pred, target = torch.tensor([[1.0, 10.0, 100.0]]), torch.tensor([[1.1, 11.0, 110.0]])
    per_channel = torch.tensor([0.01 / 1.01, 1.0 / 100.01, 100.0 / 10000.01])
    assert float(relative_mse(pred, target)) == pytest.approx(float(per_channel.mean()), rel=1e-5)
    assert float(training_loss(pred, target, TrainConfig(loss="relative"))) == float(relative_mse(pred, target))


def test_log_weighted_mse_is_unbiased_under_noise_where_the_log_loss_is_not():
    torch.manual_seed(0)
    targets = torch.distributions.Exponential(torch.tensor(0.5)).sample((4096, 3))
    assert _fitted_constant(log_weighted_mse, targets) == pytest.approx(float(targets.mean()), rel=0.02)


def test_log_weighted_mse_weighs_errors_as_the_log_loss_does_near_the_answer():
    """Small errors cost what comb2's squared log difference costs; the gradient never reaches the weight."""
    pred = torch.tensor([[0.0, 1.0, 100.0]], requires_grad=True)
    target = pred.detach() * 1.001 + 1e-4
    assert float(log_weighted_mse(pred, target)) == pytest.approx(float(comb2(pred, target, 0.0)), rel=1e-2)
    log_weighted_mse(pred, target).backward()
    expected = 2 * (pred.detach() - target) / (1 + pred.detach()) ** 2 / 3
    assert torch.allclose(pred.grad, expected, rtol=1e-5)
    assert float(training_loss(pred, target, TrainConfig(loss="log_weighted"))) == float(log_weighted_mse(pred, target))


def test_the_finish_loss_trains_the_last_steps():
    config = TrainConfig(steps=100, finish_loss="relative", finish_fraction=0.3)
    assert [config.loss_at(s) for s in (0, 69, 70, 99)] == ["comb2", "comb2", "relative", "relative"]
    assert TrainConfig(steps=100).loss_at(99) == "comb2"
    for bad in ({"finish_loss": "relative"}, {"finish_fraction": 0.1}, {"finish_loss": "l3", "finish_fraction": 0.1},
                {"finish_loss": "mse", "finish_fraction": 1.5}):
        with pytest.raises(ValueError, match="finish"):
            TrainConfig(steps=100, **bad)


def test_a_coarse_loss_applies_to_the_coarse_queries_only():
    """`TrainConfig.coarse_loss`: each query's term is its own loss's, the coarse ones (`coarse`) under the coarse
    loss; the mean of the mixed terms is the two losses' means weighted by their queries."""
    from neumip.training.loop.config import TrainConfig
    from neumip.training.loop.losses import comb2, log_weighted_mse, training_loss

    torch.manual_seed(3)
    pred, target = torch.rand(64, 3) * 2, torch.rand(64, 3) * 2
    coarse = torch.arange(64) >= 40
    config = TrainConfig(coarse_loss="log_weighted")
    want = (comb2(pred[~coarse], target[~coarse]) * 40 + log_weighted_mse(pred[coarse], target[coarse]) * 24) / 64
    torch.testing.assert_close(training_loss(pred, target, config, coarse=coarse), want)
    torch.testing.assert_close(training_loss(pred, target, TrainConfig(), coarse=coarse), comb2(pred, target))
    with pytest.raises(ValueError, match="coarse_loss"):
        TrainConfig(coarse_loss="huber")
