// Backward twin of p2g.cu (p2g_backward.rs, stress_backward.rs): a
// gather, one thread per particle. From the grid's adjoint [P̄, m̄] the
// adjoints of the particle's impulse (affine A, momentum q), its position
// and its mass; then through the impulse to v, F, C, μ, λ, the expert
// weights, the actuator acceleration, the drag coefficients and the mass.
// Adds to grad_x and grad_f (which hold the gather's share), writes the
// adjoints of v, C and the acceleration, and adds the parameters' (μ, λ,
// weights, drag, mass: summed over a window's substeps).

extern "C" __global__ void p2g_backward(
    Consts k, int n,
    const real* __restrict__ xs, const real* __restrict__ vs,
    const real* __restrict__ fs, const real* __restrict__ cs,
    const real* __restrict__ mass, const real* __restrict__ volume,
    const real* __restrict__ mu, const real* __restrict__ lambda,
    const real* __restrict__ weights, int has_accel, const real* __restrict__ accel,
    const real* __restrict__ grad_pre,
    real* __restrict__ grad_x, real* __restrict__ grad_v,
    real* __restrict__ grad_f, real* __restrict__ grad_c,
    real* __restrict__ grad_mu, real* __restrict__ grad_lambda, real* __restrict__ grad_weights,
    real* __restrict__ grad_accel, real* __restrict__ grad_effects, real* __restrict__ grad_mass)
{
    int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= n) return;
    m3 affine;
    v3 momentum;
    particle_impulse(k, p, vs, fs, cs, mass, volume, mu, lambda, weights, has_accel, accel, affine, momentum);
    real m = mass[p];
    v3 x = v3_load(xs + 3 * p);
    v3 v = v3_load(vs + 3 * p);
    m3 f = m3_load(fs + 9 * p);
    Stencil st = make_stencil(k, x);
    Moments<4> mo;
    gather_moments(k, st, grad_pre, mo);
    // The scatter's adjoint.
    v3 grad_q = lanes_xyz(mo.sum);
    m3 grad_a = moment_matrix(k, mo, st);
    v3 gx = position_adjoint(k, st, mo, momentum, affine);
    for (int c = 0; c < 3; ++c) gx.x[c] += mo.slope[c][3] * m * k.inv_dx;
    real scatter_mass = mo.sum[3];
    // The impulse's adjoint.
    real stress_scale = -k.dt * (real)4 * k.inv_dx * k.inv_dx * volume[p];
    m3 grad_tau = m3_scale(grad_a, stress_scale);
    KirchhoffGrads kg;
    if (k.pure_neo_hookean) {
        ExpertGrads e = neo_hookean_kirchhoff_vjp(f, mu[p], lambda[p], grad_tau);
        kg.f = e.f;
        kg.mu = e.mu;
        kg.lambda = e.lambda;
        kg.weights[0] = kg.weights[1] = kg.weights[2] = (real)0;
    } else {
        real w[3] = {weights[3 * p], weights[3 * p + 1], weights[3 * p + 2]};
        kg = mixture_kirchhoff_vjp(f, polar_rotation(f), mu[p], lambda[p], w, grad_tau);
    }
    v3 g_accel = v3_scale(grad_q, m * k.dt);
    v3 gv = v3_scale(grad_q, m);
    real accel_along_v = v3_dot(g_accel, v);
    real speed = v3_norm(v);
    v3 a = v3_zero();
    if (has_accel) a = v3_load(accel + 3 * p);
    if (k.drag_linear != (real)0 || k.drag_quadratic != (real)0) {
        gv = v3_sub(gv, v3_scale(g_accel, k.drag_linear + k.drag_quadratic * speed));
        if (speed > (real)0) gv = v3_sub(gv, v3_scale(v, k.drag_quadratic * v3_dot(v, g_accel) / speed));
        a = v3_sub(a, v3_scale(v, k.drag_linear + k.drag_quadratic * speed));
    }
    real impulse_mass = m3_dot(grad_a, m3_load(cs + 9 * p)) + v3_dot(grad_q, v3_add(v, v3_scale(a, k.dt)));
    v3_store(grad_x + 3 * p, v3_add(v3_load(grad_x + 3 * p), gx));
    v3_store(grad_v + 3 * p, gv);
    m3_store(grad_f + 9 * p, m3_add(m3_load(grad_f + 9 * p), kg.f));
    m3_store(grad_c + 9 * p, m3_scale(grad_a, m));
    grad_mu[p] += kg.mu;
    grad_lambda[p] += kg.lambda;
    for (int e = 0; e < 3; ++e) grad_weights[3 * p + e] += kg.weights[e];
    v3_store(grad_accel + 3 * p, has_accel ? g_accel : v3_zero());
    grad_effects[2 * p] += -accel_along_v;
    grad_effects[2 * p + 1] += -speed * accel_along_v;
    grad_mass[p] += scatter_mass + impulse_mass;
}
