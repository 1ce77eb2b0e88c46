// Stage 4 (g2p.rs): gather of velocity and the APIC matrix C, particle
// damping, F ← (I + dt C) F with the divergence check, the plastic
// projection and the singular-value clamp, advection and the position
// clip. A particle whose state became invalid is left unchanged and the
// lowest (substep, slot) key is kept in `failure`.

extern "C" __global__ void g2p(
    Consts k, int n, int substep,
    const real* __restrict__ grid,
    real* __restrict__ xs, real* __restrict__ vs,
    real* __restrict__ fs, real* __restrict__ cs,
    unsigned long long* __restrict__ failure)
{
    int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= n) return;
    v3 x = v3_load(xs + 3 * p);
    Stencil st = make_stencil(k, x);
    v3 sum_v = v3_zero();
    m3 b = m3_zero();
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
            for (int kk = 0; kk < 3; ++kk) {
                real w = st.w[0][i] * st.w[1][j] * st.w[2][kk];
                const real* node = grid + 4 * node_index(k.res, st.base[0] + i, st.base[1] + j, st.base[2] + kk);
                real offset[3] = {((real)i - st.frac[0]) * k.dx, ((real)j - st.frac[1]) * k.dx, ((real)kk - st.frac[2]) * k.dx};
                for (int r = 0; r < 3; ++r) {
                    real wv = w * node[r];
                    sum_v.x[r] += wv;
                    for (int c = 0; c < 3; ++c) b.m[r][c] += wv * offset[c];
                }
            }
        }
    }
    m3 new_c = m3_scale(b, (real)4 * k.inv_dx * k.inv_dx);
    m3 old_f = m3_load(fs + 9 * p);
    m3 new_f = m3_mul(m3_add_diagonal(m3_scale(new_c, k.dt), (real)1), old_f);
    real det = m3_det(new_f);
    unsigned long long key = ((unsigned long long)substep << 32) | (unsigned long long)p;
    if (det <= (real)0 || !is_finite_real(det)) {
        atomicMin(failure, key);
        return;
    }
    m3 projected;
    if (k.has_plastic && clamp_singular_values(new_f, k.plastic_lo, k.plastic_hi, projected)) new_f = projected;
    if (clamp_singular_values(new_f, k.svd_lo, k.svd_hi, projected)) new_f = projected;
    v3 new_v = v3_scale(sum_v, k.particle_damping_factor);
    v3 new_x = v3_add(x, v3_scale(new_v, k.dt));
    for (int a = 0; a < 3; ++a) {
        if (!is_finite_real(new_x.x[a]) || !is_finite_real(new_v.x[a])) {
            atomicMin(failure, key | (1ull << 31));
            return;
        }
    }
    for (int a = 0; a < 3; ++a) new_x.x[a] = fmin(fmax(new_x.x[a], k.clip_lo[a]), k.clip_hi[a]);
    v3_store(xs + 3 * p, new_x);
    v3_store(vs + 3 * p, new_v);
    m3_store(fs + 9 * p, new_f);
    m3_store(cs + 9 * p, new_c);
}
