"""Training and evaluation of the hybrid networks (seed 000, IV.B–C) on the matrix D.

Adam on the MSE of standardised outputs, early stopping on the validation loss (the best weights are kept).
Seeded and deterministic on CPU: the same data, config, seed and thread count give bit-identical weights.
"""

from __future__ import annotations

import contextlib
import copy
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
from models.robot import AnthropomorphicKinematics, RobotDescription, load_robot
from pipeline import metrics as pipeline_metrics
from pipeline.datasets import SPLIT_COLUMNS

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
        if self.split not in SPLIT_COLUMNS:
            raise ValueError(f"TrainConfig.split: expected one of {list(SPLIT_COLUMNS)}, got {self.split!r}")

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
    return _description_lengths(load_robot(robot))


def _description_lengths(description: RobotDescription) -> kinematics.ArmLengths:
    kin = description.kinematics
    if not isinstance(kin, AnthropomorphicKinematics):
        raise ValueError(f"robot {description.name!r}: the hybrid nets are defined for the anthropomorphic "
                         "VSL arm")  # fmt: skip
    return kin.arm()


Robot = RobotDescription | str | None  # a description, a name or a path; None: each row's ``robot`` by name


def _robot_lengths(data: pd.DataFrame, robot: Robot = None) -> kinematics.ArmLengths:
    """The link lengths whose rigid FK scores an inverse net's joints as a tip error: ``robot``'s, or those
    of the one robot named in the rows (a dataset of a description that is a file, such as a fitted twin's
    campaign, names its description: ``robot`` gives it)."""
    if isinstance(robot, RobotDescription):
        return _description_lengths(robot)
    if robot is not None:
        return _lengths(str(robot))
    robots = data["robot"].unique() if "robot" in data else ["vsl"]
    if len(robots) != 1:
        raise ValueError(f"dataset mixes robots {list(robots)}: evaluate one robot at a time")
    return _lengths(str(robots[0]))


def _errors(direction: str, pred: np.ndarray, rows: pd.DataFrame, targets,
            robot: Robot = None) -> dict[str, np.ndarray]:  # fmt: skip
    """Per-row errors: tip (mm) for both directions, joint (mrad, the norm over joints) for inverse."""
    y = rows[list(targets)].to_numpy(float)
    if direction == "forward":
        return {"tip_mm": np.linalg.norm(pred - y, axis=1) * 1e3}
    lengths = _robot_lengths(rows, robot)
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


def _descend(net: HybridNet, config: TrainConfig, tr: pd.DataFrame, va: pd.DataFrame,
             result: TrainResult, robot: Robot = None, from_start: bool = False) -> list[float]:  # fmt: skip
    """Adam epochs over ``tr`` in a seeded order until ``val`` stops improving for ``config.patience``
    epochs; the net ends with its best weights, ``result`` with the curves. Returns each epoch's time (s).
    ``from_start``: the weights it starts from (a pretrained net's) are a candidate too, the curves' first
    entry (no step taken): fine-tuning that only makes ``val`` worse keeps them."""
    device = net.in_mean.device
    cols = config.net

    def tensor(rows: pd.DataFrame, names: tuple[str, ...]) -> torch.Tensor:
        return torch.tensor(rows[list(names)].to_numpy(float), device=device)

    gen = torch.Generator().manual_seed(config.seed)  # the batch order
    xt, xv = tensor(tr, cols.inputs), tensor(va, cols.inputs)
    xs_tr, ys_tr = net.scale_inputs(xt), net.scale_targets(xt, tensor(tr, cols.targets))
    xs_va, ys_va = net.scale_inputs(xv), net.scale_targets(xv, tensor(va, cols.targets))
    # foreach: one kernel per step over all the weights, bit-identical to the per-tensor loop torch picks on a
    # CPU (a paper net's epoch 1.18 → 1.08 s); fused would be faster still but is not bit-identical
    opt = torch.optim.Adam(net.parameters(), lr=config.lr, weight_decay=config.weight_decay, foreach=True)
    best, best_state, epoch_times = float("inf"), None, []

    def judged(train_loss: float) -> bool:  # the weights now: their curves kept, True when patience ran out
        nonlocal best, best_state
        net.eval()
        with torch.no_grad():
            val_loss = float((net.members_z(xs_va).mean(0) - ys_va).square().mean())
            pred = net(xv).cpu().numpy()
        epoch = len(result.val_loss)
        result.train_loss.append(train_loss)
        result.val_loss.append(val_loss)
        errors = _errors(cols.direction, pred, va, cols.targets, robot)
        result.val_error_mm.append(float(errors["tip_mm"].mean()))
        if val_loss < best:
            best, result.best_epoch = val_loss, epoch
            best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
            return False
        return epoch - result.best_epoch >= config.patience

    if from_start:
        with torch.no_grad():
            judged(float((net.members_z(xs_tr) - ys_tr).square().mean()))
    for _ in range(config.max_epochs):
        t0 = time.perf_counter()
        net.train()
        order = torch.randperm(len(xs_tr), generator=gen).to(device)
        total = 0.0
        for idx in order.split(config.batch_size):
            loss = (net.members_z(xs_tr[idx]) - ys_tr[idx]).square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
        patience_ran_out = judged(total / len(xs_tr))
        epoch_times.append(time.perf_counter() - t0)
        if patience_ran_out:
            break
    net.load_state_dict(best_state)
    return epoch_times


