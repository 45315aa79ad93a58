"""Training and inference speed of the hybrid networks on a paper-size dataset (17,568 points, seed 000).

Prints the training time per epoch of the paper network (forward and inverse, batch 256, a few epochs), then
the single-sample latency (p50/p99 over 2,000 calls after warm-up, one thread, numpy in and out) of the
inverse models — the paper net and the small residual net — run by eager torch, by their TorchScript export
by their ONNX export on ONNX Runtime (the in-loop executor) and by its int8 quantisation (with its test-split
error beside the float graph's), against the control loop's targets:
p99 ≤ 100 µs for the paper net, ≤ 20 µs for the small residual net. Each row also gives the thread's CPU time
(what the executor cost, without the time the machine took the core away), and a last row the floor: ONNX
Runtime running a graph with no network in it. The load average is printed with them.
The dataset is simulated on the twin and built (``--source sim``, minutes) or synthesised
from the rigid kinematics with the same columns (``--source synthetic``, the default: seconds; per-epoch
time depends only on the row count and the net).
Usage: python bench/train.py [--source synthetic|sim] [--points N] [--epochs E] [--calls C]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from acquisition.recorder.sessions import SessionStore
from models import kinematics
from models.hybrid import preset
from models.robot import load_robot
from pipeline.exports import OnnxModel, quantized
from pipeline.lab import Lab
from pipeline.model_store import ONNX, load_exported, load_onnx, model_version, save_model
from pipeline.train import TrainConfig, metrics, train

TARGET_P99_US = {"paper": 100.0, "small-residual": 20.0}  # issue 18: the control loop's latency goals


def synthetic(points: int, seed: int = 0) -> pd.DataFrame:
    """D-shaped rows: random joint angles, pressures, currents; x = rigid FK + a pressure-dependent sag."""
    kin = load_robot("vsl").kinematics
    lengths = kin.arm()
    rng = np.random.default_rng(seed)
    n = points
    q = np.column_stack([rng.uniform(-1.5, 1.5, n), rng.uniform(0.2, 1.2, n), rng.uniform(-1.8, -0.4, n)])
    p = rng.uniform(0.5e5, 2.0e5, (n, 2))
    i = rng.normal(0.3, 0.1, (n, 2))
    payload = rng.choice([0.0, 0.1, 0.2], n)
    fk = kinematics.vsl_fk(q, lengths)
    x = fk + np.column_stack([np.zeros(n), np.zeros(n), -(0.01 + payload * 0.05) * 1e5 / p[:, 0]])
    x += rng.normal(0, 2e-4, x.shape)
    ik = kinematics.vsl_ik(x, lengths, 1)
    cols = {f"x_{k}": x[:, k] for k in range(3)} | {f"p_{k}": p[:, k] for k in range(2)}
    cols |= {f"i_{k}": i[:, k] for k in range(2)} | {f"q_{k}": q[:, k] for k in range(3)}
    cols |= {f"qc_{k}": q[:, k] for k in range(3)}  # commands = angles here: timing does not care
    cols |= {f"fk_{k}": fk[:, k] for k in range(3)} | {f"ik_{k}": ik[:, k] for k in range(3)}
    split = rng.choice(["train", "val", "test"], n, p=[0.7, 0.15, 0.15])
    cols |= {"payload_kg": payload, "robot": "vsl", "split_random": split, "split_group": split}
    return pd.DataFrame(cols)


def simulated(points: int, lab: Path, benches: int) -> pd.DataFrame:
    """The campaign simulated on the twin and built into D."""
    from pipeline.build import build
    from pipeline.dataset_store import DatasetStore
    from twin.runner import simulate_experiment

    start = time.perf_counter()
    simulate_experiment(
        "campaign", SessionStore(lab / "sessions"), benches=benches, overrides={"points": points}
    )
    report = build(sorted((lab / "sessions").iterdir()), Lab(lab), "campaign")
    print(f"simulated and built {report.rows:,} rows in {time.perf_counter() - start:.0f} s (not timed)")
    return DatasetStore(lab / "datasets").load("campaign", report.version)[0]


def latency_us(predict, calls: int, warmup: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Per-call wall time and this thread's CPU time (µs) of ``predict`` on one (1, 7) float64 sample, numpy
    in, numpy out. Wall time is what the loop waits; CPU time leaves out the time the VM or the kernel took
    the core away, so the two apart show how much of a p99 is the executor and how much the machine."""
    x = np.random.default_rng(0).normal(size=(1, 7))
    wall, cpu = np.empty(calls), np.empty(calls)
    for _ in range(warmup):
        predict(x)
    for k in range(calls):
        t0, c0 = time.perf_counter_ns(), time.thread_time_ns()
        predict(x)
        cpu[k] = (time.thread_time_ns() - c0) / 1e3
        wall[k] = (time.perf_counter_ns() - t0) / 1e3
    return wall, cpu


