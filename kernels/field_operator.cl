/*
 * The field operator of stage 1 (host/field.py, FieldOperator) and its
 * regularised inverse, on a field stored A-scan by A-scan: element (n, i),
 * depth n of A-scan i, at i·NZ + n, so that a column is contiguous
 * (coalesced on a GPU, one vector load per lane group on a CPU).
 *
 *   A = H·F,  H = L ∘ D:
 *     D  the depth convolution: per A-scan, A = IDFT_q(w_q·DFT_n(F)), w the
 *        scanner's Hann window (circular, as the scanner's DFT wraps);
 *     L  the lateral stencil: A[n, i] = Σ_{|d| ≤ REACH} g[d]·F[n, i − d],
 *        zero outside 0 ≤ i − d < NX (the beam does not wrap).
 *
 *   Both have real transfer functions (w real; g real and even), so H is
 *   self-adjoint: Hᴴ = H, ⟨H·x, y⟩ = ⟨x, H·y⟩, and the adjoint runs the
 *   same two kernels (tests/test_field_kernels.py checks the identity).
 *
 *   H⁺·A = IDFT_2(conj(Ĥ)/(|Ĥ|² + λ)·DFT_2(A)) over the columns zero-padded
 *   to PADDED (a power of two ≥ NX + 2·REACH): depth_fft forward, then
 *   lateral_filter (pad, FFT, the filter, inverse FFT, crop) per depth
 *   frequency, then depth_fft inverse. The filter comes from the host
 *   with both transforms' normalisation in it.
 *
 * FFTs are radix-2 Stockham autosort transforms in local memory
 * (Govindaraju et al., "High performance discrete Fourier transforms on
 * graphics processors", SC 2008): each stage reads x[j] and x[j + n/2]
 * and writes runs of Ns, ping-ponging between two local arrays, so no
 * bit-reversal pass and contiguous reads. The scanner's fft_local
 * (kernels/scanner.cl) works in place with a bit-reversal pass on one
 * array; this one needs the second array, which the field's work-groups
 * have room for. twiddle[k] = exp(−2πi·k/TWIDDLE_N), k < TWIDDLE_N/2,
 * from the host in float64; a shorter transform strides through it.
 *
 * Defines: NZ, LOG2_NZ, NX, REACH, PADDED, LOG2_PADDED, TWIDDLE_N, WG_SIZE;
 * OCTCL_DOUBLE for float64.
 */

#ifdef OCTCL_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
typedef double2 complex_t;
#else
typedef float real;
typedef float2 complex_t;
#endif

static inline complex_t cmul(complex_t a, complex_t b) {
    return (complex_t)(a.x * b.x - a.y * b.y, a.x * b.y + a.y * b.x);
}

/* x ← Σ_n x[n]·exp(sign·2πi·k·n/len), len = 1 << log2n, with y as scratch;
 * returns the array holding the result (x or y). Call with every work-item
 * of the group; returns after a barrier. */
static __local complex_t *fft_stockham(__local complex_t *x, __local complex_t *y, int log2n, int sign,
                                       __global const complex_t *twiddle) {
    const int n = 1 << log2n, middle = n >> 1, lid = get_local_id(0);
    for (int span = 1, stride = TWIDDLE_N >> 1; span < n; span <<= 1, stride >>= 1) {
        for (int j = lid; j < middle; j += WG_SIZE) {
            const int k = j & (span - 1);
            complex_t w = twiddle[k * stride];
            w.y = sign < 0 ? w.y : -w.y;
            const complex_t top = x[j], bottom = cmul(w, x[j + middle]);
            const int out = ((j - k) << 1) + k;
            y[out] = top + bottom;
            y[out + span] = top - bottom;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        __local complex_t *swap = x;
        x = y;
        y = swap;
    }
    return x;
}

/* D (= Dᴴ): one work-group per A-scan. window[q] = w_q/NZ. */
__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
void depth_convolve(__global const complex_t *field, __global complex_t *out,
                    __global const real *window, __global const complex_t *twiddle) {
    __local complex_t x[NZ], y[NZ];
    const size_t column = (size_t)get_group_id(0) * NZ;
    const int lid = get_local_id(0);
    for (int n = lid; n < NZ; n += WG_SIZE) x[n] = field[column + n];
    barrier(CLK_LOCAL_MEM_FENCE);
    __local complex_t *spectrum = fft_stockham(x, y, LOG2_NZ, -1, twiddle);
    __local complex_t *scratch = spectrum == x ? y : x;
    for (int q = lid; q < NZ; q += WG_SIZE) spectrum[q] *= window[q];
    barrier(CLK_LOCAL_MEM_FENCE);
    __local complex_t *result = fft_stockham(spectrum, scratch, LOG2_NZ, +1, twiddle);
    for (int n = lid; n < NZ; n += WG_SIZE) out[column + n] = result[n];
}

/* L (= Lᴴ): one work-item per element. taps[REACH + d] = g[d]. */
__kernel void lateral_convolve(__global const complex_t *field, __global complex_t *out,
                               __global const real *taps) {
    const int index = get_global_id(0), column = index / NZ;
    complex_t sum = (complex_t)(0, 0);
    for (int d = -REACH; d <= REACH; ++d) {
        const int source = column - d;
        if (source >= 0 && source < NX) sum += taps[REACH + d] * field[index - d * NZ];
    }
    out[index] = sum;
}

/* Per A-scan, the unnormalised DFT (sign −1) or its inverse (sign +1) along depth. */
__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
void depth_fft(__global const complex_t *field, __global complex_t *out, int sign,
               __global const complex_t *twiddle) {
    __local complex_t x[NZ], y[NZ];
    const size_t column = (size_t)get_group_id(0) * NZ;
    const int lid = get_local_id(0);
    for (int n = lid; n < NZ; n += WG_SIZE) x[n] = field[column + n];
    barrier(CLK_LOCAL_MEM_FENCE);
    __local complex_t *result = fft_stockham(x, y, LOG2_NZ, sign, twiddle);
    for (int n = lid; n < NZ; n += WG_SIZE) out[column + n] = result[n];
}

/* In place, one work-group per depth frequency q: the NX values spectrum[i·NZ + q]
 * zero-padded to PADDED, transformed, multiplied by filter[q·PADDED + p], transformed
 * back and cropped to NX. */
__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
void lateral_filter(__global complex_t *spectrum, __global const real *filter,
                    __global const complex_t *twiddle) {
    __local complex_t x[PADDED], y[PADDED];
    const int q = get_group_id(0), lid = get_local_id(0);
    for (int i = lid; i < PADDED; i += WG_SIZE)
        x[i] = i < NX ? spectrum[(size_t)i * NZ + q] : (complex_t)(0, 0);
    barrier(CLK_LOCAL_MEM_FENCE);
    __local complex_t *transformed = fft_stockham(x, y, LOG2_PADDED, -1, twiddle);
    __local complex_t *scratch = transformed == x ? y : x;
    __global const real *row = filter + (size_t)q * PADDED;
    for (int p = lid; p < PADDED; p += WG_SIZE) transformed[p] *= row[p];
    barrier(CLK_LOCAL_MEM_FENCE);
    __local complex_t *result = fft_stockham(transformed, scratch, LOG2_PADDED, +1, twiddle);
    for (int i = lid; i < NX; i += WG_SIZE) spectrum[(size_t)i * NZ + q] = result[i];
}
