/*
 * The Virtual Scanner (shared/physics.md §2) and its adjoint, in two
 * variants of the same maths:
 *
 *   render_forward / render_adjoint            one work-item per LANES
 *                                              A-scans of a bin (CPUs: long
 *                                              sequential loops vectorise
 *                                              and cache well);
 *   render_forward_group / render_adjoint_group one work-group of WG_SIZE
 *                                              work-items per A-scan (GPUs:
 *                                              scans, gathers and FFTs in
 *                                              local memory, no per-A-scan
 *                                              array in private memory).
 *
 * Forward, for A-scan i at lateral position x_i:
 *   1. Visit the candidate scatterers in depth order. A-scan i belongs to
 *      lateral bin c (a bin is P = ASCANS_PER_BIN A-scans wide, P·Δx ≥ the
 *      shadowing reach); its candidates are the host-made list c: the
 *      scatterers of bins c − 1, c, c + 1 in the scanner's depth order.
 *   2. For a candidate m within the shadowing reach, d² = (x_i − x_m)² + y_m²
 *      < R²·w0², the beam amplitude is b_m = exp(−d²/w0²)·a_m and its
 *      energy t_m = min(b_m², 1). If m also lies in the contribution window
 *      (d² < 3·w0², decided on the host in float64 and passed as the A-scan
 *      range [first, last], so that float32 rounding never flips a scatterer
 *      at the window's edge in or out) it adds
 *      c_m = T_m·b_m·e^{iφ_m}
 *      (φ_m = −2·k0·z_m mod 2π, from the host in float64) to the A-scan, with
 *      T_m = Π_{k before m} (1 − t_k): the depth-cumulative shadowing.
 *   3. The spectrum S(s) = Σ_m c_m·e^{−i·s·x_m}, x_m = 2·δk·z_m, is a type-1
 *      non-uniform DFT. Each c_m is spread onto a 2×-oversampled periodic grid
 *      of GRID = 2·NZ points with the "exponential of semicircle" kernel
 *      ψ(t) = exp(β·(sqrt(1 − t²) − 1)) over SPREAD_WIDTH = W points: grid
 *      points first_m … first_m + W − 1 (mod GRID), t = (first_m − p_m + k)·2/W
 *      for the k-th, p_m = x_m·GRID/(2π) (first_m and first_m − p_m come from
 *      the host in float64). One FFT of the grid then gives ψ̂(s)·S(s)
 *      (Barnett, Magland & af Klinteberg, SIAM J. Sci. Comput. 41 (2019) C479).
 *   4. X(s) = H(s)·FFT(grid)(s) with H(s) = w(s) / (ψ̂(s)·NZ) (Hann window,
 *      kernel deconvolution and the 1/NZ of the inverse DFT in one table),
 *      and A[n] = Σ_s X(s)·e^{2πi·s·n/NZ}: the complex A-scan.
 *
 * Adjoint, given Ā[n] = ∂L/∂Re A + i·∂L/∂Im A:
 *   X̄ = FFT(Ā)·H, b̄ = IFFT(X̄) and b̄' = IFFT(s·X̄) on the grid (both
 *   unnormalised), gathered with the same kernel: c̄_m = Σ ψ·b̄, c̄'_m = Σ ψ·b̄'.
 *   With v_m = T_m·b_m and R_m = Re(conj(c̄_m)·e^{iφ_m}) = ∂L/∂v_m:
 *     ∂L/∂z_m = Re(−2i·v_m·e^{iφ_m}·(k0·conj(c̄_m) + δk·conj(c̄'_m)))
 *     ∂L/∂u_m = R_m·v_m/2 − T_m·D_m·t_m   (u = ln E, ∂b/∂u = b/2, ∂t/∂u = t;
 *                                           the second term only if t_m < 1)
 *   where D_m = Σ_{j deeper} R_j·b_j·Π_{m<k<j}(1 − t_k) follows the affine
 *   recurrence D ← R_m·b_m + (1 − t_m)·D over the candidates in reverse
 *   depth order. Nothing is divided by (1 − t), so a mirror (t = 1) gives
 *   finite, exact gradients. T_m comes from the forward pass.
 *
 * Scale. Amplitudes arrive as a_m = mantissa_m·2^{exponent_m} (frexp on the
 * host, mantissa in [½, 1); a zero amplitude has mantissa 0 and the exponent
 * NO_AMPLITUDE). ascan_scale finds e_i, the largest exponent among the
 * scatterers in A-scan i's contribution window (a pass over the scatterers,
 * not over every A-scan's list, which cost the forward pass a third more
 * time on a CPU), and the render kernels compute the
 * contributions relative to 2^{e_i}: b̃_m = exp(−d²/w0²)·mantissa_m·
 * 2^{exponent_m − e_i} ≤ 1. The A-scan comes out relative to 2^{e_i}
 * (scale_exponent[i]; the host multiplies by it in float64 and scales Ā by
 * the same factor on the way back), while the shadowing energy
 * t_m = (exp(−d²/w0²)·mantissa_m)²·2^{2·exponent_m} keeps its absolute
 * meaning. So float32 kernels render every legal phantom as float64 does
 * whatever its overall energy: what still underflows is a contribution
 * 2^{−126} below the A-scan's own largest one, or a shadow energy t below
 * 2^{−149} (1 − t is 1 in float64 as well), or a transmission below 2^{−126}
 * behind scatterers that are themselves ≥ 10^{38} brighter; all are far
 * below the 51 dB display. The gradients do not depend on the scale.
 *
 * Lateral positions are offsets from the first A-scan of the scatterer's bin
 * (x_m − x_{P·(bin_m − 1)} ∈ [0, P·Δx)), so that x_i − x_m = (i − P·(bin_m −
 * 1))·Δx − offset_m keeps float32 accuracy far from the centre of the scan.
 *
 * Lists. The host sends per-scatterer arrays (those of x and y once, those
 * of z and E per call) and, per list, its scatterers in depth order
 * (entry_scatterer); gather_entries copies each entry's data into one Entry
 * record, so that the render kernels stream through a list's records in
 * order instead of jumping through the scatterer arrays (on a CPU the
 * random reads made the work-item forward pass 3× slower).
 *
 * Every (A-scan, list entry) pair has its own slot, so no atomics are
 * needed: entry j of list c serves the P A-scans of bin c, slot
 * (i mod P)·ENTRIES + j. The forward pass stores T there (and, in the
 * work-group variant, T·b̃ for its gather), the adjoint overwrites every slot
 * of its A-scan with the pair's (∂L/∂u, ∂L/∂z) (0 for pairs out of reach or
 * not visited), and reduce_slots sums each scatterer's slots in a fixed
 * order: the result does not depend on scheduling.
 *
 * Defines (octcl/device/scanner.py, program_defines): NZ, GRID (= 2·NZ, a
 * power of two), LOG2_GRID, LOG2_NZ, SPREAD_WIDTH (≤ 16), WG_SIZE
 * (work-group variant, a power of two), LANES (below), NO_AMPLITUDE (the
 * exponent of a zero amplitude: never the largest in a window);
 * OCTCL_DOUBLE selects double precision.
 */

