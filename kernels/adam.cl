/*
 * One Adam step (Kingma & Ba, ICLR 2015; host/optim/adam.py, the NumPy twin) of
 * a complex field F = exp(ρ)·e^{iθ} in its polar parameters, from the
 * gradient of the display loss (kernels/display_loss.cl, G_A then Hᴴ·G_A
 * by kernels/field_operator.cl):
 *
 *   G_F = Hᴴ·G_A + 2λ_E·F/(N·P_m),
 *   ∂L/∂ρ = Re(conj(G_F)·F),  ∂L/∂θ = −Im(conj(G_F)·F),
 *   m ← β1·m + (1 − β1)·g,  v ← β2·v + (1 − β2)·g²,
 *   p ← p − lr·(m/c1)/(sqrt(v/c2) + ε),  c1 = 1 − β1^t, c2 = 1 − β2^t,
 *
 * then F ← exp(ρ)·(cos θ + i·sin θ) for the next step. lr, c1 and c2 come
 * from the host each step (the clock sets lr); P_m from stats[STAT_PEAK]
 * (kernels/display_loss.cl's layout). One work-item per cell.
 *
 * Defines (host/stage1/display_device.py, program_defines, as for
 * kernels/display_loss.cl): NZ, NX, ENERGY_WEIGHT, ADAM_BETA1, ADAM_BETA2,
 * ADAM_EPSILON, STAT_PEAK; OCTCL_DOUBLE for float64.
 */

static inline real adam_update(real param, real grad, __global real *first, __global real *second, int e,
                               real lr, real first_correction, real second_correction) {
    const real m = (real)ADAM_BETA1 * first[e] + (1 - (real)ADAM_BETA1) * grad;
    const real v = (real)ADAM_BETA2 * second[e] + (1 - (real)ADAM_BETA2) * grad * grad;
    first[e] = m;
    second[e] = v;
    return param - lr * (m / first_correction) / (sqrt(v / second_correction) + (real)ADAM_EPSILON);
}

__kernel void adam_polar_step(__global const complex_t *field_grad, __global complex_t *field,
                              __global real *log_magnitude, __global real *phase,
                              __global real *first_log_magnitude, __global real *second_log_magnitude,
                              __global real *first_phase, __global real *second_phase,
                              __global const real *stats, real lr, real first_correction, real second_correction) {
    const int e = get_global_id(0);
    const complex_t f = field[e];
    const complex_t g = field_grad[e] + (2 * (real)ENERGY_WEIGHT / (NX * NZ)) / stats[STAT_PEAK] * f;
    const complex_t along = cconj_mul(g, f);
    const real rho = adam_update(log_magnitude[e], along.x, first_log_magnitude, second_log_magnitude, e,
                                 lr, first_correction, second_correction);
    const real theta = adam_update(phase[e], -along.y, first_phase, second_phase, e,
                                   lr, first_correction, second_correction);
    log_magnitude[e] = rho;
    phase[e] = theta;
    real cosine;
    const real sine = sincos(theta, &cosine);
    field[e] = exp(rho) * (complex_t)(cosine, sine);
}
