"""DeformMaster from Python: scene bundles as NumPy arrays, fitted world
models fitted and stepped frame by frame, renders, per-frame metrics and
planning.

    import deformmaster as dm
    bundle = dm.read_bundle("out/demo/scene")
    model = dm.load_model("out/demo/model")
    sim = model.simulation(bundle.hand_anchors(0))
    for t in range(1, bundle.frame_count):
        sim.step(bundle.hand_anchors(t))
    print(sim.positions.shape)

The physics runs in Rust (the same code as the command-line tools) with
the GIL released. Errors are ``DeformMasterError`` subclasses whose
message names the file and field at fault. The Gymnasium environment is
``deformmaster.env.TwinEnv``. API reference: docs/python.md.
"""

import json as _json

import numpy as _np

from ._native import (
    Bundle,
    BundleError,
    DeformMasterError,
    Model,
    ModelError,
    Simulation,
    SimulationError,
    __version__,
    load_model,
    look_at,
    read_bundle,
    split_frames,
)
from ._native import fit_from_args as _fit_from_args
from ._native import flags as _flags
from ._native import plan_from_args as _plan_from_args
from ._native import write_bundle_arrays as _write_bundle_arrays

__all__ = [
    "Bundle",
    "BundleError",
    "DeformMasterError",
    "Model",
    "ModelError",
    "Simulation",
    "SimulationError",
    "__version__",
    "fit",
    "load_model",
    "look_at",
    "plan",
    "read_bundle",
    "split_frames",
    "write_bundle",
]

_TRACK_TYPES = {
    "object_points": _np.float32,
    "object_visibility": _np.bool_,
    "object_motion_valid": _np.bool_,
    "hand_points": _np.float32,
    "hand_visibility": _np.bool_,
}
_PARTICLE_TYPES = {
    "surface_points": _np.float32,
    "surface_colors": _np.float32,
    "interior_points": _np.float32,
    "interior_colors": _np.float32,
}
_IMAGE_TYPES = {
    "rgb": _np.uint8,
    "depth": _np.float32,
    "mask_object": _np.bool_,
    "mask_hand": _np.bool_,
}


def _typed(arrays, types, where):
    missing = [k for k in types if k not in arrays]
    if missing:
        raise BundleError(f"{where}: missing {', '.join(missing)}")
    return {
        k: _np.ascontiguousarray(_np.asarray(arrays[k]).astype(t, copy=False))
        for k, t in types.items()
    }


def write_bundle(path, meta, tracks, particles, images, overwrite=False):
    """Writes a scene bundle (docs/bundle.md) and returns it read back.

    ``meta`` is bundle.json as a dict; ``tracks`` and ``particles`` are
    dicts of arrays keyed as ``Bundle.tracks`` and ``Bundle.particles``;
    ``images`` has one dict per camera keyed as ``Bundle.images(camera)``
    (rgb, depth in metres with NaN for none, mask_object, mask_hand). The
    bundle is written under a temporary name, validated, then renamed; an
    existing ``path`` is replaced only with ``overwrite=True``.
    """
    tracks = _typed(tracks, _TRACK_TYPES, "tracks")
    particles = _typed(particles, _PARTICLE_TYPES, "particles")
    images = [
        _typed(camera, _IMAGE_TYPES, f"images[{i}]") for i, camera in enumerate(images)
    ]
    return _write_bundle_arrays(
        str(path),
        _json.dumps(meta),
        images=images,
        overwrite=overwrite,
        **tracks,
        **particles,
    )


def _path_of(value, attribute):
    """A path argument given as a path or as the object loaded from it."""
    found = getattr(value, attribute, value)
    if found is None:
        raise ValueError(f"{value!r} was not loaded from a directory; give its path")
    return str(found)


def plan(model, bundle, goal, out=None, progress=None, **options):
    """Plans hand motions that bring the object to ``goal`` and carries them
    out, as ``dm-plan`` does (docs/plan.md), in this process.

    ``model`` is a dm-fit model directory (or a ``Model`` loaded from one),
    ``bundle`` the scene's bundle (or a ``Bundle``); ``goal`` a named shape
    (``"place"``, ``"straighten"``, ...), ``"frame:T"`` or a PLY file.
    Every other dm-plan option is a keyword with ``_`` for ``-``
    (``horizon=60``, ``plant="truth.json"``, ``device="cuda"``; a flag is
    ``True``). ``out`` also writes dm-plan's files there (no video);
    ``progress(stage, done, total)`` is called as the run goes; an
    exception it raises, or Ctrl-C, stops the run and is raised.

    Returns a dict: ``record`` (plan.json), ``hands`` (T, H, 3) anchors
    carried out, ``planned`` and ``executed`` (T, N, 3) float32 particle
    positions in the planning world and the plant, ``goal`` (G, 3) and
    ``frame_dt`` seconds.
    """
    args = [
        _path_of(model, "directory"),
        "--bundle",
        _path_of(bundle, "path"),
        "--goal",
        str(goal),
        # dm-plan's parser asks for --out; the run writes only where `out` says.
        "--out",
        str(out) if out is not None else "-",
    ]
    args += _flags(options)
    return _plan_from_args(args, out=None if out is None else str(out), progress=progress)


def fit(bundle, out, resume=False, stop_after=None, progress=None, **options):
    """Fits a world model to a scene as ``dm-fit`` does (docs/fit.md), in
    this process: writes the model directory ``out``, checkpointed after
    every step, and returns fit_report.json as a dict
    (``load_model(out)`` loads the model).

    ``bundle`` is the scene's bundle (a path or a ``Bundle``). Every dm-fit
    option is a keyword with ``_`` for ``-`` (``iters=3``,
    ``residual="none"``, ``device="cuda"``; a flag is ``True``).
    ``progress(message)`` gets dm-fit's progress lines. Ctrl-C, or an
    exception ``progress`` raises, pauses the fit after the step it is in
    and is raised; ``resume=True`` continues from the checkpoint.
    ``stop_after=n`` pauses after n steps and returns None.
    """
    return _fit_from_args(
        _path_of(bundle, "path"),
        str(out),
        _flags(options),
        resume=resume,
        stop_after=stop_after,
        progress=progress,
    )