def call_floor() -> OnnxModel:
    """ONNX Runtime running a one-node graph (y = x, (n, 7) float64): the cost of a call from Python with
    no network in it, the floor under every ONNX Runtime figure."""
    from onnx import TensorProto, helper

    io = [helper.make_tensor_value_info(name, TensorProto.DOUBLE, ["n", 7]) for name in ("x", "y")]
    graph = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "floor", io[:1], io[1:])
    return OnnxModel(
        helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]).SerializeToString()
    )


def _torch(module):
    """A torch module as a numpy → numpy call (inference mode, as the loop would run it)."""

    def predict(x: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return module(torch.from_numpy(x)).numpy()

    return predict


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", choices=("synthetic", "sim"), default="synthetic")
    parser.add_argument("--points", type=int, default=17568, help="dataset size (the paper's n = 17568)")
    parser.add_argument("--benches", type=int, default=128, help="twin benches (--source sim)")
    parser.add_argument("--epochs", type=int, default=3, help="epochs timed per network")
    parser.add_argument("--calls", type=int, default=2000, help="latency calls after warm-up")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="torch threads for training")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        lab = Path(tmp)
        data = (
            synthetic(args.points)
            if args.source == "synthetic"
            else simulated(args.points, lab, args.benches)
        )
        n_train = int((data["split_random"] == "train").sum())
        print(f"dataset: {len(data):,} rows ({args.source}), {n_train:,} train; torch {torch.__version__}, "
              f"{args.threads} threads")  # fmt: skip
        exported, accuracy = {}, []
        for direction, name in (("forward", "paper"), ("inverse", "paper"), ("inverse", "small-residual")):
            config = TrainConfig(
                preset(direction, name), batch_size=256, max_epochs=args.epochs, patience=999
            )
            result = train(data, config, threads=args.threads, device="cpu")
            print(f"train {direction:<8} {name:<15} batch 256: {result.epoch_time_s:6.2f} s/epoch "
                  f"({result.epoch_time_s / n_train * 1e6:.1f} µs/row, {args.epochs} epochs)")  # fmt: skip
            if direction == "inverse":
                path = save_model(lab / "models", f"{direction}-{name}", model_version("bench", config),
                                  result.model, {"train_config": config.to_dict()})  # fmt: skip
                int8 = OnnxModel(quantized((path / ONNX).read_bytes()))
                exported[name] = {"eager torch": _torch(result.model),
                                  "TorchScript": _torch(load_exported(path)),
                                  "ONNX Runtime": load_onnx(path).predict,
                                  "ORT int8": int8.predict}  # fmt: skip
                test = data[data["split_random"] == "test"]
                x = test[list(config.net.inputs)].to_numpy(float)
                for label, model in (("float", load_onnx(path)), ("int8", int8)):
                    m = metrics("inverse", model.predict(x), test)
                    tip, joint = m["tip_mean_mm"], m["joint_mean_mrad"]
                    accuracy.append(f"  inverse {name:<15} ORT {label:<5}: test tip mean {tip:.4f} mm, "
                                    f"joint mean {joint:.4f} mrad ({len(test):,} rows)")  # fmt: skip
                gap = np.abs(int8.predict(x) - load_onnx(path).predict(x)).max()
                accuracy.append(f"  inverse {name:<15} int8 − float: max |Δq| {gap * 1e3:.4f} mrad")
        print("accuracy of the exports on the test split (a few epochs of training: a relative measure):")
        print("\n".join(accuracy))
        torch.set_num_threads(1)
        print(f"latency, one thread, load average {os.getloadavg()[0]:.1f} at the start:")
        rows = [
            (name, label, fn, TARGET_P99_US[name])
            for name, ex in exported.items()
            for label, fn in ex.items()
        ]
        for name, label, fn, target in [
            *rows,
            ("(no network)", "ORT call floor", call_floor().predict, None),
        ]:
            wall, cpu = latency_us(fn, args.calls)
            p50, p99 = np.percentile(wall, [50, 99])
            verdict = (
                "" if target is None else f"  (p99 ≤ {target:.0f} µs: {'met' if p99 <= target else 'MISSED'})"
            )
            print(f"  inverse {name:<15} {label:<14} p50 {p50:6.1f} µs  p99 {p99:6.1f} µs  "
                  f"max {wall.max():7.1f} µs  CPU p50 {np.median(cpu):6.1f} p99 {np.percentile(cpu, 99):6.1f}"
                  f"{verdict}")  # fmt: skip
        print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
