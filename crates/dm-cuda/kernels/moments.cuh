// Stencil moments of per-node data n_i (4 lanes) for the adjoints of both
// transfers (grid.rs's StencilMoments): with offsets o_i = (i, j, k),
// weights w_i and their gradients per unit frac ∂w_i/∂frac_c,
//   sum = Σ w n,  moment[b] = Σ w o_b n,
//   slope[c] = Σ ∂w/∂frac_c n,  slope_moment[c][b] = Σ ∂w/∂frac_c o_b n.

struct Moments {
    real sum[4];
    real moment[3][4];
    real slope[3][4];
    real slope_moment[3][3][4];
};

__device__ __forceinline__ void axis_slopes(real f, real s[3]) {
    s[0] = f - (real)1.5;
    s[1] = (real)-2 * (f - (real)1);
    s[2] = f - (real)0.5;
}

__device__ void gather_moments(const Consts& k, const Stencil& st, const real* __restrict__ nodes, Moments& m) {
    real slopes[3][3];
    for (int a = 0; a < 3; ++a) axis_slopes(st.frac[a], slopes[a]);
    for (int l = 0; l < 4; ++l) {
        m.sum[l] = (real)0;
        for (int b = 0; b < 3; ++b) {
            m.moment[b][l] = (real)0;
            m.slope[b][l] = (real)0;
            for (int c = 0; c < 3; ++c) m.slope_moment[b][c][l] = (real)0;
        }
    }
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
            for (int kk = 0; kk < 3; ++kk) {
                const real* n = nodes + 4 * node_index(k.res, st.base[0] + i, st.base[1] + j, st.base[2] + kk);
                real w = st.w[0][i] * st.w[1][j] * st.w[2][kk];
                real dw[3] = {
                    slopes[0][i] * st.w[1][j] * st.w[2][kk],
                    st.w[0][i] * slopes[1][j] * st.w[2][kk],
                    st.w[0][i] * st.w[1][j] * slopes[2][kk],
                };
                real o[3] = {(real)i, (real)j, (real)kk};
                for (int l = 0; l < 4; ++l) {
                    real v = n[l];
                    m.sum[l] += w * v;
                    for (int b = 0; b < 3; ++b) {
                        m.moment[b][l] += w * o[b] * v;
                        m.slope[b][l] += dw[b] * v;
                        for (int c = 0; c < 3; ++c) m.slope_moment[b][c][l] += dw[b] * o[c] * v;
                    }
                }
            }
        }
    }
}

__device__ __forceinline__ v3 lanes_xyz(const real l[4]) {
    v3 r;
    r.x[0] = l[0];
    r.x[1] = l[1];
    r.x[2] = l[2];
    return r;
}

// (Σ_b moment[b] ⊗ e_b − sum ⊗ frac) dx: the matrix Σ w n (x_i − x_p)ᵀ.
__device__ __forceinline__ m3 moment_matrix(const Consts& k, const Moments& m, const Stencil& st) {
    m3 r;
    for (int row = 0; row < 3; ++row)
        for (int b = 0; b < 3; ++b) r.m[row][b] = (m.moment[b][row] - m.sum[row] * st.frac[b]) * k.dx;
    return r;
}

// Σ ∇w_i (n_i · a + n_iᵀ A (x_i − x_p)) − Σ w_i Aᵀ n_i for an affine
// field (a, A): the position adjoint of a transfer.
__device__ v3 position_adjoint(const Consts& k, const Stencil& st, const Moments& m, const v3& a, const m3& big_a) {
    v3 frac;
    for (int c = 0; c < 3; ++c) frac.x[c] = st.frac[c];
    v3 a_frac = m3_mul_v(big_a, frac);
    v3 g = v3_scale(m3_mul_v(m3_transpose(big_a), lanes_xyz(m.sum)), (real)-1);
    for (int c = 0; c < 3; ++c) {
        v3 slope = lanes_xyz(m.slope[c]);
        real through_offsets = -v3_dot(slope, a_frac);
        for (int b = 0; b < 3; ++b) through_offsets += v3_dot(m3_column(big_a, b), lanes_xyz(m.slope_moment[c][b]));
        g.x[c] += (v3_dot(slope, a) + through_offsets * k.dx) * k.inv_dx;
    }
    return g;
}
