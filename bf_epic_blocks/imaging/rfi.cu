// Interference detection on the GPU: the power sums of 4-bit voltages, and the flags applied.
// Launched by imaging/rfi.py (block_power, apply_flags), which gives the shapes in Python terms.

// rfi_block_power: ci4 bytes b (T, K) (K = channels x inputs, contiguous; high nibble real, two's
// complement) -> s1, s2 (T / m, K) the sums of |x|^2 and |x|^4 over each whole block of m samples
// (exact: integers below 2^53), and sh (T / a, K / g) the sums of |x|^2 over each whole short block of a
// samples and each group of g adjacent inputs (a stand's pols; g a power of 2 up to 32). skip (T / a
// bytes, or null): short blocks whose samples are left out of s1 and s2 (not out of sh). One thread per
// column k walks down time, so that neighbouring threads read neighbouring bytes and the bytes are read
// once; the power array the NumPy form makes (4 bytes a sample) never exists. A group's sum is a shuffle
// within the warp (g divides 32, so a group never straddles warps); every thread of a warp takes part.
// Launch: grid (ceil(K / 256)), block (256).
extern "C" __global__ void rfi_block_power(const unsigned char* __restrict__ b, double* __restrict__ s1,
                                           double* __restrict__ s2, float* __restrict__ sh,
                                           const unsigned char* __restrict__ skip, long long K, int T, int m,
                                           int a, int g) {
    const long long k = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    const bool on = k < K;
    const long long G = K / g;
    long long acc1 = 0, acc2 = 0;
    int accs = 0, im_ = 0, is_ = 0;
    for (int t = 0; t < T; ++t) {
        int p = 0;
        if (on) {
            const unsigned char v = b[(size_t)t * (size_t)K + (size_t)k];
            const int re = (int)(signed char)v >> 4;                      // arithmetic shift: the nibble's sign
            const int im = (int)(signed char)(unsigned char)(v << 4) >> 4;
            p = re * re + im * im;
        }
        if (skip == nullptr || !skip[t / a]) {
            acc1 += p;
            acc2 += p * p;
        }
        accs += p;
        if (++is_ == a) {
            int v = accs;
            for (int off = g / 2; off > 0; off /= 2) v += __shfl_down_sync(0xffffffffu, v, off, g);
            if (on && k % g == 0) sh[(size_t)(t / a) * (size_t)G + (size_t)(k / g)] = (float)v;
            accs = 0;
            is_ = 0;
        }
        if (++im_ == m) {
            if (on) {
                const size_t o = (size_t)(t / m) * (size_t)K + (size_t)k;
                s1[o] = (double)acc1;
                s2[o] = (double)acc2;
            }
            acc1 = acc2 = 0;
            im_ = 0;
        }
    }
}

// rfi_apply_flags: one thread block per (short block j, channel c): the detectors' flags combined per
// stand, the gulp's bytes copied with the flagged stands' bytes zeroed, and the stands counted.
//   x, out : (n, nchan, nstand, B) bytes, B bytes per stand (its pols' samples), contiguous
//   sk : (nsk, nchan, nstand) bit 0 low SK, bit 1 high SK (either pol);  which : (ns,) SK block of each
//   short block, -1 untested;  imp : (ns,) band-wide impulse;  imps : (ns, nstand) one stand's impulse;
//   stat : (nchan,) listed channel;  live : (nstand,) stand in use;  a : frames per short block (the last
//   holds what is left of n);  spread_max : more live stands than this flagged on their own flag all.
//   cnt : (ns, nchan, 7) int32 live stands flagged by static, sk-low, sk-high, impulse, impulse-stand,
//   spread, and by any (the same rules as imaging/rfi.py's apply_flags, which is their definition);
//   words : the rows (nstand B bytes) and both arrays start on 4-byte boundaries: copied a word at a time.
// Launch: grid (nchan, ns), block (256), dynamic shared memory nstand bytes.
extern "C" __global__ void rfi_apply_flags(const unsigned char* __restrict__ x, unsigned char* __restrict__ out,
                                           const unsigned char* __restrict__ sk, const int* __restrict__ which,
                                           const unsigned char* __restrict__ imp,
                                           const unsigned char* __restrict__ imps,
                                           const unsigned char* __restrict__ stat,
                                           const unsigned char* __restrict__ live, int* __restrict__ cnt,
                                           int n, int nchan, int nstand, int B, int a, float spread_max,
                                           int words) {
    extern __shared__ unsigned char bad[];
    __shared__ int tot[8];
    const int c = blockIdx.x, j = blockIdx.y, tid = threadIdx.x;
    if (tid < 8) tot[tid] = 0;
    __syncthreads();
    const int w = which[j];
    const bool st = stat[c] != 0, ib = imp[j] != 0;
    int own = 0;
    for (int s = tid; s < nstand; s += blockDim.x) {            // a stand's own flags (bit 0: any of them)
        const int code = w >= 0 ? sk[((size_t)w * nchan + c) * nstand + s] : 0;
        const bool lo = code & 1, hi = code & 2, is = imps[(size_t)j * nstand + s] != 0;
        const bool per = (lo || hi || is) && live[s];
        bad[s] = (unsigned char)(per | (lo << 1) | (hi << 2) | (is << 3));
        own += per;
    }
    atomicAdd(&tot[7], own);
    __syncthreads();
    const bool wide = (float)tot[7] > spread_max;
    int n_st = 0, n_lo = 0, n_hi = 0, n_imp = 0, n_is = 0, n_sp = 0, n_any = 0;
    for (int s = tid; s < nstand; s += blockDim.x) {
        const unsigned char f = bad[s];
        const bool per = f & 1, l = live[s] != 0, sp = wide && !per;
        const bool any = st || per || ib || sp;
        if (l) {
            n_st += st; n_lo += (f >> 1) & 1; n_hi += (f >> 2) & 1; n_imp += ib; n_is += (f >> 3) & 1;
            n_sp += sp; n_any += any;
        }
        bad[s] = any;
    }
    atomicAdd(&tot[0], n_st); atomicAdd(&tot[1], n_lo); atomicAdd(&tot[2], n_hi); atomicAdd(&tot[3], n_imp);
    atomicAdd(&tot[4], n_is); atomicAdd(&tot[5], n_sp); atomicAdd(&tot[6], n_any);
    __syncthreads();
    if (tid < 7) cnt[((size_t)j * nchan + c) * 7 + tid] = tot[tid];
    const int t0 = j * a, t1 = min(n, t0 + a);
    const long long R = (long long)nstand * B;                   // bytes of one (frame, channel) row
    if (words) {                                                 // rows start on 4-byte boundaries
        const int nw = (int)(R / 4);
        for (int t = t0; t < t1; ++t) {
            const size_t base = ((size_t)t * nchan + c) * (size_t)(R / 4);
            const unsigned int* xi = reinterpret_cast<const unsigned int*>(x) + base;
            unsigned int* xo = reinterpret_cast<unsigned int*>(out) + base;
            for (int q = tid; q < nw; q += blockDim.x) {
                unsigned int keep = 0;
                for (int y = 0; y < 4; ++y)
                    if (!bad[(4 * q + y) / B]) keep |= 0xffu << (8 * y);
                xo[q] = xi[q] & keep;
            }
        }
    } else {
        for (int t = t0; t < t1; ++t) {
            const size_t base = ((size_t)t * nchan + c) * (size_t)R;
            for (long long q = tid; q < R; q += blockDim.x)
                out[base + q] = bad[q / B] ? 0 : x[base + q];
        }
    }
}
