// 3x3 SVD, polar rotation and the singular-value clamp (svd.rs): the same
// algorithms and tolerances as the CPU path.

// Symmetric eigen-decomposition A = V diag(lambda) Vᵀ by cyclic Jacobi.
__device__ void symmetric_eigen(m3 a, v3& lambda, m3& v) {
    v = m3_identity();
    const real eps = DM_SINGLE ? (real)1e-6 : (real)1e-15;
    const int max_sweeps = DM_SINGLE ? 5 : 8;
    const int pairs[3][2] = {{0, 1}, {0, 2}, {1, 2}};
    for (int sweep = 0; sweep < max_sweeps; ++sweep) {
        real off = a.m[0][1] * a.m[0][1] + a.m[0][2] * a.m[0][2] + a.m[1][2] * a.m[1][2];
        real diag = a.m[0][0] * a.m[0][0] + a.m[1][1] * a.m[1][1] + a.m[2][2] * a.m[2][2];
        if (off <= eps * eps * diag) break;
        for (int pi = 0; pi < 3; ++pi) {
            int p = pairs[pi][0], q = pairs[pi][1];
            real apq = a.m[p][q];
            if (apq == (real)0) continue;
            real theta = (a.m[q][q] - a.m[p][p]) / (apq + apq);
            real sign = theta >= (real)0 ? (real)1 : (real)-1;
            real t = sign / (fabs(theta) + sqrt(theta * theta + (real)1));
            real c = (real)1 / sqrt(t * t + (real)1);
            real s = t * c;
            for (int k = 0; k < 3; ++k) {
                real akp = a.m[k][p], akq = a.m[k][q];
                a.m[k][p] = c * akp - s * akq;
                a.m[k][q] = s * akp + c * akq;
            }
            for (int k = 0; k < 3; ++k) {
                real apk = a.m[p][k], aqk = a.m[q][k];
                a.m[p][k] = c * apk - s * aqk;
                a.m[q][k] = s * apk + c * aqk;
            }
            for (int k = 0; k < 3; ++k) {
                real vkp = v.m[k][p], vkq = v.m[k][q];
                v.m[k][p] = c * vkp - s * vkq;
                v.m[k][q] = s * vkp + c * vkq;
            }
        }
    }
    lambda.x[0] = a.m[0][0];
    lambda.x[1] = a.m[1][1];
    lambda.x[2] = a.m[2][2];
}

__device__ v3 any_orthogonal(const v3& a) {
    v3 helper = v3_zero();
    if (fabs(a.x[0]) < (real)0.6) helper.x[0] = (real)1; else helper.x[1] = (real)1;
    return v3_normalize(v3_cross(a, helper));
}

// F = U diag(sigma) Vᵀ with U, V proper rotations, sigma descending.
__device__ void svd3(const m3& f, m3& u, v3& sigma, m3& v) {
    v3 lambda;
    m3 vv;
    symmetric_eigen(m3_mul(m3_transpose(f), f), lambda, vv);
    // Sort the eigenpairs descending (a stable three-element sort).
    int order[3] = {0, 1, 2};
    for (int i = 1; i < 3; ++i) {
        int key = order[i];
        int j = i - 1;
        while (j >= 0 && lambda.x[key] > lambda.x[order[j]]) { order[j + 1] = order[j]; --j; }
        order[j + 1] = key;
    }
    for (int c = 0; c < 3; ++c) m3_set_column(v, c, m3_column(vv, order[c]));
    if (m3_det(v) < (real)0) m3_set_column(v, 2, v3_scale(m3_column(v, 2), (real)-1));
    const real tiny = (real)1e-12;
    v3 f0 = m3_mul_v(f, m3_column(v, 0));
    real f0n = v3_norm(f0);
    v3 u0;
    if (f0n > tiny) u0 = v3_normalize(f0); else { u0 = v3_zero(); u0.x[0] = (real)1; }
    v3 f1 = m3_mul_v(f, m3_column(v, 1));
    v3 f1_perp = v3_sub(f1, v3_scale(u0, v3_dot(u0, f1)));
    v3 u1 = v3_norm(f1_perp) > tiny * ((real)1 + f0n) ? v3_normalize(f1_perp) : any_orthogonal(u0);
    v3 u2 = v3_cross(u0, u1);
    sigma.x[0] = v3_dot(u0, f0);
    sigma.x[1] = v3_dot(u1, f1);
    sigma.x[2] = v3_dot(u2, m3_mul_v(f, m3_column(v, 2)));
    m3_set_column(u, 0, u0);
    m3_set_column(u, 1, u1);
    m3_set_column(u, 2, u2);
}

