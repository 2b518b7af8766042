"""The S-step loss: precision-weighted regression of the composed policies onto controller actions.

For every training world ``w`` and minibatch entry ``i``, with target action ``u*`` (the
controller's mean at the sampled state), its precision ``P`` and weight ``w_i``:

    loss_w = sum_i w_i (u*_i - mu(o_i))' P_i (u*_i - mu(o_i)) / (2 B)

and the loss is the sum over worlds.  All worlds go through the bank in one pass
(:meth:`~modnet.bank.ModuleBank.forward_worlds`), so each shared module runs once and
receives the gradients of every world that uses it.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> from modnet.bank import ModuleBank
    >>> bank = ModuleBank.build(["three_link"], ["reach"], dropout=0.0)
    >>> loss = PolicyRegressionLoss(bank)
    >>> batch = TensorDict({"three_link/reach": TensorDict({
    ...     ("robot", "state"): torch.zeros(4, 6), ("task", "state"): torch.zeros(4, 6),
    ...     "target_action": torch.ones(4, 3), "precision": torch.eye(3).expand(4, 3, 3),
    ...     "weight": torch.ones(4)}, batch_size=[4])})
    >>> out = loss(batch)
    >>> out["loss_regression"].shape, out["loss_regression"].requires_grad
    (torch.Size([]), True)
"""

from __future__ import annotations

from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import LossModule

from modnet.bank import ModuleBank


class PolicyRegressionLoss(LossModule):
    """Sum over worlds of the precision-weighted regression loss of their composed policies.

    The input TensorDict holds one sub-TensorDict per world, keyed ``"robot/task"``, with
    the policy's observation keys, ``"target_action" [B, dU]``, ``"precision" [B, dU, dU]``
    and ``"weight" [B]``.  The output holds ``"loss_regression"`` (summed over worlds) and,
    detached, each world's term under ``("world_loss", world)``.
    """

    def __init__(self, bank: ModuleBank) -> None:
        super().__init__()
        self.bank = bank

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        worlds = list(tensordict.keys())
        out = self.bank.forward_worlds({w: tensordict.get(w) for w in worlds})
        total = 0.0
        per_world = {}
        for name, result in zip(worlds, out.values(), strict=True):
            batch = tensordict.get(name)
            diff = batch.get("target_action") - result.get("loc")
            quad = (diff.unsqueeze(-2) @ batch.get("precision") @ diff.unsqueeze(-1)).squeeze((-1, -2))
            term = (batch.get("weight") * quad).sum() / (2 * diff.shape[0])
            total = total + term
            per_world[name] = term.detach()
        return TensorDict({"loss_regression": total, "world_loss": per_world}, batch_size=[])
