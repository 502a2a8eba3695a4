/*
 * The Virtual Scanner (shared/physics.md §2) and its adjoint, one A-scan per
 * work-item.
 *
 * Forward, for A-scan i at lateral position x_i:
 *   1. Visit the candidate scatterers in depth order. Candidates sit in the
 *      three lateral bins around the A-scan (a bin is ASCANS_PER_BIN A-scans
 *      wide, at least the shadowing reach), each bin sorted by depth rank on
 *      the host; a three-way merge by rank gives the A-scan's depth order.
 *   2. For a candidate m within the shadowing reach, d² = (x_i − x_m)² + y_m²
 *      < R²·w0², the beam amplitude is b_m = exp(−d²/w0²)·a_m. If it also lies
 *      in the contribution window (d² < 3·w0², decided on the host in float64
 *      and passed as the A-scan range [first, last], so that float32 rounding
 *      never flips a scatterer at the window's edge in or out) it adds
 *      c_m = T·b_m·e^{iφ_m}
 *      (φ_m = −2·k0·z_m mod 2π, from the host in float64) to the A-scan.
 *      Then T ← T·(1 − min(b_m², 1)): the depth-cumulative shadowing.
 *   3. The spectrum S(s) = Σ_m c_m·e^{−i·s·x_m}, x_m = 2·δk·z_m, is a type-1
 *      non-uniform DFT. Each c_m is spread onto a 2×-oversampled periodic grid
 *      of GRID = 2·NZ points with the "exponential of semicircle" kernel
 *      ψ(t) = exp(β·(sqrt(1 − t²) − 1)) over SPREAD_WIDTH points; one FFT of
 *      the grid then gives ψ̂(s)·S(s) (Barnett, Magland & af Klinteberg,
 *      SIAM J. Sci. Comput. 41 (2019) C479).
 *   4. X(s) = H(s)·FFT(grid)(s) with H(s) = w(s) / (ψ̂(s)·NZ) (Hann window,
 *      kernel deconvolution and the 1/NZ of the inverse DFT in one table),
 *      and A[n] = Σ_s X(s)·e^{2πi·s·n/NZ}: the complex A-scan.
 *
 * Adjoint, given Ā[n] = ∂L/∂Re A + i·∂L/∂Im A:
 *   X̄ = FFT(Ā)·H, b̄ = IFFT(X̄) and b̄' = IFFT(s·X̄) on the grid (both
 *   unnormalised), gathered with the same kernel: c̄_m = Σ ψ·b̄, c̄'_m = Σ ψ·b̄'.
 *   With v_m = T_m·b_m and R_m = Re(conj(c̄_m)·e^{iφ_m}) = ∂L/∂v_m:
 *     ∂L/∂z_m = Re(−2i·v_m·e^{iφ_m}·(k0·conj(c̄_m) + δk·conj(c̄'_m)))
 *     ∂L/∂u_m = R_m·v_m/2 − T_m·D_m·b_m²   (u = ln E, ∂b/∂u = b/2;
 *                                            the second term only if b_m < 1)
 *   where D_m = Σ_{j deeper} R_j·b_j·Π_{m<k<j}(1 − t_k) is accumulated as a
 *   suffix sum while the candidates are visited in reverse depth order:
 *   D ← R_m·b_m + (1 − t_m)·D. Nothing is divided by (1 − t), so a mirror
 *   (t = 1) gives finite, exact gradients. T_m comes from the forward pass.
 *
 * Lateral positions are offsets from the first A-scan of the scatterer's bin
 * (x_m − x_{P·(c−1)} ∈ [0, P·Δx)), so that x_i − x_m = (i − P·(c−1))·Δx −
 * offset_m keeps float32 accuracy far from the centre of the scan.
 *
 * Every (A-scan, scatterer) pair has its own slot, so no atomics are needed:
 * scatterer m in bin c serves A-scans P·(c − 2) … P·(c + 1) − 1, slot
 * i − P·(c − 2) ∈ [0, 3P). The forward pass stores T there, the adjoint
 * overwrites it with the pair's (∂L/∂u, ∂L/∂z), and reduce_slots sums them.
 *
 * Compile-time constants: NZ, GRID (= 2·NZ, a power of two), LOG2_GRID,
 * LOG2_NZ, SPREAD_WIDTH (≤ 16); OCTCL_DOUBLE selects double precision.
 */

#ifdef OCTCL_DOUBLE
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real;
typedef double2 complex_t;
#if SPREAD_WIDTH <= 8
typedef double8 taps_t;
#define TAP_COUNT 8
#else
typedef double16 taps_t;
#define TAP_COUNT 16
#endif
#else
typedef float real;
typedef float2 complex_t;
#if SPREAD_WIDTH <= 8
typedef float8 taps_t;
#define TAP_COUNT 8
#else
typedef float16 taps_t;
#define TAP_COUNT 16
#endif
#endif

