"""The run's logger: ``torchrl.record.loggers`` set up inside the run directory and always closed.

:class:`RunLogger` wraps the TorchRL logger the config names (wandb, offline by default;
csv; tensorboard; or none) with the few things a run logs: the resolved config, per-world
metrics per GPS iteration, evaluation numbers and figures.  It is a context manager, so a
job that fails still closes it: Hydra multirun with the basic launcher runs every job in
one process, and an open wandb run would swallow the next job's metrics.

Examples:
    >>> import tempfile
    >>> from modnet.config import LoggerConfig
    >>> with RunLogger.open(LoggerConfig(backend="csv"), tempfile.mkdtemp(), "tiny-demo") as log:
    ...     log.iteration(0, {"three_link/reach_red": {"distance": 0.4}})
    >>> RunLogger.open(LoggerConfig(backend="none"), ".", "x").logger is None
    True
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from modnet.config import ConfigError, LoggerConfig

__all__ = ["RunLogger"]


class RunLogger:
    """Logs a run to a TorchRL logger (or nowhere when ``logger`` is None)."""

    def __init__(self, logger, backend: str) -> None:
        self.logger = logger
        self.backend = backend

    @classmethod
    def open(
        cls, config: LoggerConfig, run_dir: str | os.PathLike, name: str, group: str | None = None
    ) -> RunLogger:
        """Start the logger ``config.backend`` writing under ``run_dir`` (wandb: ``run_dir/wandb``).

        ``name`` names the experiment; ``group`` gathers runs in wandb (e.g. a sweep's universe).

        Raises :class:`~modnet.config.ConfigError` when the backend cannot start here (e.g. the
        tensorboard package is not installed), before any training.
        """
        if config.backend == "none":
            return cls(None, "none")
        from torchrl.record.loggers import get_logger

        kwargs: dict[str, Any] = {}
        if config.backend == "wandb":
            kwargs["wandb_kwargs"] = {"mode": config.mode, "project": config.project, "group": group}
        try:
            logger = get_logger(config.backend, logger_name=str(run_dir), experiment_name=name, **kwargs)
        except ImportError as err:
            raise ConfigError(
                f"logger={config.backend} cannot start: {err} (pip install {config.backend}); "
                "or choose logger=csv, logger=wandb or logger=none"
            ) from err
        return cls(logger, config.backend)

    def __enter__(self) -> RunLogger:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self.logger is not None:
            self.logger.close()
            self.logger = None

    # --- what a run logs ---------------------------------------------------------------------------
    def config(self, flat: Mapping[str, Any]) -> None:
        """The resolved config, as ``{"gps.lr": 0.001, ...}``."""
        if self.logger is not None:
            self.logger.log_hparams({k: _plain(v) for k, v in flat.items()})

    def iteration(self, iteration: int, diagnostics: Mapping[str, Mapping[str, float]]) -> None:
        """One GPS iteration's per-world metrics as ``train/<robot>/<task>/<metric>``, and their means."""
        if self.logger is None:
            return
        metrics = {
            f"train/{world}/{name}": value
            for world, values in diagnostics.items()
            for name, value in values.items()
        }
        for name in ("distance", "sampled_cost"):
            values = [v[name] for v in diagnostics.values() if name in v]
            if values:
                metrics[f"train/mean/{name}"] = float(np.mean(values))
        self.logger.log_metrics(metrics, step=iteration)

    def scalars(self, metrics: Mapping[str, float], step: int = 0) -> None:
        if self.logger is not None and metrics:
            self.logger.log_metrics(dict(metrics), step=step)

    def figures(self, paths: Mapping[str, str | os.PathLike]) -> None:
        """Images (PNG/GIF files) under the given names; the csv logger keeps them as files only."""
        if self.logger is None or self.backend == "csv":
            return
        if self.backend == "wandb":
            import wandb

            self.logger.experiment.log({name: wandb.Image(str(path)) for name, path in paths.items()})
        elif self.backend == "tensorboard":
            import imageio.v3 as iio

            for name, path in paths.items():
                image = np.asarray(iio.imread(Path(path), index=0))[..., :3]
                self.logger.experiment.add_image(name, image, dataformats="HWC")


def _plain(value: Any) -> Any:
    """Config values loggers accept: lists become strings."""
    return str(value) if isinstance(value, (list, tuple)) else value
