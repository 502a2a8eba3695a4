/*
 * L-BFGS's vector operations (host/lbfgs.py's algorithm; host/lbfgs_device.py the op and the loop)
 * on device vectors of n reals: a complex field is the real vector of its (Re, Im) pairs, 2·NX·NZ
 * reals. Dot products land in a small device array `scalars`, and the updates of the two-loop
 * recursion read their coefficients from it, so the recursion runs without a host round trip:
 *
 *   dot_partial      partials[g] = Σ x_i·y_i over group g's elements: work-item j of the launch's
 *                    G·WG_SIZE adds elements j, j + G·WG_SIZE, … in that order, then the group
 *                    adds its work-items' sums by a fixed tree in local memory (no atomics: the
 *                    same bits every run);
 *   finish_sum       scalars[slot] = Σ_g partials[g], one work-group, the same way;
 *   axpy             out = x + c·d, c from the host (the line search's trial point x + t·d);
 *   axpy_ratio       y += ((scalars[plus] − scalars[minus])/scalars[divisor])·x:
 *                      first loop  q −= ρ_i·⟨s_i, q⟩·y_i    (plus a zero slot, minus ⟨s_i, q⟩,
 *                                                           divisor ⟨s_i, y_i⟩ = 1/ρ_i),
 *                      second loop q += (α_i − β_i)·s_i,   α_i − β_i = ρ_i·(⟨s_i, q⟩ − ⟨y_i, q⟩),
 *                                                           ⟨s_i, q⟩ the first loop's;
 *   axpy_ratio_dot   axpy_ratio, then the group sums of ⟨y, z⟩ as dot_partial's: an update of the
 *                    recursion and the dot product after it in one pass over the vectors;
 *   scale_ratio      x *= scalars[numerator]/scalars[denominator]   (H_k⁰ = ⟨s, y⟩/⟨y, y⟩);
 *   pair_difference  s = x' − x, y = g' − g, the curvature pair of a step.
 *
 * Element-wise kernels take one work-item per element; dot_partial and axpy_ratio_dot take G groups
 * of WG_SIZE.
 *
 * Defines: WG_SIZE (a power of two); OCTCL_DOUBLE for float64.
 */

#ifdef OCTCL_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
#else
typedef float real;
#endif

/* Σ of every work-item's value over the group by a fixed tree; valid in every work-item. */
static real group_sum(real value, __local real *sums) {
    const int lid = get_local_id(0);
    sums[lid] = value;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int width = WG_SIZE >> 1; width > 0; width >>= 1) {
        if (lid < width) sums[lid] += sums[lid + width];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    return sums[0];
}

__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
void dot_partial(__global const real *x, __global const real *y, int n, __global real *partials) {
    __local real sums[WG_SIZE];
    real sum = 0;
    for (int i = get_global_id(0); i < n; i += get_global_size(0)) sum += x[i] * y[i];
    sum = group_sum(sum, sums);
    if (get_local_id(0) == 0) partials[get_group_id(0)] = sum;
}

__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
void finish_sum(__global const real *partials, int count, __global real *scalars, int slot) {
    __local real sums[WG_SIZE];
    real sum = 0;
    for (int g = get_local_id(0); g < count; g += WG_SIZE) sum += partials[g];
    sum = group_sum(sum, sums);
    if (get_local_id(0) == 0) scalars[slot] = sum;
}

__kernel void axpy(__global const real *x, real c, __global const real *d, __global real *out) {
    const int i = get_global_id(0);
    out[i] = x[i] + c * d[i];
}

__kernel void axpy_ratio(__global const real *x, __global real *y, __global const real *scalars,
                         int plus, int minus, int divisor) {
    const int i = get_global_id(0);
    y[i] += (scalars[plus] - scalars[minus]) / scalars[divisor] * x[i];
}

/* y += ((scalars[plus] − scalars[minus])/scalars[divisor])·x; partials[g] = Σ y_i·z_i (the updated y),
 * z another vector than y. */
__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
void axpy_ratio_dot(__global const real *x, __global real *y, __global const real *scalars, int plus, int minus,
                    int divisor, __global const real *z, int n, __global real *partials) {
    __local real sums[WG_SIZE];
    const real c = (scalars[plus] - scalars[minus]) / scalars[divisor];
    real sum = 0;
    for (int i = get_global_id(0); i < n; i += get_global_size(0)) {
        const real updated = y[i] + c * x[i];
        y[i] = updated;
        sum += updated * z[i];
    }
    sum = group_sum(sum, sums);
    if (get_local_id(0) == 0) partials[get_group_id(0)] = sum;
}

__kernel void scale_ratio(__global real *x, __global const real *scalars, int numerator, int denominator) {
    const int i = get_global_id(0);
    x[i] *= scalars[numerator] / scalars[denominator];
}

__kernel void pair_difference(__global const real *x_next, __global const real *x, __global const real *g_next,
                              __global const real *g, __global real *s, __global real *y) {
    const int i = get_global_id(0);
    s[i] = x_next[i] - x[i];
    y[i] = g_next[i] - g[i];
}
