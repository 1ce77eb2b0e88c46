#!/usr/bin/env python3
"""The reference MLS-MPM block (crates/dm-mpm/src/scenes.rs, `bench_block`)
in NVIDIA Warp and Taichi on the CPU, timed like `dm-bench mpm` and
`dm-bench grad`, so the three can be compared on one machine.

Prints one JSON line on stdout per run (see README.md beside this file);
`--check` adds a JSON line on stderr showing that the block falls and
deforms. `--peer deformmaster` runs the built `dm-bench` binary with the
same arguments and prints its result in the same JSON form.
"""

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time

# ---- the scene (bench_block) ------------------------------------------------

DT = 8e-4
GRAVITY = -9.8
YOUNGS = 400.0
POISSON = 0.2
DENSITY = 1.0
WALL_CELLS = 3
CLIP = (0.05, 0.95)
SVD_CLAMP = (0.5, 2.0)
EMPTY_NODE_MASS_RATIO = 1e-4
GRID_DAMPING = 1.0  # 0.999 per 8e-4 s in the product; the block runs undamped
LO = (0.35, 0.15, 0.35)
CENTRE = (0.5, 0.3, 0.5)
SPIN, SQUEEZE = 2.0, 1.0
WARMUP = 20
EXPERT_WEIGHTS = {"nh": (1.0, 0.0, 0.0), "moce": (0.5, 0.3, 0.2)}


def initial_state(n, seed=0):
    """Positions uniform in the block, velocity = drift + spin about z +
    uniform compression about the block's centre (float32 arrays)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    x = np.asarray(LO) + 0.3 * rng.random((n, 3))
    r = x - np.asarray(CENTRE)
    v = np.empty_like(x)
    v[:, 0] = 0.3 - SPIN * r[:, 1] - SQUEEZE * r[:, 0]
    v[:, 1] = -1.5 + SPIN * r[:, 0] - SQUEEZE * r[:, 1]
    v[:, 2] = -SQUEEZE * r[:, 2]
    return x.astype(np.float32), v.astype(np.float32)


def scene_numbers(grid):
    dx = 1.0 / grid
    vol = (0.5 * dx) ** 3
    mass = vol * DENSITY
    return {
        "dx": dx,
        "inv_dx": float(grid),
        "vol": vol,
        "mass": mass,
        "empty_mass": EMPTY_NODE_MASS_RATIO * mass,
        "stress_scale": -DT * 4.0 * grid * grid * vol,
        "apic_scale": 4.0 * grid * grid,
    }


def free_fall_mean_y(t):
    """Mean height of the block before it meets the bottom wall (about 0.036 s)."""
    return CENTRE[1] - 1.5 * t + 0.5 * GRAVITY * t * t


def summarise(x, f):
    """What --check prints: the block's height, spread and deformation."""
    import numpy as np

    x = x.astype(np.float64)
    f = f.astype(np.float64)
    det = np.linalg.det(f)
    sv = np.linalg.svd(f, compute_uv=False)
    return {
        "mean_y": float(x[:, 1].mean()),
        "min_y": float(x[:, 1].min()),
        "extent_xyz": [float(e) for e in (x.max(0) - x.min(0))],
        "mean_abs_J_minus_1": float(np.abs(det - 1.0).mean()),
        "max_singular_value": float(sv.max()),
        "min_singular_value": float(sv.min()),
        "finite": bool(np.isfinite(x).all() and np.isfinite(f).all()),
    }


# ---- NVIDIA Warp --------------------------------------------------------------


