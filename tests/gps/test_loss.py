import torch
from tensordict import TensorDict

from modnet.bank import ModuleBank
from modnet.gps.loss import PolicyRegressionLoss
from modnet.gps.sampling import STATE_KEYS

WORLD = "three_link/reach"


def batch_for(bank: ModuleBank, size: int = 64, seed: int = 0) -> TensorDict:
    generator = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            ("robot", "state"): torch.randn(size, 6, generator=generator),
            ("task", "state"): torch.randn(size, 6, generator=generator),
            "target_action": torch.randn(size, 3, generator=generator),
            "precision": torch.diag(torch.tensor([1.0, 2.0, 4.0])).expand(size, 3, 3),
            "weight": torch.rand(size, generator=generator) + 0.5,
        },
        batch_size=[size],
    )


def network_and_jacobian(bank: ModuleBank, batch: TensorDict) -> tuple[torch.Tensor, torch.Tensor]:
    """The composed policy's mean and its Jacobian in ``x = [robot_state, task_state]``, one
    sample at a time by ``torch.autograd.functional.jacobian`` (not the loss's own pass)."""
    sizes = [batch.get(key).shape[-1] for key in STATE_KEYS]

    def mean(x: torch.Tensor) -> torch.Tensor:
        parts = dict(zip(STATE_KEYS, x.unsqueeze(0).split(sizes, dim=-1), strict=True))
        out = bank.forward_worlds({WORLD: TensorDict(parts, batch_size=[1])})
        return out[("three_link", "reach")]["loc"][0]

    x = torch.cat([batch.get(key) for key in STATE_KEYS], -1)
    with torch.no_grad():
        loc = torch.stack([mean(row) for row in x])
    jacobian = torch.stack([torch.autograd.functional.jacobian(mean, row) for row in x])
    return loc, jacobian


def test_the_regression_term_is_the_precision_weighted_squared_error():
    bank = ModuleBank.build(["three_link"], ["reach"], dropout=0.0, seed=0)
    batch = batch_for(bank)
    out = PolicyRegressionLoss(bank)(TensorDict({WORLD: batch}, batch_size=[]))
    loc, _ = network_and_jacobian(bank, batch)
    diff = batch["target_action"] - loc
    expected = (batch["weight"] * (diff.pow(2) * torch.tensor([1.0, 2.0, 4.0])).sum(-1)).sum() / (2 * 64)
    assert torch.allclose(out["loss_regression"], expected, rtol=1e-4)
    assert "feedback_loss" not in out.keys(True) or WORLD not in out["feedback_loss"].keys()


def test_the_feedback_term_vanishes_at_the_networks_own_jacobian_and_pulls_it_to_the_gains():
    """The feedback term compares the network's Jacobian, in units of the state's scale, with
    the targets: nil at its own Jacobian (computed here by autograd one sample at a time), and
    a step down the loss's gradient, its actions' targets where the network acts, brings the
    Jacobian nearer other gains (the trainer's test shows many steps do so on a real world)."""
    bank = ModuleBank.build(["three_link"], ["reach"], dropout=0.0, seed=0)
    batch = batch_for(bank)
    scale = torch.linspace(0.5, 2.0, 12).expand(64, 12)
    loc, jacobian = network_and_jacobian(bank, batch)
    batch["target_action"] = loc
    batch["state_scale"] = scale
    batch["feedback_target"] = jacobian * scale.unsqueeze(-2)
    loss = PolicyRegressionLoss(bank, feedback_weight=100.0)
    own = loss(TensorDict({WORLD: batch}, batch_size=[]))["feedback_loss"][WORLD]
    assert float(own) < 1e-8

    batch["feedback_target"] = 3 * jacobian * scale.unsqueeze(-2)  # three times as stiff

    def feedback() -> torch.Tensor:
        return loss(TensorDict({WORLD: batch}, batch_size=[]))["feedback_loss"][WORLD]

    before = float(feedback())
    params = [p for p in bank.parameters() if p.requires_grad]
    total = loss(TensorDict({WORLD: batch}, batch_size=[]))["loss_regression"]
    grads = torch.autograd.grad(total, params, allow_unused=True)  # the action scale has none
    with torch.no_grad():
        for param, grad in zip(params, grads, strict=True):
            if grad is not None:
                param.sub_(1e-2 * grad)
    assert before > 0 and float(feedback()) < 0.99 * before  # its gradient leads downhill