typedef struct {
    int a_scans;          /* Nx */
    int ascans_per_bin;   /* P: a bin is P A-scans wide, P·Δx ≥ shadowing reach */
    int bins;             /* number of lateral bins */
    int slots;            /* 3·P slots per scatterer */
    real pitch_um;        /* Δx between A-scans */
    real inv_w0_sq;       /* 1/w0², µm⁻² */
    real shadow_d2;       /* R²·w0², µm² */
    real es_beta;         /* β of the spreading kernel */
    real k0;              /* 2π/λ, rad/µm */
    real dk;              /* δk, rad/µm */
    real min_transmission;/* an A-scan stops once T ≤ this (0: only behind a mirror) */
} ScannerParams;

inline complex_t cmul(complex_t a, complex_t b) {
    return (complex_t)(a.x * b.x - a.y * b.y, a.x * b.y + a.y * b.x);
}

inline complex_t cconj_mul(complex_t a, complex_t b) { /* conj(a)·b */
    return (complex_t)(a.x * b.x + a.y * b.y, a.x * b.y - a.y * b.x);
}

/* In-place radix-2 FFT of length 1 << log2n on a private array:
 * a[k] ← Σ_n a[n]·exp(sign·2πi·k·n/len). twiddle[k] = exp(−2πi·k/GRID),
 * k < GRID/2; a shorter transform strides through it. */
void fft(complex_t *a, int log2n, int sign, __global const complex_t *twiddle) {
    const int n = 1 << log2n;
    for (int i = 1, j = 0; i < n; ++i) { /* bit-reversal permutation */
        int bit = n >> 1;
        for (; j & bit; bit >>= 1) j ^= bit;
        j |= bit;
        if (i < j) { complex_t t = a[i]; a[i] = a[j]; a[j] = t; }
    }
    for (int span = 1, stride = GRID >> 1; span < n; span <<= 1, stride >>= 1) {
        for (int start = 0; start < n; start += 2 * span) {
            for (int k = 0; k < span; ++k) {
                complex_t w = twiddle[k * stride];
                w.y *= sign < 0 ? 1 : -1;
                const complex_t t = cmul(w, a[start + k + span]);
                a[start + k + span] = a[start + k] - t;
                a[start + k] += t;
            }
        }
    }
}

/* T ← T·(1 − t), carried as an unevaluated sum hi + lo (double-word
 * arithmetic). A deep scatterer sits below up to 300,000 others whose factors
 * 1 − t round in the 7th digit: rounded products would drift by ~1e−3 in
 * float32. The remainder of 1 − t is exact (Fast2Sum, t ≤ 1) and so is the
 * product's rounding error (fma), so T keeps ~1e−7 relative accuracy. */
inline void attenuate(real *hi, real *lo, real t) {
    const real factor = 1 - t;
    const real factor_lo = (1 - factor) - t;
    const real product = *hi * factor;
    const real correction = fma(*hi, factor, -product) + (*hi * factor_lo + *lo * factor);
    *hi = product + correction;
    *lo = correction - (*hi - product);
}

/* Spreading-kernel weights ψ at the SPREAD_WIDTH grid points first_tap … of a
 * scatterer at grid position p: ψ((l − p)·2/W), zero for unused lanes. */
inline taps_t spread_weights(real p, real beta, int *first_tap) {
#if TAP_COUNT == 8
    const taps_t lane = (taps_t)(0, 1, 2, 3, 4, 5, 6, 7);
#else
    const taps_t lane = (taps_t)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
#endif
    const real start = ceil(p - (real)(0.5 * SPREAD_WIDTH));
    *first_tap = (int)start;
    const taps_t t = (start - p + lane) * (real)(2.0 / SPREAD_WIDTH);
    const taps_t weight = exp(beta * (sqrt(fmax(1 - t * t, (real)0)) - 1));
    return lane < (real)SPREAD_WIDTH ? weight : (taps_t)0;
}

/* The three-way merge of an A-scan's candidate bins in depth order: the next
 * candidate (smallest depth rank) forwards, or the previous one (largest
 * rank) backwards; −1 when the bins are exhausted. */
inline int next_deeper(int *cursor, const int *end, __global const int *rank) {
    int best = -1, best_rank = INT_MAX;
    for (int b = 0; b < 3; ++b)
        if (cursor[b] < end[b] && rank[cursor[b]] < best_rank) { best = b; best_rank = rank[cursor[b]]; }
    return best < 0 ? -1 : cursor[best]++;
}

