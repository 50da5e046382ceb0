"""Network building blocks: a plain MLP and an ensemble MLP whose members run in one batched
matmul (the two critics of SAC, the reward-model ensemble)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn


def mlp(in_dim: int, out_dim: int, hidden_dim: int, hidden_layers: int) -> nn.Sequential:
    """ReLU MLP with orthogonal weights and zero biases (pytorch_sac's initialisation)."""
    dims = [in_dim] + [hidden_dim] * hidden_layers
    layers: list[nn.Module] = []
    for a, b in zip(dims[:-1], dims[1:], strict=True):
        layers += [nn.Linear(a, b), nn.ReLU(inplace=True)]
    layers.append(nn.Linear(dims[-1], out_dim))
    for m in layers:
        if isinstance(m, nn.Linear):
            nn.init.orthogonal_(m.weight)
            nn.init.zeros_(m.bias)
    return nn.Sequential(*layers)


class EnsembleLinear(nn.Module):
    """`n` independent linear layers applied to an input of shape (n, batch, in_dim)."""

    def __init__(self, n: int, in_dim: int, out_dim: int, init: str = "default"):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(n, in_dim, out_dim))
        self.bias = nn.Parameter(torch.zeros(n, 1, out_dim))
        for w in self.weight.data:
            if init == "orthogonal":
                nn.init.orthogonal_(w.T)
            else:  # nn.Linear's default, member by member
                nn.init.kaiming_uniform_(w.T, a=math.sqrt(5))
        if init != "orthogonal":
            bound = 1 / math.sqrt(in_dim)
            nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor, detach_params: bool = False) -> torch.Tensor:
        if detach_params:
            return torch.baddbmm(self.bias.detach(), x, self.weight.detach())
        return torch.baddbmm(self.bias, x, self.weight)


class EnsembleMLP(nn.Module):
    """`n` MLPs of identical shape evaluated together: (n, batch, in_dim) -> (n, batch, out_dim)."""

    def __init__(
        self,
        n: int,
        in_dim: int,
        out_dim: int,
        hidden_dim: int,
        hidden_layers: int,
        activation: type[nn.Module] = nn.ReLU,
        output_activation: type[nn.Module] | None = None,
        init: str = "default",
    ):
        super().__init__()
        dims = [in_dim] + [hidden_dim] * hidden_layers + [out_dim]
        self.n = n
        self.layers = nn.ModuleList(
            EnsembleLinear(n, a, b, init) for a, b in zip(dims[:-1], dims[1:], strict=True)
        )
        # In place where the module allows it: the preceding baddbmm does not need its output
        # for backward, and it saves an activation-sized allocation per layer.
        inplace = activation in (nn.ReLU, nn.LeakyReLU)
        self.activation = activation(inplace=True) if inplace else activation()
        self.output_activation = output_activation() if output_activation else None

    def forward(self, x: torch.Tensor, detach_params: bool = False) -> torch.Tensor:
        """`detach_params=True` lets gradients flow to the input only (SAC's actor loss), which
        skips computing weight gradients that would be thrown away."""
        if x.dim() == 2:
            x = x.unsqueeze(0).expand(self.n, -1, -1)
        for i, layer in enumerate(self.layers):
            x = layer(x, detach_params)
            if i < len(self.layers) - 1:
                x = self.activation(x)
        return self.output_activation(x) if self.output_activation else x


def _host(param: torch.Tensor) -> np.ndarray:
    """A view of a CPU parameter; a copy of one on another device."""
    return param.detach().cpu().numpy()


class NumpyMLP:
    """Batch-of-one inference on the CPU through NumPy views of a torch MLP's parameters.

    The views share memory with the parameters, so optimiser steps and `load_state_dict` (both
    in place) show up without copying. A torch call costs ~100 us of overhead per step here;
    this costs a few microseconds plus the arithmetic. Parameters on a GPU are copied to the
    host instead: such a copy is made anew when they change.
    """

    def __init__(self, layers: list[nn.Module], activation: str = "relu",
                 output_activation: str | None = None):
        self.params = []
        for layer in layers:
            if isinstance(layer, nn.Linear):
                # Kept (out, in) as torch stores it: w @ x is the fastest NumPy matvec here.
                self.params.append((_host(layer.weight), _host(layer.bias)))
            elif isinstance(layer, EnsembleLinear):
                # x of shape (1, in) broadcasts against (n, in, out) to (n, 1, out).
                self.params.append((_host(layer.weight), _host(layer.bias)))
        self.ensemble = any(isinstance(layer, EnsembleLinear) for layer in layers)
        self.activation, self.output_activation = activation, output_activation

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """x: (in,) for an nn.Linear stack, (1, in) for an ensemble."""
        last = len(self.params) - 1
        for i, (w, b) in enumerate(self.params):
            x = x @ w if self.ensemble else w @ x
            x += b  # in place on the fresh product: one allocation per layer, not two
            if i < last:
                if self.activation == "relu":
                    np.maximum(x, 0, out=x)
                else:
                    np.maximum(x, 0.01 * x, out=x)
        return np.tanh(x) if self.output_activation == "tanh" else x
