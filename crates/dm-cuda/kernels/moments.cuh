// Stencil moments of per-node data n_i (lanes) for the adjoints of both
// transfers (grid.rs's StencilMoments): with offsets o_i = (i, j, k),
// weights w_i and their gradients per unit frac ∂w_i/∂frac_c,
//   sum = Σ w n,  moment[b] = Σ w o_b n,
//   slope[c] = Σ ∂w/∂frac_c n,  slope_moment[c][b] = Σ ∂w/∂frac_c o_b n.

// `L` lanes of each node are gathered (3: a velocity, 4: momentum and mass).
template <int L>
struct Moments {
    real sum[L];
    real moment[3][L];
    real slope[3][L];
    real slope_moment[3][3][L];
};

__device__ __forceinline__ void axis_slopes(real f, real s[3]) {
    s[0] = f - (real)1.5;
    s[1] = (real)-2 * (f - (real)1);
    s[2] = f - (real)0.5;
}

// Each weight factorises over the axes, so the sums are built axis by axis
// (z, then y, then x) from four 1D factors per axis — weight w, w·o, slope
// s, s·o — keeping only products with at most one slope and one moment
// factor (grid.rs's gather_moments). Inlined, so the sums stay in registers.
template <int L>
__device__ __forceinline__ void gather_moments(const Consts& k, const Stencil& st, const real* __restrict__ nodes, Moments<L>& m) {
    real slopes[3][3];
    for (int a = 0; a < 3; ++a) axis_slopes(st.frac[a], slopes[a]);
#pragma unroll
    for (int l = 0; l < L; ++l) {
        m.sum[l] = (real)0;
        for (int b = 0; b < 3; ++b) {
            m.moment[b][l] = (real)0;
            m.slope[b][l] = (real)0;
            for (int c = 0; c < 3; ++c) m.slope_moment[b][c][l] = (real)0;
        }
    }
#pragma unroll
    for (int i = 0; i < 3; ++i) {
        // Sums over the (j, k) slab, named y factor _ z factor.
        real w_w[L], o_w[L], w_o[L], s_w[L], w_s[L], so_w[L], s_o[L], o_s[L], w_so[L];
#pragma unroll
        for (int l = 0; l < L; ++l) {
            w_w[l] = o_w[l] = w_o[l] = s_w[l] = w_s[l] = so_w[l] = s_o[l] = o_s[l] = w_so[l] = (real)0;
        }
#pragma unroll
        for (int j = 0; j < 3; ++j) {
            const real* n = nodes + 4 * node_index(k.res, st.base[0] + i, st.base[1] + j, st.base[2]);
            real wy = st.w[1][j], sy = slopes[1][j];
            real wy_o = wy * (real)j, sy_o = sy * (real)j;
#pragma unroll
            for (int l = 0; l < L; ++l) {
                real n0 = n[l], n1 = n[4 + l], n2 = n[8 + l];
                real a0 = n0 * st.w[2][0], a1 = n1 * st.w[2][1], a2 = n2 * st.w[2][2];
                real b0 = n0 * slopes[2][0], b1 = n1 * slopes[2][1], b2 = n2 * slopes[2][2];
                real z_w = a0 + a1 + a2;
                real z_o = a2 * (real)2 + a1;
                real z_s = b0 + b1 + b2;
                real z_so = b2 * (real)2 + b1;
                w_w[l] += z_w * wy;
                o_w[l] += z_w * wy_o;
                w_o[l] += z_o * wy;
                s_w[l] += z_w * sy;
                w_s[l] += z_s * wy;
                so_w[l] += z_w * sy_o;
                s_o[l] += z_o * sy;
                o_s[l] += z_s * wy_o;
                w_so[l] += z_so * wy;
            }
        }
        real wx = st.w[0][i], sx = slopes[0][i];
        real wx_o = wx * (real)i, sx_o = sx * (real)i;
#pragma unroll
        for (int l = 0; l < L; ++l) {
            m.sum[l] += w_w[l] * wx;
            m.moment[1][l] += o_w[l] * wx;
            m.moment[2][l] += w_o[l] * wx;
            m.slope[1][l] += s_w[l] * wx;
            m.slope[2][l] += w_s[l] * wx;
            m.slope_moment[1][1][l] += so_w[l] * wx;
            m.slope_moment[1][2][l] += s_o[l] * wx;
            m.slope_moment[2][1][l] += o_s[l] * wx;
            m.slope_moment[2][2][l] += w_so[l] * wx;
            m.moment[0][l] += w_w[l] * wx_o;
            m.slope_moment[1][0][l] += s_w[l] * wx_o;
            m.slope_moment[2][0][l] += w_s[l] * wx_o;
            m.slope[0][l] += w_w[l] * sx;
            m.slope_moment[0][1][l] += o_w[l] * sx;
            m.slope_moment[0][2][l] += w_o[l] * sx;
            m.slope_moment[0][0][l] += w_w[l] * sx_o;
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
template <int L>
__device__ __forceinline__ m3 moment_matrix(const Consts& k, const Moments<L>& m, const Stencil& st) {
    m3 r;
    for (int row = 0; row < 3; ++row)
        for (int b = 0; b < 3; ++b) r.m[row][b] = (m.moment[b][row] - m.sum[row] * st.frac[b]) * k.dx;
    return r;
}

// Σ ∇w_i (n_i · a + n_iᵀ A (x_i − x_p)) − Σ w_i Aᵀ n_i for an affine
// field (a, A): the position adjoint of a transfer.
template <int L>
__device__ __forceinline__ v3 position_adjoint(const Consts& k, const Stencil& st, const Moments<L>& m, const v3& a, const m3& big_a) {
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
