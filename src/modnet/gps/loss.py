"""The S-step loss: precision-weighted regression of the composed policies onto controller actions.

For every training world ``w`` and minibatch entry ``i``, with target action ``u*`` (the
controller's mean at the sampled state), its precision ``P`` and weight ``w_i``:

    loss_w = sum_i w_i (u*_i - mu(o_i))' P_i (u*_i - mu(o_i)) / (2 B)

and the loss is the sum over worlds.  With ``feedback_weight`` and a world's feedback targets
(``"feedback_target" [B, dU, dX]``, the controllers' gains ``K`` times ``"state_scale" [B,
dX]``), it adds how far the network's response to the state is from the controllers':

    feedback_w = weight * sum_i w_i tr(G_i' P_i G_i) / (2 B dX),  G_i = J(o_i) S_i - K_i S_i

with ``J`` the Jacobian of ``mu`` in the state ``x = [robot_state, task_state]`` and ``S_i``
the state's scale: the actions' change for a change of one scale in each state entry.
All worlds go through the bank in one pass
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

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import LossModule

from modnet.bank import ModuleBank
from modnet.gps.sampling import STATE_KEYS


def state_jacobian(loc: torch.Tensor, x: list[torch.Tensor], create_graph: bool = False) -> torch.Tensor:
    """``d loc / d x [..., dU, dX]`` of actions ``loc [..., dU]`` in the state leaves ``x`` (the
    parts of ``x = [robot_state, task_state]``, each of which ``loc`` was computed from), one
    backward pass per action dimension; ``create_graph`` to differentiate it in turn.

    Examples:
        >>> robot = torch.tensor([[1.0, 2.0]], requires_grad=True)
        >>> task = torch.tensor([[3.0]], requires_grad=True)
        >>> loc = torch.stack([robot[:, 0] * task[:, 0], robot[:, 1] ** 2], -1)  # [1, 2]
        >>> state_jacobian(loc, [robot, task])[0].tolist()
        [[3.0, 0.0, 1.0], [0.0, 4.0, 0.0]]
    """
    rows = [
        torch.cat(torch.autograd.grad(loc[..., j].sum(), x, retain_graph=True, create_graph=create_graph), -1)
        for j in range(loc.shape[-1])
    ]
    return torch.stack(rows, dim=-2)


class PolicyRegressionLoss(LossModule):
    """Sum over worlds of the precision-weighted regression loss of their composed policies.

    The input TensorDict holds one sub-TensorDict per world, keyed ``"robot/task"``, with
    the policy's observation keys, ``"target_action" [B, dU]``, ``"precision" [B, dU, dU]``
    and ``"weight" [B]``.  The output holds ``"loss_regression"`` (summed over worlds) and,
    detached, each world's term under ``("world_loss", world)``; with ``feedback_weight``, the
    feedback term of the worlds that carry feedback targets under ``("feedback_loss", world)``
    (also in ``"loss_regression"`` and ``"world_loss"``).

    Args:
        bank: the module bank whose composed policies regress.
        feedback_weight: the weight of the feedback term (0: the regression alone, the GPS
            code's). Only state policies have a Jacobian in the state.
    """

    def __init__(self, bank: ModuleBank, feedback_weight: float = 0.0) -> None:
        super().__init__()
        self.bank = bank
        self.feedback_weight = feedback_weight

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        worlds = list(tensordict.keys())
        inputs = {w: self._with_state_leaves(tensordict.get(w)) for w in worlds}
        with torch.enable_grad():
            out = self.bank.forward_worlds(inputs)
        total = 0.0
        per_world, feedback = {}, {}
        for name, result in zip(worlds, out.values(), strict=True):
            batch = inputs[name]
            diff = batch.get("target_action") - result.get("loc")
            precision = batch.get("precision")
            quad = (diff.unsqueeze(-2) @ precision @ diff.unsqueeze(-1)).squeeze((-1, -2))
            term = (batch.get("weight") * quad).sum() / (2 * diff.shape[0])
            if self._fits_feedback(batch):
                feedback[name] = self._feedback_term(batch, result.get("loc"))
                term = term + feedback[name]
                feedback[name] = feedback[name].detach()
            total = total + term
            per_world[name] = term.detach()
        return TensorDict(
            {"loss_regression": total, "world_loss": per_world, "feedback_loss": feedback}, batch_size=[]
        )

    def _fits_feedback(self, batch: TensorDictBase) -> bool:
        return bool(self.feedback_weight) and "feedback_target" in batch.keys()

    def _with_state_leaves(self, batch: TensorDictBase) -> TensorDictBase:
        """``batch``, with state leaves that autograd can differentiate by where it fits feedback."""
        if not self._fits_feedback(batch):
            return batch
        batch = batch.clone(recurse=False)
        for key in STATE_KEYS:
            batch.set(key, batch.get(key).detach().requires_grad_(True))
        return batch

    def _feedback_term(self, batch: TensorDictBase, loc: torch.Tensor) -> torch.Tensor:
        jacobian = state_jacobian(loc, [batch.get(key) for key in STATE_KEYS], create_graph=True)
        gap = jacobian * batch.get("state_scale").unsqueeze(-2) - batch.get("feedback_target")
        quad = (gap * (batch.get("precision") @ gap)).sum((-2, -1)) / gap.shape[-1]  # tr(G' P G) / dX
        return self.feedback_weight * (batch.get("weight") * quad).sum() / (2 * gap.shape[0])