inline int next_shallower(int *cursor, const int *begin, __global const int *rank) {
    int best = -1, best_rank = -1;
    for (int b = 0; b < 3; ++b)
        if (cursor[b] > begin[b] && rank[cursor[b] - 1] > best_rank) { best = b; best_rank = rank[cursor[b] - 1]; }
    return best < 0 ? -1 : --cursor[best];
}

inline void candidate_bins(const ScannerParams p, int ascan, __global const int *bin_start,
                           int *begin, int *end) {
    const int centre = ascan / p.ascans_per_bin + 1; /* bins are shifted by one */
    for (int b = 0; b < 3; ++b) {
        begin[b] = bin_start[centre - 1 + b];
        end[b] = bin_start[centre + b];
    }
}

/* The scene as the host laid it out (scatterers bin-major, depth-rank-minor)
 * and the constant tables; shared by the forward and adjoint kernels. */
#define SCENE_ARGUMENTS                                                             \
    __global const real *x_offset_um, __global const real *y_um,                  \
    __global const real *amplitude, __global const real *grid_pos,                \
    __global const complex_t *carrier, __global const int *rank,                  \
    __global const int *bin, __global const int *bin_start,                       \
    __global const int2 *contributes_to,                                          \
    __global const real *transfer, __global const complex_t *twiddle

/* d² = (x_i − x_m)² + y_m² of A-scan i and scatterer m, from m's bin offset. */
inline real squared_distance(const ScannerParams p, int i, int bin_m, real x_offset, real y) {
    const real dx = (i - p.ascans_per_bin * (bin_m - 1)) * p.pitch_um - x_offset;
    return dx * dx + y * y;
}

/* The (A-scan i, scatterer m) pair's own slot (see the header). */
inline size_t slot_index(const ScannerParams p, int i, int m, int bin_m) {
    return (size_t)m * p.slots + i - p.ascans_per_bin * (bin_m - 2);
}

/*
 * Forward: complex A-scans a_scan[i·NZ + n].
 * Scatterer arrays are in bin-major, depth-rank-minor order (host sorted).
 * If slot_data is not null, T of each visited pair is stored for the adjoint
 * and the merge cursors where the A-scan stopped go to stop_cursor.
 */
__kernel void render_forward(const ScannerParams p,
                             SCENE_ARGUMENTS,
                             __global complex_t *a_scan,
                             __global complex_t *slot_data, __global int *stop_cursor) {
    const int i = get_global_id(0);
    if (i >= p.a_scans) return;
    int begin[3], end[3], cursor[3];
    candidate_bins(p, i, bin_start, begin, end);
    for (int b = 0; b < 3; ++b) cursor[b] = begin[b];

    complex_t grid[GRID];
    for (int l = 0; l < GRID; ++l) grid[l] = (complex_t)(0, 0);

    real transmission = 1, transmission_lo = 0;
    int m;
    while (transmission > p.min_transmission && (m = next_deeper(cursor, end, rank)) >= 0) {
        const real d2 = squared_distance(p, i, bin[m], x_offset_um[m], y_um[m]);
        if (d2 >= p.shadow_d2) continue;
        const real beam_amplitude = exp(-d2 * p.inv_w0_sq) * amplitude[m];
        if (slot_data) slot_data[slot_index(p, i, m, bin[m])].x = transmission;
        if (i >= contributes_to[m].x && i <= contributes_to[m].y) {
            const complex_t c = (transmission * beam_amplitude) * carrier[m];
            int first;
            const taps_t w = spread_weights(grid_pos[m], p.es_beta, &first);
            const real *wv = (const real *)&w;
            for (int t = 0; t < SPREAD_WIDTH; ++t) grid[(first + t) & (GRID - 1)] += c * wv[t];
        }
        attenuate(&transmission, &transmission_lo, fmin(beam_amplitude * beam_amplitude, (real)1));
    }
    if (stop_cursor)
        for (int b = 0; b < 3; ++b) stop_cursor[3 * i + b] = cursor[b];

    fft(grid, LOG2_GRID, -1, twiddle);
    /* X[q] = H[q]·grid[s_q mod GRID], s_q = q (q ≤ NZ/2) or q − NZ; in place:
     * q < NZ/2 reads its own index, q > NZ/2 reads q + NZ, not yet written. */
    for (int q = 0; q < NZ; ++q)
        grid[q] = transfer[q] * grid[q <= NZ / 2 ? q : q + NZ];
    fft(grid, LOG2_NZ, +1, twiddle);
    for (int n = 0; n < NZ; ++n) a_scan[(size_t)i * NZ + n] = grid[n];
}

