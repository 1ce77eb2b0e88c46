"""Tiny ONNX stand-ins with the signatures of models_manifest/.

Real segmentation, tracking and depth weights cannot be downloaded here, so
dm-prep's adapters are tested end to end on these few-KB models. Each has
exactly the input/output names, dtypes and shapes of its manifest entry and a
simple, checkable behaviour:

* sam2 encoder: average-pools the normalised image to the three feature maps
  (1x1 convolutions with fixed weights: every channel = channel mean);
* sam2 decoder: mask logit = 8 * (feature mean - threshold) inside the
  bounding box of the prompt points (the box prompt), -8 outside;
* cotracker3: tracks = query xy + (mean(frame t) - mean(frame 0)) px along x;
  visibility = 1 while the frame mean is below 200;
* depth anything 3: depth = 2 + mean over channels of the normalised image;
* moge 2: points = (0, 0, 2 - mean over channels of the image), mask = 1.

Usage: .venv/bin/python scripts/make_model_fixtures.py --out fixtures/models
(needs PyPI onnx and numpy; scripts/requirements.txt).
"""

import argparse
import hashlib
import os

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17


def const(name, array):
    return numpy_helper.from_array(np.asarray(array), name)


def save(graph, path):
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="dm-fixture")
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, path)
    digest = hashlib.sha256(open(path, "rb").read()).hexdigest()
    print(f"{path}: {os.path.getsize(path)} bytes, sha256 {digest}")


def pooled_mean(inp, pool, channels, out, nodes, inits):
    """AveragePool(pool) then a 1x1 conv averaging the 3 input channels into `channels`."""
    nodes.append(helper.make_node("AveragePool", [inp], [out + "_pool"], kernel_shape=[pool, pool], strides=[pool, pool]))
    inits.append(const(out + "_w", np.full((channels, 3, 1, 1), 1.0 / 3.0, np.float32)))
    nodes.append(helper.make_node("Conv", [out + "_pool", out + "_w"], [out]))


def sam2_encoder(path):
    nodes, inits = [], []
    pooled_mean("image", 16, 256, "image_embed", nodes, inits)
    pooled_mean("image", 4, 32, "high_res_feats_0", nodes, inits)
    pooled_mean("image", 8, 64, "high_res_feats_1", nodes, inits)
    graph = helper.make_graph(
        nodes,
        "sam2_encoder_fixture",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 1024, 1024])],
        [
            helper.make_tensor_value_info("high_res_feats_0", TensorProto.FLOAT, [1, 32, 256, 256]),
            helper.make_tensor_value_info("high_res_feats_1", TensorProto.FLOAT, [1, 64, 128, 128]),
            helper.make_tensor_value_info("image_embed", TensorProto.FLOAT, [1, 256, 64, 64]),
        ],
        inits,
    )
    save(graph, path)