class HybridRegressor(Estimator):
    """A hybrid network as an estimator (the one contract, ``models.estimator``):
    ``HybridRegressor(TrainConfig(net=preset("forward", "small-residual"))).fit(data)`` trains a
    :class:`HybridNet` on the ``train`` rows of ``config.split``, early-stopped on ``val`` (the best weights
    are kept), learning ``net_`` (the net: what the model store saves) and ``history_`` (its
    :class:`TrainResult`: curves, best epoch, timings). ``predict(rows)`` gives the outputs (n, 3) of a
    DataFrame holding the net's input columns (or of an (n, 7) array). Randomness comes from
    ``config.seed``; ``threads`` (default: every core) and ``device`` (default: CUDA if there is one) are
    part of what makes a run bit-identical.

    ``pretrained``: a net of the same :class:`NetConfig` to start from, its weights and its input and output
    scaling (fine-tuning a net pretrained on the twin's campaign, ``pipeline.pretrain``; it is copied, never
    changed). ``robot``: the description (or its name or file) whose rigid FK turns an inverse net's joints
    into the validation tip error; by default the robot the rows name (a dataset of a fitted twin, whose
    description is a file, needs it)."""

    def __init__(self, config: TrainConfig | None = None, threads: int | None = None,
                 device: str | None = None, pretrained: HybridNet | None = None,
                 robot: Robot = None) -> None:  # fmt: skip
        self.config = config
        self.threads = threads
        self.device = device
        self.pretrained = pretrained
        self.robot = robot

    def fit(self, data: pd.DataFrame) -> HybridRegressor:
        config = self.config
        if config is None:
            raise ValueError("HybridRegressor needs a TrainConfig (its net, optimiser and split)")
        if self.pretrained is not None and self.pretrained.config != config.net:
            raise ValueError(f"pretrained net is {self.pretrained.config}, the config's is {config.net}: "
                             "fine-tuning starts from a net of the same shape")  # fmt: skip
        tr, va = (_rows(data, config.net, config.split, p) for p in ("train", "val"))
        if len(tr) < 2 or len(va) < 1:
            raise ValueError(f"{config.split}: needs ≥ 2 train and ≥ 1 val rows, has {len(tr)} and {len(va)}")
        device = self.device or ("cuda" if torch.cuda.is_available() else "cpu")
        if device.startswith("cuda"):
            os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")  # deterministic cuBLAS
        result = TrainResult(model=None, config=config, n_train=len(tr), n_val=len(va), device=device)  # type: ignore[arg-type]
        start = time.perf_counter()
        with _torch_settings(self.threads or os.cpu_count() or 1), torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed)  # the initial weights
            if self.pretrained is not None:
                net = copy.deepcopy(self.pretrained).to(device)
            else:
                x_tr, y_tr = (tr[list(c)].to_numpy(float) for c in (config.net.inputs, config.net.targets))
                net = HybridNet(config.net).fit_scaler(x_tr, y_tr).to(device)
            epoch_times = _descend(net, config, tr, va, result, self.robot, self.pretrained is not None)
        net.eval()
        result.model = net
        result.train_time_s = time.perf_counter() - start
        result.epoch_time_s = float(np.mean(epoch_times))
        log.debug(  # the commands print their own summaries
            "trained %s-%s: %d epochs, best %d, val %.3f mm, %.1f s",
            config.net.direction, config.net.name, len(epoch_times), result.best_epoch,
            result.val_error_mm[result.best_epoch], result.train_time_s,
        )  # fmt: skip
        self.net_, self.history_ = net, result
        return self

    def predict(self, rows: pd.DataFrame | np.ndarray) -> np.ndarray:
        self.check_fitted()
        x = rows[list(self.config.net.inputs)].to_numpy(float) if isinstance(rows, pd.DataFrame) else rows
        return self.net_.predict(x)