def warp_peer():
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.init()

    @wp.func
    def stencil_base(c: float, res: int):
        b = wp.floor(c - 0.5)
        i = int(0)
        if b >= 0.0:
            i = wp.min(int(b), res - 3)
        return i

    @wp.func
    def axis_weights(f: float):
        d0 = 1.5 - f
        d1 = f - 1.0
        d2 = f - 0.5
        return wp.vec3(0.5 * d0 * d0, 0.75 - d1 * d1, 0.5 * d2 * d2)

    @wp.func
    def polar_rotation(f: wp.mat33):
        # Scaled Newton iteration, as crates/dm-mpm/src/svd.rs polar_rotation (f32).
        x = f
        for it in range(6):
            det = wp.determinant(x)
            x_inv_t = wp.transpose(wp.inverse(x))
            nxt = x
            if it < 2:
                gamma = wp.sqrt(wp.sqrt(wp.ddot(x_inv_t, x_inv_t) / wp.ddot(x, x)))
                nxt = 0.5 * (gamma * x + x_inv_t / gamma)
            else:
                nxt = 0.5 * (x + x_inv_t)
            x = nxt
            if it >= 2 and wp.abs(det - 1.0) <= 1.0e-6:
                break
        return x

    @wp.func
    def kirchhoff(f: wp.mat33, mu: float, la: float, w: wp.vec3):
        ident = wp.identity(n=3, dtype=float)
        ft = wp.transpose(f)
        j = wp.determinant(f)
        tau = wp.mat33(0.0)
        if w[0] != 0.0:
            tau = tau + w[0] * (mu * (f * ft - ident) + (la * wp.log(j)) * ident)
        if w[1] != 0.0:
            r = polar_rotation(f)
            tau = tau + w[1] * ((2.0 * mu) * ((f - r) * ft) + (la * (j - 1.0) * j) * ident)
        if w[2] != 0.0:
            green = 0.5 * (ft * f - ident)
            tau = tau + w[2] * (f * ((2.0 * mu) * green + (la * wp.trace(green)) * ident) * ft)
        return tau

    @wp.func
    def clamp_singular_values(f: wp.mat33, lo: float, hi: float, guarded: int):
        # Gershgorin discs of FᵀF inside [lo², hi²]: surely within, no SVD
        # (crates/dm-mpm/src/svd.rs singular_values_surely_within).
        inside = int(0)
        if guarded != 0:
            c = wp.transpose(f) * f
            r0 = wp.abs(c[0, 1]) + wp.abs(c[0, 2])
            r1 = wp.abs(c[1, 0]) + wp.abs(c[1, 2])
            r2 = wp.abs(c[2, 0]) + wp.abs(c[2, 1])
            lo2 = lo * lo
            hi2 = hi * hi
            if (c[0, 0] - r0 >= lo2 and c[0, 0] + r0 <= hi2
                    and c[1, 1] - r1 >= lo2 and c[1, 1] + r1 <= hi2
                    and c[2, 2] - r2 >= lo2 and c[2, 2] + r2 <= hi2):
                inside = 1
        out = f
        if inside == 0:
            u = wp.mat33()
            s = wp.vec3()
            v = wp.mat33()
            wp.svd3(f, u, s, v)
            sc = wp.vec3(wp.clamp(s[0], lo, hi), wp.clamp(s[1], lo, hi), wp.clamp(s[2], lo, hi))
            out = u * wp.diag(sc) * wp.transpose(v)
        return out

    @wp.kernel
    def p2g(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
            f: wp.array(dtype=wp.mat33), c: wp.array(dtype=wp.mat33),
            youngs: wp.array(dtype=float), nu: float, weights: wp.vec3,
            res: int, dx: float, inv_dx: float, mass: float, stress_scale: float,
            grid_p: wp.array3d(dtype=wp.vec3), grid_m: wp.array3d(dtype=float)):
        p = wp.tid()
        g = x[p] * inv_dx
        bx = stencil_base(g[0], res)
        by = stencil_base(g[1], res)
        bz = stencil_base(g[2], res)
        frac = g - wp.vec3(float(bx), float(by), float(bz))
        wx = axis_weights(frac[0])
        wy = axis_weights(frac[1])
        wz = axis_weights(frac[2])
        e = youngs[p]
        mu = e / (2.0 * (1.0 + nu))
        la = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
        tau = kirchhoff(f[p], mu, la, weights)
        affine = stress_scale * tau + mass * c[p]
        momentum = mass * v[p]
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    dpos = (wp.vec3(float(i), float(j), float(k)) - frac) * dx
                    w = wx[i] * wy[j] * wz[k]
                    wp.atomic_add(grid_p, bx + i, by + j, bz + k, w * (momentum + affine * dpos))
                    wp.atomic_add(grid_m, bx + i, by + j, bz + k, w * mass)

    @wp.kernel
    def grid_update(grid_p: wp.array3d(dtype=wp.vec3), grid_m: wp.array3d(dtype=float),
                    res: int, dt: float, gravity: float, damping: float, empty_mass: float,
                    grid_v: wp.array3d(dtype=wp.vec3)):
        i, j, k = wp.tid()
        m = grid_m[i, j, k]
        u = wp.vec3(0.0)
        if m > empty_mass:
            u = (grid_p[i, j, k] / m + wp.vec3(0.0, dt * gravity, 0.0)) * damping
            ux = u[0]
            uy = u[1]
            uz = u[2]
            if (i < 3 and ux < 0.0) or (i + 3 >= res and ux > 0.0):
                ux = 0.0
            if (j < 3 and uy < 0.0) or (j + 3 >= res and uy > 0.0):
                uy = 0.0
            if (k < 3 and uz < 0.0) or (k + 3 >= res and uz > 0.0):
                uz = 0.0
            u = wp.vec3(ux, uy, uz)
        grid_v[i, j, k] = u

    @wp.kernel
    def g2p(x: wp.array(dtype=wp.vec3), f: wp.array(dtype=wp.mat33),
            grid_v: wp.array3d(dtype=wp.vec3),
            res: int, dx: float, inv_dx: float, dt: float, apic_scale: float,
            clip_lo: float, clip_hi: float, svd_lo: float, svd_hi: float, guarded: int,
            x_out: wp.array(dtype=wp.vec3), v_out: wp.array(dtype=wp.vec3),
            f_out: wp.array(dtype=wp.mat33), c_out: wp.array(dtype=wp.mat33)):
        p = wp.tid()
        xp = x[p]
        g = xp * inv_dx
        bx = stencil_base(g[0], res)
        by = stencil_base(g[1], res)
        bz = stencil_base(g[2], res)
        frac = g - wp.vec3(float(bx), float(by), float(bz))
        wx = axis_weights(frac[0])
        wy = axis_weights(frac[1])
        wz = axis_weights(frac[2])
        new_v = wp.vec3(0.0)
        b = wp.mat33(0.0)
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    dpos = (wp.vec3(float(i), float(j), float(k)) - frac) * dx
                    w = wx[i] * wy[j] * wz[k]
                    gv = grid_v[bx + i, by + j, bz + k]
                    new_v = new_v + w * gv
                    b = b + w * wp.outer(gv, dpos)
        new_c = apic_scale * b
        new_f = (wp.identity(n=3, dtype=float) + dt * new_c) * f[p]
        new_f = clamp_singular_values(new_f, svd_lo, svd_hi, guarded)
        nx = xp + dt * new_v
        x_out[p] = wp.vec3(wp.clamp(nx[0], clip_lo, clip_hi),
                           wp.clamp(nx[1], clip_lo, clip_hi),
                           wp.clamp(nx[2], clip_lo, clip_hi))
        v_out[p] = new_v
        f_out[p] = new_f
        c_out[p] = new_c

    @wp.kernel
    def mean_square(x: wp.array(dtype=wp.vec3), inv_n: float, loss: wp.array(dtype=float)):
        p = wp.tid()
        wp.atomic_add(loss, 0, inv_n * wp.dot(x[p], x[p]))

    class WarpBlock:
        """One state set per substep in the window (gradient mode), or two
        swapped each substep (throughput mode), plus one grid per substep."""

        def __init__(self, n, grid, experts, guarded, states, grids, requires_grad):
            import numpy as np

            self.n, self.res = n, grid
            self.k = scene_numbers(grid)
            self.weights = wp.vec3(*EXPERT_WEIGHTS[experts])
            self.guarded = 1 if guarded else 0
            rg = requires_grad
            self.x = [wp.zeros(n, dtype=wp.vec3, requires_grad=rg) for _ in range(states)]
            self.v = [wp.zeros(n, dtype=wp.vec3, requires_grad=rg) for _ in range(states)]
            self.f = [wp.zeros(n, dtype=wp.mat33, requires_grad=rg) for _ in range(states)]
            self.c = [wp.zeros(n, dtype=wp.mat33, requires_grad=rg) for _ in range(states)]
            shape = (grid, grid, grid)
            self.gp = [wp.zeros(shape, dtype=wp.vec3, requires_grad=rg) for _ in range(grids)]
            self.gm = [wp.zeros(shape, dtype=float, requires_grad=rg) for _ in range(grids)]
            self.gv = [wp.zeros(shape, dtype=wp.vec3, requires_grad=rg) for _ in range(grids)]
            self.youngs = wp.array(np.full(n, YOUNGS, dtype=np.float32), dtype=float, requires_grad=rg)
            self.loss = wp.zeros(1, dtype=float, requires_grad=rg)
            self.reset()

        def reset(self):
            import numpy as np

            x, v = initial_state(self.n)
            self.x[0].assign(x)
            self.v[0].assign(v)
            self.f[0].assign(np.tile(np.eye(3, dtype=np.float32), (self.n, 1, 1)))
            self.c[0].zero_()

        def substep(self, s_in, s_out, g):
            k, res, n = self.k, self.res, self.n
            self.gp[g].zero_()
            self.gm[g].zero_()
            wp.launch(p2g, dim=n, inputs=[
                self.x[s_in], self.v[s_in], self.f[s_in], self.c[s_in], self.youngs, POISSON,
                self.weights, res, k["dx"], k["inv_dx"], k["mass"], k["stress_scale"],
                self.gp[g], self.gm[g]])
            wp.launch(grid_update, dim=(res, res, res), inputs=[
                self.gp[g], self.gm[g], res, DT, GRAVITY, GRID_DAMPING, k["empty_mass"], self.gv[g]])
            wp.launch(g2p, dim=n, inputs=[
                self.x[s_in], self.f[s_in], self.gv[g], res, k["dx"], k["inv_dx"], DT,
                k["apic_scale"], CLIP[0], CLIP[1], SVD_CLAMP[0], SVD_CLAMP[1], self.guarded,
                self.x[s_out], self.v[s_out], self.f[s_out], self.c[s_out]])

        def state(self, s):
            return self.x[s].numpy(), self.f[s].numpy()

        def zero_gradients(self):
            for arrays in (self.x, self.v, self.f, self.c, self.gp, self.gm, self.gv):
                for a in arrays:
                    a.grad.zero_()
            self.youngs.grad.zero_()
            self.loss.grad.zero_()

    def throughput(n, grid, experts, substeps, guarded, check):
        wp.set_module_options({"enable_backward": False})
        block = WarpBlock(n, grid, experts, guarded, states=2, grids=1, requires_grad=False)
        before = summarise(*block.state(0))
        cur = 0
        for _ in range(WARMUP):
            block.substep(cur, 1 - cur, 0)
            cur = 1 - cur
        wp.synchronize()
        warm = summarise(*block.state(cur))
        start = time.perf_counter()
        for _ in range(substeps):
            block.substep(cur, 1 - cur, 0)
            cur = 1 - cur
        wp.synchronize()
        seconds = time.perf_counter() - start
        after = summarise(*block.state(cur)) if check else None
        return seconds, (before, warm, after)

    def grad_window(n, grid, window, repeats, guarded):
        block = WarpBlock(n, grid, "nh", guarded, states=window + 1, grids=window, requires_grad=True)
        times, forward_times, total = [], [], 0.0
        for rep in range(repeats + 1):  # the first compiles and is not timed
            block.reset()
            tape = wp.Tape()
            wp.synchronize()
            start = time.perf_counter()
            block.zero_gradients()  # timed, as Taichi's Tape clears its gradients
            with tape:
                block.loss.zero_()
                for s in range(window):
                    block.substep(s, s + 1, s)
                wp.launch(mean_square, dim=n, inputs=[block.x[window], 1.0 / n, block.loss])
            wp.synchronize()
            forward = time.perf_counter() - start
            tape.backward(loss=block.loss)
            grad = block.youngs.grad.numpy()
            elapsed = time.perf_counter() - start
            if rep > 0:
                times.append(elapsed)
                forward_times.append(forward)
            total = float(grad.astype("float64").sum())
            loss = float(block.loss.numpy()[0])
            tape.reset()
        return times, forward_times, {"loss": loss, "sum_dL_dE": total,
                                      "finite": bool(math.isfinite(total))}

    return {"name": "warp", "version": wp.__version__,
            "note": "Warp runs CPU kernels on one thread; --threads does not apply",
            "throughput": throughput, "grad_window": grad_window}


