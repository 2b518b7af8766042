"""The building blocks of a module bank: one architecture record, one network, one TorchRL module.

A modular policy for robot ``r`` doing task ``k`` is ``f_r(g_k(o_task), o_robot)`` (Devin et
al., ICRA 2017).  Every module of a bank, whatever degree of variation ("factor") it belongs
to, has the same shape: it reads the interfaces written by modules upstream of it plus its own
observations, runs a small network (ReLU by default, :data:`ACTIVATIONS`), and writes either
a new interface (task and object modules) or the mean and scale of a Gaussian over actions
(robot modules, and the monolithic per-world baseline).

* :class:`ModuleArch` is the frozen record of one module's architecture: what
  ``manifest.json`` stores and all that is needed to rebuild it.
* :class:`Normalizer`, :class:`SpatialSoftmax`, :class:`PixelEncoder`,
  :class:`InterfaceHead` and :class:`GaussianHead` are the small ``nn.Module`` parts.
* :class:`ModuleNet` puts them together; :class:`BankModule` wraps it as a
  :class:`~tensordict.nn.TensorDictModule` with the keys the architecture names.

Keys: a module of factor ``f`` writes its interface at ``("interface", f)``
(:func:`interface_key`); a robot module writes ``"loc"`` and ``"scale"``.

Examples:
    >>> import torch
    >>> from tensordict import TensorDict
    >>> arch = ModuleArch(
    ...     factor="task", head="interface", out_dim=12, observations=((("task", "state"), 6),)
    ... )
    >>> task = BankModule(arch)
    >>> task.in_keys, task.out_keys
    ([('task', 'state')], [('interface', 'task')])
    >>> td = task(TensorDict({("task", "state"): torch.randn(5, 6)}, batch_size=[5]))
    >>> td["interface", "task"].shape
    torch.Size([5, 12])
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from typing import Any, Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey, unravel_key
from torch import nn

from modnet.specs import PIXELS_SHAPE

__all__ = [
    "BankModule",
    "GaussianHead",
    "InterfaceHead",
    "ModuleArch",
    "ModuleNet",
    "Normalizer",
    "PixelEncoder",
    "SpatialSoftmax",
    "interface_key",
    "key_from_str",
    "key_to_str",
]

MIN_STD = 1e-3  # floor of the normalisation scale (GPS: zero-variance state dimensions)
HEADS = ("interface", "gaussian")
#: The nonlinearity of a module's fully connected layers (its hidden layers and its interface
#: bottleneck; convolutions stay ReLU). ReLU is the paper's (Levine et al.'s network); the
#: others are smooth, so the network's Jacobian in its inputs changes with the weights and
#: biases everywhere, not only where a unit switches on or off.
ACTIVATIONS: dict[str, type[nn.Module]] = {
    "relu": nn.ReLU,
    "tanh": nn.Tanh,
    "elu": nn.ELU,
    "softplus": nn.Softplus,
    "silu": nn.SiLU,
}
Activation = Literal["relu", "tanh", "elu", "softplus", "silu"]


def interface_key(factor: str) -> tuple[str, str]:
    """The key the modules of ``factor`` write their interface to.

    Examples:
        >>> interface_key("task")
        ('interface', 'task')
    """
    return ("interface", factor)


def key_to_str(key: NestedKey) -> str:
    """``("task", "state")`` -> ``"task/state"`` (how ``manifest.json`` spells keys).

    Examples:
        >>> key_to_str(("task", "state")), key_to_str("loc")
        ('task/state', 'loc')
    """
    key = unravel_key(key)
    return "/".join(key) if isinstance(key, tuple) else key


def key_from_str(text: str) -> NestedKey:
    """The inverse of :func:`key_to_str`.

    Examples:
        >>> key_from_str("task/state"), key_from_str("loc")
        (('task', 'state'), 'loc')
    """
    if not isinstance(text, str) or not text or "" in text.split("/"):
        raise ValueError(f"not a key: {text!r}")
    return unravel_key(tuple(text.split("/")))


def check_positive_ints(name: str, values: Sequence[int], allow_empty: bool = True) -> tuple[int, ...]:
    """``values`` as a tuple if every one is a positive ``int``, else ``ValueError`` naming ``name``."""
    values = tuple(values)
    if not allow_empty and not values:
        raise ValueError(f"{name} must not be empty")
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in values):
        raise ValueError(f"{name} must hold positive integers, got {values!r}")
    return values


def check_dropout(name: str, p: float) -> float:
    """Return ``p`` as a float if it is a valid dropout probability, else ``ValueError``."""
    if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0.0 <= p < 1.0:
        raise ValueError(f"{name} must be a probability in [0, 1), got {p!r}")
    return float(p)


@dataclass(frozen=True)
class ModuleArch:
    """The architecture of one bank module: its inputs, its network and what it writes.

    Inputs, in this order: the interfaces of the upstream factors in ``reads`` (raw), the
    observation vectors in ``observations`` (z-scored by the module's own
    :class:`Normalizer`), and optionally the uint8 image at ``pixels`` (through a
    :class:`PixelEncoder`).  They are concatenated and fed to ``hidden`` fully connected
    layers with the nonlinearity ``activation`` (one of :data:`ACTIVATIONS`; ReLU by default)
    and dropout ``dropout``; then the head: ``"interface"`` (a bottleneck of ``out_dim``
    units with dropout ``interface_dropout``, written at ``("interface", factor)``) or
    ``"gaussian"`` (a linear action mean ``"loc"`` of ``out_dim`` and a learned
    state-independent ``"scale"`` starting at ``exp(init_log_std)``).

    Examples:
        >>> robot = ModuleArch(
        ...     factor="robot", head="gaussian", out_dim=4,
        ...     observations=((("robot", "state"), 8),), reads=(("task", 12),),
        ... )
        >>> robot.inputs
        {('interface', 'task'): 12, ('robot', 'state'): 8}
        >>> robot.outputs
        {'loc': 4, 'scale': 4}
        >>> ModuleArch.from_json(robot.to_json()) == robot
        True
    """

    factor: str
    head: Literal["interface", "gaussian"]
    out_dim: int
    observations: tuple[tuple[NestedKey, int], ...] = ()
    reads: tuple[tuple[str, int], ...] = ()
    pixels: NestedKey | None = None
    image_shape: tuple[int, int, int] = PIXELS_SHAPE
    hidden: tuple[int, ...] = (80, 80)
    conv_channels: tuple[int, ...] = (10, 20)
    kernel_size: int = 3
    conv_strides: tuple[int, ...] = ()  # one per convolution; () is stride 1 throughout
    softmax_temperature: float = 1.0  # of the spatial softmax; lower is sharper
    dropout: float = 0.0
    interface_dropout: float = 0.0
    init_log_std: float = 0.0
    activation: Activation = "relu"

    def __post_init__(self) -> None:
        set_ = lambda name, value: object.__setattr__(self, name, value)
        if not isinstance(self.factor, str) or not self.factor:
            raise ValueError(f"factor must be a non-empty string, got {self.factor!r}")
        if self.head not in HEADS:
            raise ValueError(f"head must be one of {', '.join(HEADS)}, got {self.head!r}")
        check_positive_ints("out_dim", (self.out_dim,))
        set_("observations", tuple((unravel_key(k), d) for k, d in self.observations))
        check_positive_ints("observation sizes", [d for _, d in self.observations])
        set_("reads", tuple((str(f), w) for f, w in self.reads))
        check_positive_ints("interface widths", [w for _, w in self.reads])
        if self.pixels is not None:
            set_("pixels", unravel_key(self.pixels))
            check_positive_ints("conv_channels", self.conv_channels, allow_empty=False)
        set_("image_shape", check_positive_ints("image_shape", self.image_shape))
        if len(self.image_shape) != 3:
            raise ValueError(f"image_shape is (height, width, channels), got {self.image_shape}")
        set_("hidden", check_positive_ints("hidden", self.hidden))
        set_("conv_channels", check_positive_ints("conv_channels", self.conv_channels))
        set_("conv_strides", check_positive_ints("conv_strides", self.conv_strides))
        if self.conv_strides and len(self.conv_strides) != len(self.conv_channels):
            raise ValueError(
                f"conv_strides needs one stride per convolution ({len(self.conv_channels)}), "
                f"got {self.conv_strides}"
            )
        if not isinstance(self.kernel_size, int) or self.kernel_size < 1 or self.kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be a positive odd integer, got {self.kernel_size!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {', '.join(ACTIVATIONS)}, got {self.activation!r}")
        set_("dropout", check_dropout("dropout", self.dropout))
        set_("interface_dropout", check_dropout("interface_dropout", self.interface_dropout))
        temperature = self.softmax_temperature
        if isinstance(temperature, bool) or not isinstance(temperature, (int, float)):
            raise ValueError(f"softmax_temperature must be a number, got {temperature!r}")
        if not 0 < temperature < math.inf:
            raise ValueError(f"softmax_temperature must be a positive finite number, got {temperature!r}")
        set_("softmax_temperature", float(temperature))
        if not math.isfinite(self.init_log_std):
            raise ValueError(f"init_log_std must be finite, got {self.init_log_std!r}")
        keys = [interface_key(f) for f, _ in self.reads] + [k for k, _ in self.observations]
        keys += [] if self.pixels is None else [self.pixels]
        if len(keys) != len(set(keys)) or not keys:
            raise ValueError(f"a module needs distinct inputs, got {keys}")

    @property
    def inputs(self) -> dict[NestedKey, int | tuple[int, ...]]:
        """Every key the module reads and its size (the image shape for pixels)."""
        sizes: dict[NestedKey, int | tuple[int, ...]] = {interface_key(f): w for f, w in self.reads}
        sizes.update(self.observations)
        if self.pixels is not None:
            sizes[self.pixels] = self.image_shape
        return sizes

    @property
    def outputs(self) -> dict[NestedKey, int]:
        """Every key the module writes and its size."""
        if self.head == "interface":
            return {interface_key(self.factor): self.out_dim}
        return {"loc": self.out_dim, "scale": self.out_dim}

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict (keys spelled by :func:`key_to_str`)."""
        out = asdict(self)
        out["observations"] = [[key_to_str(k), d] for k, d in self.observations]
        out["reads"] = [list(r) for r in self.reads]
        out["pixels"] = None if self.pixels is None else key_to_str(self.pixels)
        for name in ("image_shape", "hidden", "conv_channels", "conv_strides"):
            out[name] = list(out[name])
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> ModuleArch:
        """Rebuild from :meth:`to_json`; ``ValueError`` on anything malformed."""
        if not isinstance(data, dict):
            raise ValueError(f"an architecture must be a JSON object, got {type(data).__name__}")
        unknown = set(data) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"unknown architecture fields {sorted(unknown)}")
        try:
            data = dict(data)
            data["observations"] = tuple((key_from_str(k), d) for k, d in data.get("observations", ()))
            data["reads"] = tuple((f, w) for f, w in data.get("reads", ()))
            if data.get("pixels") is not None:
                data["pixels"] = key_from_str(data["pixels"])
            for name in ("image_shape", "hidden", "conv_channels", "conv_strides"):
                if name in data:
                    data[name] = tuple(data[name])
            return cls(**data)
        except (TypeError, KeyError) as err:
            raise ValueError(f"malformed architecture: {err}") from err


