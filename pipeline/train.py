"""Training and evaluation of the hybrid networks (seed 000, IV.B–C) on the matrix D.

Adam on the MSE of standardised outputs, early stopping on the validation loss (the best weights are kept).
Seeded and deterministic on CPU: the same data, config, seed and thread count give bit-identical weights.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from dataclasses import asdict, dataclass, field
from functools import lru_cache

import numpy as np
import pandas as pd
import torch

from models import kinematics
from models.estimator import Estimator
from models.hybrid import HybridNet, NetConfig
from models.robot import AnthropomorphicKinematics, load_robot
from pipeline import metrics as pipeline_metrics

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainConfig:
    """Optimiser, stopping and split settings of one training run."""

    net: NetConfig
    lr: float = 1e-3
    batch_size: int = 256
    max_epochs: int = 300
    patience: int = 20
    weight_decay: float = 0.0
    split: str = "split_random"
    seed: int = 0

    def __post_init__(self) -> None:
        if self.split not in ("split_random", "split_group"):
            raise ValueError(
                f"TrainConfig.split: expected 'split_random' or 'split_group', got {self.split!r}"
            )

    def to_dict(self) -> dict:
        return asdict(self) | {"net": self.net.to_dict()}

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        return cls(**{**d, "net": NetConfig.from_dict(d["net"])})


@dataclass
class TrainResult:
    """A trained net and its learning curves (one value per epoch)."""

    model: HybridNet
    config: TrainConfig
    train_loss: list[float] = field(default_factory=list)
    val_loss: list[float] = field(default_factory=list)
    val_error_mm: list[float] = field(default_factory=list)  # tip error (inverse: of the rigid FK of q̂)
    best_epoch: int = -1
    train_time_s: float = 0.0
    epoch_time_s: float = 0.0
    n_train: int = 0
    n_val: int = 0
    device: str = "cpu"

    def to_dict(self) -> dict:
        """Everything but the model (JSON-able), for a model card."""
        return {k: v for k, v in asdict(self).items() if k != "model"} | {"config": self.config.to_dict()}


def _rows(data: pd.DataFrame, net: NetConfig, split: str, part: str) -> pd.DataFrame:
    """The rows of one part with finite inputs and targets (IK is NaN out of reach)."""
    cols = [*net.inputs, *net.targets]
    if missing := [c for c in (*cols, split) if c not in data]:
        raise ValueError(f"dataset lacks the columns {missing} that a {net.direction} net needs")
    rows = data[data[split] == part]
    return rows[np.isfinite(rows[cols].to_numpy(float)).all(1)]


@lru_cache(maxsize=8)
def _lengths(robot: str) -> kinematics.ArmLengths:
    kin = load_robot(robot).kinematics
    if not isinstance(kin, AnthropomorphicKinematics):
        raise ValueError(f"robot {robot!r}: the hybrid nets are defined for the anthropomorphic VSL arm")
    return kinematics.ArmLengths(kin.l1_m, kin.l2_m, kin.l3_m)


def _robot_lengths(data: pd.DataFrame) -> kinematics.ArmLengths:
    robots = data["robot"].unique() if "robot" in data else ["vsl"]
    if len(robots) != 1:
        raise ValueError(f"dataset mixes robots {list(robots)}: evaluate one robot at a time")
    return _lengths(str(robots[0]))


def _errors(direction: str, pred: np.ndarray, rows: pd.DataFrame, targets) -> dict[str, np.ndarray]:
    """Per-row errors: tip (mm) for both directions, joint (mrad, the norm over joints) for inverse."""
    y = rows[list(targets)].to_numpy(float)
    if direction == "forward":
        return {"tip_mm": np.linalg.norm(pred - y, axis=1) * 1e3}
    lengths = _robot_lengths(rows)
    tip = np.linalg.norm(kinematics.vsl_fk(pred, lengths) - kinematics.vsl_fk(y, lengths), axis=1)
    return {"joint_mrad": np.linalg.norm(pred - y, axis=1) * 1e3, "tip_mm": tip * 1e3}


@contextlib.contextmanager
def _torch_settings(threads: int):
    """Fixed thread count and deterministic algorithms for the run; the previous settings come back after."""
    old_threads, old_det = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.set_num_threads(old_threads)
        torch.use_deterministic_algorithms(old_det)


def train(
    data: pd.DataFrame, config: TrainConfig, threads: int | None = None, device: str | None = None
) -> TrainResult:
    """Fit a :class:`HybridNet` on the ``train`` rows of ``config.split``, early-stopped on ``val``."""
    net_cfg = config.net
    tr, va = (_rows(data, net_cfg, config.split, p) for p in ("train", "val"))
    if len(tr) < 2 or len(va) < 1:
        raise ValueError(f"{config.split}: needs ≥ 2 train and ≥ 1 val rows, has {len(tr)} and {len(va)}")
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda"):
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")  # deterministic cuBLAS
    x_tr, y_tr = (tr[list(c)].to_numpy(float) for c in (net_cfg.inputs, net_cfg.targets))
    x_va = va[list(net_cfg.inputs)].to_numpy(float)
    result = TrainResult(model=None, config=config, n_train=len(tr), n_val=len(va), device=device)  # type: ignore[arg-type]
    start = time.perf_counter()
    with _torch_settings(threads or os.cpu_count() or 1), torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        model = HybridNet(net_cfg).fit_scaler(x_tr, y_tr).to(device)
        gen = torch.Generator().manual_seed(config.seed)
        xt, yt = (torch.tensor(a, device=device) for a in (x_tr, y_tr))
        xs_tr, ys_tr = model.scale_inputs(xt), model.scale_targets(xt, yt)
        xv = torch.tensor(x_va, device=device)
        xs_va = model.scale_inputs(xv)
        ys_va = model.scale_targets(
            xv, torch.tensor(va[list(net_cfg.targets)].to_numpy(float), device=device)
        )
        opt = torch.optim.Adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
        best, best_state, epoch_times = float("inf"), None, []
        for epoch in range(config.max_epochs):
            t0 = time.perf_counter()
            model.train()
            order = torch.randperm(len(xs_tr), generator=gen).to(device)
            total = 0.0
            for idx in order.split(config.batch_size):
                loss = (model.members_z(xs_tr[idx]) - ys_tr[idx]).square().mean()
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                total += float(loss.detach()) * len(idx)
            model.eval()
            with torch.no_grad():
                val_loss = float((model.members_z(xs_va).mean(0) - ys_va).square().mean())
                pred = model(xv).cpu().numpy()
            epoch_times.append(time.perf_counter() - t0)
            result.train_loss.append(total / len(xs_tr))
            result.val_loss.append(val_loss)
            result.val_error_mm.append(
                float(_errors(net_cfg.direction, pred, va, net_cfg.targets)["tip_mm"].mean())
            )
            if val_loss < best:
                best, result.best_epoch = val_loss, epoch
                best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
            elif epoch - result.best_epoch >= config.patience:
                break
        model.load_state_dict(best_state)
    model.eval()
    result.model = model
    result.train_time_s = time.perf_counter() - start
    result.epoch_time_s = float(np.mean(epoch_times))
    log.info(
        "trained %s-%s: %d epochs, best %d, val %.3f mm, %.1f s",
        net_cfg.direction, net_cfg.name, len(epoch_times), result.best_epoch,
        result.val_error_mm[result.best_epoch], result.train_time_s,
    )  # fmt: skip
    return result


class HybridRegressor(Estimator):
    """A hybrid network as an estimator (the one contract, ``models.estimator``):
    ``HybridRegressor(TrainConfig(net=preset("forward", "small-residual"))).fit(data)`` trains it on the
    ``train`` rows of ``config.split``, early-stopped on ``val`` (:func:`train`), learning ``net_`` (the
    :class:`HybridNet`) and ``history_`` (its :class:`TrainResult`); ``predict(rows)`` gives the outputs
    (n, 3) of a DataFrame holding the net's input columns (or an (n, 7) array). Seeded by ``config.seed``."""

    def __init__(self, config: TrainConfig | None = None, threads: int | None = None,
                 device: str | None = None) -> None:  # fmt: skip
        self.config = config
        self.threads = threads
        self.device = device

    def fit(self, data: pd.DataFrame) -> HybridRegressor:
        if self.config is None:
            raise ValueError("HybridRegressor needs a TrainConfig (its net, optimiser and split)")
        self.history_ = train(data, self.config, threads=self.threads, device=self.device)
        self.net_ = self.history_.model
        return self

    def predict(self, rows: pd.DataFrame | np.ndarray) -> np.ndarray:
        self.check_fitted()
        x = rows[list(self.config.net.inputs)].to_numpy(float) if isinstance(rows, pd.DataFrame) else rows
        return self.net_.predict(x)


