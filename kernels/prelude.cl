/*
 * What every octcl kernel file shares; octcl/device/programs.py puts this file before each one
 * (then `#line 1`, so that a compiler's line numbers are the kernel file's).
 *
 *   real, real2, complex_t   float, float2, float2; or double, double2, double2 where the host
 *                            defines OCTCL_DOUBLE (a float64 build, cl_khr_fp64). real2 is a
 *                            double-word number (hi, lo) or an affine map (a, b); complex_t is
 *                            (Re, Im).
 *   cmul, cconj_mul          a·b and conj(a)·b of two complex_t.
 *   group_sum                the fixed-order sum over a work-group (below).
 *
 * The helpers are static inline: a program that calls none of them compiles none of them.
 * Every other shared constant comes from the host as a -D define (octcl/device/programs.py,
 * build_options): no kernel file defines a value that the host also holds.
 */

#ifdef OCTCL_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
typedef double2 real2;
typedef double2 complex_t;
#else
typedef float real;
typedef float2 real2;
typedef float2 complex_t;
#endif

/* a·b = (a.x·b.x − a.y·b.y) + i·(a.x·b.y + a.y·b.x). */
static inline complex_t cmul(complex_t a, complex_t b) {
    return (complex_t)(a.x * b.x - a.y * b.y, a.x * b.y + a.y * b.x);
}

/* conj(a)·b = (a.x·b.x + a.y·b.y) + i·(a.x·b.y − a.y·b.x). */
static inline complex_t cconj_mul(complex_t a, complex_t b) {
    return (complex_t)(a.x * b.x + a.y * b.y, a.x * b.y - a.y * b.x);
}

/* Σ_l value_l over the `items` work-items of a work-group (a power of two: the kernel's
 * reqd_work_group_size, so that the loop unrolls), by a fixed tree in local memory: for
 * width = items/2, items/4, …, 1, work-item l < width adds scratch[l + width] to scratch[l].
 * The same additions in the same order on every run, so a sum repeats bit for bit (no atomics).
 * Every work-item calls it and every one gets the sum. scratch holds `items` reals; a caller that
 * reuses it for another sum puts a barrier between the two (every work-item reads scratch[0]
 * first). */
static inline real group_sum(real value, __local real *scratch, int items) {
    const int lid = get_local_id(0);
    scratch[lid] = value;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int width = items >> 1; width > 0; width >>= 1) {
        if (lid < width) scratch[lid] += scratch[lid + width];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    return scratch[0];
}