# ---- Taichi -------------------------------------------------------------------


def taichi_peer(threads, n, grid, experts, guarded, states, grids, needs_grad, serial_p2g):
    import numpy as np
    import taichi as ti

    ti.init(arch=ti.cpu, cpu_max_num_threads=threads, default_fp=ti.f32,
            log_level=ti.WARN)
    k = scene_numbers(grid)
    res = grid
    dx, inv_dx = k["dx"], k["inv_dx"]
    mass, stress_scale, apic_scale = k["mass"], k["stress_scale"], k["apic_scale"]
    empty_mass = k["empty_mass"]
    w_nh, w_fc, w_sv = EXPERT_WEIGHTS[experts]
    use_guard = 1 if guarded else 0
    ng = needs_grad

    x = ti.Vector.field(3, ti.f32, shape=(states, n), needs_grad=ng)
    v = ti.Vector.field(3, ti.f32, shape=(states, n), needs_grad=ng)
    f = ti.Matrix.field(3, 3, ti.f32, shape=(states, n), needs_grad=ng)
    c = ti.Matrix.field(3, 3, ti.f32, shape=(states, n), needs_grad=ng)
    youngs = ti.field(ti.f32, shape=n, needs_grad=ng)
    gp = ti.Vector.field(3, ti.f32, shape=(grids, res, res, res), needs_grad=ng)
    gm = ti.field(ti.f32, shape=(grids, res, res, res), needs_grad=ng)
    gv = ti.Vector.field(3, ti.f32, shape=(grids, res, res, res), needs_grad=ng)
    loss = ti.field(ti.f32, shape=(), needs_grad=ng)
    # Gradient mode: G2P writes F before the clamp, a kernel with its own
    # derivative clamps it (ti.svd has no reverse-mode derivative).
    f_pre = ti.Matrix.field(3, 3, ti.f32, shape=(states, n), needs_grad=True) if ng else None
    clamp_active = ti.field(ti.i32, shape=())

    @ti.func
    def stencil_base(cc):
        b = ti.floor(cc - 0.5)
        i = 0
        if b >= 0.0:
            i = ti.min(ti.cast(b, ti.i32), res - 3)
        return i

    @ti.func
    def axis_weights(fr):
        return ti.Vector([0.5 * (1.5 - fr) ** 2, 0.75 - (fr - 1.0) ** 2, 0.5 * (fr - 0.5) ** 2])

    @ti.func
    def polar_rotation(fm):
        # Scaled Newton iteration, as crates/dm-mpm/src/svd.rs polar_rotation (f32).
        xm = fm
        for it in range(6):
            det = xm.determinant()
            x_inv_t = xm.inverse().transpose()
            nxt = xm
            if it < 2:
                gamma = ti.sqrt(ti.sqrt(x_inv_t.norm_sqr() / xm.norm_sqr()))
                nxt = 0.5 * (gamma * xm + x_inv_t / gamma)
            else:
                nxt = 0.5 * (xm + x_inv_t)
            xm = nxt
            if it >= 2 and ti.abs(det - 1.0) <= 1e-6:
                break
        return xm

    @ti.func
    def kirchhoff(fm, mu, la):
        ident = ti.Matrix.identity(ti.f32, 3)
        ft = fm.transpose()
        j = fm.determinant()
        tau = ti.Matrix.zero(ti.f32, 3, 3)
        if ti.static(w_nh != 0.0):
            tau += w_nh * (mu * (fm @ ft - ident) + la * ti.log(j) * ident)
        if ti.static(w_fc != 0.0):
            r = polar_rotation(fm)
            tau += w_fc * (2.0 * mu * (fm - r) @ ft + la * (j - 1.0) * j * ident)
        if ti.static(w_sv != 0.0):
            green = 0.5 * (ft @ fm - ident)
            tau += w_sv * (fm @ (2.0 * mu * green + la * green.trace() * ident) @ ft)
        return tau

    @ti.func
    def clamp_singular_values(fm):
        lo, hi = SVD_CLAMP
        inside = 0
        if ti.static(use_guard):
            cm = fm.transpose() @ fm
            r0 = ti.abs(cm[0, 1]) + ti.abs(cm[0, 2])
            r1 = ti.abs(cm[1, 0]) + ti.abs(cm[1, 2])
            r2 = ti.abs(cm[2, 0]) + ti.abs(cm[2, 1])
            if (cm[0, 0] - r0 >= lo * lo and cm[0, 0] + r0 <= hi * hi
                    and cm[1, 1] - r1 >= lo * lo and cm[1, 1] + r1 <= hi * hi
                    and cm[2, 2] - r2 >= lo * lo and cm[2, 2] + r2 <= hi * hi):
                inside = 1
        out = fm
        if inside == 0:
            u, sig, vm = ti.svd(fm)
            if ti.static(needs_grad):
                for d in ti.static(range(3)):
                    if sig[d, d] < lo or sig[d, d] > hi:
                        clamp_active[None] += 1
            for d in ti.static(range(3)):
                sig[d, d] = ti.min(ti.max(sig[d, d], lo), hi)
            out = u @ sig @ vm.transpose()
        return out

    @ti.kernel
    def clear_grid(g: ti.i32):
        for i, j, kk in ti.ndrange(res, res, res):
            gp[g, i, j, kk] = ti.Vector([0.0, 0.0, 0.0])
            gm[g, i, j, kk] = 0.0

    @ti.func
    def p2g_particle(s, g, p):
        if True:
            gx = x[s, p] * inv_dx
            base = ti.Vector([stencil_base(gx[0]), stencil_base(gx[1]), stencil_base(gx[2])])
            frac = gx - ti.cast(base, ti.f32)
            wx = axis_weights(frac[0])
            wy = axis_weights(frac[1])
            wz = axis_weights(frac[2])
            e = youngs[p]
            mu = e / (2.0 * (1.0 + POISSON))
            la = e * POISSON / ((1.0 + POISSON) * (1.0 - 2.0 * POISSON))
            tau = kirchhoff(f[s, p], mu, la)
            affine = stress_scale * tau + mass * c[s, p]
            momentum = mass * v[s, p]
            for i, j, kk in ti.static(ti.ndrange(3, 3, 3)):
                dpos = (ti.Vector([i, j, kk], ti.f32) - frac) * dx
                w = wx[i] * wy[j] * wz[kk]
                gp[g, base[0] + i, base[1] + j, base[2] + kk] += w * (momentum + affine @ dpos)
                gm[g, base[0] + i, base[1] + j, base[2] + kk] += w * mass

    if serial_p2g:
        # One thread scatters: Taichi then demotes the atomic adds to plain
        # ones (x86 has no float atomic add; each is a compare-and-swap loop).
        @ti.kernel
        def p2g(s: ti.i32, g: ti.i32):
            ti.loop_config(serialize=True)
            for p in range(n):
                p2g_particle(s, g, p)
    else:
        @ti.kernel
        def p2g(s: ti.i32, g: ti.i32):
            for p in range(n):
                p2g_particle(s, g, p)

    @ti.kernel
    def grid_update(g: ti.i32):
        for i, j, kk in ti.ndrange(res, res, res):
            m = gm[g, i, j, kk]
            u = ti.Vector([0.0, 0.0, 0.0])
            if m > empty_mass:
                u = (gp[g, i, j, kk] / m + ti.Vector([0.0, DT * GRAVITY, 0.0])) * GRID_DAMPING
                idx = ti.Vector([i, j, kk])
                for a in ti.static(range(3)):
                    if (idx[a] < WALL_CELLS and u[a] < 0.0) or (idx[a] + WALL_CELLS >= res and u[a] > 0.0):
                        u[a] = 0.0
            gv[g, i, j, kk] = u

    @ti.kernel
    def g2p(s: ti.i32, s_out: ti.i32, g: ti.i32):
        for p in range(n):
            xp = x[s, p]
            gx = xp * inv_dx
            base = ti.Vector([stencil_base(gx[0]), stencil_base(gx[1]), stencil_base(gx[2])])
            frac = gx - ti.cast(base, ti.f32)
            wx = axis_weights(frac[0])
            wy = axis_weights(frac[1])
            wz = axis_weights(frac[2])
            new_v = ti.Vector.zero(ti.f32, 3)
            b = ti.Matrix.zero(ti.f32, 3, 3)
            for i, j, kk in ti.static(ti.ndrange(3, 3, 3)):
                dpos = (ti.Vector([i, j, kk], ti.f32) - frac) * dx
                w = wx[i] * wy[j] * wz[kk]
                gvel = gv[g, base[0] + i, base[1] + j, base[2] + kk]
                new_v += w * gvel
                b += w * gvel.outer_product(dpos)
            new_c = apic_scale * b
            new_f = (ti.Matrix.identity(ti.f32, 3) + DT * new_c) @ f[s, p]
            nx = xp + DT * new_v
            x[s_out, p] = ti.min(ti.max(nx, CLIP[0]), CLIP[1])
            v[s_out, p] = new_v
            if ti.static(needs_grad):
                f_pre[s_out, p] = new_f
            else:
                f[s_out, p] = clamp_singular_values(new_f)
            c[s_out, p] = new_c

    @ti.kernel
    def clamp_forward(s_out: ti.i32):
        for p in range(n):
            f[s_out, p] = clamp_singular_values(f_pre[s_out, p])

    @ti.kernel
    def clamp_pass_gradient(s_out: ti.i32):
        for p in range(n):
            f_pre.grad[s_out, p] += f.grad[s_out, p]

    @ti.ad.grad_replaced
    def clamp(s_out):
        clamp_forward(s_out)

    @ti.ad.grad_for(clamp)
    def clamp_grad(s_out):
        # The clamp is the identity where it leaves every singular value
        # as it is; clamp_active counts where it does not.
        clamp_pass_gradient(s_out)

    @ti.kernel
    def mean_square(s: ti.i32):
        for p in range(n):
            loss[None] += x[s, p].norm_sqr() / n

    def reset():
        xs, vs = initial_state(n)
        xn = np.zeros((states, n, 3), np.float32)
        vn = np.zeros((states, n, 3), np.float32)
        fn = np.zeros((states, n, 3, 3), np.float32)
        xn[0], vn[0], fn[0] = xs, vs, np.eye(3, dtype=np.float32)
        x.from_numpy(xn)
        v.from_numpy(vn)
        f.from_numpy(fn)
        c.fill(0.0)
        youngs.fill(YOUNGS)

    def substep(s_in, s_out, g):
        clear_grid(g)
        p2g(s_in, g)
        grid_update(g)
        g2p(s_in, s_out, g)
        if needs_grad:
            clamp(s_out)

    def state(s):
        return x.to_numpy()[s], f.to_numpy()[s]

    return {"ti": ti, "reset": reset, "substep": substep, "state": state,
            "mean_square": mean_square, "loss": loss, "youngs": youngs,
            "clamp_active": clamp_active}


