"""A trained network as the control loop runs it, without Python's torch: TorchScript and ONNX.

Both take float64 (n, 7) raw SI inputs and give float64 (n, 3) raw SI outputs (the standardisation is inside).
The ONNX file is run by ONNX Runtime (:class:`OnnxModel`, one thread, every graph optimisation): the in-loop
executor of `vslab simulate|run --inverse-model`. The model store writes both beside the weights and checks
their bytes against the card before loading either.
"""

from __future__ import annotations

import io
import logging
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch

from models.hybrid import HybridNet

N_IN = 7


class _Exported(torch.nn.Module):
    """What the control loop calls: float64 (n, 7) raw SI inputs in, float64 (n, 3) raw SI outputs out."""

    def __init__(self, net: torch.nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x.to(torch.float64)).to(torch.float64)


def torchscript(model: HybridNet) -> torch.jit.ScriptModule:
    """The TorchScript of ``model`` (traced and frozen: weights become constants, no Python needed)."""
    example = torch.zeros(4, N_IN, dtype=torch.float64)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", torch.jit.TracerWarning)  # the fitted check becomes a constant: it is
        warnings.simplefilter("ignore", DeprecationWarning)  # TorchScript: still what a C++/RT loop can load
        traced = torch.jit.trace(_Exported(model.eval()).eval(), example, check_inputs=[(example[:1],)])
        return torch.jit.freeze(traced)


def onnx_bytes(model: HybridNet) -> bytes:
    """The ONNX graph of ``model`` (opset 17; input ``x`` and output ``y`` with a free batch size). Made by
    torch's TorchScript-based exporter: the graph of a traced MLP needs no more (the dynamo exporter would
    add onnxscript for nothing)."""
    buffer = io.BytesIO()
    example = (torch.zeros(1, N_IN, dtype=torch.float64),)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        torch.onnx.export(_Exported(model.eval()).eval(), example, buffer, dynamo=False, opset_version=17,
                          input_names=["x"], output_names=["y"],
                          dynamic_axes={"x": {0: "n"}, "y": {0: "n"}})  # fmt: skip
    return buffer.getvalue()


def quantized(onnx: bytes) -> bytes:
    """``onnx`` with int8 weights: ONNX Runtime's dynamic quantisation (every Gemm's weights int8 per output
    channel, its input quantised on the fly at each call; the standardisation stays float). A quarter of the
    bytes to read per call; its error against the float graph is the bench's to measure."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    quiet = logging.getLogger()  # it suggests a pre-processing pass on the root logger at every call
    level = quiet.level
    with tempfile.TemporaryDirectory(prefix="vslab-int8-") as tmp:
        plain, target = Path(tmp) / "float.onnx", Path(tmp) / "int8.onnx"
        plain.write_bytes(onnx)
        try:
            quiet.setLevel(logging.ERROR)
            quantize_dynamic(plain, target, per_channel=True, weight_type=QuantType.QInt8)
        finally:
            quiet.setLevel(level)
        return target.read_bytes()


class OnnxModel:
    """An ONNX file run by ONNX Runtime on one CPU thread: ``predict((n, 7) float64) -> (n, 3) float64``
    (the interface of :meth:`HybridNet.predict`, so a compensator takes either)."""

    def __init__(self, data: bytes, threads: int = 1) -> None:
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        self.session = ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])

    def predict(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != N_IN:
            raise ValueError(f"expected inputs (n, {N_IN}), got {x.shape}")
        return self.session.run(None, {"x": x})[0]