def _summary(err: np.ndarray, prefix: str, unit: str) -> dict[str, float]:
    if len(err) == 0:
        return {f"{prefix}_{s}_{unit}": float("nan") for s in ("mean", "median", "p95", "max")}
    return {
        f"{prefix}_mean_{unit}": float(err.mean()),
        f"{prefix}_median_{unit}": float(np.median(err)),
        f"{prefix}_p95_{unit}": float(np.percentile(err, 95)),
        f"{prefix}_max_{unit}": float(err.max()),
    }


def metrics(direction: str, pred: np.ndarray, rows: pd.DataFrame) -> dict:
    """Error summary of predictions ``pred`` (n, 3) for ``rows`` of D (see :func:`evaluate`)."""
    net = NetConfig(direction)
    errs = _errors(direction, np.asarray(pred, float), rows, net.targets)
    out: dict = {"direction": direction, "n": len(rows)}
    if direction == "inverse":
        out |= _summary(errs["joint_mrad"], "joint", "mrad")
    out |= _summary(errs["tip_mm"], "tip", "mm")
    payload = rows["payload_kg"].to_numpy(float)
    cells = pipeline_metrics.cell_records(errs, pipeline_metrics.cell_pressure_pa(rows), payload)
    return out | {"per_cell": cells}


def evaluate(model: HybridNet, data: pd.DataFrame, split: str = "split_random", part: str = "test") -> dict:
    """Errors of ``model`` on one part of D: mean, median, p95, max and ``per_cell`` (p_0 bin × payload).

    Forward: the 3-D tip error |x̂ − x| (mm). Inverse: the joint error |q̂ − q| (mrad) and the tip error of the
    rigid FK of q̂ against the rigid FK of q (mm). That is only a proxy: the inverse model's real test is in
    the loop (Experiment 2), where q̂ is commanded and the measured tip is compared with the goal.
    """
    rows = _rows(data, model.config, split, part)
    return metrics(
        model.config.direction, model.predict(rows[list(model.config.inputs)].to_numpy(float)), rows
    )


def evaluate_rigid(
    data: pd.DataFrame, direction: str, split: str = "split_random", part: str = "test"
) -> dict:
    """The model-based baseline's errors (forward: fk vs x; inverse: ik vs q), as :func:`evaluate` gives."""
    net = NetConfig(direction)  # type: ignore[arg-type]
    rows = _rows(data, net, split, part)
    return metrics(direction, rows[list(net.inputs[:3])].to_numpy(float), rows)
