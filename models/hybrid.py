"""The hybrid, learning-based kinematics of seed 000 (IV.B–C): ReLU MLPs that take the model-based
kinematics (rigid FK of q, or rigid IK of x) plus link pressures and joint currents, and output the tip
position (forward) or the compensated joint angles (inverse).

Variants: ``residual`` nets predict only the correction over the model column (output = model + net, last
layer zero-initialised, so an untrained net is the rigid model); ``ensemble`` nets average K members and
report their spread. The input/output standardisation lives in buffers, so it travels with the weights.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Literal

import numpy as np
import torch
from torch import Tensor, nn

from models.errors import NotFittedError

FORWARD_INPUTS = ("fk_0", "fk_1", "fk_2", "p_0", "p_1", "i_0", "i_1")
FORWARD_TARGETS = ("x_0", "x_1", "x_2")
INVERSE_INPUTS = ("ik_0", "ik_1", "ik_2", "p_0", "p_1", "i_0", "i_1")
INVERSE_TARGETS = ("qc_0", "qc_1", "qc_2")  # the commands that landed the tip (D's qc: servo goals)
PAPER_HIDDEN = (64, 256, 1024, 1024, 256, 64)  # seed 000, IV.B
N_MODEL = 3  # the first three inputs are the model-based prediction of the three outputs


def columns_for(direction: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(input columns, target columns) of D for a forward or an inverse model."""
    if direction == "forward":
        return FORWARD_INPUTS, FORWARD_TARGETS
    if direction == "inverse":
        return INVERSE_INPUTS, INVERSE_TARGETS
    raise ValueError(f"direction must be 'forward' or 'inverse', got {direction!r}")


class DirectedColumns:
    """The columns of D that a model of ``self.direction`` reads and predicts (networks and baselines)."""

    direction: str

    @property
    def inputs(self) -> tuple[str, ...]:
        return columns_for(self.direction)[0]

    @property
    def targets(self) -> tuple[str, ...]:
        return columns_for(self.direction)[1]


@dataclass(frozen=True)
class NetConfig(DirectedColumns):
    """What a hybrid network is: its direction, hidden widths, residual or not, ensemble size, a name."""

    direction: Literal["forward", "inverse"]
    hidden: tuple[int, ...] = PAPER_HIDDEN
    residual: bool = False
    ensemble: int = 1
    name: str = "custom"

    def __post_init__(self) -> None:
        if self.direction not in ("forward", "inverse"):
            raise ValueError(f"NetConfig.direction: expected 'forward' or 'inverse', got {self.direction!r}")
        if self.ensemble < 1 or any(int(h) < 1 for h in self.hidden):
            raise ValueError(f"NetConfig {self.name!r}: ensemble and hidden widths must be ≥ 1")
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))

    def to_dict(self) -> dict:
        return asdict(self) | {"hidden": list(self.hidden)}

    @classmethod
    def from_dict(cls, d: dict) -> NetConfig:
        """The config of ``to_dict``'s output; ValueError naming what is wrong with any other mapping."""
        if not isinstance(d, dict):
            raise ValueError(f"NetConfig: expected a mapping, got {type(d).__name__}")
        known = {f.name for f in fields(cls)}
        if unknown := sorted(set(d) - known):
            raise ValueError(f"NetConfig: unknown field(s) {unknown} (known: {sorted(known)})")
        hidden = d.get("hidden", PAPER_HIDDEN)
        if not isinstance(hidden, list | tuple) or not all(isinstance(h, int) and h >= 1 for h in hidden):
            raise ValueError(f"NetConfig.hidden: expected a list of positive integers, got {hidden!r}")
        if not isinstance(d.get("ensemble", 1), int) or not isinstance(d.get("residual", False), bool):
            raise ValueError("NetConfig: ensemble must be an integer and residual true or false")
        return cls(**{**d, "hidden": tuple(hidden)})


def _presets() -> dict[str, NetConfig]:
    out = {}
    for direction in ("forward", "inverse"):
        for cfg in (
            NetConfig(direction, PAPER_HIDDEN, False, 1, "paper"),
            NetConfig(direction, PAPER_HIDDEN, True, 1, "residual"),
            NetConfig(direction, (64, 64), True, 1, "small-residual"),
            NetConfig(direction, (64, 64), True, 5, "ensemble-small-residual"),
        ):
            out[f"{direction}-{cfg.name}"] = cfg
    return out


PRESETS: dict[str, NetConfig] = _presets()


def preset(direction: str, name: str) -> NetConfig:
    """A preset of a direction: 'paper', 'residual', 'small-residual' or 'ensemble-small-residual'."""
    key = f"{direction}-{name}"
    if key not in PRESETS:
        known = sorted({k.split("-", 1)[1] for k in PRESETS})
        raise KeyError(f"no preset {name!r} for direction {direction!r} (known: {known})")
    return PRESETS[key]


def _mlp(n_in: int, hidden: tuple[int, ...], n_out: int, zero_last: bool) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(n_in, width), nn.ReLU()]
        n_in = width
    last = nn.Linear(n_in, n_out)
    if zero_last:
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
    return nn.Sequential(*layers, last)