def sam2_decoder(path):
    nodes, inits = [], []
    # Feature mean over the 32 channels of the 256x256 map.
    nodes.append(helper.make_node("ReduceMean", ["high_res_feats_0"], ["feat"], axes=[1], keepdims=1))  # (1,1,256,256)
    inits.append(const("threshold", np.array(0.0, np.float32)))
    inits.append(const("gain", np.array(8.0, np.float32)))
    nodes.append(helper.make_node("Sub", ["feat", "threshold"], ["centred"]))
    nodes.append(helper.make_node("Mul", ["centred", "gain"], ["logit_in"]))
    # Bounding box of the prompt points (1024-pixel input frame).
    nodes.append(helper.make_node("ReduceMin", ["point_coords"], ["pmin"], axes=[1], keepdims=0))  # (L,2)
    nodes.append(helper.make_node("ReduceMax", ["point_coords"], ["pmax"], axes=[1], keepdims=0))
    centres = (np.arange(256, dtype=np.float32) + 0.5) * 4.0
    inits.append(const("grid_x", centres.reshape(1, 1, 1, 256)))
    inits.append(const("grid_y", centres.reshape(1, 1, 256, 1)))
    inits.append(const("idx0", np.array([0], np.int64)))
    inits.append(const("idx1", np.array([1], np.int64)))
    inits.append(const("shape4", np.array([-1, 1, 1, 1], np.int64)))
    for corner in ("pmin", "pmax"):
        for axis, idx in (("x", "idx0"), ("y", "idx1")):
            nodes.append(helper.make_node("Gather", [corner, idx], [f"{corner}_{axis}_g"], axis=1))
            nodes.append(helper.make_node("Reshape", [f"{corner}_{axis}_g", "shape4"], [f"{corner}_{axis}"]))
    conditions = []
    for axis in ("x", "y"):
        nodes.append(helper.make_node("GreaterOrEqual", [f"grid_{axis}", f"pmin_{axis}"], [f"ge_{axis}"]))
        nodes.append(helper.make_node("LessOrEqual", [f"grid_{axis}", f"pmax_{axis}"], [f"le_{axis}"]))
        conditions += [f"ge_{axis}", f"le_{axis}"]
    nodes.append(helper.make_node("And", conditions[0:2], ["in_x"]))
    nodes.append(helper.make_node("And", conditions[2:4], ["in_y"]))
    nodes.append(helper.make_node("And", ["in_x", "in_y"], ["inside"]))  # (L,1,256,256)
    inits.append(const("outside", np.array(-8.0, np.float32)))
    nodes.append(helper.make_node("Where", ["inside", "logit_in", "outside"], ["masks"]))
    # One candidate per label; its score is the mean sigmoid inside the box.
    nodes.append(helper.make_node("Sigmoid", ["masks"], ["prob"]))
    nodes.append(helper.make_node("ReduceMean", ["prob"], ["iou_predictions"], axes=[2, 3], keepdims=0))  # (L,1)
    # image_embed, high_res_feats_1, point_labels, mask_input and
    # has_mask_input are unused here but stay graph inputs (the signature).
    graph = helper.make_graph(
        nodes,
        "sam2_decoder_fixture",
        [
            helper.make_tensor_value_info("image_embed", TensorProto.FLOAT, [1, 256, 64, 64]),
            helper.make_tensor_value_info("high_res_feats_0", TensorProto.FLOAT, [1, 32, 256, 256]),
            helper.make_tensor_value_info("high_res_feats_1", TensorProto.FLOAT, [1, 64, 128, 128]),
            helper.make_tensor_value_info("point_coords", TensorProto.FLOAT, ["num_labels", "num_points", 2]),
            helper.make_tensor_value_info("point_labels", TensorProto.FLOAT, ["num_labels", "num_points"]),
            helper.make_tensor_value_info("mask_input", TensorProto.FLOAT, ["num_labels", 1, 256, 256]),
            helper.make_tensor_value_info("has_mask_input", TensorProto.FLOAT, ["num_labels"]),
        ],
        [
            helper.make_tensor_value_info("masks", TensorProto.FLOAT, ["num_labels", "num_masks", 256, 256]),
            helper.make_tensor_value_info("iou_predictions", TensorProto.FLOAT, ["num_labels", "num_masks"]),
        ],
        inits,
    )
    save(graph, path)


def cotracker3(path):
    nodes, inits = [], []
    nodes.append(helper.make_node("ReduceMean", ["video"], ["frame_mean"], axes=[2, 3, 4], keepdims=0))  # (1,T)
    inits.append(const("first", np.array([0], np.int64)))
    nodes.append(helper.make_node("Gather", ["frame_mean", "first"], ["mean0"], axis=1))  # (1,1)
    nodes.append(helper.make_node("Sub", ["frame_mean", "mean0"], ["shift"]))  # (1,T)
    inits.append(const("shift_shape", np.array([1, -1, 1, 1], np.int64)))
    nodes.append(helper.make_node("Reshape", ["shift", "shift_shape"], ["shift4"]))  # (1,T,1,1)
    inits.append(const("x_only", np.array([1.0, 0.0], np.float32)))
    nodes.append(helper.make_node("Mul", ["shift4", "x_only"], ["shift_xy"]))  # (1,T,1,2)
    inits.append(const("xy_start", np.array([1], np.int64)))
    inits.append(const("xy_end", np.array([3], np.int64)))
    inits.append(const("last_axis", np.array([2], np.int64)))
    nodes.append(helper.make_node("Slice", ["queries", "xy_start", "xy_end", "last_axis"], ["query_xy"]))  # (1,N,2)
    inits.append(const("q_shape", np.array([1, 1, -1, 2], np.int64)))
    nodes.append(helper.make_node("Reshape", ["query_xy", "q_shape"], ["query_xy4"]))  # (1,1,N,2)
    nodes.append(helper.make_node("Add", ["query_xy4", "shift_xy"], ["tracks"]))  # (1,T,N,2)
    inits.append(const("occluded_above", np.array(200.0, np.float32)))
    nodes.append(helper.make_node("Less", ["frame_mean", "occluded_above"], ["visible_t"]))
    nodes.append(helper.make_node("Cast", ["visible_t"], ["visible_f"], to=TensorProto.FLOAT))
    inits.append(const("v_shape", np.array([1, -1, 1], np.int64)))
    nodes.append(helper.make_node("Reshape", ["visible_f", "v_shape"], ["visible3"]))  # (1,T,1)
    # Broadcast over the N queries: zeros shaped like the x coordinates.
    inits.append(const("x_start", np.array([1], np.int64)))
    inits.append(const("x_end", np.array([2], np.int64)))
    nodes.append(helper.make_node("Slice", ["queries", "x_start", "x_end", "last_axis"], ["qx"]))  # (1,N,1)
    inits.append(const("zero", np.array(0.0, np.float32)))
    nodes.append(helper.make_node("Mul", ["qx", "zero"], ["qzero"]))
    inits.append(const("n_shape", np.array([1, 1, -1], np.int64)))
    nodes.append(helper.make_node("Reshape", ["qzero", "n_shape"], ["zeros_n"]))  # (1,1,N)
    nodes.append(helper.make_node("Add", ["visible3", "zeros_n"], ["visibility"]))  # (1,T,N)
    graph = helper.make_graph(
        nodes,
        "cotracker3_fixture",
        [
            helper.make_tensor_value_info("video", TensorProto.FLOAT, [1, "num_frames", 3, 384, 512]),
            helper.make_tensor_value_info("queries", TensorProto.FLOAT, [1, "num_queries", 3]),
        ],
        [
            helper.make_tensor_value_info("tracks", TensorProto.FLOAT, [1, "num_frames", "num_queries", 2]),
            helper.make_tensor_value_info("visibility", TensorProto.FLOAT, [1, "num_frames", "num_queries"]),
        ],
        inits,
    )
    save(graph, path)