/*
 * Adjoint: given a_scan_bar (Ā, same layout as a_scan), overwrite each visited
 * pair's slot with (∂L/∂u, ∂L/∂z) of that A-scan. Unvisited slots must hold 0.
 */
__kernel void render_adjoint(const ScannerParams p,
                             SCENE_ARGUMENTS,
                             __global const complex_t *a_scan_bar,
                             __global complex_t *slot_data, __global const int *stop_cursor) {
    const int i = get_global_id(0);
    if (i >= p.a_scans) return;
    int begin[3], end[3], cursor[3];
    candidate_bins(p, i, bin_start, begin, end);
    for (int b = 0; b < 3; ++b) cursor[b] = stop_cursor[3 * i + b];

    /* X̄ = FFT(Ā)·H, then the two grid adjoints b̄ = IFFT(X̄), b̄' = IFFT(s·X̄). */
    complex_t grid_bar[GRID], grid_bar_s[GRID];
    for (int l = 0; l < GRID; ++l) {
        grid_bar[l] = l < NZ ? a_scan_bar[(size_t)i * NZ + l] : (complex_t)(0, 0);
        grid_bar_s[l] = (complex_t)(0, 0);
    }
    fft(grid_bar, LOG2_NZ, -1, twiddle);
    for (int q = NZ - 1; q >= 0; --q) { /* descending: q + NZ is written before q is read */
        const complex_t x_bar = transfer[q] * grid_bar[q];
        const int s = q <= NZ / 2 ? q : q - NZ;
        const int l = q <= NZ / 2 ? q : q + NZ;
        grid_bar[q] = (complex_t)(0, 0);
        grid_bar[l] = x_bar;
        grid_bar_s[l] = (real)s * x_bar;
    }
    fft(grid_bar, LOG2_GRID, +1, twiddle);
    fft(grid_bar_s, LOG2_GRID, +1, twiddle);

    real downstream = 0; /* D: sensitivity to the transmission just below the visited scatterer */
    int m;
    while ((m = next_shallower(cursor, begin, rank)) >= 0) {
        const real d2 = squared_distance(p, i, bin[m], x_offset_um[m], y_um[m]);
        if (d2 >= p.shadow_d2) continue;
        const real beam_amplitude = exp(-d2 * p.inv_w0_sq) * amplitude[m];
        const real beam_energy = beam_amplitude * beam_amplitude;
        __global complex_t *slot = slot_data + slot_index(p, i, m, bin[m]);
        const real transmission = slot->x;
        real grad_u = 0, grad_z = 0, grad_transmission = 0;
        if (i >= contributes_to[m].x && i <= contributes_to[m].y) {
            int first;
            const taps_t w = spread_weights(grid_pos[m], p.es_beta, &first);
            const real *wv = (const real *)&w;
            complex_t c_bar = (complex_t)(0, 0), c_bar_s = (complex_t)(0, 0);
            for (int t = 0; t < SPREAD_WIDTH; ++t) {
                const int l = (first + t) & (GRID - 1);
                c_bar += wv[t] * grid_bar[l];
                c_bar_s += wv[t] * grid_bar_s[l];
            }
            const real v = transmission * beam_amplitude;
            const real r = cconj_mul(c_bar, carrier[m]).x;  /* ∂L/∂v */
            grad_u = r * v / 2;
            /* Re(−2i·v·e^{iφ}·(k0·conj(c̄) + δk·conj(c̄'))) = 2v·Im(e^{iφ}·conj(k0·c̄ + δk·c̄')) */
            grad_z = 2 * v * cconj_mul(p.k0 * c_bar + p.dk * c_bar_s, carrier[m]).y;
            grad_transmission = r * beam_amplitude;
        }
        if (beam_energy < 1) grad_u -= transmission * downstream * beam_energy;
        *slot = (complex_t)(grad_u, grad_z);
        downstream = grad_transmission + (1 - fmin(beam_energy, (real)1)) * downstream;
    }
}

/* Sum each scatterer's slots: gradient[m] = (∂L/∂u_m, ∂L/∂z_m). */
__kernel void reduce_slots(const ScannerParams p, __global const int *bin,
                           __global const complex_t *slot_data, __global complex_t *gradient,
                           const int count) {
    const int m = get_global_id(0);
    if (m >= count) return;
    const int first_ascan = p.ascans_per_bin * (bin[m] - 2);
    complex_t total = (complex_t)(0, 0);
    for (int s = 0; s < p.slots; ++s) {
        const int ascan = first_ascan + s;
        if (ascan >= 0 && ascan < p.a_scans) total += slot_data[(size_t)m * p.slots + s];
    }
    gradient[m] = total;
}
