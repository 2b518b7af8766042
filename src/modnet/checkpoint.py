"""Checkpoints of a training run: the GPS trainer's whole state after a complete iteration.

One file, ``checkpoint.pt`` in the run directory, rewritten after every iteration through a
temporary file and ``os.replace`` (a killed run leaves the previous complete checkpoint,
never half of one).  It holds plain tensors, numbers, strings, lists and dicts only and is
read with ``torch.load(..., weights_only=True)``: loading never runs code from the file.
Next to the trainer's state it keeps the run's *identity* (universe, worlds, algorithm,
architecture...): resuming under a different one is refused, naming what differs.

Examples:
    >>> import tempfile, torch
    >>> from pathlib import Path
    >>> path = Path(tempfile.mkdtemp()) / "checkpoint.pt"
    >>> save_checkpoint(path, {"iteration": 1, "w": torch.ones(2)}, {"universe": "tiny"})
    >>> load_checkpoint(path, {"universe": "tiny"}).iteration
    1
    >>> load_checkpoint(path, {"universe": "color_reach"})
    Traceback (most recent call last):
    ...
    modnet.checkpoint.CheckpointError: ... universe: 'tiny' in the checkpoint, 'color_reach' in this run
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from modnet.files import write_atomically

__all__ = ["CHECKPOINT", "Checkpoint", "CheckpointError", "load_checkpoint", "save_checkpoint"]

CHECKPOINT = "checkpoint.pt"
FORMAT = "modnet.checkpoint/1"


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be resumed: missing, corrupt, or written by a different run."""


@dataclass
class Checkpoint:
    """What :func:`load_checkpoint` returns: the trainer's state and the run identity it was saved with."""

    trainer: dict[str, Any]  # GPSTrainer.state_dict()
    identity: dict[str, Any]

    @property
    def iteration(self) -> int:
        """Complete GPS iterations in the checkpoint."""
        return int(self.trainer["iteration"])


def save_checkpoint(path: str | os.PathLike, trainer_state: dict[str, Any], identity: dict[str, Any]) -> None:
    """Write ``trainer_state`` (``GPSTrainer.state_dict()``) and the JSON-able ``identity`` atomically."""
    payload = {"format": FORMAT, "identity": json.dumps(identity, sort_keys=True), "trainer": trainer_state}
    write_atomically(Path(path), lambda tmp: torch.save(payload, tmp))


def _reason(err: Exception) -> str:
    """The informative part of ``torch.load``'s error (it wraps it in long advice to load unsafely)."""
    text = str(err)
    if "WeightsUnpickler error:" in text:
        detail = text.split("WeightsUnpickler error:", 1)[1].strip().split(". ")[0].split("\n")[0]
        return f"not plain tensors and numbers ({detail})"
    return text.split(". ")[0]


def load_checkpoint(path: str | os.PathLike, identity: dict[str, Any] | None = None) -> Checkpoint:
    """Read a checkpoint (``weights_only``); with ``identity``, refuse one saved by a different run.

    Raises :class:`CheckpointError` with one message for a missing, unreadable or foreign file.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint to resume at {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # truncated, not a torch file, or objects that would need code to load
        raise CheckpointError(
            f"corrupt checkpoint {path}: {_reason(err)}; delete it to start the run over"
        ) from err
    if not isinstance(payload, dict) or payload.get("format") != FORMAT or "trainer" not in payload:
        raise CheckpointError(
            f"corrupt checkpoint {path}: not a {FORMAT} file; delete it to start the run over"
        )
    try:
        saved = json.loads(payload["identity"])
        int(payload["trainer"]["iteration"])
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(f"corrupt checkpoint {path}: {err}; delete it to start the run over") from err
    if identity is not None:
        current = json.loads(json.dumps(identity, sort_keys=True))  # compare as JSON sees them
        differences = [
            f"{key}: {saved.get(key, 'absent')!r} in the checkpoint, "
            f"{current.get(key, 'absent')!r} in this run"
            for key in sorted(set(saved) | set(current))
            if saved.get(key) != current.get(key)
        ]
        if differences:
            raise CheckpointError(f"checkpoint {path} belongs to a different run; " + "; ".join(differences))
    return Checkpoint(payload["trainer"], saved)
