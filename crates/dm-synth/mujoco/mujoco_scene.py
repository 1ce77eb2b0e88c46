#!/usr/bin/env python3
"""Simulates one foreign-physics scene with MuJoCo.

Usage: mujoco_scene.py DIR
       mujoco_scene.py DIR --serve HANDS HOLD_RADIUS_M

Reads DIR/request.json (written by dm-synth --engine mujoco: the object's
flex mesh, material, hands, hidden effect and the truth particles' rest
positions), simulates the object as a MuJoCo flex held by mocap hands
through equality constraints, and writes

  DIR/cloud_frames.npy   (T, N, 3) float32: every truth particle per frame,
                         carried by the flex element it lies in at rest
  DIR/vertex_frames.npy  (T, V, 3) float32: the flex vertices per frame
  DIR/result.json        engine version, step, wall time

Progress goes to stderr as "frame K/T" lines. Exit 1 with a message on
stderr when the simulation diverges.

With --serve the scene is a plant stepped on request: after the settling
frames (no grip held), each line on stdin is a JSON command and each gets
one JSON line on stdout, {"ok": true} or {"ok": false, "error": ...}:

  {"op": "replay", "frame": t}   the scripted hands' frame t -> t + 1; they
                                 grip their vertices on the first replay
  {"op": "step", "from": [[x, y, z], ...], "to": [...], "grasp": [b, ...]}
                                 one frame of HANDS planned hands moving
                                 linearly; a hand marked in grasp lets go and
                                 grips every vertex within HOLD_RADIUS_M (the
                                 scripted hands let go at the first step)
  {"op": "free"}                 one frame with the hands as they are
  {"op": "release"}              every grip let go
  {"op": "state"}                the answer line has "particles": N and is
                                 followed by N x 3 float32 positions, then
                                 N x 3 float32 velocities (over the last
                                 frame), little-endian
  {"op": "quit"}
"""

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

try:
    import mujoco
except ImportError:
    sys.stderr.write("error: this Python cannot import mujoco (pip install 'mujoco>=3.3')\n")
    sys.exit(3)


def flex_xml(req, planned_hands=0):
    """The MJCF model: floor, mocap hands, the flex and the grips. With
    planned hands (a plant), every grip starts let go and each planned hand
    has a grip on every vertex, let go until it grasps."""
    dim = req["dim"]
    verts = np.asarray(req["vertices"], dtype=np.float64)
    elems = np.asarray(req["elements"], dtype=np.int64)
    point = " ".join(f"{c:.6f}" for c in verts.ravel())
    element = " ".join(str(i) for i in elems.ravel())
    mu = req["floor_friction"]
    # Frictionless floor unless the scene hides floor friction: the world
    # model's own floor slips, so a null scene carries no friction.
    contact = (
        f'condim="3" friction="{mu} 0.005 0.0001"' if mu > 0 else 'condim="1"'
    )
    if dim == 1:
        edges = '<edge equality="true" solref="0.004 1"/>'
        elastic = ""
    else:
        edges = ""
        elastic = ' elastic2d="both"' if dim == 2 else ""
    thickness = f' thickness="{req["thickness"]}"' if dim == 2 else ""
    g = " ".join(f"{c:.9f}" for c in req["gravity"])
    dt = 1.0 / req["fps"] / req["substeps_per_frame"]
    hands = "\n".join(
        f'<body name="hand{k}" mocap="true" pos="{h["grasp"][0]:.6f} {h["grasp"][1]:.6f} {h["grasp"][2]:.6f}"/>'
        for k, h in enumerate(req["hands"])
    )
    active = ' active="false"' if planned_hands else ""
    grips = []
    for k, h in enumerate(req["hands"]):
        for v in h["held_vertices"]:
            a = verts[v] - np.asarray(h["grasp"])
            grips.append(
                f'<connect name="grip{k}_{v}" body1="hand{k}" body2="object_{v}" anchor="{a[0]:.6f} {a[1]:.6f} {a[2]:.6f}" solref="0.004 1"{active}/>'
            )
    # Planned hands rest far above until they grasp.
    hands += "".join(
        f'\n<body name="plan{k}" mocap="true" pos="0 0 10"/>' for k in range(planned_hands)
    )
    for k in range(planned_hands):
        for v in range(len(verts)):
            grips.append(
                f'<connect name="plan{k}_{v}" body1="plan{k}" body2="object_{v}" anchor="0 0 0" solref="0.004 1" active="false"/>'
            )
    return f"""
<mujoco model="dm-synth foreign scene">
  <option timestep="{dt:.9f}" gravity="{g}" integrator="discrete"/>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1" pos="0 0 {req["floor_height"]}" {contact}/>
    {hands}
    <flexcomp name="object" type="direct" dim="{dim}" radius="{req["radius"]}" point="{point}" element="{element}" mass="{req["mass_kg"]}">
      {edges}
      <elasticity young="{req["young_pa"]}" poisson="{req["poisson"]}" damping="{req["damping_s"]}"{thickness}{elastic}/>
      <contact {contact} selfcollide="none"/>
    </flexcomp>
  </worldbody>
  <equality>
    {chr(10).join(grips)}
  </equality>
</mujoco>
"""