class Normalizer(nn.Module):
    """Per-dimension z-scoring ``(x - loc) / scale`` with buffers saved in the state dict.

    Starts as the identity; :meth:`set` (or :meth:`fit` from samples) changes it.  The
    scale is floored at ``1e-3`` so constant dimensions do not blow up (GPS section 5).

    Examples:
        >>> norm = Normalizer(2)
        >>> norm.fit(torch.tensor([[0.0, 5.0], [2.0, 5.0]]))
        >>> norm.loc, norm.scale
        (tensor([1., 5.]), tensor([1.0000, 0.0010]))
        >>> norm(torch.tensor([3.0, 5.0]))
        tensor([2., 0.])
    """

    loc: torch.Tensor
    scale: torch.Tensor

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.register_buffer("loc", torch.zeros(dim))
        self.register_buffer("scale", torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.loc) / self.scale

    @torch.no_grad()
    def set(self, mean: torch.Tensor, std: torch.Tensor, min_std: float = MIN_STD) -> None:
        """Use ``mean`` and ``std`` (each ``[dim]``); ``std`` is floored at ``min_std``."""
        mean = torch.as_tensor(mean, dtype=self.loc.dtype).reshape(-1)
        std = torch.as_tensor(std, dtype=self.scale.dtype).reshape(-1)
        if mean.shape != self.loc.shape or std.shape != self.scale.shape:
            raise ValueError(
                f"normalisation of size {self.loc.numel()} given mean of shape "
                f"{tuple(mean.shape)} and std of shape {tuple(std.shape)}"
            )
        if not (torch.isfinite(mean).all() and torch.isfinite(std).all()):
            raise ValueError("normalisation mean and std must be finite")
        self.loc.copy_(mean)
        self.scale.copy_(std.abs().clamp_min(min_std))

    def fit(self, samples: torch.Tensor) -> None:
        """Set from ``samples`` ``[..., dim]`` (population std over every leading dim)."""
        flat = samples.detach().reshape(-1, self.loc.numel()).to(self.loc.dtype)
        self.set(flat.mean(0), flat.std(0, correction=0))