class HybridNet(nn.Module):
    """K ReLU MLPs on standardised inputs; ``forward`` maps raw SI inputs (n, 7) to raw SI outputs (n, 3).

    Residual nets standardise the correction (target − model column) about zero, so the output is
    ``model column + out_std · z`` and a zero last layer reproduces the model exactly.
    """

    def __init__(self, config: NetConfig):
        super().__init__()
        self.config = config
        n_in, n_out = len(config.inputs), len(config.targets)
        self.members = nn.ModuleList(
            _mlp(n_in, config.hidden, n_out, config.residual) for _ in range(config.ensemble)
        )
        self.register_buffer("in_mean", torch.zeros(n_in))
        self.register_buffer("in_std", torch.ones(n_in))
        self.register_buffer("out_mean", torch.zeros(n_out))
        self.register_buffer("out_std", torch.ones(n_out))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.uint8))

    # ------------------------------------------------------------------ scaler
    def fit_scaler(self, x: np.ndarray | Tensor, y: np.ndarray | Tensor) -> HybridNet:
        """Fit the input and output standardisation on training rows (raw SI units); returns self."""
        x = torch.tensor(np.asarray(x, dtype=np.float64)) if not isinstance(x, Tensor) else x.double().cpu()
        y = torch.tensor(np.asarray(y, dtype=np.float64)) if not isinstance(y, Tensor) else y.double().cpu()
        if x.ndim != 2 or x.shape[1] != self.in_mean.numel() or y.shape != (len(x), self.out_mean.numel()):
            raise ValueError(
                f"fit_scaler: expected x (n, 7) and y (n, 3), got {tuple(x.shape)}, {tuple(y.shape)}"
            )
        if len(x) < 2 or not (torch.isfinite(x).all() and torch.isfinite(y).all()):
            raise ValueError("fit_scaler: needs at least two rows of finite values")
        in_std = x.std(0)
        self.in_mean.copy_(x.mean(0))
        self.in_std.copy_(torch.where(in_std > 1e-12, in_std, torch.ones_like(in_std)))
        if self.config.residual:
            r = y - x[:, :N_MODEL]
            out_mean, out_std = torch.zeros(r.shape[1], dtype=r.dtype), r.square().mean(0).sqrt()
        else:
            out_mean, out_std = y.mean(0), y.std(0)
        self.out_mean.copy_(out_mean)
        self.out_std.copy_(torch.where(out_std > 1e-12, out_std, torch.ones_like(out_std)))
        self.fitted.fill_(1)
        return self

    def _check_fitted(self) -> None:
        if not int(self.fitted):
            raise NotFittedError(
                f"HybridNet {self.config.name!r}: call fit_scaler (or train) before predicting"
            )

    def scale_inputs(self, x: Tensor) -> Tensor:
        """Standardised float32 inputs of raw inputs."""
        return ((x.to(self.in_mean.dtype) - self.in_mean) / self.in_std).float()

    def scale_targets(self, x: Tensor, y: Tensor) -> Tensor:
        """The standardised training target (of the correction for residual nets) for raw x, y."""
        y = y.to(self.out_mean.dtype)
        if self.config.residual:
            y = y - x[:, :N_MODEL].to(y.dtype)
        return ((y - self.out_mean) / self.out_std).float()

    # ------------------------------------------------------------------ evaluation
    def members_z(self, xs: Tensor) -> Tensor:
        """Standardised outputs of every member (K, n, 3) for standardised inputs xs (n, 7)."""
        return torch.stack([m(xs) for m in self.members])

    def _raw(self, x: Tensor, z: Tensor) -> Tensor:
        dtype = x.dtype if x.is_floating_point() else torch.float32
        out = z.to(self.out_std.dtype) * self.out_std + self.out_mean
        out = out.to(dtype)
        return x[..., :N_MODEL].to(dtype) + out if self.config.residual else out

    def member_outputs(self, x: Tensor) -> Tensor:
        """Raw outputs of every member (K, n, 3) for raw inputs (n, 7)."""
        self._check_fitted()
        return self._raw(x, self.members_z(self.scale_inputs(x)))

    def forward(self, x: Tensor) -> Tensor:
        """Raw SI outputs (n, 3), the members' mean, in the input's float dtype."""
        self._check_fitted()
        xs = self.scale_inputs(x)
        # one member: its output is the mean (no stack and reduce in the exported graph: fewer nodes a call)
        z = self.members[0](xs) if len(self.members) == 1 else self.members_z(xs).mean(0)
        return self._raw(x, z)

    @torch.no_grad()
    def predict(self, x: np.ndarray) -> np.ndarray:
        """Outputs (n, 3) for inputs (n, 7) as numpy (no grad, eval mode)."""
        return self._eval(lambda t: self(t), x)

    @torch.no_grad()
    def predict_std(self, x: np.ndarray) -> np.ndarray:
        """The members' spread (n, 3) (zero for a single net)."""
        return self._eval(lambda t: self.member_outputs(t).std(0, correction=0), x)

    def _eval(self, fn, x: np.ndarray) -> np.ndarray:
        was_training = self.training
        self.eval()
        try:
            t = torch.tensor(np.asarray(x, dtype=np.float64), device=self.in_mean.device)
            return fn(t).cpu().numpy()
        finally:
            self.train(was_training)

    # ------------------------------------------------------------------ persistence
    @classmethod
    def from_state(cls, config: NetConfig, tensors: dict[str, Tensor]) -> HybridNet:
        """Rebuild a fitted net from its config and a tensors-only state dict (e.g. from safetensors).
        RuntimeError (torch's) if names or shapes differ from the config's net; ValueError if a tensor has
        non-finite values or the scaler was never fitted."""
        net = cls(config)
        net.load_state_dict(tensors, strict=True)
        bad = [k for k, t in tensors.items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]
        if bad:
            raise ValueError(f"non-finite values in {', '.join(sorted(bad)[:3])}")
        if not int(net.fitted):
            raise ValueError("the input/output scaler was never fitted (not a trained net)")
        return net