def apply_mass_and_drag(model, req):
    """Per-vertex mass factors (a density gradient) and linear air drag as
    world-frame damping on each vertex's slide joints (force -c m v)."""
    factors = req.get("vertex_mass_factors")
    drag = req["air_drag_per_s"]
    flex_bodies = model.flex_vertbodyid[: model.flex_vertnum[0]]
    for v, b in enumerate(flex_bodies):
        if factors is not None:
            model.body_mass[b] *= factors[v]
            model.body_inertia[b] *= factors[v]
        if drag > 0:
            for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]):
                if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE:
                    model.dof_damping[model.jnt_dofadr[j]] = drag * model.body_mass[b]
    if factors is not None:
        mujoco.mj_setConst(model, mujoco.MjData(model))


class Embedding:
    """Each truth particle as a fixed combination of flex vertices (the
    element that holds it at rest), plus for shells and ropes an offset
    carried by the element's current orientation."""

    def __init__(self, dim, verts, elems, points):
        self.dim, self.elems = dim, elems
        if dim == 3:
            self.elem, self.bary = self._in_tets(verts, elems, points)
        elif dim == 2:
            self.elem, self.bary, self.offset = self._on_triangles(verts, elems, points)
        else:
            self.elem, self.s, self.offset, self.rest_tangent = self._on_segments(verts, elems, points)

    @staticmethod
    def _best(points, count, width, bary_of):
        """The element whose smallest barycentric weight is largest (the
        one containing the point, or the nearest by that measure)."""
        best = np.full(len(points), -np.inf)
        elem = np.zeros(len(points), dtype=np.int64)
        bary = np.zeros((len(points), width))
        for start in range(0, count, 256):
            ids = np.arange(start, min(count, start + 256))
            b = bary_of(ids)  # (P, E, k)
            score = b.min(axis=2)
            k = score.argmax(axis=1)
            s = score[np.arange(len(points)), k]
            better = s > best
            best[better] = s[better]
            elem[better] = ids[k[better]]
            bary[better] = b[np.arange(len(points)), k][better]
        return elem, bary

    def _in_tets(self, verts, tets, points):
        v0 = verts[tets[:, 0]]
        m = np.stack([verts[tets[:, i]] - v0 for i in (1, 2, 3)], axis=2)  # (E,3,3) columns
        inv = np.linalg.inv(m)

        def bary_of(ids):
            d = points[:, None, :] - v0[None, ids]
            l = np.einsum("eij,pej->pei", inv[ids], d)
            return np.concatenate([1.0 - l.sum(axis=2, keepdims=True), l], axis=2)

        return self._best(points, len(tets), 4, bary_of)

    def _on_triangles(self, verts, tris, points):
        a = verts[tris[:, 0], :2]
        m = np.stack([verts[tris[:, i], :2] - a for i in (1, 2)], axis=2)
        inv = np.linalg.inv(m)

        def bary_of(ids):
            d = points[:, None, :2] - a[None, ids]
            l = np.einsum("eij,pej->pei", inv[ids], d)
            return np.concatenate([1.0 - l.sum(axis=2, keepdims=True), l], axis=2)

        elem, bary = self._best(points, len(tris), 3, bary_of)
        mid = np.einsum("pk,pkc->pc", bary, verts[tris[elem]])
        offset = points[:, 2] - mid[:, 2]
        return elem, bary, offset

    def _on_segments(self, verts, segs, points):
        a, b = verts[segs[:, 0]], verts[segs[:, 1]]
        ab = b - a
        t = np.einsum("pec,ec->pe", points[:, None, :] - a[None], ab) / (ab * ab).sum(axis=1)
        t = np.clip(t, 0.0, 1.0)
        closest = a[None] + t[..., None] * ab[None]
        dist = np.linalg.norm(points[:, None, :] - closest, axis=2)
        elem = dist.argmin(axis=1)
        idx = np.arange(len(points))
        s = t[idx, elem]
        offset = points - closest[idx, elem]
        tangent = ab[elem] / np.linalg.norm(ab[elem], axis=1, keepdims=True)
        return elem, s, offset, tangent

    def positions(self, verts):
        e = self.elems[self.elem]
        if self.dim == 3:
            return np.einsum("pk,pkc->pc", self.bary, verts[e])
        if self.dim == 2:
            tri = verts[e]
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
            return np.einsum("pk,pkc->pc", self.bary, tri) + self.offset[:, None] * normal
        a, b = verts[e[:, 0]], verts[e[:, 1]]
        tangent = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
        return a + self.s[:, None] * (b - a) + rotate_between(self.rest_tangent, tangent, self.offset)


