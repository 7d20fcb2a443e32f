"""Training losses for high-dynamic-range MBTF values. Pure torch.

`comb2` (author code) compares log1p(max(x, -0.1)) of prediction and target: a specular highlight
100x brighter than its surroundings then weighs like a few-times-brighter one, instead of taking
over the whole batch as it does under plain MSE. But a log loss is biased under noisy targets: the
minimiser of E[(log p - log t)^2] is the geometric mean of t, darker than its mean where the 16-spp
targets are noisy (highlights, shadows' edges).

`relative_mse` (Lehtinen et al., Noise2Noise) divides the squared error by the prediction squared,
detached from the gradient, plus `RELATIVE_FLOOR`: a highlight weighs as much as its surround, yet the
minimiser of each term is the target's mean, so noise does not bias it.
"""

from __future__ import annotations

import torch

from neumip.training.loop.config import TrainConfig

LOG_FLOOR = -0.1
"""Values are clamped to at least this before log1p (keeps log1p finite for slightly negative outputs)."""


def log_space(x: torch.Tensor) -> torch.Tensor:
    """(N, 3) linear RGB -> (N, 3) log1p(max(x, -0.1))."""
    return torch.log1p(torch.clamp(x, min=LOG_FLOOR))


def comb2(pred: torch.Tensor, target: torch.Tensor, l1_weight: float = 0.1) -> torch.Tensor:
    """(N, 3), (N, 3) -> scalar: MSE + l1_weight * L1, both of the log-space difference."""
    return _terms("comb2", pred, target, l1_weight).mean()


RELATIVE_FLOOR = 0.01
"""Added to the detached prediction squared in `relative_mse`'s denominator (dark values do not blow up)."""


def relative_mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(N, 3), (N, 3) -> scalar mean of (pred - target)^2 / (pred^2 + RELATIVE_FLOOR), the denominator detached."""
    return _terms("relative", pred, target).mean()


def log_weighted_mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(N, 3), (N, 3) -> scalar mean of ((pred - target) / (1 + pred))^2, the denominator detached.

    The log loss's weights without its bias: near the answer, (log1p(p) - log1p(t))^2 is
    ((p - t) / (1 + p))^2, so a highlight weighs as it does under `comb2`, but with the denominator
    detached each term's minimiser is the target's mean."""
    return _terms("log_weighted", pred, target).mean()


def mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(N, 3), (N, 3) -> scalar mean squared error in linear RGB."""
    return _terms("mse", pred, target).mean()


def training_loss(pred: torch.Tensor, target: torch.Tensor, config: TrainConfig, name: str | None = None,
                  coarse: torch.Tensor | None = None) -> torch.Tensor:
    """The loss `name` names (default `config.loss`), (N, 3), (N, 3) -> scalar; with `config.coarse_loss` and
    `coarse` (N,) bool (the queries at `config.coarse_level` or coarser), that loss for those queries: the mean of
    each query's term under its own loss."""
    name = config.loss if name is None else name
    if coarse is None or not config.coarse_loss:
        return _terms(name, pred, target, config.l1_weight).mean()
    fine = _terms(name, pred, target, config.l1_weight)
    rough = _terms(config.coarse_loss, pred, target, config.l1_weight)
    return torch.where(coarse[:, None], rough, fine).mean()


def _terms(name: str, pred: torch.Tensor, target: torch.Tensor, l1_weight: float = 0.1) -> torch.Tensor:
    """(N, 3) each value's term of loss `name` (comb2's L1 weighed by `l1_weight`), whose mean is the loss (`comb2`,
    `relative_mse`, ...)."""
    if name == "comb2":
        diff = log_space(pred) - log_space(target)
        return diff * diff + l1_weight * diff.abs()
    if name == "relative":
        diff = pred - target
        return diff * diff / (pred.detach() ** 2 + RELATIVE_FLOOR)
    if name == "log_weighted":
        diff = (pred - target) / (1.0 + pred.detach().clamp(min=0.0))
        return diff * diff
    diff = pred - target
    return diff * diff
