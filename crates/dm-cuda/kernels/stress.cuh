// Kirchhoff stress τ = P Fᵀ of the constitutive experts and their
// mixture (experts.rs): NH μ(FFᵀ − I) + λ ln J I; FCR 2μ(F − R)Fᵀ +
// λ(J − 1)J I; StVK F(2μE + λ tr E I)Fᵀ. Zero-weight experts are skipped.

__device__ __forceinline__ m3 neo_hookean_kirchhoff(const m3& f, const m3& ft, real j, real mu, real lambda) {
    return m3_add_diagonal(m3_scale(m3_add_diagonal(m3_mul(f, ft), (real)-1), mu), lambda * log(j));
}

__device__ m3 mixture_kirchhoff(const m3& f, real mu, real lambda, const real w[3]) {
    m3 ft = m3_transpose(f);
    real j = m3_det(f);
    m3 tau = m3_zero();
    if (w[0] != (real)0) tau = m3_add(tau, m3_scale(neo_hookean_kirchhoff(f, ft, j, mu, lambda), w[0]));
    if (w[1] != (real)0) {
        m3 r = polar_rotation(f);
        m3 term = m3_add_diagonal(m3_scale(m3_mul(m3_sub(f, r), ft), mu + mu), lambda * (j - (real)1) * j);
        tau = m3_add(tau, m3_scale(term, w[1]));
    }
    if (w[2] != (real)0) {
        m3 green = m3_scale(m3_add_diagonal(m3_mul(ft, f), (real)-1), (real)0.5);
        m3 inner = m3_add_diagonal(m3_scale(green, mu + mu), lambda * m3_trace(green));
        tau = m3_add(tau, m3_scale(m3_mul(m3_mul(f, inner), ft), w[2]));
    }
    return tau;
}