def taichi_throughput(threads, n, grid, experts, substeps, guarded, check, serial_p2g):
    t = taichi_peer(threads, n, grid, experts, guarded, states=2, grids=1, needs_grad=False,
                    serial_p2g=serial_p2g)
    ti = t["ti"]
    t["reset"]()
    before = summarise(*t["state"](0))
    cur = 0
    for _ in range(WARMUP):
        t["substep"](cur, 1 - cur, 0)
        cur = 1 - cur
    ti.sync()
    warm = summarise(*t["state"](cur))
    start = time.perf_counter()
    for _ in range(substeps):
        t["substep"](cur, 1 - cur, 0)
        cur = 1 - cur
    ti.sync()
    seconds = time.perf_counter() - start
    after = summarise(*t["state"](cur)) if check else None
    return seconds, (before, warm, after)


def taichi_grad_window(threads, n, grid, window, repeats, guarded, serial_p2g):
    t = taichi_peer(threads, n, grid, "nh", guarded, states=window + 1, grids=window, needs_grad=True,
                    serial_p2g=serial_p2g)
    ti, loss, youngs = t["ti"], t["loss"], t["youngs"]
    times, forward_times = [], []
    for rep in range(repeats + 1):  # the first compiles and is not timed
        t["reset"]()
        t["clamp_active"][None] = 0
        ti.sync()
        start = time.perf_counter()
        with ti.ad.Tape(loss=loss):
            for s in range(window):
                t["substep"](s, s + 1, s)
            t["mean_square"](window)
            ti.sync()
            forward = time.perf_counter() - start
        grad = youngs.grad.to_numpy()
        elapsed = time.perf_counter() - start
        if rep > 0:
            times.append(elapsed)
            forward_times.append(forward)
    total = float(grad.astype("float64").sum())
    active = int(t["clamp_active"][None])
    info = {"loss": float(loss[None]), "sum_dL_dE": total, "finite": bool(math.isfinite(total)),
            "clamp_derivative": "identity: ti.svd has no reverse-mode derivative in Taichi",
            "clamp_active": active}
    if active:
        info["warning"] = f"the clamp changed {active} singular values in the window; its derivative there is not exact"
    return times, forward_times, info


