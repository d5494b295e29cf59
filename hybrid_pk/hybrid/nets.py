"""Residual-network architectures of Ojer et al. 2024 (appendix, section 4) and ours.

Every network maps normalised joints ``u: (N, dof)`` to one correction ``(N, 3)``
(position or rotation, in the units of the head's output scale). Names:

- ``D1, D4, D4w, D4W``: dense, ReLU after every hidden layer, linear output
  (appendix widths: 5000 / 3500-2500-1500-750 / 5000-3000-1000-500 /
  6000-3000-1500-1000).
- ``Rw, Rd``: ResNets of Chen et al. [22] grouped in *components* of one dense block
  followed by two identity blocks of the same width (appendix: 700-500-200 and
  500-200-100-70-30). See :class:`ChenResNet` for the blocks.
- ``B1``-``B4``: the baselines of section 4 ([23], [22], [25], [24]). The paper gives
  no sizes for them; what is assumed is written in :data:`ARCHITECTURES`.
- ``mlp`` (ours): a small smooth MLP, ``mlp`` = 3 x 256 SiLU, or ``mlp:WxD`` for D
  hidden layers of width W; smooth activations give the IK smooth Jacobians.

Parameter counts are trainable parameters (weights, biases, BatchNorm scale and
shift); BatchNorm running statistics are buffers and not counted (Keras' summary
counts them as non-trainable parameters).
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from hybrid_pk.errors import HybridPKError

__all__ = [
    "ARCHITECTURES",
    "Architecture",
    "ChenResNet",
    "DenseBlock",
    "DenseNet",
    "GroupedDenseNet",
    "IdentityBlock",
    "ResidualHead",
    "build_net",
    "count_parameters",
    "make_activation",
    "parse_arch",
]

_ACTIVATIONS: dict[str, Callable[[], nn.Module]] = {
    "relu": nn.ReLU,
    "silu": nn.SiLU,
    "tanh": nn.Tanh,
    "sigmoid": nn.Sigmoid,
    "gelu": nn.GELU,
}


def make_activation(name: str) -> nn.Module:
    """A fresh activation module by name (``relu``, ``silu``, ``tanh``, ``sigmoid``, ``gelu``)."""
    if name not in _ACTIVATIONS:
        raise HybridPKError(f"unknown activation {name!r}; one of {', '.join(_ACTIVATIONS)}")
    return _ACTIVATIONS[name]()


class DenseNet(nn.Module):
    """Fully connected network: hidden layers with an activation, linear output.

    Args:
        in_features: inputs (the robot's ``dof``).
        hidden: widths of the hidden layers, e.g. ``(5000, 3000, 1000, 500)``.
        out_features: outputs (3).
        activation: ``relu`` (paper), ``silu``, ``tanh``, ``sigmoid`` or ``gelu``.
    """

    def __init__(
        self,
        in_features: int,
        hidden: Sequence[int],
        out_features: int = 3,
        activation: str = "relu",
    ) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width = in_features
        for h in hidden:
            layers += [nn.Linear(width, h), make_activation(activation)]
            width = h
        layers.append(nn.Linear(width, out_features))
        self.layers = nn.Sequential(*layers)

    def forward(self, u: Tensor) -> Tensor:
        """``(N, in_features) -> (N, out_features)``."""
        return self.layers(u)


class GroupedDenseNet(nn.Module):
    """``groups`` independent dense networks of one shape, evaluated in one batched
    product per layer (the local networks: one per joint).

    ``(N, groups, in_features) -> (N, groups, out_features)``; each group's layers are
    initialised as :class:`torch.nn.Linear` would.

    Args:
        groups: number of networks.
        in_features, out_features: inputs and outputs of each.
        hidden: widths of the hidden layers.
        activation: as :class:`DenseNet`.
    """

    def __init__(
        self,
        groups: int,
        in_features: int,
        hidden: Sequence[int],
        out_features: int,
        activation: str = "silu",
    ) -> None:
        super().__init__()
        dims = [in_features, *hidden, out_features]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for n_in, n_out in itertools.pairwise(dims):
            bound = 1.0 / n_in**0.5
            self.weights.append(
                nn.Parameter(torch.empty(groups, n_in, n_out).uniform_(-bound, bound))
            )
            self.biases.append(nn.Parameter(torch.empty(groups, n_out).uniform_(-bound, bound)))
        self.act = make_activation(activation)

    def zero_output(self) -> None:
        """Zero the last layer (the networks start at zero output)."""
        with torch.no_grad():
            self.weights[-1].zero_()
            self.biases[-1].zero_()

    def forward(self, u: Tensor) -> Tensor:
        h = u
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            h = torch.einsum("ngi,gio->ngo", h, w) + b
            if i < last:
                h = self.act(h)
        return h


def _dense_bn(n_in: int, n_out: int) -> list[nn.Module]:
    return [nn.Linear(n_in, n_out), nn.BatchNorm1d(n_out)]


class DenseBlock(nn.Module):
    """Chen et al.'s block with a dense shortcut (it changes the width).

    ``y = relu(main(x) + BN(Dense(x)))`` with ``main = Dense-BN-ReLU, Dense-BN-ReLU,
    Dense-BN`` (the dense analogue of ResNet-50's convolutional block, following the
    authors' published Keras code of [22]).
    """

    def __init__(self, n_in: int, units: int) -> None:
        super().__init__()
        self.main = nn.Sequential(
            *_dense_bn(n_in, units), nn.ReLU(), *_dense_bn(units, units), nn.ReLU()
        )
        self.main.extend(_dense_bn(units, units))
        self.shortcut = nn.Sequential(*_dense_bn(n_in, units))

    def forward(self, x: Tensor) -> Tensor:
        return nn.functional.relu(self.main(x) + self.shortcut(x))


class IdentityBlock(nn.Module):
    """Chen et al.'s block with an identity shortcut: ``y = relu(main(x) + x)``, ``main``
    as in :class:`DenseBlock`."""

    def __init__(self, units: int) -> None:
        super().__init__()
        self.main = nn.Sequential(
            *_dense_bn(units, units), nn.ReLU(), *_dense_bn(units, units), nn.ReLU()
        )
        self.main.extend(_dense_bn(units, units))

    def forward(self, x: Tensor) -> Tensor:
        return nn.functional.relu(self.main(x) + x)


class ChenResNet(nn.Module):
    """ResNet for regression (Chen et al. 2020 [22]) in components.

    Each component is one :class:`DenseBlock` followed by ``identity_blocks``
    :class:`IdentityBlock` s of the same width (Ojer et al., appendix: two). As in the
    authors' code, the last block is followed by BatchNorm and a linear output layer.

    Assumptions (the appendix draws the blocks, Fig. 11, without every detail): each
    block has three Dense-BatchNorm stages, ReLU between them and after the addition;
    BatchNorm uses PyTorch's defaults (Keras' momentum 0.99 is PyTorch's 0.01 — we
    keep 0.1 so that running statistics settle within the paper's short trainings).

    Args:
        in_features: inputs (``dof``).
        widths: one width per component, e.g. ``(700, 500, 200)``.
        out_features: outputs (3).
        identity_blocks: identity blocks per component.
    """

    def __init__(
        self,
        in_features: int,
        widths: Sequence[int],
        out_features: int = 3,
        identity_blocks: int = 2,
    ) -> None:
        super().__init__()
        blocks: list[nn.Module] = []
        width = in_features
        for w in widths:
            blocks.append(DenseBlock(width, w))
            blocks += [IdentityBlock(w) for _ in range(identity_blocks)]
            width = w
        self.blocks = nn.Sequential(*blocks)
        self.head = nn.Sequential(nn.BatchNorm1d(width), nn.Linear(width, out_features))

    def forward(self, u: Tensor) -> Tensor:
        """``(N, in_features) -> (N, out_features)``."""
        return self.head(self.blocks(u))


@dataclass(frozen=True)
class Architecture:
    """A named architecture: its family, its arguments, and where it comes from."""

    family: str  # "dense" or "resnet"
    args: dict
    source: str


ARCHITECTURES: dict[str, Architecture] = {
    "D1": Architecture("dense", {"hidden": (5000,)}, "Ojer et al. appendix"),
    "D4": Architecture("dense", {"hidden": (3500, 2500, 1500, 750)}, "Ojer et al. appendix"),
    "D4w": Architecture("dense", {"hidden": (5000, 3000, 1000, 500)}, "Ojer et al. appendix"),
    "D4W": Architecture("dense", {"hidden": (6000, 3000, 1500, 1000)}, "Ojer et al. appendix"),
    "Rw": Architecture("resnet", {"widths": (700, 500, 200)}, "Ojer et al. appendix"),
    "Rd": Architecture("resnet", {"widths": (500, 200, 100, 70, 30)}, "Ojer et al. appendix"),
    # Baselines: the paper cites them without sizes. B2 is the published optimal model
    # of [22] (width 16, depth 28 = three components); B1, B3, B4 are assumptions that
    # follow the cited papers' descriptions (plain MLP; a small sigmoid network
    # trained after an EKF calibration; a GA-sized sigmoid DNN).
    "B1": Architecture(
        "dense",
        {"hidden": (100, 100, 100), "activation": "relu"},
        "Theofanidis et al. [23]; assumed 3 x 100 ReLU",
    ),
    "B2": Architecture(
        "resnet", {"widths": (16, 16, 16)}, "Chen et al. [22] optimal model (width 16, depth 28)"
    ),
    "B3": Architecture(
        "dense",
        {"hidden": (20,), "activation": "sigmoid"},
        "Nguyen et al. [25]; assumed one hidden layer of 20 sigmoid units",
    ),
    "B4": Architecture(
        "dense",
        {"hidden": (40, 30, 20), "activation": "sigmoid"},
        "Chen et al. [24] GA-DNN; assumed 40-30-20 sigmoid (a GA result)",
    ),
    "mlp": Architecture(
        "dense", {"hidden": (256, 256, 256), "activation": "silu"}, "ours: smooth MLP"
    ),
}

_MLP = re.compile(r"^mlp:(\d+)x(\d+)$")


def parse_arch(name: str) -> Architecture:
    """The :class:`Architecture` of a name (``D4w``, ``Rw``, ``mlp``, ``mlp:128x4``, ...).

    Names are case-sensitive (``D4w`` and ``D4W`` are different networks).

    Raises:
        HybridPKError: for an unknown name (the message lists the known ones).
    """
    if name in ARCHITECTURES:
        return ARCHITECTURES[name]
    m = _MLP.match(name)
    if m:
        width, depth = int(m.group(1)), int(m.group(2))
        if width < 1 or depth < 1:
            raise HybridPKError(f"network {name!r}: width and depth must be >= 1")
        return Architecture("dense", {"hidden": (width,) * depth, "activation": "silu"}, "ours")
    raise HybridPKError(
        f"unknown network architecture {name!r}; known: {', '.join(ARCHITECTURES)}, "
        "or mlp:WIDTHxDEPTH (e.g. mlp:128x4)"
    )


def build_net(name: str, in_features: int, out_features: int = 3) -> nn.Module:
    """A fresh network of architecture ``name`` (see :func:`parse_arch`).

    Args:
        name: architecture name.
        in_features: inputs (the robot's ``dof``).
        out_features: outputs (3: a position or a rotation correction).
    """
    arch = parse_arch(name)
    if arch.family == "resnet":
        return ChenResNet(in_features, out_features=out_features, **arch.args)
    return DenseNet(in_features, out_features=out_features, **arch.args)


def count_parameters(net: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in net.parameters() if p.requires_grad)


class ResidualHead(nn.Module):
    """A network and the scale of its output: ``(N, n_inputs) u -> (N, 3)`` in physical
    units.

    The network predicts in units of ``scale (3,)`` (the RMS of its training targets,
    e.g. tens of µm), so its outputs are O(1) whatever the size of the residual.

    Args:
        arch: architecture name (:func:`~hybrid_pk.hybrid.nets.build_net`).
        n_inputs: number of inputs (the robot's ``dof`` for the paper's inputs).
        scale: ``(3,)`` output unit [m or rad].
        zero_init: start with a zero output layer (the hybrid starts as the base model).
    """

    def __init__(self, arch: str, n_inputs: int, scale: Tensor, zero_init: bool = False) -> None:
        super().__init__()
        self.arch = arch
        self.net = build_net(arch, n_inputs, 3)
        self.register_buffer("scale", scale.detach().to(torch.float64).reshape(3).clone())
        if zero_init:
            last = [m for m in self.net.modules() if isinstance(m, nn.Linear)][-1]
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)

    @property
    def net_dtype(self) -> torch.dtype:
        return next(self.net.parameters()).dtype

    def forward(self, u: Tensor) -> Tensor:
        """``(*B, n_inputs)`` inputs -> ``(*B, 3)`` correction [m or rad], dtype of ``u``."""
        batch = u.shape[:-1]
        out = self.net(u.reshape(-1, u.shape[-1]).to(self.net_dtype))
        return out.to(u.dtype).reshape(*batch, 3) * self.scale.to(u.dtype)

    def correct(self, u: Tensor, geo: dict[str, Tensor], w: Tensor | None) -> Tensor:
        """``(*B, 3)`` correction in joint 1's axes: the output weighted by ``w (*B,)``
        (None: 1) and turned by ``geo["A"] (*B, 3, 3)`` when the inputs give one."""
        out = self(u) if w is None else w[..., None] * self(u)
        A = geo.get("A")
        return out if A is None else (A.to(out.dtype) @ out[..., None])[..., 0]

    def extra_repr(self) -> str:
        return f"arch={self.arch!r}"
