/*
 * L-BFGS's vector operations (host/optim/lbfgs.py's algorithm; host/optim/lbfgs_device.py the op,
 * the loop and the compact representation's small algebra) on device vectors of n reals: a complex
 * field is the real vector of its (Re, Im) pairs, 2·NX·NZ reals. The pairs (s_j, y_j) live in two
 * rings of slots, `s` and `y`, slot j the n reals from j·n; `stored` is a mask of the slots a kernel
 * reads, bit j for slot j, at most 63 slots (a loop over the slots ends at the mask's highest bit).
 * Sums go into partials and from there, in a fixed order (no atomics: the same bits every run),
 * into a small device array `scalars`:
 *
 *   dot_partial      partials[g] = Σ x_i·y_i over group g's elements: work-item j of the launch's
 *                    G·REDUCTION_GROUP_SIZE adds elements j, j + G·REDUCTION_GROUP_SIZE, … in that
 *                    order, then the group adds its work-items' sums by the prelude's group_sum (a
 *                    fixed tree in local memory);
 *   finish_sum       scalars[slot] = Σ_g partials[g], one work-group, the same way;
 *   axpy             out = x + c·d, c from the host (the line search's trial point x + t·d);
 *   pair_dots        a trial step's pair and every dot product the next direction needs, in one
 *                    pass: s_new = x' − x and y_new = g' − g into the rings' slot `fresh`, the sums
 *                    ⟨g', g'⟩, ⟨s_new, y_new⟩, ⟨y_new, y_new⟩, ⟨s_new, g'⟩, ⟨y_new, g'⟩
 *                    (k = 0 … PAIR_SUMS − 1, PAIR_SUMS = 5), and for each stored slot j ⟨s_j, g'⟩,
 *                    ⟨y_j, g'⟩, ⟨s_j, y_new⟩, ⟨y_j, y_new⟩ (k = PAIR_SUMS + 4j …); work-item p
 *                    of P adds the elements p, p + P, … and writes its sum k to partials[k·P + p],
 *                    so a group's g' and y_new come from cache for each slot after the first;
 *   finish_sums      scalars[base + k] = Σ_p partials[k·P + p] for pair_dots' sums of the stored
 *                    slots and the first PAIR_SUMS, one work-group each, as finish_sum;
 *   direction        d = c[0]·g + Σ_{j stored} (c[1 + 2j]·s_j + c[2 + 2j]·y_j), the coefficients c a
 *                    device array, the slots in increasing order, and the first trial point
 *                    x + t·d in the same pass.
 *
 * Element-wise kernels take one work-item per element; dot_partial and pair_dots take groups of
 * REDUCTION_GROUP_SIZE, finish_sum one group, finish_sums one group per sum.
 *
 * Defines (host/optim/lbfgs_device.py, program_defines): REDUCTION_GROUP_SIZE (a power of two),
 * PAIR_SUMS; OCTCL_DOUBLE for float64.
 */

__kernel __attribute__((reqd_work_group_size(REDUCTION_GROUP_SIZE, 1, 1)))
void dot_partial(__global const real *x, __global const real *y, int n, __global real *partials) {
    __local real sums[REDUCTION_GROUP_SIZE];
    real sum = 0;
    for (int i = get_global_id(0); i < n; i += get_global_size(0)) sum += x[i] * y[i];
    sum = group_sum(sum, sums, REDUCTION_GROUP_SIZE);
    if (get_local_id(0) == 0) partials[get_group_id(0)] = sum;
}

__kernel __attribute__((reqd_work_group_size(REDUCTION_GROUP_SIZE, 1, 1)))
void finish_sum(__global const real *partials, int count, __global real *scalars, int slot) {
    __local real sums[REDUCTION_GROUP_SIZE];
    real sum = 0;
    for (int g = get_local_id(0); g < count; g += REDUCTION_GROUP_SIZE) sum += partials[g];
    sum = group_sum(sum, sums, REDUCTION_GROUP_SIZE);
    if (get_local_id(0) == 0) scalars[slot] = sum;
}

