"""ONNX export of a trained DOPE network, checked against PyTorch, and static INT8 quantisation.

The exported graph takes `image` (N x 3 x H x W float32 RGB in 0..1, H and W multiples of 16, batch, height and
width dynamic) and returns `belief` (N x 9 x H/8 x W/8) and `affinity` (N x 16 x H/8 x W/8) of the last stage.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from n2d_dope.network import DopeNet

INPUT, OUTPUTS = "image", ("belief", "affinity")


def session(path: str | Path, threads: int = 0) -> ort.InferenceSession:
    """An onnxruntime CPU session (CUDA first when onnxruntime-gpu is installed)."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    # Idle worker threads must sleep, not spin: a spinning pool starves the ROS executor and the camera driver
    # sharing a robot PC's few cores (measured: dope_node received 3 of 30 frames/s on 2 cores).
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    providers = [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in ort.get_available_providers()]
    return ort.InferenceSession(str(path), options, providers=providers)


def export_onnx(net: DopeNet, path: str | Path, input_size: tuple[int, int], opset: int = 17) -> dict:
    """Write `net` as ONNX and return how far onnxruntime's outputs are from PyTorch's on a random image."""
    net = net.cpu().eval()
    net.export_last_only = True
    w, h = input_size
    example = torch.rand(1, 3, h, w, generator=torch.Generator().manual_seed(0))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the TorchScript exporter announces its deprecation
            torch.onnx.export(net, (example,), str(path), input_names=[INPUT], output_names=list(OUTPUTS),
                              opset_version=opset, dynamo=False,
                              dynamic_axes={INPUT: {0: "batch", 2: "height", 3: "width"},
                                            **{o: {0: "batch", 2: "rows", 3: "cols"} for o in OUTPUTS}})
        with torch.no_grad():
            expected = [t.numpy() for t in net(example)]
    finally:
        net.export_last_only = False
    got = session(path).run(list(OUTPUTS), {INPUT: example.numpy()})
    return {"opset": opset, "max_abs_diff_vs_torch": float(max(np.abs(a - b).max() for a, b in zip(expected, got)))}


def quantize_int8(fp32: str | Path, int8: str | Path, calibration: list[np.ndarray]) -> dict:
    """Static INT8 quantisation (QDQ, per-channel weights) calibrated on `calibration` images (1 x 3 x H x W), and
    how far its belief maps are from the fp32 model's on those images."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.items = iter(calibration)

        def get_next(self):
            item = next(self.items, None)
            return None if item is None else {INPUT: item}

    int8 = Path(int8)
    prepared = int8.with_name(int8.stem + ".prep.onnx")
    try:
        quant_pre_process(str(fp32), str(prepared), skip_symbolic_shape=True)
        quantize_static(str(prepared), str(int8), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
    finally:
        prepared.unlink(missing_ok=True)
    a, b = session(fp32), session(int8)
    diffs = [np.abs(a.run([OUTPUTS[0]], {INPUT: x})[0] - b.run([OUTPUTS[0]], {INPUT: x})[0]).max() for x in calibration]
    return {"calibration_frames": len(calibration), "belief_max_abs_diff_vs_fp32": float(max(diffs))}