/* Vector maths works on LANES reals at a time: 8 floats or 4 doubles, the
 * 256 bits of an AVX2 register; the host launches one work-item per LANES
 * A-scans. (Wider vectors of doubles are passed differently without
 * AVX-512, and PoCL's LLVM then fails to compile their builtins: exp, sqrt,
 * fma, select.) A comparison of reals gives a lane_mask_t (−1 where it
 * holds, 0 elsewhere); one of lane indices an int vector, widened by
 * index_mask to the reals' mask. */
#if defined(OCTCL_DOUBLE) && LANES == 4
typedef double4 lanes_t;
typedef int4 lane_index_t;
typedef long4 lane_mask_t;
typedef long lane_flag_t;
#define convert_lanes convert_double4
#define index_mask(mask) convert_long4(mask)
#define LANE_NUMBERS ((int4)(0, 1, 2, 3))
#elif !defined(OCTCL_DOUBLE) && LANES == 8
typedef float8 lanes_t;
typedef int8 lane_index_t;
typedef int8 lane_mask_t;
typedef int lane_flag_t;
#define convert_lanes convert_float8
#define index_mask(mask) (mask)
#define LANE_NUMBERS ((int8)(0, 1, 2, 3, 4, 5, 6, 7))
#else
#error "LANES: 8 floats or 4 doubles, VECTOR_BYTES = 32 (octcl/device/scanner.py)"
#endif
#define LANE(vector, l) (((real *)&(vector))[l])
#define LANE_HOLDS(mask, l) (((lane_flag_t *)&(mask))[l])
#define LANE_INDEX(vector, l) (((int *)&(vector))[l])

typedef struct {
    int a_scans;          /* Nx */
    int ascans_per_bin;   /* P: a bin is P A-scans wide, P·Δx ≥ shadowing reach */
    int entries;          /* ENTRIES: list entries in all, the slots' row length */
    int padding;
    real pitch_um;        /* Δx between A-scans */
    real inv_w0_sq;       /* 1/w0², µm⁻² */
    real shadow_d2;       /* R²·w0², µm² */
    real es_beta;         /* β of the spreading kernel */
    real k0;              /* 2π/λ, rad/µm */
    real dk;              /* δk, rad/µm */
    real min_transmission;/* an A-scan stops once T ≤ this (0: only behind a mirror) */
} ScannerParams;

/* Macros rather than functions so that they take a real or a lanes_t alike:
 * one definition for the work-group kernels' scalars and the work-item
 * kernels' vector lanes. */
/* exp(−d²/w0²)·mantissa: the beam amplitude without its binary exponent. */
#define beam_mantissa(p, d2, mantissa) (exp(-(d2) * (p).inv_w0_sq) * (mantissa))
/* t = min(b², 1), b = beam_mantissa·2^exponent: the absolute shadowing energy.
 * For lanes the exponent comes as a lane_index_t, not as one int: OpenCL's
 * ldexp(floatn, int) is legal, but Oclgrind 21.10 reads lanes 1 … n − 1 of
 * that scalar exponent from past its end (docs/scanner.md, "Implementations"). */
#define shadow_energy(beam, exponent) fmin(ldexp((beam) * (beam), 2 * (exponent)), (real)1)

/* ψ(t) = exp(β·(sqrt(1 − t²) − 1)) at t = (offset + k)·2/W, offset = first − p. */
static inline real spread_weight(real offset, int k, real beta) {
    const real t = (offset + k) * (real)(2.0 / SPREAD_WIDTH);
    return exp(beta * (sqrt(fmax(1 - t * t, (real)0)) - 1));
}