class SpatialSoftmax(nn.Module):
    """Feature points: the expected image position of each channel's softmax.

    ``[..., C, H, W]`` -> ``[..., 2 C]`` ordered ``x_0, y_0, x_1, y_1, ...``.  Pixel column
    ``j`` sits at ``x = j / W - 0.5`` and row ``i`` at ``y = i / H - 0.5``, so coordinates
    lie in ``[-0.5, 0.5)``.

    Examples:
        >>> maps = torch.zeros(1, 1, 4, 8)
        >>> maps[0, 0, 1, 6] = 100.0  # one bright pixel: row 1, column 6
        >>> SpatialSoftmax()(maps)
        tensor([[ 0.2500, -0.2500]])
    """

    def __init__(self, temperature: float = 1.0) -> None:
        super().__init__()
        self.temperature = float(temperature)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        *lead, channels, height, width = features.shape
        attention = torch.softmax(features.flatten(-2) / self.temperature, dim=-1)
        attention = attention.unflatten(-1, (height, width))
        xs = torch.arange(width, dtype=features.dtype, device=features.device) / width - 0.5
        ys = torch.arange(height, dtype=features.dtype, device=features.device) / height - 0.5
        x = (attention.sum(-2) * xs).sum(-1)
        y = (attention.sum(-1) * ys).sum(-1)
        return torch.stack([x, y], -1).reshape(*lead, 2 * channels)


