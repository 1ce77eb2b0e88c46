// Backward twin of g2p.cu (g2p_backward.rs). Pass 1, one thread per
// particle: the gather recomputed with its moments, the adjoints of the
// clip, the clamps, the F update and the damping; writes the adjoints of x
// and F, what pass 2 scatters, and adds the particle's share of the
// damping factor's adjoint. Pass 2 (`g2p_backward_scatter`, in
// p2g.cu's scatter): ū_i += w (ṽ̄ + B̄ (x_i − x_p)).

extern "C" __global__ void g2p_backward_gather(
    Consts k, int n, const real* __restrict__ grid,
    const real* __restrict__ xs, const real* __restrict__ fs,
    const real* __restrict__ out_x, const real* __restrict__ out_v,
    const real* __restrict__ out_f, const real* __restrict__ out_c,
    real* __restrict__ grad_x, real* __restrict__ grad_f,
    real* __restrict__ bar_v, real* __restrict__ bar_b, real* __restrict__ damping_share)
{
    int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= n) return;
    v3 x = v3_load(xs + 3 * p);
    m3 f = m3_load(fs + 9 * p);
    Stencil st = make_stencil(k, x);
    Moments<3> mo;
    gather_moments(k, st, grid, mo);
    real apic = (real)4 * k.inv_dx * k.inv_dx;
    v3 v_tilde = lanes_xyz(mo.sum);
    m3 c_new = m3_scale(moment_matrix(k, mo, st), apic);
    v3 v_new = v3_scale(v_tilde, k.particle_damping_factor);
    m3 step = m3_add_diagonal(m3_scale(c_new, k.dt), (real)1);
    m3 f_pre = m3_mul(step, f);
    v3 x_pre = v3_add(x, v3_scale(v_new, k.dt));
    v3 x_bar = v3_load(out_x + 3 * p);
    for (int a = 0; a < 3; ++a) {
        if (x_pre.x[a] < k.clip_lo[a] || x_pre.x[a] > k.clip_hi[a]) x_bar.x[a] = (real)0;
    }
    // The clamps' adjoints, outermost first.
    m3 f_plastic = f_pre;
    if (k.has_plastic) {
        m3 projected;
        if (clamp_singular_values(f_pre, k.plastic_lo, k.plastic_hi, projected)) f_plastic = projected;
    }
    m3 f_bar = clamp_singular_values_vjp(f_plastic, k.svd_lo, k.svd_hi, m3_load(out_f + 9 * p));
    if (k.has_plastic) f_bar = clamp_singular_values_vjp(f_pre, k.plastic_lo, k.plastic_hi, f_bar);
    v3 v_new_bar = v3_add(v3_load(out_v + 3 * p), v3_scale(x_bar, k.dt));
    m3 c_new_bar = m3_add(m3_load(out_c + 9 * p), m3_scale(m3_mul(f_bar, m3_transpose(f)), k.dt));
    m3_store(grad_f + 9 * p, m3_mul(m3_transpose(step), f_bar));
    v3 vt_bar = v3_scale(v_new_bar, k.particle_damping_factor);
    m3 bbar = m3_scale(c_new_bar, apic);
    v3_store(grad_x + 3 * p, v3_add(x_bar, position_adjoint(k, st, mo, vt_bar, bbar)));
    v3_store(bar_v + 3 * p, vt_bar);
    m3_store(bar_b + 9 * p, bbar);
    damping_share[p] += v3_dot(v_new_bar, v_tilde);
}

// Pass 2: ū_i += w (ṽ̄ + B̄ (x_i − x_p)), the particles in cell order.
extern "C" __global__ void g2p_backward_scatter(
    Consts k, int n, const unsigned* __restrict__ order, const unsigned* __restrict__ keys,
    const real* __restrict__ xs, const real* __restrict__ bar_v, const real* __restrict__ bar_b,
    real* __restrict__ grad_u)
{
    int p;
    Stencil st;
    unsigned key;
    bool valid = sorted_particle(k, n, order, keys, xs, p, st, key);
    v3 vt_bar = v3_zero();
    m3 bbar = m3_zero();
    if (valid) {
        vt_bar = v3_load(bar_v + 3 * p);
        bbar = m3_load(bar_b + 9 * p);
    }
    scatter_sorted(k, valid, st, key, vt_bar, bbar, (real)0, grad_u);
}
