// Shared types of the MPM kernels: the float type, small fixed-size
// vectors and matrices, the substep constants and the B-spline stencil.
// Compiled once per precision: REAL is `float` or `double`.

#ifndef REAL
#define REAL float
#endif
typedef REAL real;

#define DM_SINGLE (sizeof(real) == 4)

// Names the precision in the compiled module (`.entry dm_precision_float`
// or `dm_precision_double`) for tools that read the PTX, such as the CUDA
// emulator of the tests.
#define DM_PASTE_TOKENS(a, b) a##b
#define DM_PASTE(a, b) DM_PASTE_TOKENS(a, b)
extern "C" __global__ void DM_PASTE(dm_precision_, REAL)() {}
#define FULL_MASK 0xffffffffu

// Mirrors `dm_cuda::consts::KernelConsts` field for field.
struct Consts {
    real dt, dx, inv_dx;
    real origin[3];
    real gravity[3];
    real grid_damping;
    real particle_damping_factor;
    real clip_lo[3];
    real clip_hi[3];
    real svd_lo, svd_hi;
    real plastic_lo, plastic_hi;
    real floor_up[3];
    real floor_limit, floor_friction;
    real drag_linear, drag_quadratic;
    real empty_node_mass;
    real kp, kd;
    int res;
    int wall_cells;
    int has_plastic;
    int has_floor;
    int pure_neo_hookean;
    int actuator_mode;  // 0 none, 1 spring-damper (distributed or single), 2 rigid
};

struct v3 { real x[3]; };
struct m3 { real m[3][3]; };  // row-major in registers

__device__ __forceinline__ v3 v3_load(const real* p) { v3 r; r.x[0] = p[0]; r.x[1] = p[1]; r.x[2] = p[2]; return r; }
__device__ __forceinline__ void v3_store(real* p, const v3& a) { p[0] = a.x[0]; p[1] = a.x[1]; p[2] = a.x[2]; }
__device__ __forceinline__ v3 v3_zero() { v3 r; r.x[0] = r.x[1] = r.x[2] = (real)0; return r; }
__device__ __forceinline__ real v3_dot(const v3& a, const v3& b) { return a.x[0] * b.x[0] + a.x[1] * b.x[1] + a.x[2] * b.x[2]; }
__device__ __forceinline__ real v3_norm(const v3& a) { return sqrt(v3_dot(a, a)); }
__device__ __forceinline__ v3 v3_scale(const v3& a, real s) { v3 r; for (int i = 0; i < 3; ++i) r.x[i] = a.x[i] * s; return r; }
__device__ __forceinline__ v3 v3_div(const v3& a, real s) { v3 r; for (int i = 0; i < 3; ++i) r.x[i] = a.x[i] / s; return r; }
__device__ __forceinline__ v3 v3_add(const v3& a, const v3& b) { v3 r; for (int i = 0; i < 3; ++i) r.x[i] = a.x[i] + b.x[i]; return r; }
__device__ __forceinline__ v3 v3_sub(const v3& a, const v3& b) { v3 r; for (int i = 0; i < 3; ++i) r.x[i] = a.x[i] - b.x[i]; return r; }
__device__ __forceinline__ v3 v3_cross(const v3& a, const v3& b) {
    v3 r;
    r.x[0] = a.x[1] * b.x[2] - a.x[2] * b.x[1];
    r.x[1] = a.x[2] * b.x[0] - a.x[0] * b.x[2];
    r.x[2] = a.x[0] * b.x[1] - a.x[1] * b.x[0];
    return r;
}
__device__ __forceinline__ v3 v3_normalize(const v3& a) { return v3_scale(a, (real)1 / v3_norm(a)); }