__kernel void axpy(__global const real *x, real c, __global const real *d, __global real *out) {
    const int i = get_global_id(0);
    out[i] = x[i] + c * d[i];
}

/* Every work-item writes its own sums, so that no barrier sits in the loop over the slots (with a group's tree
 * there, Intel's CPU runtime took 4-6 ms for this pass at m = 10 instead of 1.3-2.2 ms). */
__kernel __attribute__((reqd_work_group_size(REDUCTION_GROUP_SIZE, 1, 1)))
void pair_dots(__global const real *x_next, __global const real *x, __global const real *g_next,
               __global const real *g, __global real *s, __global real *y, int n, int fresh, ulong stored,
               __global real *partials) {
    const int items = get_global_size(0), id = get_global_id(0);
    __global real *s_new = s + (size_t)fresh * n, *y_new = y + (size_t)fresh * n;
    real squared = 0, curvature = 0, change_squared = 0, step_gradient = 0, change_gradient = 0;
    for (int i = id; i < n; i += items) {
        const real step = x_next[i] - x[i], change = g_next[i] - g[i], gradient = g_next[i];
        s_new[i] = step;
        y_new[i] = change;
        squared += gradient * gradient;
        curvature += step * change;
        change_squared += change * change;
        step_gradient += step * gradient;
        change_gradient += change * gradient;
    }
    partials[id] = squared;
    partials[items + id] = curvature;
    partials[2 * items + id] = change_squared;
    partials[3 * items + id] = step_gradient;
    partials[4 * items + id] = change_gradient;
    for (int slot = 0; (stored >> slot) != 0; ++slot) {
        if (((stored >> slot) & 1) == 0) continue;
        __global const real *s_j = s + (size_t)slot * n, *y_j = y + (size_t)slot * n;
        real s_gradient = 0, y_gradient = 0, s_change = 0, y_change = 0;
        for (int i = id; i < n; i += items) {
            const real gradient = g_next[i], change = y_new[i], step = s_j[i], other = y_j[i];
            s_gradient += step * gradient;
            y_gradient += other * gradient;
            s_change += step * change;
            y_change += other * change;
        }
        __global real *out = partials + (PAIR_SUMS + 4 * slot) * items + id;
        out[0] = s_gradient;
        out[items] = y_gradient;
        out[2 * items] = s_change;
        out[3 * items] = y_change;
    }
}

__kernel __attribute__((reqd_work_group_size(REDUCTION_GROUP_SIZE, 1, 1)))
void finish_sums(__global const real *partials, int count, ulong stored, __global real *scalars, int base) {
    __local real sums[REDUCTION_GROUP_SIZE];
    const int k = get_group_id(0);
    if (k >= PAIR_SUMS && ((stored >> ((k - PAIR_SUMS) / 4)) & 1) == 0) return;  /* the whole group */
    real sum = 0;
    for (int g = get_local_id(0); g < count; g += REDUCTION_GROUP_SIZE) sum += partials[k * count + g];
    sum = group_sum(sum, sums, REDUCTION_GROUP_SIZE);
    if (get_local_id(0) == 0) scalars[base + k] = sum;
}

__kernel void direction(__global const real *g, __global const real *s, __global const real *y, int n,
                        ulong stored, __global const real *coefficients, __global const real *x, real step,
                        __global real *d, __global real *trial) {
    const int i = get_global_id(0);
    real sum = coefficients[0] * g[i];
    for (int slot = 0; (stored >> slot) != 0; ++slot) {
        if (((stored >> slot) & 1) == 0) continue;
        const size_t at = (size_t)slot * n + i;
        sum += coefficients[1 + 2 * slot] * s[at] + coefficients[2 + 2 * slot] * y[at];
    }
    d[i] = sum;
    trial[i] = x[i] + step * sum;
}