def train(
    data: pd.DataFrame,
    config: TrainConfig,
    threads: int | None = None,
    device: str | None = None,
    pretrained: HybridNet | None = None,
    robot: Robot = None,
) -> TrainResult:
    """The net and learning curves of ``HybridRegressor(config, threads, device, pretrained, robot)
    .fit(data)`` (its ``history_``): a convenience for the grid and the benches, which save the net with its
    curves."""
    return HybridRegressor(config, threads, device, pretrained, robot).fit(data).history_


def model_card(result: TrainResult, dataset: dict, metrics: dict, threads: int | None) -> dict:
    """What a saved net's card says of its training (``model_store.save_model`` adds its name, version,
    files and hashes): the dataset (name, version), the config, the test ``metrics``, the learning curves,
    timings and sizes."""
    losses = zip(result.train_loss, result.val_loss, result.val_error_mm, strict=True)
    curves = [
        {"epoch": k, "train_loss": a, "val_loss": b, "val_error_mm": c} for k, (a, b, c) in enumerate(losses)
    ]
    return {
        "dataset": dataset, "train_config": result.config.to_dict(), "seed": result.config.seed,
        "metrics": metrics, "curves": curves, "best_epoch": result.best_epoch,
        "train_time_s": result.train_time_s, "epoch_time_s": result.epoch_time_s, "threads": threads,
        "n_train": result.n_train, "n_val": result.n_val,
    }  # fmt: skip


def _summary(err: np.ndarray, prefix: str, unit: str) -> dict[str, float]:
    if len(err) == 0:
        return {f"{prefix}_{s}_{unit}": float("nan") for s in ("mean", "median", "p95", "max")}
    return {
        f"{prefix}_mean_{unit}": float(err.mean()),
        f"{prefix}_median_{unit}": float(np.median(err)),
        f"{prefix}_p95_{unit}": float(np.percentile(err, 95)),
        f"{prefix}_max_{unit}": float(err.max()),
    }


def metrics(direction: str, pred: np.ndarray, rows: pd.DataFrame, robot: Robot = None) -> dict:
    """Error summary of predictions ``pred`` (n, 3) for ``rows`` of D (see :func:`evaluate`)."""
    net = NetConfig(direction)
    errs = _errors(direction, np.asarray(pred, float), rows, net.targets, robot)
    out: dict = {"direction": direction, "n": len(rows)}
    if direction == "inverse":
        out |= _summary(errs["joint_mrad"], "joint", "mrad")
    out |= _summary(errs["tip_mm"], "tip", "mm")
    payload = rows["payload_kg"].to_numpy(float)
    cells = pipeline_metrics.cell_records(errs, pipeline_metrics.cell_pressure_pa(rows), payload)
    return out | {"per_cell": cells}


def evaluate(model: HybridNet, data: pd.DataFrame, split: str = "split_random", part: str = "test",
             robot: Robot = None) -> dict:  # fmt: skip
    """Errors of ``model`` on one part of D: mean, median, p95, max and ``per_cell`` (p_0 bin × payload).

    Forward: the 3-D tip error |x̂ − x| (mm). Inverse: the joint error |q̂ − q| (mrad) and the tip error of the
    rigid FK of q̂ against the rigid FK of q (mm). That is only a proxy: the inverse model's real test is in
    the loop (Experiment 2), where q̂ is commanded and the measured tip is compared with the goal.
    ``robot``: whose rigid FK that is (by default the robot the rows name).
    """
    rows = _rows(data, model.config, split, part)
    pred = model.predict(rows[list(model.config.inputs)].to_numpy(float))
    return metrics(model.config.direction, pred, rows, robot)


def evaluate_rigid(
    data: pd.DataFrame, direction: str, split: str = "split_random", part: str = "test"
) -> dict:
    """The model-based baseline's errors (forward: fk vs x; inverse: ik vs q), as :func:`evaluate` gives."""
    net = NetConfig(direction)  # type: ignore[arg-type]
    rows = _rows(data, net, split, part)
    return metrics(direction, rows[list(net.inputs[:3])].to_numpy(float), rows)
