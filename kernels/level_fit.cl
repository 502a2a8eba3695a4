/*
 * Stage 1's level intervals on a device field (host/stage1/projections.py, retrieve_field, and
 * host/stage1/hinge.py, fit_levels; host/stage1/levels_device.py the op). A-scans as
 * kernels/field_operator.cl stores them, pixel (n, i) at i·NZ + n; lower and upper in the same
 * order. Each pixel p's aimed level allows |A_p| in [l_p, u_p]; the set 𝓜 of such A is a product
 * of annuli, and its projection keeps each pixel's phase:
 *
 *   P_𝓜(A)_p = A_p·c_p/|A_p|,  c_p = min(max(|A_p|, l_p), u_p)   (|A_p| > 0; c_p itself at A_p = 0).
 *
 * Projections (Nesterov-accelerated alternating projections, step α, momentum β):
 *
 *   interval_difference  D = P_𝓜(A) − A, at A = H·Y_k;
 *   momentum_step        F_{k+1} = Y_k + α·X,  X = H⁺·D,
 *                        Y_{k+1} = F_{k+1} + β·(F_{k+1} − F_k),
 *                        the update and the next step's extrapolation in one pass.
 *
 * Hinge (fit_levels): f(F) = ½·Σ_p dist(|A_p|, [l_p, u_p])² = ½·Σ_p |r_p|², r = A − P_𝓜(A);
 * its gradient with respect to (Re F, Im F) is Hᴴ·r.
 *
 *   hinge_residual       r and partial sums of ½·|r|²: work-item j of the launch's
 *                        G·REDUCTION_GROUP_SIZE adds pixels j, j + G·REDUCTION_GROUP_SIZE, … in
 *                        that order, then its group adds the work-items' sums by the prelude's
 *                        group_sum (a fixed tree in local memory); no atomics, so the same bits
 *                        every run. kernels/lbfgs.cl's finish_sum adds the G group sums.
 *
 * Element-wise kernels take one work-item per pixel. In-place calls (out = the input A) are
 * allowed: each work-item reads its pixel before writing it.
 *
 * Defines (host/stage1/levels_device.py, program_defines): REDUCTION_GROUP_SIZE (a power of two);
 * OCTCL_DOUBLE for float64.
 */

/* P_𝓜 at one pixel. |A| as sqrt(Re² + Im²): hypot cost 30 times as much in Intel's CPU runtime, and
 * the two differ only where Re² + Im² leaves the normal range (|A| < 1e−19 in float32, the field
 * scaled so that max|A| ~ 1), far below the rounding of H·F. */
static inline complex_t projected(complex_t a, real lower, real upper) {
    const real magnitude = sqrt(a.x * a.x + a.y * a.y);
    const real clipped = fmin(fmax(magnitude, lower), upper);
    return magnitude > 0 ? a * (clipped / magnitude) : (complex_t)(clipped, 0);
}

/* out = P_𝓜(A) − A. */
__kernel void interval_difference(__global const complex_t *a_scans, __global const real *lower,
                                  __global const real *upper, __global complex_t *out) {
    const int p = get_global_id(0);
    const complex_t a = a_scans[p];
    out[p] = projected(a, lower[p], upper[p]) - a;
}

/* field: F_k → F_{k+1}; ahead: Y_k → Y_{k+1}; correction = X = H⁺·D. */
__kernel void momentum_step(__global complex_t *field, __global complex_t *ahead,
                            __global const complex_t *correction, real step, real momentum) {
    const int p = get_global_id(0);
    const complex_t next = ahead[p] + step * correction[p];
    ahead[p] = next + momentum * (next - field[p]);
    field[p] = next;
}

/* residual = A − P_𝓜(A); partials[g] = ½·Σ|r_p|² over group g's pixels. */
__kernel __attribute__((reqd_work_group_size(REDUCTION_GROUP_SIZE, 1, 1)))
void hinge_residual(__global const complex_t *a_scans, __global const real *lower, __global const real *upper,
                    int pixels, __global complex_t *residual, __global real *partials) {
    __local real sums[REDUCTION_GROUP_SIZE];
    real sum = 0;
    for (int p = get_global_id(0); p < pixels; p += get_global_size(0)) {
        const complex_t a = a_scans[p];
        const complex_t r = a - projected(a, lower[p], upper[p]);
        residual[p] = r;
        sum += r.x * r.x + r.y * r.y;
    }
    sum = group_sum(sum, sums, REDUCTION_GROUP_SIZE);
    if (get_local_id(0) == 0) partials[get_group_id(0)] = (real)0.5 * sum;
}