# ---- the product, for the same-run comparison -----------------------------------


def deformmaster(args):
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    binary = args.dm_bench or os.path.join(root, "target", "release", "dm-bench")
    if not os.path.exists(binary):
        return {"error": f"{binary} is not built (make build)"}
    try:
        version = subprocess.run(["git", "-C", root, "describe", "--always", "--dirty"],
                                 capture_output=True, text=True).stdout.strip() or "unknown"
    except OSError:
        version = "unknown"
    common = [binary, "--threads", str(args.threads)]
    if args.grad_window:
        cmd = common + ["grad", "--particles", str(args.particles), "--window",
                        str(args.grad_window), "--grid", str(args.grid), "--repeats", str(args.repeats)]
    else:
        cmd = common + ["mpm", "--particles", str(args.particles), "--grid", str(args.grid),
                        "--experts", args.experts, "--substeps", str(args.substeps)]
    run = subprocess.run(cmd, capture_output=True, text=True)
    if run.returncode != 0:
        lines = run.stderr.strip().splitlines()
        reason = next((l.strip() for l in lines if "error" in l.lower()), lines[-1] if lines else "")
        return {"version": version, "error": f"dm-bench exited with {run.returncode}: {reason}"}
    values = dict(line.split(None, 1) for line in run.stdout.splitlines() if line.strip())
    if args.check:
        print(json.dumps({"peer": "deformmaster", "check": run.stderr.strip()}), file=sys.stderr)
    out = {"version": version, "threads": args.threads}
    if args.grad_window:
        out["grad_window_s"] = float(values["grad_window_s"])
    else:
        rate = float(values["particle_substeps_per_s"])
        out["seconds"] = args.particles * args.substeps / rate
        out["particle_substeps_per_s"] = rate
    return out