class PixelEncoder(nn.Module):
    """uint8 ``[..., H, W, 3]`` images -> float CHW in [0, 1] -> ReLU convs -> feature points.

    Convolutions are "same"-padded so feature points keep the image's coordinates; a stride
    of 2 in the first one (as in Levine et al.'s visuomotor network) quarters the cost of
    every layer after it.  ``temperature`` divides the last maps before the softmax: at 1
    a small object (a 4-pixel block) barely moves its channel's feature point, and 60
    epochs of pose regression (``modnet.pretrain``) leave a colour block 0.4 m off in two
    of four colour modules; at 0.05 each finds its own block within 0.045 m
    (``benchmarks/pretrain_vision.py``).

    Examples:
        >>> encoder = PixelEncoder(channels=(10, 20), kernel_size=3, strides=(2, 1))
        >>> encoder(torch.zeros(2, 5, 64, 80, 3, dtype=torch.uint8)).shape
        torch.Size([2, 5, 40])
    """

    def __init__(
        self,
        channels: Sequence[int] = (10, 20),
        kernel_size: int = 3,
        in_channels: int = 3,
        strides: Sequence[int] = (),
        temperature: float = 1.0,
    ):
        super().__init__()
        strides = tuple(strides) or (1,) * len(channels)
        layers: list[nn.Module] = []
        for out_channels, stride in zip(channels, strides, strict=True):
            conv = nn.Conv2d(in_channels, out_channels, kernel_size, stride, padding=kernel_size // 2)
            layers += [conv, nn.ReLU()]
            in_channels = out_channels
        self.convs = nn.Sequential(*layers)
        self.points = SpatialSoftmax(temperature)
        self.out_dim = 2 * in_channels

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        *lead, height, width, channels = pixels.shape
        images = pixels.reshape(-1, height, width, channels).permute(0, 3, 1, 2)
        images = images.to(torch.get_default_dtype()) / 255.0
        return self.points(self.convs(images)).reshape(*lead, self.out_dim)


class InterfaceHead(nn.Module):
    """The bottleneck a module hands downstream: ``Linear -> activation -> Dropout``."""

    def __init__(
        self, in_dim: int, width: int, dropout: float = 0.0, activation: Activation = "relu"
    ) -> None:
        super().__init__()
        self.layers = nn.Sequential(nn.Linear(in_dim, width), ACTIVATIONS[activation](), nn.Dropout(dropout))

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        return self.layers(hidden)


class GaussianHead(nn.Module):
    """A linear action mean and a learned, state-independent log-std per action dimension.

    Examples:
        >>> head = GaussianHead(80, 4, init_log_std=0.0)
        >>> loc, scale = head(torch.zeros(3, 80))
        >>> loc.shape, scale[0]
        (torch.Size([3, 4]), tensor([1., 1., 1., 1.], grad_fn=<SelectBackward0>))
    """

    def __init__(self, in_dim: int, action_dim: int, init_log_std: float = 0.0) -> None:
        super().__init__()
        self.mean = nn.Linear(in_dim, action_dim)
        self.log_std = nn.Parameter(torch.full((action_dim,), float(init_log_std)))

    def forward(self, hidden: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc = self.mean(hidden)
        return loc, self.log_std.exp().expand_as(loc)


def hidden_layers(
    in_dim: int, widths: Sequence[int], dropout: float = 0.0, activation: Activation = "relu"
) -> nn.Sequential:
    """``[Linear -> activation -> Dropout] * len(widths)`` (dropout omitted when 0).

    Examples:
        >>> hidden_layers(6, (80, 80), activation="tanh")[1]
        Tanh()
    """
    layers: list[nn.Module] = []
    for width in widths:
        layers += [nn.Linear(in_dim, width), ACTIVATIONS[activation]()]
        if dropout:
            layers.append(nn.Dropout(dropout))
        in_dim = width
    return nn.Sequential(*layers)


class ModuleNet(nn.Module):
    """The network of one bank module, laid out by a :class:`ModuleArch`.

    ``forward(*inputs)`` takes the tensors of ``arch.inputs`` in order and returns the
    interface (``"interface"`` head) or ``(loc, scale)`` (``"gaussian"`` head).

    Examples:
        >>> arch = ModuleArch(factor="task", head="interface", out_dim=12,
        ...                   observations=((("task", "state"), 6),), hidden=(80, 80, 80))
        >>> ModuleNet(arch)(torch.zeros(7, 6)).shape
        torch.Size([7, 12])
    """

    def __init__(self, arch: ModuleArch) -> None:
        super().__init__()
        self.num_interfaces = len(arch.reads)
        self.normalizers = nn.ModuleList(Normalizer(d) for _, d in arch.observations)
        in_dim = sum(w for _, w in arch.reads) + sum(d for _, d in arch.observations)
        self.pixels = None
        if arch.pixels is not None:
            self.pixels = PixelEncoder(
                arch.conv_channels,
                arch.kernel_size,
                arch.image_shape[-1],
                arch.conv_strides,
                arch.softmax_temperature,
            )
            in_dim += self.pixels.out_dim
        self.trunk = hidden_layers(in_dim, arch.hidden, arch.dropout, arch.activation)
        last = arch.hidden[-1] if arch.hidden else in_dim
        if arch.head == "interface":
            self.head: nn.Module = InterfaceHead(last, arch.out_dim, arch.interface_dropout, arch.activation)
        else:
            self.head = GaussianHead(last, arch.out_dim, arch.init_log_std)

    def first_linear(self) -> nn.Linear:
        """The layer that reads the concatenated inputs (interfaces, observations, image features)."""
        if len(self.trunk):
            return self.trunk[0]
        return self.head.layers[0] if isinstance(self.head, InterfaceHead) else self.head.mean

    @torch.no_grad()
    def refit_normalization(self, observations: Sequence[torch.Tensor]) -> None:
        """Refit every :class:`Normalizer` to ``observations`` (one tensor per normaliser) and
        fold the change into :meth:`first_linear`, so the network computes the same function.

        GPS fixes the normalisation on its first samples; the states visited later (an arm
        swung far from its start) then reach the network as z-scores in the tens.  Refitting
        this way keeps the inputs well scaled without undoing any training.
        """
        layer = self.first_linear()
        start = layer.in_features - sum(n.loc.numel() for n in self.normalizers)
        if self.pixels is not None:
            start -= self.pixels.out_dim
        for norm, x in zip(self.normalizers, observations, strict=True):
            old_loc, old_scale = norm.loc.clone(), norm.scale.clone()
            norm.fit(x)
            cols = slice(start, start + old_loc.numel())
            weight = layer.weight[:, cols]
            layer.bias += weight @ ((norm.loc - old_loc) / old_scale)
            layer.weight[:, cols] = weight * (norm.scale / old_scale)
            start = cols.stop

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        n_if, n_obs = self.num_interfaces, len(self.normalizers)
        parts = list(inputs[:n_if])
        parts += [norm(x) for norm, x in zip(self.normalizers, inputs[n_if : n_if + n_obs], strict=True)]
        if self.pixels is not None:
            parts.append(self.pixels(inputs[n_if + n_obs]))
        return self.head(self.trunk(torch.cat(parts, -1)))


class BankModule(TensorDictModule):
    """One module of a bank as a :class:`~tensordict.nn.TensorDictModule`.

    ``in_keys`` and ``out_keys`` are ``arch.inputs`` and ``arch.outputs``; the network is a
    :class:`ModuleNet`.  The module owns its observation normalisation
    (:meth:`set_normalization`, :meth:`fit_normalization`) and, for a Gaussian head, its
    log-std (:attr:`log_std`, :meth:`set_std`).

    Examples:
        >>> arch = ModuleArch(factor="robot", head="gaussian", out_dim=3,
        ...                   observations=((("robot", "state"), 6),), reads=(("task", 12),))
        >>> robot = BankModule(arch)
        >>> robot.set_normalization(torch.zeros(6), torch.full((6,), 2.0))
        >>> robot.in_keys, robot.out_keys
        ([('interface', 'task'), ('robot', 'state')], ['loc', 'scale'])
        >>> robot.set_std(torch.tensor([0.5, 0.5, 0.5]))
        >>> robot.log_std.exp()
        tensor([0.5000, 0.5000, 0.5000], grad_fn=<ExpBackward0>)
    """

    def __init__(self, arch: ModuleArch) -> None:
        super().__init__(ModuleNet(arch), in_keys=list(arch.inputs), out_keys=list(arch.outputs))
        self.arch = arch

    @property
    def factor(self) -> str:
        return self.arch.factor

    @property
    def log_std(self) -> nn.Parameter:
        """The learned log-std of a Gaussian head (an interface head has none)."""
        return self.module.head.log_std

    @torch.no_grad()
    def set_std(self, std: torch.Tensor) -> None:
        """Set the policy's state-independent std (e.g. GPS's fitted diagonal covariance)."""
        std = torch.as_tensor(std, dtype=self.log_std.dtype).expand_as(self.log_std)
        self.log_std.copy_(std.clamp_min(torch.finfo(std.dtype).tiny).log())

    def _normalizer(self, key: NestedKey | None) -> Normalizer:
        keys = [k for k, _ in self.arch.observations]
        if key is None and len(keys) == 1:
            return self.module.normalizers[0]
        key = None if key is None else unravel_key(key)
        if key not in keys:
            raise ValueError(
                f"{self.arch.factor} module normalises {[key_to_str(k) for k in keys]}; "
                f"name one of them (got {key!r})"
            )
        return self.module.normalizers[keys.index(key)]

    def set_normalization(self, mean: torch.Tensor, std: torch.Tensor, key: NestedKey | None = None) -> None:
        """Z-score the observation ``key`` (optional when there is one) with ``mean``/``std``."""
        self._normalizer(key).set(mean, std)

    def normalization(self, key: NestedKey | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The ``(mean, std)`` used for observation ``key``."""
        norm = self._normalizer(key)
        return norm.loc.clone(), norm.scale.clone()

    def fit_normalization(self, data: TensorDictBase, keep_function: bool = False) -> None:
        """Set every observation's normalisation from the samples in ``data``; with
        ``keep_function`` the first layer absorbs the change (:meth:`ModuleNet.refit_normalization`)."""
        if keep_function:
            self.module.refit_normalization([data.get(key) for key, _ in self.arch.observations])
            return
        for key, _ in self.arch.observations:
            self._normalizer(key).fit(data.get(key))