// Matrices travel column-major (nalgebra's layout): entry (r, c) at c*3 + r.
__device__ __forceinline__ m3 m3_load(const real* p) {
    m3 r;
    for (int i = 0; i < 3; ++i) for (int j = 0; j < 3; ++j) r.m[i][j] = p[j * 3 + i];
    return r;
}
__device__ __forceinline__ void m3_store(real* p, const m3& a) {
    for (int i = 0; i < 3; ++i) for (int j = 0; j < 3; ++j) p[j * 3 + i] = a.m[i][j];
}
__device__ __forceinline__ m3 m3_zero() { m3 r; for (int i = 0; i < 3; ++i) for (int j = 0; j < 3; ++j) r.m[i][j] = (real)0; return r; }
__device__ __forceinline__ m3 m3_identity() { m3 r = m3_zero(); r.m[0][0] = r.m[1][1] = r.m[2][2] = (real)1; return r; }
__device__ __forceinline__ m3 m3_transpose(const m3& a) { m3 r; for (int i = 0; i < 3; ++i) for (int j = 0; j < 3; ++j) r.m[i][j] = a.m[j][i]; return r; }
__device__ __forceinline__ m3 m3_mul(const m3& a, const m3& b) {
    m3 r;
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            r.m[i][j] = a.m[i][0] * b.m[0][j] + a.m[i][1] * b.m[1][j] + a.m[i][2] * b.m[2][j];
    return r;
}
__device__ __forceinline__ v3 m3_mul_v(const m3& a, const v3& v) {
    v3 r;
    for (int i = 0; i < 3; ++i) r.x[i] = a.m[i][0] * v.x[0] + a.m[i][1] * v.x[1] + a.m[i][2] * v.x[2];
    return r;
}
__device__ __forceinline__ m3 m3_scale(const m3& a, real s) { m3 r; for (int i = 0; i < 3; ++i) for (int j = 0; j < 3; ++j) r.m[i][j] = a.m[i][j] * s; return r; }
__device__ __forceinline__ m3 m3_add(const m3& a, const m3& b) { m3 r; for (int i = 0; i < 3; ++i) for (int j = 0; j < 3; ++j) r.m[i][j] = a.m[i][j] + b.m[i][j]; return r; }
__device__ __forceinline__ m3 m3_sub(const m3& a, const m3& b) { m3 r; for (int i = 0; i < 3; ++i) for (int j = 0; j < 3; ++j) r.m[i][j] = a.m[i][j] - b.m[i][j]; return r; }
__device__ __forceinline__ m3 m3_add_diagonal(const m3& a, real d) { m3 r = a; r.m[0][0] += d; r.m[1][1] += d; r.m[2][2] += d; return r; }
__device__ __forceinline__ real m3_trace(const m3& a) { return a.m[0][0] + a.m[1][1] + a.m[2][2]; }
__device__ __forceinline__ real m3_norm_squared(const m3& a) {
    real s = (real)0;
    for (int i = 0; i < 3; ++i) for (int j = 0; j < 3; ++j) s += a.m[i][j] * a.m[i][j];
    return s;
}
__device__ __forceinline__ real m3_det(const m3& a) {
    const real (*m)[3] = a.m;
    return m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
         - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
         + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
}
// The cofactor matrix: F⁻ᵀ = cofactor(F) / det F.
__device__ __forceinline__ m3 m3_cofactor(const m3& a) {
    const real (*m)[3] = a.m;
    m3 r;
    r.m[0][0] = m[1][1] * m[2][2] - m[1][2] * m[2][1];
    r.m[0][1] = m[1][2] * m[2][0] - m[1][0] * m[2][2];
    r.m[0][2] = m[1][0] * m[2][1] - m[1][1] * m[2][0];
    r.m[1][0] = m[0][2] * m[2][1] - m[0][1] * m[2][2];
    r.m[1][1] = m[0][0] * m[2][2] - m[0][2] * m[2][0];
    r.m[1][2] = m[0][1] * m[2][0] - m[0][0] * m[2][1];
    r.m[2][0] = m[0][1] * m[1][2] - m[0][2] * m[1][1];
    r.m[2][1] = m[0][2] * m[1][0] - m[0][0] * m[1][2];
    r.m[2][2] = m[0][0] * m[1][1] - m[0][1] * m[1][0];
    return r;
}
__device__ __forceinline__ v3 m3_column(const m3& a, int c) { v3 r; for (int i = 0; i < 3; ++i) r.x[i] = a.m[i][c]; return r; }
__device__ __forceinline__ void m3_set_column(m3& a, int c, const v3& v) { for (int i = 0; i < 3; ++i) a.m[i][c] = v.x[i]; }
__device__ __forceinline__ int is_finite_real(real x) { return isfinite(x); }

// The 3x3x3 quadratic B-spline support of one particle (grid.rs).
struct Stencil {
    int base[3];
    real w[3][3];
    real frac[3];
};

__device__ __forceinline__ int stencil_base(real coord_cells, int res) {
    real b = floor(coord_cells - (real)0.5);
    if (b >= (real)0) {
        // Clamped before the cast, so a huge value ends at res - 3.
        if (b > (real)(res - 3)) return res - 3;
        return (int)b;
    }
    return 0;  // negative or NaN
}

__device__ __forceinline__ Stencil make_stencil(const Consts& k, const v3& x) {
    Stencil st;
    for (int a = 0; a < 3; ++a) {
        real g = (x.x[a] - k.origin[a]) * k.inv_dx;
        st.base[a] = stencil_base(g, k.res);
        real f = g - (real)st.base[a];
        st.frac[a] = f;
        real d0 = (real)1.5 - f;
        real d1 = f - (real)1;
        real d2 = f - (real)0.5;
        st.w[a][0] = (real)0.5 * d0 * d0;
        st.w[a][1] = (real)0.75 - d1 * d1;
        st.w[a][2] = (real)0.5 * d2 * d2;
    }
    return st;
}

__device__ __forceinline__ long long node_index(int res, int i, int j, int k) {
    return ((long long)i * res + j) * res + k;
}
