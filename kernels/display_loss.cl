/*
 * The display fit's loss and its gradient (host/stage1/display_loss.py,
 * display_loss, the float64/float32 NumPy twin), on A-scans A = H·F that
 * kernels/field_operator.cl made, stored A-scan by A-scan: pixel (n, i) at
 * e = i·NZ + n.
 *
 * With P = |A|², m the brightest pixel (the first in the host's row-major
 * order on ties), c = LOG_FLOOR·P_m (LOG_FLOOR = 10⁻²⁴), s = DISPLAY_SLOPE
 * and N pixels:
 *
 *   ℓ = ½·ln(P + c),  D = 1 + s·(ℓ − ℓ_m),
 *   D̃ = max(D, −1) where the target is visible, max(D, 0) at level 0,
 *   e = D̃ − D*,  r = hp(D̃) − hp(D*),  hp(X) = X − box3(X) (edges replicated),
 *   L = Σ(|e| + e²)/N + ½·Σ|r|/N + λ_E·(Σ|F|²/N)/P_m.
 *
 * Backwards (sgn 0 = 0; a clamp passes the gradient where D is at or above
 * its bound):
 *
 *   ∂L/∂D̃ = (sgn e + 2e)/N + ½·(sgn r − box3ᵀ(sgn r))/N,  box3ᵀ = box3
 *           (the edge-replicated 3×3 mean is its own adjoint: along each
 *           axis an edge value counts twice both ways),
 *   ∂L/∂ℓ = s·∂L/∂D − δ_m·s·Σ ∂L/∂D,
 *   G_A = ∂L/∂ℓ·A/(P + c) − δ_m·2A_m·λ_E·(Σ|F|²/N)/P_m².
 *
 * G_F = Hᴴ·G_A + 2λ_E·F/(N·P_m) follows in kernels/adam.cl's step.
 *
 * Passes, each a kernel (the sums and the brightest pixel are global, so
 * each ends a pass): peak_partials, finish_peak, display_error,
 * high_pass_residual, display_gradient, finish_loss, a_scan_gradient.
 * A pass runs PARTIALS work-groups of REDUCTION_GROUP_SIZE work-items,
 * PASS_SIZE in all, each work-item over the pixels e ≡ its global id
 * (mod PASS_SIZE) (contiguous across work-items: vector lanes on a CPU,
 * coalesced on a GPU). Sums are reduced per work-item in that order, per
 * work-group by the prelude's group_sum (a fixed tree in local memory) and
 * over the work-groups by one work-group: no atomics, so a fit repeats bit
 * for bit on a device.
 *
 * stats[] (real), its slots numbered by the host: STAT_PEAK P_m, STAT_ENERGY
 * Σ|F|², STAT_ERROR Σ(|e| + e²), STAT_RESIDUAL Σ|r|, STAT_DISPLAY_GRADIENT
 * Σ ∂L/∂D; brightest[0] = e_m.
 *
 * Defines (host/stage1/display_device.py, program_defines): NZ, NX,
 * REDUCTION_GROUP_SIZE (a power of two), PARTIALS (work-groups of a pass
 * over the pixels), DISPLAY_SLOPE, FLOOR_VISIBLE (−1), HIGH_PASS_WEIGHT,
 * ENERGY_WEIGHT, LOG_FLOOR, STAT_PEAK, STAT_ENERGY, STAT_ERROR,
 * STAT_RESIDUAL, STAT_DISPLAY_GRADIENT; OCTCL_DOUBLE for float64.
 */

#define PIXELS (NX * NZ)
#define PASS_SIZE (PARTIALS * REDUCTION_GROUP_SIZE)

/* The host's row-major index of device pixel e, for the tie order of the brightest pixel. */
static inline int host_index(int e) { return (e % NZ) * NX + e / NZ; }

/* (P, e) pairs: the larger P wins, on a tie the first in the host's order. */
static inline bool brighter(real power, int e, real best_power, int best) {
    return power > best_power || (power == best_power && host_index(e) < host_index(best));
}

static void group_brightest(__local real *power, __local int *index) {
    const int lid = get_local_id(0);
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int width = REDUCTION_GROUP_SIZE >> 1; width > 0; width >>= 1) {
        if (lid < width && brighter(power[lid + width], index[lid + width], power[lid], index[lid])) {
            power[lid] = power[lid + width];
            index[lid] = index[lid + width];
        }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
}