/* Double-word (hi + lo) products, for the transmission T = Π (1 − t): a deep
 * scatterer sits below up to 300,000 others whose factors 1 − t round in the
 * 7th digit, and rounded float32 products would drift by ~1e−3. The
 * remainder of 1 − t is exact (Fast2Sum, t ≤ 1) and so is a product's
 * rounding error (fma), so T keeps ~1e−7 relative accuracy. */
static inline real2 one_minus(real t) { /* 1 − t as hi + lo */
    const real hi = 1 - t;
    return (real2)(hi, (1 - hi) - t);
}

static inline real2 dw_mul(real2 a, real2 b) {
    const real product = a.x * b.x;
    const real error = fma(a.x, b.x, -product) + (a.x * b.y + a.y * b.x);
    const real hi = product + error;
    return (real2)(hi, error - (hi - product));
}

/* A scatterer as a list sees it. */
typedef struct {
    real x_offset_um;      /* x − x of the first A-scan of its bin */
    real y_um;
    real mantissa;         /* amplitude a = mantissa·2^exponent */
    real tap_offset;       /* first_tap − p, p its position on the spreading grid */
    complex_t carrier;     /* e^{iφ}, φ = −2·k0·z */
    int bin;
    int exponent;
    int first_tap;
    int window_first;      /* its contribution window: A-scans window_first … window_last */
    int window_last;
} Entry;

/* sizeof(Entry) as this compiler lays it out, for the host's buffer. */
__kernel void entry_size(__global int *size) { *size = sizeof(Entry); }

/* Entry j of every list from the per-scatterer arrays (input order), and
 * entry_index[3·m + k] = j for its scatterer m, which it holds as the k-th
 * of its lists bin_m − 1 … bin_m + 1 (the reduction's map back). */
__kernel void gather_entries(const ScannerParams p,
                             __global const int *entry_scatterer, __global const int *list_start,
                             __global const real *x_offset_um, __global const real *y_um,
                             __global const int *bin, __global const int2 *window,
                             __global const real *mantissa, __global const int *exponent,
                             __global const int *first_tap, __global const real *tap_offset,
                             __global const real *phase, __global Entry *entry,
                             __global int *entry_index) {
    const int j = get_global_id(0);
    if (j >= p.entries) return;
    const int m = entry_scatterer[j];
    Entry e;
    e.x_offset_um = x_offset_um[m];
    e.y_um = y_um[m];
    e.mantissa = mantissa[m];
    e.tap_offset = tap_offset[m];
    real cosine;
    const real sine = sincos(phase[m], &cosine);
    e.carrier = (complex_t)(cosine, sine);
    e.bin = bin[m];
    e.exponent = exponent[m];
    e.first_tap = first_tap[m];
    e.window_first = window[m].x;
    e.window_last = window[m].y;
    entry[j] = e;
    int list = bin[m] + 1; /* the largest of its lists that starts at or before j */
    while (list_start[list] > j) --list;
    entry_index[3 * m + list - bin[m] + 1] = j;
}

/* d² = (x_i − x_m)² + y_m² of A-scan i and an entry, from its bin offset. */
static inline real squared_distance(const ScannerParams p, int i, const Entry e) {
    const real dx = (i - p.ascans_per_bin * (e.bin - 1)) * p.pitch_um - e.x_offset_um;
    return dx * dx + e.y_um * e.y_um;
}

/* A-scan i is in the entry's contribution window (decided on the host). */
static inline bool contributes(const Entry e, int i) {
    return i >= e.window_first && i <= e.window_last;
}

/* The lists and the constant tables; shared by the forward and adjoint
 * kernels of both variants. */
#define SCENE_ARGUMENTS                                                             \
    __global const Entry *entry, __global const int *list_start,                  \
    __global const real *transfer, __global const complex_t *twiddle

/* ==================================== one work-item per LANES A-scans */

/* In-place radix-2 FFT of length 1 << log2n on a private array:
 * a[k] ← Σ_n a[n]·exp(sign·2πi·k·n/len). twiddle[k] = exp(−2πi·k/GRID),
 * k < GRID/2; a shorter transform strides through it. */
