/*
 * NumPy's classic argsort (the portable introsort of NumPy ≤ 1.24, functions
 * aquicksort_ and aheapsort_ in numpy/_core/src/npysort/quicksort.cpp and
 * heapsort.cpp), run as a single work-item: the algorithm is sequential, and
 * its order among equal keys is what the Virtual Scanner's shadowing sees.
 *
 * Keys are the float64 depths mapped to int64 on the host by the monotone map
 *   k(z) = b ^ ((b >> 63) & 0x7FFFFFFFFFFFFFFF),   b = the bits of z,
 * after −0.0 → +0.0 and every NaN → one positive NaN: k(a) < k(b) exactly
 * when NumPy's float comparison says a < b (NaNs last, equal to each other).
 * So the kernel compares `long` and needs no cl_khr_fp64.
 *
 * The algorithm (Musser's introsort, iterative, over positions pl … pr):
 *   1. While the range holds more than SMALL_PARTITION + 1 = 16 entries:
 *      order the entries at pl, pm = pl + (pr − pl)/2, pr (median of 3),
 *      park the median at pr − 1 as the pivot and partition pl + 1 … pr − 2
 *      with two pointers, both stopping at keys equal to the pivot; put the
 *      pivot back between the parts. Push the larger part, with the depth
 *      budget decremented once per partition, and continue with the smaller.
 *   2. A range of ≤ 16 entries is finished by straight insertion sort.
 *   3. A range reached with a negative depth budget (initially
 *      2·floor(log2 n)) is heapsorted instead: O(n log n) worst case.
 *   4. Pop the next range; stop when the stack is empty.
 * The smaller part is processed first, so at most log2 n ranges are pending.
 *
 * NumPy sorts an index array and reads keys through it (v[tosort[i]]). Here
 * the key travels with its index (key[i] is always the key of order[i]),
 * which makes the same comparisons and moves without the indirection.
 *
 * Reference: D. R. Musser, "Introspective sorting and selection
 * algorithms", Software: Practice and Experience 27 (1997) 983–993.
 *
 * Defines (octcl/device/depth_order.py, program_defines): SMALL_PARTITION
 * (NumPy's SMALL_QUICKSORT, 15: partition while pr − pl > 15), the value
 * the host's Python twin sorts with.
 */

#define MAX_PENDING 32       /* pending ranges: ≤ log2 n < 31 for int positions */

typedef struct {
    int count;        /* n, the number of keys */
    int depth_limit;  /* 2·floor(log2 n): partitions allowed before heapsort */
} introsort_params;

static inline void swap_entries(__global long *key, __global int *order, int a, int b)
{
    const long k = key[a];
    key[a] = key[b];
    key[b] = k;
    const int o = order[a];
    order[a] = order[b];
    order[b] = o;
}

/* Move the entry at 1-based heap slot `slot` down the max-heap of `n` slots
 * (slot s is position base + s − 1), as aheapsort_ does. */
static void sift_down(__global long *key, __global int *order, int base, int slot, int n)
{
    const long moving_key = key[base + slot - 1];
    const int moving_index = order[base + slot - 1];
    int child = slot << 1;
    while (child <= n) {
        if (child < n && key[base + child - 1] < key[base + child]) {
            child += 1;
        }
        if (!(moving_key < key[base + child - 1])) {
            break;
        }
        key[base + slot - 1] = key[base + child - 1];
        order[base + slot - 1] = order[base + child - 1];
        slot = child;
        child += child;
    }
    key[base + slot - 1] = moving_key;
    order[base + slot - 1] = moving_index;
}

/* Heapsort of positions first … first + n − 1 (aheapsort_). */
static void heapsort_range(__global long *key, __global int *order, int first, int n)
{
    for (int slot = n >> 1; slot > 0; --slot) {
        sift_down(key, order, first, slot, n);
    }
    while (n > 1) {
        swap_entries(key, order, first, first + n - 1);
        n -= 1;
        sift_down(key, order, first, 1, n);
    }
}

/* Straight insertion sort of positions pl … pr. */
static void insertion_sort_range(__global long *key, __global int *order, int pl, int pr)
{
    for (int pi = pl + 1; pi <= pr; ++pi) {
        const long moving_key = key[pi];
        const int moving_index = order[pi];
        int pj = pi;
        while (pj > pl && moving_key < key[pj - 1]) {
            key[pj] = key[pj - 1];
            order[pj] = order[pj - 1];
            --pj;
        }
        key[pj] = moving_key;
        order[pj] = moving_index;
    }
}

/* Sorts key[0 … n−1] in place and writes to order the permutation that
 * np.argsort (classic introsort) returns for the original keys. */
__kernel void introsort_argsort(const introsort_params params, __global long *key,
                                __global int *order)
{
    const int n = params.count;
    for (int i = 0; i < n; ++i) {
        order[i] = i;
    }
    int pending_first[MAX_PENDING], pending_last[MAX_PENDING], pending_depth[MAX_PENDING];
    int pending = 0;
    int pl = 0, pr = n - 1, depth = params.depth_limit;
    for (;;) {
        if (depth < 0) {
            heapsort_range(key, order, pl, pr - pl + 1);
        } else {
            while (pr - pl > SMALL_PARTITION) {
                const int pm = pl + ((pr - pl) >> 1);
                if (key[pm] < key[pl]) swap_entries(key, order, pm, pl);
                if (key[pr] < key[pm]) swap_entries(key, order, pr, pm);
                if (key[pm] < key[pl]) swap_entries(key, order, pm, pl);
                const long pivot = key[pm];
                int pi = pl, pj = pr - 1;
                swap_entries(key, order, pm, pj);
                /* key[pl] ≤ pivot and key[pr − 1] = pivot stop both scans. */
                for (;;) {
                    do { ++pi; } while (key[pi] < pivot);
                    do { --pj; } while (pivot < key[pj]);
                    if (pi >= pj) break;
                    swap_entries(key, order, pi, pj);
                }
                swap_entries(key, order, pi, pr - 1);
                --depth;
                if (pi - pl < pr - pi) {
                    pending_first[pending] = pi + 1;
                    pending_last[pending] = pr;
                    pr = pi - 1;
                } else {
                    pending_first[pending] = pl;
                    pending_last[pending] = pi - 1;
                    pl = pi + 1;
                }
                pending_depth[pending++] = depth;
            }
            insertion_sort_range(key, order, pl, pr);
        }
        if (pending == 0) break;
        --pending;
        pl = pending_first[pending];
        pr = pending_last[pending];
        depth = pending_depth[pending];
    }
}