// Rotation of the polar decomposition F = R S: scaled Newton iteration,
// falling back to the SVD when an iterate is singular.
__device__ m3 polar_rotation(const m3& f) {
    const real tol = DM_SINGLE ? (real)1e-6 : (real)1e-14;
    const int max_iterations = DM_SINGLE ? 6 : 12;
    m3 x = f;
    bool degenerate = false;
    for (int iteration = 0; iteration < max_iterations; ++iteration) {
        real det = m3_det(x);
        if (!(fabs(det) > (real)1e-20)) { degenerate = true; break; }
        m3 x_inv_t = m3_scale(m3_cofactor(x), (real)1 / det);
        m3 next;
        if (iteration < 2) {
            real gamma = sqrt(sqrt(m3_norm_squared(x_inv_t) / m3_norm_squared(x)));
            next = m3_scale(m3_add(m3_scale(x, gamma), m3_scale(x_inv_t, (real)1 / gamma)), (real)0.5);
        } else {
            next = m3_scale(m3_add(x, x_inv_t), (real)0.5);
        }
        bool converged = iteration >= 2 && fabs(det - (real)1) <= tol;
        x = next;
        if (converged) break;
    }
    if (degenerate) {
        m3 u, v;
        v3 s;
        svd3(f, u, s, v);
        return m3_mul(u, m3_transpose(v));
    }
    return x;
}

// Cheap sufficient test that every singular value of F lies in [lo, hi]:
// the Gershgorin discs of FᵀF inside [lo², hi²].
__device__ bool singular_values_surely_within(const m3& f, real lo, real hi) {
    m3 c = m3_mul(m3_transpose(f), f);
    real lo2 = lo * lo, hi2 = hi * hi;
    real radius[3] = {
        fabs(c.m[0][1]) + fabs(c.m[0][2]),
        fabs(c.m[1][0]) + fabs(c.m[1][2]),
        fabs(c.m[2][0]) + fabs(c.m[2][1]),
    };
    bool inside = true;
    for (int i = 0; i < 3; ++i) {
        inside = inside && (lo2 <= c.m[i][i] - radius[i]) && (c.m[i][i] + radius[i] <= hi2);
    }
    return inside;
}

// Eigenvalues of a symmetric matrix in closed form, descending.
__device__ void symmetric_eigenvalues(const m3& a, real out[3]) {
    real p1 = a.m[0][1] * a.m[0][1] + a.m[0][2] * a.m[0][2] + a.m[1][2] * a.m[1][2];
    real q = m3_trace(a) / (real)3;
    real d0 = a.m[0][0] - q, d1 = a.m[1][1] - q, d2 = a.m[2][2] - q;
    real p2 = d0 * d0 + d1 * d1 + d2 * d2 + p1 + p1;
    if (p2 <= (real)1e-30) { out[0] = out[1] = out[2] = q; return; }
    real p = sqrt(p2 / (real)6);
    m3 b = m3_scale(m3_add_diagonal(a, -q), (real)1 / p);
    real r = fmin(fmax(m3_det(b) * (real)0.5, (real)-1), (real)1);
    real phi = acos(r) / (real)3;
    real l1 = q + (p + p) * cos(phi);
    real l3 = q + (p + p) * cos(phi + (real)(2.0 * 3.14159265358979323846 / 3.0));
    out[0] = l1;
    out[1] = (real)3 * q - l1 - l3;
    out[2] = l3;
}

// Projects the singular values of F into [lo, hi]; false when F is
// already inside (then `out` is untouched).
__device__ bool clamp_singular_values(const m3& f, real lo, real hi, m3& out) {
    if (singular_values_surely_within(f, lo, hi)) return false;
    real eig[3];
    symmetric_eigenvalues(m3_mul(m3_transpose(f), f), eig);
    const real margin = (real)1e-3;
    if (eig[2] >= lo * lo * ((real)1 + margin) && eig[0] <= hi * hi * ((real)1 - margin)) return false;
    m3 u, v;
    v3 s;
    svd3(f, u, s, v);
    v3 c;
    bool changed = false;
    for (int i = 0; i < 3; ++i) {
        c.x[i] = fmin(fmax(s.x[i], lo), hi);
        changed = changed || c.x[i] != s.x[i];
    }
    if (!changed) return false;
    m3 us = u;
    for (int col = 0; col < 3; ++col)
        for (int row = 0; row < 3; ++row) us.m[row][col] *= c.x[col];
    out = m3_mul(us, m3_transpose(v));
    return true;
}