static void fft(complex_t *a, int log2n, int sign, __global const complex_t *twiddle) {
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

/* The W spreading weights of a scatterer, weight[t] = ψ((offset + t)·2/W)
 * for t < W, zero up to TAP_VECTORS·LANES, computed LANES at a time so that
 * the maths vectorises on a CPU. */
#define TAP_VECTORS ((SPREAD_WIDTH + LANES - 1) / LANES)
static inline void spread_weights(real offset, real beta, lanes_t weight[TAP_VECTORS]) {
    for (int k = 0; k < TAP_VECTORS; ++k) {
        const lanes_t tap = convert_lanes(k * LANES + LANE_NUMBERS);
        const lanes_t t = (offset + tap) * (real)(2.0 / SPREAD_WIDTH);
        const lanes_t psi = exp(beta * (sqrt(fmax(1 - t * t, (real)0)) - 1));
        weight[k] = select((lanes_t)0, psi, tap < (real)SPREAD_WIDTH);
    }
}

/*
 * Scale: scale_exponent[i] = e_i, the largest exponent among the scatterers
 * whose contribution window [first, last] holds A-scan i (NO_AMPLITUDE where
 * none), one work-item per scatterer. A maximum does not depend on the order
 * of the atomic updates, so the result is deterministic. scale_exponent must
 * hold NO_AMPLITUDE on entry.
 */
__kernel void ascan_scale(__global const int2 *window, __global const int *exponent,
                          __global int *scale_exponent, const int count) {
    const int m = get_global_id(0);
    if (m >= count || exponent[m] == NO_AMPLITUDE) return;
    for (int i = window[m].x; i <= window[m].y; ++i) atomic_max(&scale_exponent[i], exponent[m]);
}

/* The LANES A-scans of bin list − 1 that a work-item of render_forward /
 * render_adjoint takes: ceil(P/LANES) work-items per bin, the A-scans
 * first … first + lanes − 1 (fewer than LANES in a bin's last work-item
 * when LANES does not divide P). They share list c, so each entry is read
 * once for all of them, its beam amplitudes, energies and transmissions
 * are computed lane-wise in vector registers, and its spreading weights
 * once for every lane it contributes to. Each lane does for its A-scan
 * what one work-item per A-scan would, in the same order: the same sums,
 * the same stopping rule (an inversion writes the same file, byte for
 * byte, as with one work-item per A-scan: docs/benchmarks.md). */
typedef struct {
    int list;        /* c, the bin's list (bins are shifted by one) */
    int lane0;       /* the first lane's A-scan within its bin: its slot row */
    int first;       /* ... and within the B-scan */
    int lanes;       /* A-scans taken, ≤ LANES; ≤ 0 for a work-item past the last */
    lane_index_t ascan; /* first + 0 … LANES − 1 */
} LaneBlock;

static inline LaneBlock lane_block(const ScannerParams p) {
    const int chunks = (p.ascans_per_bin + LANES - 1) / LANES;
    LaneBlock b;
    b.list = get_global_id(0) / chunks + 1;
    b.lane0 = (int)(get_global_id(0) % chunks) * LANES;
    b.first = (b.list - 1) * p.ascans_per_bin + b.lane0;
    b.lanes = min(min(LANES, p.ascans_per_bin - b.lane0), p.a_scans - b.first);
    b.ascan = b.first + LANE_NUMBERS;
    return b;
}

/* squared_distance for each lane's A-scan. */
static inline lanes_t squared_distance_lanes(const ScannerParams p, lane_index_t ascan, const Entry e) {
    const lanes_t dx = convert_lanes(ascan - p.ascans_per_bin * (e.bin - 1)) * p.pitch_um - e.x_offset_um;
    return dx * dx + e.y_um * e.y_um;
}

/* contributes for each lane's A-scan. */
static inline lane_mask_t contributes_lanes(const Entry e, lane_index_t ascan) {
    return index_mask((ascan >= e.window_first) & (ascan <= e.window_last));
}

/* The scale exponents of the block's A-scans (NO_AMPLITUDE past the last). */
static inline lane_index_t scale_lanes(const LaneBlock b, __global const int *scale_exponent) {
    lane_index_t scale = NO_AMPLITUDE;
    for (int l = 0; l < b.lanes; ++l) LANE_INDEX(scale, l) = scale_exponent[b.first + l];
    return scale;
}

/*
 * Forward: complex A-scans a_scan[i·NZ + n], relative to 2^{scale_exponent[i]}.
 * If slot_data is not null, T of each visited pair within reach is stored
 * for the adjoint and the number of visited entries goes to stop_position.
 * One work-item per LANES A-scans of a bin (LaneBlock); grid_scratch holds
 * each A-scan's GRID-point spreading grid. On a 2-core CPU (PoCL) this
 * takes a third of the time of one work-item per A-scan, which read every
 * entry and computed its weights P times (docs/benchmarks.md).
 */
__kernel void render_forward(const ScannerParams p,
                             SCENE_ARGUMENTS,
                             __global complex_t *a_scan, __global const int *scale_exponent,
                             __global complex_t *slot_data, __global int *stop_position,
                             __global complex_t *grid_scratch) {
    const LaneBlock b = lane_block(p);
    if (b.lanes <= 0) return;
    const int begin = list_start[b.list], end = list_start[b.list + 1];
    const lane_index_t scale = scale_lanes(b, scale_exponent);
    int stop[LANES];
    for (int l = 0; l < b.lanes; ++l) stop[l] = end - begin;
    __global complex_t *grid = grid_scratch + (size_t)b.first * GRID;
    for (int l = 0; l < b.lanes * GRID; ++l) grid[l] = (complex_t)(0, 0);

    lanes_t transmission = 1, transmission_lo = 0; /* T per lane, double-word (hi, lo) */
    lane_mask_t active = index_mask(b.ascan < b.first + b.lanes);
    for (int j = begin; j < end; ++j) {
        const lane_mask_t stopping = active & (transmission <= p.min_transmission);
        if (any(stopping)) {
            for (int l = 0; l < b.lanes; ++l) if (LANE_HOLDS(stopping, l)) stop[l] = j - begin;
            active &= ~stopping;
            if (!any(active)) break;
        }
        const Entry e = entry[j];
        const lanes_t d2 = squared_distance_lanes(p, b.ascan, e);
        const lane_mask_t reach = active & (d2 < p.shadow_d2);
        if (!any(reach)) continue;
        const lanes_t beam = beam_mantissa(p, d2, e.mantissa);
        if (slot_data)
            for (int l = 0; l < b.lanes; ++l)
                if (LANE_HOLDS(reach, l)) slot_data[(size_t)(b.lane0 + l) * p.entries + j].x = LANE(transmission, l);
        const lane_mask_t contributing = reach & contributes_lanes(e, b.ascan);
        if (any(contributing)) {
            const lanes_t relative = transmission * ldexp(beam, e.exponent - scale);
            lanes_t w[TAP_VECTORS];
            spread_weights(e.tap_offset, p.es_beta, w);
            const real *wv = (const real *)w;
            for (int l = 0; l < b.lanes; ++l) {
                if (!LANE_HOLDS(contributing, l)) continue;
                const complex_t c = LANE(relative, l) * e.carrier;
                __global complex_t *row = grid + (size_t)l * GRID;
                for (int t = 0; t < SPREAD_WIDTH; ++t) row[(e.first_tap + t) & (GRID - 1)] += c * wv[t];
            }
        }
        /* T ← dw_mul(T, one_minus(t)) lane-wise */
        const lanes_t energy = shadow_energy(beam, (lane_index_t)e.exponent);
        const lanes_t factor = 1 - energy, factor_lo = (1 - factor) - energy;
        const lanes_t product = transmission * factor;
        const lanes_t error = fma(transmission, factor, -product)
                              + (transmission * factor_lo + transmission_lo * factor);
        const lanes_t hi = product + error;
        transmission_lo = select(transmission_lo, error - (hi - product), reach);
        transmission = select(transmission, hi, reach);
    }

    for (int l = 0; l < b.lanes; ++l) {
        const int i = b.first + l;
        if (stop_position) stop_position[i] = stop[l];
        complex_t row[GRID];
        for (int k = 0; k < GRID; ++k) row[k] = grid[(size_t)l * GRID + k];
        fft(row, LOG2_GRID, -1, twiddle);
        /* X[q] = H[q]·grid[s_q mod GRID], s_q = q (q ≤ NZ/2) or q − NZ; in place:
         * q < NZ/2 reads its own index, q > NZ/2 reads q + NZ, not yet written. */
        for (int q = 0; q < NZ; ++q) row[q] = transfer[q] * row[q <= NZ / 2 ? q : q + NZ];
        fft(row, LOG2_NZ, +1, twiddle);
        for (int n = 0; n < NZ; ++n) a_scan[(size_t)i * NZ + n] = row[n];
    }
}

/*
 * Adjoint: given a_scan_bar (Ā·2^{scale_exponent[i]}, the layout of a_scan),
 * write every slot of the A-scan: (∂L/∂u, ∂L/∂z) of the pair for visited
 * pairs within reach, 0 for the others. One work-item per LANES A-scans of
 * a bin (LaneBlock); grid_scratch holds each A-scan's two grid adjoints,
 * b̄ then b̄', 2·GRID points.
 */
__kernel void render_adjoint(const ScannerParams p,
                             SCENE_ARGUMENTS,
                             __global const complex_t *a_scan_bar, __global const int *scale_exponent,
                             __global complex_t *slot_data, __global const int *stop_position,
                             __global complex_t *grid_scratch) {
    const LaneBlock b = lane_block(p);
    if (b.lanes <= 0) return;
    const int begin = list_start[b.list], end = list_start[b.list + 1];
    const lane_index_t scale = scale_lanes(b, scale_exponent);
    lane_index_t stop = begin; /* lanes past the last stop at once */
    for (int l = 0; l < b.lanes; ++l) {
        const int i = b.first + l;
        LANE_INDEX(stop, l) = begin + stop_position[i];
        __global complex_t *slot = slot_data + (size_t)(b.lane0 + l) * p.entries;
        for (int j = LANE_INDEX(stop, l); j < end; ++j) slot[j] = (complex_t)(0, 0);

        /* X̄ = FFT(Ā)·H, then the two grid adjoints b̄ = IFFT(X̄), b̄' = IFFT(s·X̄). */
        complex_t grid_bar[GRID], grid_bar_s[GRID];
        for (int k = 0; k < GRID; ++k) {
            grid_bar[k] = k < NZ ? a_scan_bar[(size_t)i * NZ + k] : (complex_t)(0, 0);
            grid_bar_s[k] = (complex_t)(0, 0);
        }
        fft(grid_bar, LOG2_NZ, -1, twiddle);
        for (int q = NZ - 1; q >= 0; --q) { /* descending: q + NZ is written before q is read */
            const complex_t x_bar = transfer[q] * grid_bar[q];
            const int s = q <= NZ / 2 ? q : q - NZ;
            const int k = q <= NZ / 2 ? q : q + NZ;
            grid_bar[q] = (complex_t)(0, 0);
            grid_bar[k] = x_bar;
            grid_bar_s[k] = (real)s * x_bar;
        }
        fft(grid_bar, LOG2_GRID, +1, twiddle);
        fft(grid_bar_s, LOG2_GRID, +1, twiddle);
        __global complex_t *rows = grid_scratch + (size_t)i * 2 * GRID;
        for (int k = 0; k < GRID; ++k) {
            rows[k] = grid_bar[k];
            rows[GRID + k] = grid_bar_s[k];
        }
    }
    int last = begin; /* one past the deepest visited entry of any lane */
    for (int l = 0; l < b.lanes; ++l) last = max(last, LANE_INDEX(stop, l));

    lanes_t downstream = 0; /* D per lane: sensitivity to the transmission just below the visited scatterer */
    for (int j = last - 1; j >= begin; --j) {
        const lane_mask_t visited = index_mask(j < stop);
        const Entry e = entry[j];
        const lanes_t d2 = squared_distance_lanes(p, b.ascan, e);
        const lane_mask_t reach = visited & (d2 < p.shadow_d2);
        lanes_t transmission = 0;
        for (int l = 0; l < b.lanes; ++l) {
            __global complex_t *slot = slot_data + (size_t)(b.lane0 + l) * p.entries + j;
            if (LANE_HOLDS(reach, l)) LANE(transmission, l) = slot->x;
            else if (LANE_HOLDS(visited, l)) *slot = (complex_t)(0, 0);
        }
        if (!any(reach)) continue;
        const lanes_t beam = beam_mantissa(p, d2, e.mantissa);
        const lanes_t energy = shadow_energy(beam, (lane_index_t)e.exponent);
        lanes_t grad_u = 0, grad_z = 0, grad_transmission = 0;
        const lane_mask_t contributing = reach & contributes_lanes(e, b.ascan);
        if (any(contributing)) {
            lanes_t w[TAP_VECTORS];
            spread_weights(e.tap_offset, p.es_beta, w);
            const real *wv = (const real *)w;
            const lanes_t relative = ldexp(beam, e.exponent - scale);
            for (int l = 0; l < b.lanes; ++l) {
                if (!LANE_HOLDS(contributing, l)) continue;
                __global const complex_t *grid_bar = grid_scratch + (size_t)(b.first + l) * 2 * GRID;
                __global const complex_t *grid_bar_s = grid_bar + GRID;
                complex_t c_bar = (complex_t)(0, 0), c_bar_s = (complex_t)(0, 0);
                for (int t = 0; t < SPREAD_WIDTH; ++t) {
                    const int k = (e.first_tap + t) & (GRID - 1);
                    c_bar += wv[t] * grid_bar[k];
                    c_bar_s += wv[t] * grid_bar_s[k];
                }
                const real v = LANE(transmission, l) * LANE(relative, l);
                const real r = cconj_mul(c_bar, e.carrier).x;  /* ∂L/∂v */
                LANE(grad_u, l) = r * v / 2;
                /* Re(−2i·v·e^{iφ}·(k0·conj(c̄) + δk·conj(c̄'))) = 2v·Im(e^{iφ}·conj(k0·c̄ + δk·c̄')) */
                LANE(grad_z, l) = 2 * v * cconj_mul(p.k0 * c_bar + p.dk * c_bar_s, e.carrier).y;
                LANE(grad_transmission, l) = r * LANE(relative, l);
            }
        }
        grad_u -= select((lanes_t)0, transmission * downstream * energy, energy < 1);
        for (int l = 0; l < b.lanes; ++l)
            if (LANE_HOLDS(reach, l))
                slot_data[(size_t)(b.lane0 + l) * p.entries + j] = (complex_t)(LANE(grad_u, l), LANE(grad_z, l));
        downstream = select(downstream, grad_transmission + (1 - energy) * downstream, reach);
    }
}

/* ============================================ one work-group per A-scan */

/* In-place radix-2 FFT of length 1 << log2n of a local array, the work-group
 * sharing each stage's butterflies (same transform as fft above). Call with
 * every work-item of the group; returns after a barrier. */
static void fft_local(__local complex_t *a, int log2n, int sign, __global const complex_t *twiddle) {
    const int n = 1 << log2n, lid = get_local_id(0);
    for (int i = lid; i < n; i += WG_SIZE) { /* bit reversal: disjoint swaps */
        int reversed = 0;
        for (int b = 0; b < log2n; ++b) reversed |= ((i >> b) & 1) << (log2n - 1 - b);
        if (i < reversed) { const complex_t t = a[i]; a[i] = a[reversed]; a[reversed] = t; }
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int span = 1, stride = GRID >> 1; span < n; span <<= 1, stride >>= 1) {
        for (int butterfly = lid; butterfly < n / 2; butterfly += WG_SIZE) {
            const int k = butterfly & (span - 1);
            const int top = (butterfly - k) * 2 + k;
            complex_t w = twiddle[k * stride];
            w.y *= sign < 0 ? 1 : -1;
            const complex_t t = cmul(w, a[top + span]);
            a[top + span] = a[top] - t;
            a[top] += t;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
}

/* First list entry in [lo, hi) whose first tap is ≥ value (taps ascend along
 * a list, since entries are in depth order and p_m grows with z_m). */
static inline int first_tap_at_least(__global const Entry *entry, int lo, int hi, int value) {
    while (lo < hi) {
        const int mid = lo + (hi - lo) / 2;
        if (entry[mid].first_tap < value) lo = mid + 1; else hi = mid;
    }
    return lo;
}

/*
 * Forward, one work-group per A-scan; the same outputs as render_forward
 * (slot_data and stop_position are required: slot .y holds T·b̃ for the
 * gather). Per tile of WG_SIZE consecutive list entries:
 *   T_j = T_tile · Π_{tile entries k < j} (1 − t_k), an exclusive
 *   work-group scan of double-word products (Hillis–Steele);
 * then each grid point l gathers Σ ψ·T·b̃·e^{iφ} over the entries whose taps
 * cover it (a range of the list, found by binary search on first_tap), in
 * list order; then both FFTs run in local memory.
 */
__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
void render_forward_group(const ScannerParams p,
                          SCENE_ARGUMENTS,
                          __global complex_t *a_scan, __global const int *scale_exponent,
                          __global complex_t *slot_data, __global int *stop_position) {
    const int i = get_group_id(0), lid = get_local_id(0);
    const int list = i / p.ascans_per_bin + 1;
    const int begin = list_start[list], end = list_start[list + 1];
    __global complex_t *slot = slot_data + (size_t)(i % p.ascans_per_bin) * p.entries;
    __local real2 scan[WG_SIZE];
    __local complex_t grid[GRID];
    __local int visited;

    if (lid == 0) visited = end - begin;
    barrier(CLK_LOCAL_MEM_FENCE);
    const int scale = scale_exponent[i];
    real2 transmission = (real2)(1, 0); /* T before the tile, the same in every work-item */
    for (int base = begin; base < end; base += WG_SIZE) {
        const int j = base + lid;
        Entry e;
        real beam = 0, d2 = 0;
        real2 factor = (real2)(1, 0);
        if (j < end) {
            e = entry[j];
            d2 = squared_distance(p, i, e);
            if (d2 < p.shadow_d2) {
                beam = beam_mantissa(p, d2, e.mantissa);
                factor = one_minus(shadow_energy(beam, e.exponent));
            }
        }
        scan[lid] = factor;
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int offset = 1; offset < WG_SIZE; offset <<= 1) { /* inclusive product scan */
            const real2 earlier = lid >= offset ? scan[lid - offset] : (real2)(1, 0);
            barrier(CLK_LOCAL_MEM_FENCE);
            scan[lid] = dw_mul(earlier, scan[lid]);
            barrier(CLK_LOCAL_MEM_FENCE);
        }
        const real2 before = dw_mul(transmission, lid ? scan[lid - 1] : (real2)(1, 0));
        if (j < end) {
            if (before.x <= p.min_transmission) {
                atomic_min(&visited, j - begin);
                slot[j] = (complex_t)(0, 0);
            } else if (d2 < p.shadow_d2) {
                slot[j] = (complex_t)(before.x, contributes(e, i) ? before.x * ldexp(beam, e.exponent - scale) : 0);
            } else {
                slot[j] = (complex_t)(0, 0);
            }
        }
        transmission = dw_mul(transmission, scan[WG_SIZE - 1]);
        barrier(CLK_LOCAL_MEM_FENCE);
        if (transmission.x <= p.min_transmission) break; /* uniform: every work-item has the same T */
    }
    barrier(CLK_GLOBAL_MEM_FENCE | CLK_LOCAL_MEM_FENCE);
    const int stop = begin + visited;
    if (lid == 0) stop_position[i] = visited;

    /* Gather: grid point l receives from the entries with first_tap ≡ l − k
     * (mod GRID), k = 0 … W − 1; first_tap runs from −W/2 to GRID − W/2 + 1,
     * so the wrapped ranges are those of l ± GRID. */
    for (int l = lid; l < GRID; l += WG_SIZE) {
        complex_t sum = (complex_t)(0, 0);
        for (int wrap = -GRID; wrap <= GRID; wrap += GRID) {
            const int lowest = l + wrap - SPREAD_WIDTH + 1;
            for (int j = first_tap_at_least(entry, begin, stop, lowest); j < stop; ++j) {
                const int first = entry[j].first_tap;
                if (first > l + wrap) break;
                const real v = slot[j].y;
                if (v != 0) sum += (v * spread_weight(entry[j].tap_offset, l + wrap - first, p.es_beta)) * entry[j].carrier;
            }
        }
        grid[l] = sum;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    fft_local(grid, LOG2_GRID, -1, twiddle);
    /* X[q] = H[q]·grid[s_q mod GRID] in place: q ≤ NZ/2 reads its own index,
     * q > NZ/2 reads q + NZ, which no work-item writes. */
    for (int q = lid; q < NZ; q += WG_SIZE) grid[q] = transfer[q] * grid[q <= NZ / 2 ? q : q + NZ];
    barrier(CLK_LOCAL_MEM_FENCE);
    fft_local(grid, LOG2_NZ, +1, twiddle);
    for (int n = lid; n < NZ; n += WG_SIZE) a_scan[(size_t)i * NZ + n] = grid[n];
}

/*
 * Adjoint, one work-group per A-scan; the same outputs as render_adjoint.
 * The grid adjoints b̄, b̄' live in local memory; each entry's c̄, c̄' is an
 * independent gather. The shadow sensitivity D runs over tiles from the
 * deepest: within a tile, the maps F_k: D ↦ (1 − t_k)·D + R_k·b̃_k of the
 * entries after j compose (an exclusive suffix scan of affine maps,
 * (a, b)∘(a', b') = (a·a', a·b' + b)), and D before entry j is that
 * composition applied to the D carried from the deeper tiles.
 */
__kernel __attribute__((reqd_work_group_size(WG_SIZE, 1, 1)))
void render_adjoint_group(const ScannerParams p,
                          SCENE_ARGUMENTS,
                          __global const complex_t *a_scan_bar, __global const int *scale_exponent,
                          __global complex_t *slot_data, __global const int *stop_position) {
    const int i = get_group_id(0), lid = get_local_id(0);
    const int list = i / p.ascans_per_bin + 1;
    const int begin = list_start[list], end = list_start[list + 1];
    const int stop = begin + stop_position[i];
    const int scale = scale_exponent[i];
    __global complex_t *slot = slot_data + (size_t)(i % p.ascans_per_bin) * p.entries;
    __local complex_t grid_bar[GRID], grid_bar_s[GRID];
    __local real2 scan[WG_SIZE];

    for (int j = stop + lid; j < end; j += WG_SIZE) slot[j] = (complex_t)(0, 0);
    for (int l = lid; l < GRID; l += WG_SIZE) {
        grid_bar[l] = l < NZ ? a_scan_bar[(size_t)i * NZ + l] : (complex_t)(0, 0);
        grid_bar_s[l] = (complex_t)(0, 0);
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    fft_local(grid_bar, LOG2_NZ, -1, twiddle);
    /* X̄[q] = H[q]·FFT(Ā)[q] moves to grid index q (q ≤ NZ/2) or q + NZ, which
     * only work-item q touches. */
    for (int q = lid; q < NZ; q += WG_SIZE) {
        const complex_t x_bar = transfer[q] * grid_bar[q];
        const int s = q <= NZ / 2 ? q : q - NZ;
        const int l = q <= NZ / 2 ? q : q + NZ;
        if (l != q) grid_bar[q] = (complex_t)(0, 0);
        grid_bar[l] = x_bar;
        grid_bar_s[l] = (real)s * x_bar;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    fft_local(grid_bar, LOG2_GRID, +1, twiddle);
    fft_local(grid_bar_s, LOG2_GRID, +1, twiddle);

    real downstream = 0; /* D below the current tile, the same in every work-item */
    for (int top = stop - WG_SIZE; top > begin - WG_SIZE; top -= WG_SIZE) {
        const int j = top + lid;
        const bool valid = j >= begin;
        Entry e;
        real d2 = p.shadow_d2, beam = 0, energy = 0, transmission = 0;
        real grad_u = 0, grad_z = 0;
        real2 map = (real2)(1, 0); /* F_j as (a, b), the identity when out of reach */
        if (valid) {
            e = entry[j];
            d2 = squared_distance(p, i, e);
        }
        if (d2 < p.shadow_d2) {
            beam = beam_mantissa(p, d2, e.mantissa);
            energy = shadow_energy(beam, e.exponent);
            transmission = slot[j].x;
            real grad_transmission = 0;
            if (contributes(e, i)) {
                complex_t c_bar = (complex_t)(0, 0), c_bar_s = (complex_t)(0, 0);
                for (int t = 0; t < SPREAD_WIDTH; ++t) {
                    const real w = spread_weight(e.tap_offset, t, p.es_beta);
                    const int l = (e.first_tap + t) & (GRID - 1);
                    c_bar += w * grid_bar[l];
                    c_bar_s += w * grid_bar_s[l];
                }
                const real relative = ldexp(beam, e.exponent - scale);
                const real v = transmission * relative;
                const real r = cconj_mul(c_bar, e.carrier).x;
                grad_u = r * v / 2;
                grad_z = 2 * v * cconj_mul(p.k0 * c_bar + p.dk * c_bar_s, e.carrier).y;
                grad_transmission = r * relative;
            }
            map = (real2)(1 - energy, grad_transmission);
        }
        scan[lid] = map;
        barrier(CLK_LOCAL_MEM_FENCE);
        for (int offset = 1; offset < WG_SIZE; offset <<= 1) { /* inclusive suffix scan */
            const real2 deeper = lid + offset < WG_SIZE ? scan[lid + offset] : (real2)(1, 0);
            barrier(CLK_LOCAL_MEM_FENCE);
            const real2 own = scan[lid];
            scan[lid] = (real2)(own.x * deeper.x, own.x * deeper.y + own.y);
            barrier(CLK_LOCAL_MEM_FENCE);
        }
        const real2 after = lid + 1 < WG_SIZE ? scan[lid + 1] : (real2)(1, 0);
        if (d2 < p.shadow_d2) {
            if (energy < 1) grad_u -= transmission * (after.x * downstream + after.y) * energy;
            slot[j] = (complex_t)(grad_u, grad_z);
        } else if (valid) {
            slot[j] = (complex_t)(0, 0);
        }
        downstream = scan[0].x * downstream + scan[0].y;
        barrier(CLK_LOCAL_MEM_FENCE);
    }
}

/* Sum each scatterer's slots: gradient[m] = (∂L/∂u_m, ∂L/∂z_m). Scatterer m
 * has one entry in each of the lists bin_m − 1 … bin_m + 1 that exist
 * (entry_index[3m + k], −1 for none), each serving P A-scans. */
__kernel void reduce_slots(const ScannerParams p, __global const int *bin,
                           __global const int *entry_index, __global const complex_t *slot_data,
                           __global complex_t *gradient, const int count) {
    const int m = get_global_id(0);
    if (m >= count) return;
    complex_t total = (complex_t)(0, 0);
    for (int k = 0; k < 3; ++k) {
        const int j = entry_index[3 * m + k];
        if (j < 0) continue;
        const int first_ascan = p.ascans_per_bin * (bin[m] - 2 + k);
        for (int s = 0; s < p.ascans_per_bin; ++s) {
            const int ascan = first_ascan + s;
            if (ascan >= 0 && ascan < p.a_scans) total += slot_data[(size_t)s * p.entries + j];
        }
    }
    gradient[m] = total;
}