/* Per work-group: the brightest pixel of its pixels and their Σ|F|². */
__kernel __attribute__((reqd_work_group_size(REDUCTION_GROUP_SIZE, 1, 1)))
void peak_partials(__global const complex_t *a_scans, __global const complex_t *field,
                   __global real *partial_power, __global int *partial_index, __global real *partial_energy) {
    __local real power[REDUCTION_GROUP_SIZE], scratch[REDUCTION_GROUP_SIZE];
    __local int index[REDUCTION_GROUP_SIZE];
    const int lid = get_local_id(0);
    real best_power = -1, energy = 0;
    int best = 0;
    for (int e = get_global_id(0); e < PIXELS; e += PASS_SIZE) {
        const complex_t a = a_scans[e], f = field[e];
        if (brighter(dot(a, a), e, best_power, best)) {
            best_power = dot(a, a);
            best = e;
        }
        energy += dot(f, f);
    }
    power[lid] = best_power;
    index[lid] = best;
    group_brightest(power, index);
    energy = group_sum(energy, scratch, REDUCTION_GROUP_SIZE);
    if (lid == 0) {
        partial_power[get_group_id(0)] = power[0];
        partial_index[get_group_id(0)] = index[0];
        partial_energy[get_group_id(0)] = energy;
    }
}

/* One work-group: P_m, e_m and Σ|F|² from the partials of peak_partials. */
__kernel __attribute__((reqd_work_group_size(REDUCTION_GROUP_SIZE, 1, 1)))
void finish_peak(__global const real *partial_power, __global const int *partial_index,
                 __global const real *partial_energy, __global real *stats, __global int *brightest) {
    __local real power[REDUCTION_GROUP_SIZE], scratch[REDUCTION_GROUP_SIZE];
    __local int index[REDUCTION_GROUP_SIZE];
    const int lid = get_local_id(0);
    real best_power = -1, energy = 0;
    int best = 0;
    for (int g = lid; g < PARTIALS; g += REDUCTION_GROUP_SIZE) {
        if (brighter(partial_power[g], partial_index[g], best_power, best)) {
            best_power = partial_power[g];
            best = partial_index[g];
        }
        energy += partial_energy[g];
    }
    power[lid] = best_power;
    index[lid] = best;
    group_brightest(power, index);
    energy = group_sum(energy, scratch, REDUCTION_GROUP_SIZE);
    if (lid == 0) {
        stats[STAT_PEAK] = power[0];
        brightest[0] = index[0];
        stats[STAT_ENERGY] = energy;
    }
}

/* D̃ of each pixel, whether its clamp passes the gradient (D at or above the bound), and Σ(|e| + e²) per
 * work-group. */
__kernel __attribute__((reqd_work_group_size(REDUCTION_GROUP_SIZE, 1, 1)))
void display_error(__global const complex_t *a_scans, __global const real *stats, __global const int *brightest,
                   __global const real *goal_display, __global const char *visible,
                   __global real *clamped, __global char *passes, __global real *partial_error) {
    __local real scratch[REDUCTION_GROUP_SIZE];
    const real peak = stats[STAT_PEAK], shift = (real)LOG_FLOOR * peak;
    const complex_t a_m = a_scans[brightest[0]];
    const real log_peak = log(dot(a_m, a_m) + shift);
    real term = 0;
    for (int e = get_global_id(0); e < PIXELS; e += PASS_SIZE) {
        const complex_t a = a_scans[e];
        const real d = 1 + (real)DISPLAY_SLOPE * (real)0.5 * (log(dot(a, a) + shift) - log_peak);
        const real floor_value = visible[e] ? (real)FLOOR_VISIBLE : (real)0;
        const real d_clamped = fmax(d, floor_value), error = d_clamped - goal_display[e];
        clamped[e] = d_clamped;
        passes[e] = d >= floor_value;
        term += fabs(error) + error * error;
    }
    const real sum = group_sum(term, scratch, REDUCTION_GROUP_SIZE);
    if (get_local_id(0) == 0) partial_error[get_group_id(0)] = sum;
}

/* box3 of an image at pixel (n, i): its 3×3 neighbours' mean, the indices clamped into the image (the edge
 * replicated). */
static inline real box3(__global const real *image, int n, int i) {
    real sum = 0;
    for (int di = -1; di <= 1; ++di) {
        const int column = clamp(i + di, 0, NX - 1) * NZ;
        for (int dn = -1; dn <= 1; ++dn) sum += image[column + clamp(n + dn, 0, NZ - 1)];
    }
    return sum / 9;
}