def rotate_between(u, w, x):
    """Rotates each x by the smallest rotation taking unit u onto unit w."""
    axis = np.cross(u, w)
    c = (u * w).sum(axis=1, keepdims=True)
    # Rodrigues with k = axis (|k| = sin): x c + k × x + k (k·x) / (1 + c).
    kx = np.cross(axis, x)
    kdotx = (axis * x).sum(axis=1, keepdims=True)
    return x * c + kx + axis * kdotx / np.maximum(1.0 + c, 1e-9)


def hand_pose(pose):
    """Mocap position and quaternion of a [x, y, z, twist_rad] pose."""
    x, y, z, a = pose
    return np.array([x, y, z]), np.array([np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)])


def main():
    if len(sys.argv) == 5 and sys.argv[2] == "--serve":
        return serve(Path(sys.argv[1]), int(sys.argv[3]), float(sys.argv[4]))
    if len(sys.argv) != 2:
        sys.stderr.write(__doc__)
        return 2
    root = Path(sys.argv[1])
    req = json.loads((root / "request.json").read_text())
    model = mujoco.MjModel.from_xml_string(flex_xml(req))
    apply_mass_and_drag(model, req)
    data = mujoco.MjData(model)
    verts0 = np.asarray(req["vertices"], dtype=np.float64)
    elems = np.asarray(req["elements"], dtype=np.int64)
    cloud = np.asarray(req["cloud_rest"], dtype=np.float64)
    embedding = Embedding(req["dim"], verts0, elems, cloud)
    hands = req["hands"]
    frames, settle, substeps = req["frames"], req["settle_frames"], req["substeps_per_frame"]
    poses = [np.asarray(h["poses"], dtype=np.float64) for h in hands]

    def set_hands(frame, frac):
        for k, p in enumerate(poses):
            a = p[min(frame, len(p) - 1)]
            b = p[min(frame + 1, len(p) - 1)]
            pos, quat = hand_pose(a + frac * (b - a))
            data.mocap_pos[k] = pos
            data.mocap_quat[k] = quat

    start = time.time()
    set_hands(0, 0.0)
    mujoco.mj_forward(model, data)
    nv = model.flex_vertnum[0]
    vertex_frames = np.zeros((frames, nv, 3), dtype=np.float32)
    cloud_frames = np.zeros((frames, len(cloud), 3), dtype=np.float32)
    total = settle + frames - 1
    done = 0

    def step_frame(frame, moving):
        """One recorded frame of substeps; the hands hold still while settling."""
        nonlocal done
        for s in range(substeps):
            set_hands(frame, (s + 1) / substeps if moving else 0.0)
            mujoco.mj_step(model, data)
        verts = data.flexvert_xpos[:nv]
        if not np.all(np.isfinite(verts)) or np.abs(verts).max() > 100.0:
            sys.stderr.write(f"error: the MuJoCo simulation diverged in frame {frame}\n")
            sys.exit(1)
        done += 1
        sys.stderr.write(f"frame {done}/{total}\n")

    for _ in range(settle):
        step_frame(0, moving=False)
    for t in range(frames):
        if t > 0:
            step_frame(t - 1, moving=True)
        verts = np.array(data.flexvert_xpos[:nv])
        vertex_frames[t] = verts
        cloud_frames[t] = embedding.positions(verts)
    np.save(root / "cloud_frames.npy", cloud_frames)
    np.save(root / "vertex_frames.npy", vertex_frames)
    result = {
        "engine": "mujoco",
        "version": mujoco.__version__,
        "timestep_s": float(model.opt.timestep),
        "steps": int((settle + frames - 1) * substeps),
        "seconds": time.time() - start,
        "mass_kg": float(sum(model.body_mass[b] for b in model.flex_vertbodyid[:nv])),
        # MuJoCo's own warnings (ill-conditioned solves and the like), summed.
        "warnings": int(sum(w.number for w in data.warning)),
    }
    (root / "result.json").write_text(json.dumps(result, indent=1))
    return 0