# ---- command line -------------------------------------------------------------


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--peer", choices=["warp", "taichi", "deformmaster"], required=True)
    ap.add_argument("--particles", type=int, default=8000)
    ap.add_argument("--grid", type=int, default=32)
    ap.add_argument("--experts", choices=["nh", "moce"], default="nh")
    ap.add_argument("--substeps", type=int, default=400, help="timed substeps, after 20 warm-up substeps")
    ap.add_argument("--threads", type=int, default=2, help="CPU threads (Taichi cpu_max_num_threads)")
    ap.add_argument("--grad-window", type=int, default=0, metavar="W",
                    help="time forward with tape + backward of W substeps (Neo-Hookean) instead")
    ap.add_argument("--repeats", type=int, default=5, help="timed repetitions of --grad-window (median)")
    ap.add_argument("--clamp", choices=["guarded", "always"], default="guarded",
                    help="guarded: SVD only when a Gershgorin test of FᵀF cannot show the singular "
                         "values inside [0.5, 2] (as the product); always: an SVD per particle per substep")
    ap.add_argument("--p2g", choices=["parallel", "serial"], default="parallel",
                    help="Taichi: P2G over --threads threads with atomic adds (parallel), or on one "
                         "thread with plain adds (serial); the other kernels stay parallel")
    ap.add_argument("--check", action="store_true",
                    help="print the block's height and deformation before and after, on stderr")
    ap.add_argument("--dm-bench", default=None, help="dm-bench binary for --peer deformmaster")
    args = ap.parse_args()
    if args.particles < 1 or args.substeps < 1 or args.repeats < 1 or args.grad_window < 0:
        ap.error("--particles, --substeps and --repeats must be positive, --grad-window not negative")

    # The frameworks print banners on stdout (some from native code): send
    # everything to stderr and keep stdout for the one JSON line.
    sys.stdout.flush()
    json_out = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)

    grad_mode = args.grad_window > 0
    guarded = args.clamp == "guarded"
    line = {"peer": args.peer, "version": None, "particles": args.particles, "grid": args.grid,
            "experts": "nh" if grad_mode else args.experts, "threads": args.threads}
    if grad_mode:
        line.update({"window": args.grad_window, "repeats": args.repeats})
    else:
        line["substeps"] = args.substeps
    line["clamp"] = args.clamp

    try:
        if args.peer == "deformmaster":
            line.update(deformmaster(args))
            line["clamp"] = "guarded"
            print(json.dumps(line), file=json_out, flush=True)
            return
        if args.peer == "warp":
            peer = warp_peer()
            line["version"] = peer["version"]
            line["threads"] = 1
            line["threads_requested"] = args.threads
            line["note"] = peer["note"]
        else:
            import taichi as ti

            line["version"] = ".".join(map(str, ti.__version__))
            line["p2g"] = args.p2g
        if grad_mode:
            if args.peer == "warp":
                times, fwd, info = peer["grad_window"](args.particles, args.grid, args.grad_window,
                                                       args.repeats, guarded)
            else:
                times, fwd, info = taichi_grad_window(args.threads, args.particles, args.grid,
                                                      args.grad_window, args.repeats, guarded,
                                                      args.p2g == "serial")
            line["grad_window_s"] = statistics.median(times)
            line["forward_s"] = statistics.median(fwd)
            line.update(info)
        else:
            if args.peer == "warp":
                seconds, checks = peer["throughput"](args.particles, args.grid, args.experts,
                                                     args.substeps, guarded, args.check)
            else:
                seconds, checks = taichi_throughput(args.threads, args.particles, args.grid,
                                                    args.experts, args.substeps, guarded, args.check,
                                                    args.p2g == "serial")
            line["seconds"] = seconds
            line["particle_substeps_per_s"] = args.particles * args.substeps / seconds
            if args.check:
                before, warm, after = checks
                print(json.dumps({"peer": args.peer, "check": {
                    "initial": before,
                    "after_warmup": dict(warm, free_fall_mean_y=free_fall_mean_y(WARMUP * DT)),
                    "after_timed": after}}), file=sys.stderr)
            if not checks[1]["finite"]:
                line["error"] = "state not finite after the warm-up"
    except Exception as exc:  # one JSON line, whatever failed
        line["error"] = f"{type(exc).__name__}: {exc}"
    sys.stdout.flush()
    print(json.dumps(line), file=json_out, flush=True)


if __name__ == "__main__":
    main()