/* sgn r, r = hp(D̃) − hp(D*), and Σ|r| per work-group. */
__kernel __attribute__((reqd_work_group_size(REDUCTION_GROUP_SIZE, 1, 1)))
void high_pass_residual(__global const real *clamped, __global const real *goal_high_pass,
                        __global real *residual_sign, __global real *partial_residual) {
    __local real scratch[REDUCTION_GROUP_SIZE];
    real term = 0;
    for (int e = get_global_id(0); e < PIXELS; e += PASS_SIZE) {
        const real residual = clamped[e] - box3(clamped, e % NZ, e / NZ) - goal_high_pass[e];
        residual_sign[e] = sign(residual);
        term += fabs(residual);
    }
    const real sum = group_sum(term, scratch, REDUCTION_GROUP_SIZE);
    if (get_local_id(0) == 0) partial_residual[get_group_id(0)] = sum;
}

/* ∂L/∂D (zero where a clamp holds D̃ at its bound) and its Σ per work-group. */
__kernel __attribute__((reqd_work_group_size(REDUCTION_GROUP_SIZE, 1, 1)))
void display_gradient(__global const real *clamped, __global const char *passes,
                      __global const real *goal_display, __global const real *residual_sign,
                      __global real *display_grad, __global real *partial_display_grad) {
    __local real scratch[REDUCTION_GROUP_SIZE];
    real total = 0;
    for (int e = get_global_id(0); e < PIXELS; e += PASS_SIZE) {
        const real error = clamped[e] - goal_display[e];
        const real d_clamped = (sign(error) + 2 * error
                                + (real)HIGH_PASS_WEIGHT * (residual_sign[e] - box3(residual_sign, e % NZ, e / NZ)))
                               / PIXELS;
        const real d_display = passes[e] ? d_clamped : 0;
        display_grad[e] = d_display;
        total += d_display;
    }
    const real sum = group_sum(total, scratch, REDUCTION_GROUP_SIZE);
    if (get_local_id(0) == 0) partial_display_grad[get_group_id(0)] = sum;
}

/* One work-group: Σ(|e| + e²), Σ|r| and Σ ∂L/∂D from their partials, and the loss into losses[step]. */
__kernel __attribute__((reqd_work_group_size(REDUCTION_GROUP_SIZE, 1, 1)))
void finish_loss(__global const real *partial_error, __global const real *partial_residual,
                 __global const real *partial_display_grad, __global real *stats, __global real *losses, int step) {
    __local real scratch[REDUCTION_GROUP_SIZE];
    const int lid = get_local_id(0);
    real error = 0, residual = 0, display_grad = 0;
    for (int g = lid; g < PARTIALS; g += REDUCTION_GROUP_SIZE) {
        error += partial_error[g];
        residual += partial_residual[g];
        display_grad += partial_display_grad[g];
    }
    error = group_sum(error, scratch, REDUCTION_GROUP_SIZE);
    barrier(CLK_LOCAL_MEM_FENCE);
    residual = group_sum(residual, scratch, REDUCTION_GROUP_SIZE);
    barrier(CLK_LOCAL_MEM_FENCE);
    display_grad = group_sum(display_grad, scratch, REDUCTION_GROUP_SIZE);
    if (lid == 0) {
        stats[STAT_ERROR] = error;
        stats[STAT_RESIDUAL] = residual;
        stats[STAT_DISPLAY_GRADIENT] = display_grad;
        losses[step] = (error + (real)HIGH_PASS_WEIGHT * residual) / PIXELS
                       + (real)ENERGY_WEIGHT * (stats[STAT_ENERGY] / PIXELS) / stats[STAT_PEAK];
    }
}

/* G_A, the loss's gradient with respect to the A-scans (header). */
__kernel void a_scan_gradient(__global const complex_t *a_scans, __global const real *display_grad,
                              __global const real *stats, __global const int *brightest,
                              __global complex_t *a_scan_grad) {
    const int e = get_global_id(0);
    const real peak = stats[STAT_PEAK];
    const complex_t a = a_scans[e];
    real d_log = (real)DISPLAY_SLOPE * display_grad[e];
    complex_t grad;
    if (e == brightest[0]) {
        d_log -= (real)DISPLAY_SLOPE * stats[STAT_DISPLAY_GRADIENT];
        grad = d_log / (dot(a, a) + (real)LOG_FLOOR * peak) * a
               - 2 * (real)ENERGY_WEIGHT * (stats[STAT_ENERGY] / PIXELS) / (peak * peak) * a;
    } else {
        grad = d_log / (dot(a, a) + (real)LOG_FLOOR * peak) * a;
    }
    a_scan_grad[e] = grad;
}
