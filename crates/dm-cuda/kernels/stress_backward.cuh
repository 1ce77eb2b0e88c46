// VJPs of the experts' Kirchhoff stresses and their mixture
// (experts_backward.rs): given G = ∂L/∂τ, the gradients of F, μ, λ and
// ⟨G, τₖ⟩ per expert (the weights' gradients).

__device__ __forceinline__ real m3_dot(const m3& a, const m3& b) {
    real s = (real)0;
    for (int i = 0; i < 3; ++i) for (int j = 0; j < 3; ++j) s += a.m[i][j] * b.m[i][j];
    return s;
}

__device__ __forceinline__ m3 inverse_transpose(const m3& f, real j) {
    return m3_scale(m3_cofactor(f), (real)1 / j);
}

struct ExpertGrads {
    m3 f;
    real mu, lambda;
};

// τ = μ(FFᵀ − I) + λ ln J I.
__device__ ExpertGrads neo_hookean_kirchhoff_vjp(const m3& f, real mu, real lambda, const m3& g) {
    real j = m3_det(f);
    m3 g_sym2 = m3_add(g, m3_transpose(g));
    real trace_g = m3_trace(g);
    ExpertGrads out;
    out.f = m3_add(m3_scale(m3_mul(g_sym2, f), mu), m3_scale(inverse_transpose(f, j), lambda * trace_g));
    out.mu = m3_dot(g, m3_mul(f, m3_transpose(f))) - trace_g;
    out.lambda = trace_g * log(j);
    return out;
}

// τ = 2μ(F − R)Fᵀ + λ(J − 1)J I, given R.
__device__ ExpertGrads fixed_corotated_kirchhoff_vjp(const m3& f, const m3& r, real mu, real lambda, const m3& g) {
    real j = m3_det(f);
    real two_mu = mu + mu;
    real trace_g = m3_trace(g);
    m3 f_minus_r = m3_sub(f, r);
    m3 g_f = m3_mul(g, f);
    m3 grad_r = m3_scale(g_f, -two_mu);
    real volume_scale = lambda * (j + j - (real)1) * j * trace_g;
    ExpertGrads out;
    out.f = m3_add(m3_add(m3_scale(m3_add(g_f, m3_mul(m3_transpose(g), f_minus_r)), two_mu),
                          polar_rotation_vjp(f, r, grad_r)),
                   m3_scale(inverse_transpose(f, j), volume_scale));
    out.mu = m3_dot(g, m3_mul(f_minus_r, m3_transpose(f))) * (real)2;
    out.lambda = trace_g * (j - (real)1) * j;
    return out;
}

// τ = F S Fᵀ, S = 2μE + λ tr(E) I, E = (FᵀF − I)/2.
__device__ ExpertGrads stvk_kirchhoff_vjp(const m3& f, real mu, real lambda, const m3& g) {
    m3 ft = m3_transpose(f);
    m3 green = m3_scale(m3_add_diagonal(m3_mul(ft, f), (real)-1), (real)0.5);
    real trace_e = m3_trace(green);
    real two_mu = mu + mu;
    m3 second_piola = m3_add_diagonal(m3_scale(green, two_mu), lambda * trace_e);
    m3 h = m3_mul(m3_mul(ft, g), f);
    m3 h_sym = m3_scale(m3_add(h, m3_transpose(h)), (real)0.5);
    m3 g_sym2 = m3_add(g, m3_transpose(g));
    ExpertGrads out;
    out.f = m3_add(m3_mul(m3_mul(g_sym2, f), second_piola),
                   m3_mul(f, m3_add_diagonal(m3_scale(h_sym, two_mu), lambda * m3_trace(h))));
    out.mu = m3_dot(h, green) * (real)2;
    out.lambda = m3_trace(h) * trace_e;
    return out;
}

struct KirchhoffGrads {
    m3 f;
    real mu, lambda;
    real weights[3];
};

// VJP of the mixture τ = Σₖ wₖ τₖ given R = polar_rotation(F); a
// zero-weight expert adds nothing to F's gradient but keeps its ⟨G, τₖ⟩.
__device__ KirchhoffGrads mixture_kirchhoff_vjp(const m3& f, const m3& r, real mu, real lambda, const real w[3], const m3& g) {
    KirchhoffGrads out;
    out.f = m3_zero();
    out.mu = (real)0;
    out.lambda = (real)0;
    for (int k = 0; k < 3; ++k) {
        real grad_mu, grad_lambda;
        if (w[k] != (real)0) {
            ExpertGrads e = k == 0 ? neo_hookean_kirchhoff_vjp(f, mu, lambda, g)
                          : k == 1 ? fixed_corotated_kirchhoff_vjp(f, r, mu, lambda, g)
                                   : stvk_kirchhoff_vjp(f, mu, lambda, g);
            out.f = m3_add(out.f, m3_scale(e.f, w[k]));
            grad_mu = e.mu;
            grad_lambda = e.lambda;
        } else if (k == 0) {
            real trace_g = m3_trace(g);
            grad_mu = m3_dot(g, m3_mul(f, m3_transpose(f))) - trace_g;
            grad_lambda = trace_g * log(m3_det(f));
        } else if (k == 1) {
            real j = m3_det(f);
            grad_mu = m3_dot(g, m3_mul(m3_sub(f, r), m3_transpose(f))) * (real)2;
            grad_lambda = m3_trace(g) * (j - (real)1) * j;
        } else {
            m3 ft = m3_transpose(f);
            m3 green = m3_scale(m3_add_diagonal(m3_mul(ft, f), (real)-1), (real)0.5);
            m3 h = m3_mul(m3_mul(ft, g), f);
            grad_mu = m3_dot(h, green) * (real)2;
            grad_lambda = m3_trace(h) * m3_trace(green);
        }
        out.mu += grad_mu * w[k];
        out.lambda += grad_lambda * w[k];
        out.weights[k] = mu * grad_mu + lambda * grad_lambda;
    }
    return out;
}
