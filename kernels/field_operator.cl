/*
 * The field operator of stage 1 (host/stage1/operator.py, FieldOperator) and its
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
 *   same two kernels (tests/stage1/test_operator_device.py checks the identity).
 *
 *   H⁺·A = IDFT_2(conj(Ĥ)/(|Ĥ|² + λ)·DFT_2(A)) over the columns zero-padded
 *   to PADDED (a power of two ≥ NX + 2·REACH): depth_fft forward, then
 *   lateral_filter (pad, FFT, the filter, inverse FFT, crop) per depth
 *   frequency, then depth_fft inverse. The filter comes from the host
 *   with both transforms' normalisation in it.
 *
 * FFTs are Stockham autosort transforms in local memory
 * (Govindaraju et al., "High performance discrete Fourier transforms on
 * graphics processors", SC 2008): each stage reads x[j + r·n/R] (r < R)
 * and writes runs of Ns, ping-ponging between two local arrays, so no
 * bit-reversal pass and contiguous reads; radix 4 (and one radix-2 stage
 * for an odd power of two), so a 256-point transform takes 4 stages and 4
 * barriers. The scanner's fft_local (kernels/scanner.cl) works in place
 * with a bit-reversal pass on one array; this one needs the second array,
 * which the field's work-groups have room for. twiddle[k] =
 * exp(−2πi·k/TWIDDLE_N), k < TWIDDLE_N, from the host in float64; a
 * shorter transform strides through it.
 *
 * Defines (host/stage1/operator_device.py, program_defines): NZ, LOG2_NZ, NX,
 * REACH, PADDED, LOG2_PADDED, TWIDDLE_N, WG_SIZE; OCTCL_DOUBLE for float64.
 */

/* x·exp(sign·2πi·k/TWIDDLE_N) from the table twiddle[k] = exp(−2πi·k/TWIDDLE_N), k < TWIDDLE_N. */
static inline complex_t twiddled(complex_t x, int k, int sign, __global const complex_t *twiddle) {
    complex_t w = twiddle[k];
    w.y = sign < 0 ? w.y : -w.y;
    return cmul(w, x);
}

/* ±i·x: the quarter turn of a radix-4 butterfly, exp(sign·iπ/2)·x. */
static inline complex_t quarter_turn(complex_t x, int sign) {
    return sign < 0 ? (complex_t)(x.y, -x.x) : (complex_t)(-x.y, x.x);
}

/* x ← Σ_n x[n]·exp(sign·2πi·k·n/len), len = 1 << log2n, with y as scratch;
 * returns the array holding the result (x or y). Radix-4 stages while the
 * length allows, one radix-2 stage last for an odd log2n: a stage of
 * radix R with span Ns reads x[j + r·len/R] (r < R) for each of the len/R
 * butterflies j, turns input r by exp(sign·2πi·r·(j mod Ns)/(Ns·R)),
 * transforms the R values and writes them to y[(j − j mod Ns)·R + j mod Ns
 * + r·Ns]. Call with every work-item of the group; returns after a
 * barrier. */
static __local complex_t *fft_stockham(__local complex_t *x, __local complex_t *y, int log2n, int sign,
                                       __global const complex_t *twiddle) {
    const int n = 1 << log2n, lid = get_local_id(0);
    int span = 1;
    for (; span * 4 <= n; span *= 4) {
        const int quarter = n >> 2, stride = TWIDDLE_N / (4 * span);
        for (int j = lid; j < quarter; j += WG_SIZE) {
            const int k = j & (span - 1);
            const complex_t v0 = x[j];
            const complex_t v1 = twiddled(x[j + quarter], k * stride, sign, twiddle);
            const complex_t v2 = twiddled(x[j + 2 * quarter], 2 * k * stride, sign, twiddle);
            const complex_t v3 = twiddled(x[j + 3 * quarter], 3 * k * stride, sign, twiddle);
            const complex_t even = v0 + v2, odd = v1 + v3;
            const complex_t even_difference = v0 - v2, odd_difference = quarter_turn(v1 - v3, sign);
            const int out = ((j - k) << 2) + k;
            y[out] = even + odd;
            y[out + span] = even_difference + odd_difference;
            y[out + 2 * span] = even - odd;
            y[out + 3 * span] = even_difference - odd_difference;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        __local complex_t *swap = x;
        x = y;
        y = swap;
    }
    if (span < n) { /* log2n odd: one radix-2 stage */
        const int middle = n >> 1, stride = TWIDDLE_N / (2 * span);
        for (int j = lid; j < middle; j += WG_SIZE) {
            const int k = j & (span - 1);
            const complex_t top = x[j], bottom = twiddled(x[j + middle], k * stride, sign, twiddle);
            const int out = ((j - k) << 1) + k;
            y[out] = top + bottom;
            y[out + span] = top - bottom;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        x = y;
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
