// Vector-Jacobian products of the polar rotation and the singular-value
// clamp (svd_backward.rs).

// Gap below which two singular values count as equal (SIGMA_EQUAL_RTOL).
#define SIGMA_EQUAL_RTOL 1e-12
// Floor on |σᵢ + σⱼ| (SIGMA_SUM_FLOOR).
#define SIGMA_SUM_FLOOR 1e-12

__device__ __forceinline__ m3 cross_matrix(const v3& w) {
    m3 r = m3_zero();
    r.m[0][1] = -w.x[2]; r.m[0][2] = w.x[1];
    r.m[1][0] = w.x[2];  r.m[1][2] = -w.x[0];
    r.m[2][0] = -w.x[1]; r.m[2][1] = w.x[0];
    return r;
}

__device__ __forceinline__ v3 skew_axial(const m3& a) {
    v3 r;
    r.x[0] = a.m[2][1] - a.m[1][2];
    r.x[1] = a.m[0][2] - a.m[2][0];
    r.x[2] = a.m[1][0] - a.m[0][1];
    return r;
}

// ∂L/∂F of R = polar_rotation(F), given ∂L/∂R.
__device__ m3 polar_rotation_vjp(const m3& f, const m3& r, const m3& grad_r) {
    m3 rt = m3_transpose(r);
    m3 s = m3_mul(rt, f);
    s = m3_scale(m3_add(s, m3_transpose(s)), (real)0.5);
    m3 system = m3_sub(m3_add_diagonal(m3_zero(), m3_trace(s)), s);
    v3 rhs = skew_axial(m3_mul(rt, grad_r));
    real det = m3_det(system);
    if (det == (real)0) return m3_zero();
    // The inverse is cofactor(system)ᵀ / det.
    m3 inverse = m3_scale(m3_transpose(m3_cofactor(system)), (real)1 / det);
    return m3_mul(r, cross_matrix(m3_mul_v(inverse, rhs)));
}

// VJP of F ↦ clamp_singular_values(F, lo, hi) (F itself when inside).
__device__ m3 clamp_singular_values_vjp(const m3& f, real lo, real hi, const m3& grad_out) {
    m3 unused;
    if (!clamp_singular_values(f, lo, hi, unused)) return grad_out;
    m3 u, v;
    v3 sigma;
    svd3(f, u, sigma, v);
    real clamped[3], slope[3];
    for (int i = 0; i < 3; ++i) {
        clamped[i] = fmin(fmax(sigma.x[i], lo), hi);
        slope[i] = (sigma.x[i] > lo && sigma.x[i] < hi) ? (real)1 : (real)0;
    }
    m3 g = m3_mul(m3_mul(m3_transpose(u), grad_out), v);
    m3 q = m3_zero();
    for (int i = 0; i < 3; ++i) q.m[i][i] = slope[i] * g.m[i][i];
    for (int i = 0; i < 3; ++i) {
        for (int j = i + 1; j < 3; ++j) {
            real gap = sigma.x[j] - sigma.x[i];
            real size = fabs(sigma.x[i]) + fabs(sigma.x[j]);
            real divided_difference;
            if (fabs(gap) <= (real)SIGMA_EQUAL_RTOL * size) {
                real mid = (sigma.x[i] + sigma.x[j]) * (real)0.5;
                divided_difference = (mid > lo && mid < hi) ? (real)1 : (real)0;
            } else {
                divided_difference = fmin(fmax((clamped[j] - clamped[i]) / gap, (real)0), (real)1);
            }
            real sum = sigma.x[i] + sigma.x[j];
            const real floor_sum = (real)SIGMA_SUM_FLOOR;
            if (fabs(sum) < floor_sum) sum = sum < (real)0 ? -floor_sum : floor_sum;
            real rotation_ratio = (clamped[i] + clamped[j]) / sum;
            real sym = (g.m[i][j] + g.m[j][i]) * (real)0.5 * divided_difference;
            real anti = (g.m[i][j] - g.m[j][i]) * (real)0.5 * rotation_ratio;
            q.m[i][j] = sym + anti;
            q.m[j][i] = sym - anti;
        }
    }
    return m3_mul(m3_mul(u, q), m3_transpose(v));
}