def depth_anything3(path):
    nodes, inits = [], []
    nodes.append(helper.make_node("ReduceMean", ["image"], ["mean"], axes=[1], keepdims=0))  # (1,H,W)
    inits.append(const("two", np.array(2.0, np.float32)))
    nodes.append(helper.make_node("Add", ["mean", "two"], ["depth"]))
    graph = helper.make_graph(
        nodes,
        "depth_anything3_fixture",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 504, 504])],
        [helper.make_tensor_value_info("depth", TensorProto.FLOAT, [1, 504, 504])],
        inits,
    )
    save(graph, path)


def moge2(path):
    nodes, inits = [], []
    nodes.append(helper.make_node("ReduceMean", ["image"], ["mean"], axes=[1], keepdims=1))  # (1,1,H,W)
    inits.append(const("two", np.array(2.0, np.float32)))
    nodes.append(helper.make_node("Sub", ["two", "mean"], ["z"]))
    inits.append(const("zero", np.array(0.0, np.float32)))
    nodes.append(helper.make_node("Mul", ["mean", "zero"], ["zeros"]))
    nodes.append(helper.make_node("Concat", ["zeros", "zeros", "z"], ["xyz"], axis=1))  # (1,3,H,W)
    nodes.append(helper.make_node("Transpose", ["xyz"], ["points"], perm=[0, 2, 3, 1]))
    inits.append(const("one", np.array(1.0, np.float32)))
    nodes.append(helper.make_node("Add", ["zeros", "one"], ["ones"]))
    inits.append(const("squeeze_axis", np.array([1], np.int64)))
    nodes.append(helper.make_node("Squeeze", ["ones", "squeeze_axis"], ["mask"]))
    graph = helper.make_graph(
        nodes,
        "moge2_fixture",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "height", "width"])],
        [
            helper.make_tensor_value_info("points", TensorProto.FLOAT, [1, "height", "width", 3]),
            helper.make_tensor_value_info("mask", TensorProto.FLOAT, [1, "height", "width"]),
        ],
        inits,
    )
    save(graph, path)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="fixtures/models")
    args = parser.parse_args()
    os.makedirs(args.out, exist_ok=True)
    sam2_encoder(os.path.join(args.out, "sam2.1_hiera_tiny.encoder.onnx"))
    sam2_decoder(os.path.join(args.out, "sam2.1_hiera_tiny.decoder.onnx"))
    cotracker3(os.path.join(args.out, "cotracker3_offline.onnx"))
    depth_anything3(os.path.join(args.out, "da3_small.onnx"))
    moge2(os.path.join(args.out, "moge2_vits_normal.onnx"))


if __name__ == "__main__":
    main()