class Plant:
    """The scene as a plant: MuJoCo stepped a frame per command."""

    def __init__(self, req, planned_hands, hold_radius):
        self.model = mujoco.MjModel.from_xml_string(flex_xml(req, planned_hands))
        apply_mass_and_drag(self.model, req)
        # A diverging step must stay diverged (reported), not reset to rest.
        self.model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)
        self.data = mujoco.MjData(self.model)
        self.req, self.hold_radius = req, hold_radius
        self.nv = self.model.flex_vertnum[0]
        verts0 = np.asarray(req["vertices"], dtype=np.float64)
        cloud = np.asarray(req["cloud_rest"], dtype=np.float64)
        self.embedding = Embedding(req["dim"], verts0, np.asarray(req["elements"], dtype=np.int64), cloud)
        self.poses = [np.asarray(h["poses"], dtype=np.float64) for h in req["hands"]]
        self.substeps = req["substeps_per_frame"]
        self.frame_dt = 1.0 / req["fps"]
        self.vertex_body = self.model.flex_vertbodyid[: self.nv]
        body = lambda name: mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, name)
        self.scripted_mocap = [self.model.body_mocapid[body(f"hand{k}")] for k in range(len(self.poses))]
        self.planned_body = [body(f"plan{k}") for k in range(planned_hands)]
        self.planned_mocap = [self.model.body_mocapid[b] for b in self.planned_body]
        equality = lambda name: mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_EQUALITY, name)
        self.scripted_grips = [
            (body(f"hand{k}"), [equality(f"grip{k}_{v}") for v in h["held_vertices"]], h["held_vertices"])
            for k, h in enumerate(req["hands"])
        ]
        # Each planned hand's grip on every vertex.
        self.planned_grips = [
            [equality(f"plan{k}_{v}") for v in range(self.nv)] for k in range(planned_hands)
        ]
        self.scripted_held = False
        self.set_scripted(0, 0.0)
        mujoco.mj_forward(self.model, self.data)
        self.current = self.cloud()
        self.previous = self.current
        for _ in range(req["settle_frames"]):
            self.frame(lambda frac: None)

    def set_scripted(self, frame, frac):
        for k, p in enumerate(self.poses):
            a = p[min(frame, len(p) - 1)]
            b = p[min(frame + 1, len(p) - 1)]
            pos, quat = hand_pose(a + frac * (b - a))
            self.data.mocap_pos[self.scripted_mocap[k]] = pos
            self.data.mocap_quat[self.scripted_mocap[k]] = quat

    def cloud(self):
        return self.embedding.positions(np.array(self.data.flexvert_xpos[: self.nv]))

    def grip(self, hand_body, eq_ids, vertices):
        """Holds `vertices` where they are now, relative to the hand
        (positions brought up to date first)."""
        mujoco.mj_forward(self.model, self.data)
        hand_x, hand_r = self.data.xpos[hand_body], self.data.xmat[hand_body].reshape(3, 3)
        for eq, v in zip(eq_ids, vertices):
            b = self.vertex_body[v]
            x = self.data.flexvert_xpos[v]
            self.model.eq_data[eq, 0:3] = hand_r.T @ (x - hand_x)
            self.model.eq_data[eq, 3:6] = self.data.xmat[b].reshape(3, 3).T @ (x - self.data.xpos[b])
            self.data.eq_active[eq] = 1

    def let_go(self, eq_ids):
        for eq in eq_ids:
            self.data.eq_active[eq] = 0

    def frame(self, move):
        """One frame: `move(frac)` places the hands at each substep."""
        for s in range(self.substeps):
            move((s + 1) / self.substeps)
            mujoco.mj_step(self.model, self.data)
        verts = self.data.flexvert_xpos[: self.nv]
        bad = sum(
            self.data.warning[int(w)].number
            for w in (mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL, mujoco.mjtWarning.mjWARN_BADQACC)
        )
        if bad or not np.all(np.isfinite(verts)) or np.abs(verts).max() > 100.0:
            raise RuntimeError("the MuJoCo simulation diverged")
        self.previous, self.current = self.current, self.cloud()

    def replay(self, t):
        if not self.scripted_held:
            self.set_scripted(t, 0.0)
            for body, ids, vertices in self.scripted_grips:
                self.grip(body, ids, vertices)
            self.scripted_held = True
        self.frame(lambda frac: self.set_scripted(t, frac))

    def release(self):
        for _, ids, _ in self.scripted_grips:
            self.let_go(ids)
        for ids in self.planned_grips:
            self.let_go(ids)
        self.scripted_held = False

    def step(self, start, end, grasp):
        start, end = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
        if len(start) != len(self.planned_body) or len(end) != len(start) or len(grasp) != len(start):
            raise ValueError(f"a step needs {len(self.planned_body)} hands in from, to and grasp")
        if self.scripted_held:
            for _, ids, _ in self.scripted_grips:
                self.let_go(ids)
            self.scripted_held = False
        for k, body in enumerate(self.planned_body):
            self.data.mocap_pos[self.planned_mocap[k]] = start[k]
            if grasp[k]:
                self.let_go(self.planned_grips[k])
                mujoco.mj_forward(self.model, self.data)
                near = np.linalg.norm(self.data.flexvert_xpos[: self.nv] - start[k], axis=1)
                held = np.flatnonzero(near < self.hold_radius)
                if len(held) == 0:
                    held = [int(near.argmin())]
                self.grip(body, [self.planned_grips[k][v] for v in held], held)

        def move(frac):
            for k in range(len(self.planned_body)):
                self.data.mocap_pos[self.planned_mocap[k]] = start[k] + frac * (end[k] - start[k])

        self.frame(move)

    def state(self):
        velocity = (self.current - self.previous) / self.frame_dt
        return self.current.astype("<f4"), velocity.astype("<f4")


def serve(root, planned_hands, hold_radius):
    req = json.loads((root / "request.json").read_text())
    # The answers get the process's stdout to themselves: MuJoCo's C code
    # prints its warnings to file descriptor 1, which now goes to stderr.
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = sys.stderr

    def answer(header, payload=b""):
        out.write((json.dumps(header) + "\n").encode())
        out.write(payload)
        out.flush()

    try:
        plant = Plant(req, planned_hands, hold_radius)
    except Exception as e:  # the model did not build or settle
        sys.stderr.write(f"error: {e}\n")
        return 1
    answer({"ok": True, "particles": len(req["cloud_rest"])})
    for line in sys.stdin:
        try:
            command = json.loads(line)
            op = command["op"]
            if op == "quit":
                answer({"ok": True})
                return 0
            if op == "state":
                x, v = plant.state()
                answer({"ok": True, "particles": len(x)}, x.tobytes() + v.tobytes())
                continue
            if op == "replay":
                plant.replay(int(command["frame"]))
            elif op == "step":
                plant.step(command["from"], command["to"], command["grasp"])
            elif op == "free":
                plant.frame(lambda frac: None)
            elif op == "release":
                plant.release()
            else:
                raise ValueError(f"unknown op {op!r}")
            answer({"ok": True})
        except Exception as e:
            answer({"ok": False, "error": f"{type(e).__name__}: {e}"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
