// Interference detection on the GPU: the power sums of 4-bit voltages, and the flags applied.
// Launched by imaging/rfi.py (block_power, apply_flags), which gives the shapes in Python terms.

// rfi_block_power: ci4 bytes b (T, K) (K = channels x inputs, contiguous, K a multiple of 4; high nibble
// real, two's complement), read as 32-bit words w (4 inputs each) -> s1, s2 (T / m, K) the sums of |x|^2
// and |x|^4 over each whole block of m samples (exact: integers below 2^53; zeroed by the caller, each
// time chunk adds its part), and sh (T / a, K / g) the sums of |x|^2 over each whole short block of a
// samples and each group of g adjacent inputs (a stand's pols; g a power of 2 up to 32). m is a multiple
// of a. skip (T / a bytes, or null): short blocks whose samples are left out of s1 and s2 (not out of sh).
// Thread (word w, chunk y) walks the frames [y chunk, (y + 1) chunk) (chunk a multiple of a, at most 2^16
// frames, so that a chunk's sums fit int32: |x|^4 <= 2^14) a short block at a time, with no division
// inside a short block: a warp reads 128 neighbouring bytes a frame, and the power array the NumPy form
// makes (4 bytes a sample) never exists. A group wider than a word is summed by a shuffle within the warp
// (every thread of a warp takes part). Launch: grid (ceil(K / 4 / 256), ceil(T / chunk)), block (256).
extern "C" __global__ void rfi_block_power(const unsigned int* __restrict__ b, double* __restrict__ s1,
                                           double* __restrict__ s2, float* __restrict__ sh,
                                           const unsigned char* __restrict__ skip, long long K4, int T, int m,
                                           int a, int g, int chunk) {
    const long long w = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    const bool on = w < K4;
    const long long K = 4 * K4, G = K / g;
    const int t0 = blockIdx.y * chunk, t1 = min(T, t0 + chunk);
    const int nbm = (T / m) * m, ns = T / a;                 // frames in whole blocks; whole short blocks
    int acc1[4] = {0, 0, 0, 0}, acc2[4] = {0, 0, 0, 0};
    for (int ta = t0, sb = t0 / a; ta < t1; ta += a, ++sb) {
        const int tb = min(ta + a, t1);
        int c1[4] = {0, 0, 0, 0}, c2[4] = {0, 0, 0, 0};
#pragma unroll 4
        for (int t = ta; t < tb; ++t) {
            const unsigned int v = on ? b[(size_t)t * (size_t)K4 + (size_t)w] : 0u;
#pragma unroll
            for (int q = 0; q < 4; ++q) {
                const int re = (int)(v << (24 - 8 * q)) >> 28;          // arithmetic shifts: the nibbles' signs
                const int im = (int)(v << (28 - 8 * q)) >> 28;
                const int p = re * re + im * im;
                c1[q] += p;
                c2[q] += p * p;
            }
        }
        if (sb < ns) {                                           // a whole short block: its group sums
            const size_t row = (size_t)sb * (size_t)G;
            if (g <= 4) {
                for (int q = 0; q < 4; q += g) {
                    int v2 = 0;
                    for (int e = 0; e < g; ++e) v2 += c1[q + e];
                    if (on) sh[row + (size_t)((4 * w + q) / g)] = (float)v2;
                }
            } else {
                int v2 = c1[0] + c1[1] + c1[2] + c1[3];
                for (int off = g / 8; off > 0; off /= 2) v2 += __shfl_down_sync(0xffffffffu, v2, off, g / 4);
                if (on && (4 * w) % g == 0) sh[row + (size_t)(4 * w / g)] = (float)v2;
            }
        }
        if (ta < nbm && !(skip != nullptr && sb < ns && skip[sb])) {
            for (int q = 0; q < 4; ++q) {
                acc1[q] += c1[q];
                acc2[q] += c2[q];
            }
        }
        if (ta < nbm && (tb % m == 0 || tb == t1)) {              // a block or the chunk ends: add its part
            if (on) {
                const size_t o = (size_t)(ta / m) * (size_t)K + (size_t)(4 * w);
                for (int q = 0; q < 4; ++q) {
                    if (acc1[q]) atomicAdd(&s1[o + q], (double)acc1[q]);
                    if (acc2[q]) atomicAdd(&s2[o + q], (double)acc2[q]);
                }
            }
            acc1[0] = acc1[1] = acc1[2] = acc1[3] = 0;
            acc2[0] = acc2[1] = acc2[2] = acc2[3] = 0;
        }
    }
}

// rfi_sk_code: per (block i, channel and stand k): bit 0 where any of its np pols' SK is below the low
// threshold, bit 1 above the high one (imaging/rfi.py's sk_code, which is the definition).
//   s1, s2 : (nb, K np) power sums of blocks of m samples;  lo, hi : (L,) thresholds, indexed by S1 (an
//   integer for quantised data, L = 128 m + 1) or one pair (L = 1);  min_s1 : a block with S1 below it (or
//   S1 = 0) has no power and no SK flag.  Launch: grid (ceil(nb K / 256)), block (256).
extern "C" __global__ void rfi_sk_code(const double* __restrict__ s1, const double* __restrict__ s2,
                                       const double* __restrict__ lo, const double* __restrict__ hi,
                                       unsigned char* __restrict__ code, long long n, int np, double m,
                                       long long L, double min_s1) {
    const long long k = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (k >= n) return;
    unsigned char c = 0;
    for (int p = 0; p < np; ++p) {
        const double a1 = s1[k * np + p], a2 = s2[k * np + p];
        if (a1 == 0.0 || a1 < min_s1) continue;
        const double sk = (m + 1.0) / (m - 1.0) * (m * a2 / (a1 * a1) - 1.0);
        const long long j = L == 1 ? 0 : min((long long)a1, L - 1);
        if (sk < lo[j]) c |= 1;
        else if (sk > hi[j]) c |= 2;
    }
    code[k] = c;
}

// rfi_warp_median: the median of v[0 .. L) (L <= 128, in shared memory, one warp's), NumPy's rule (the mean of
// the two middle values where L is even), to every lane of the warp: each lane ranks its values against all
// L (ties broken by position, so that the ranks are 0 .. L - 1), and the values ranked L / 2 (and L / 2 - 1)
// are the middle of the sorted list. No sort, no local arrays: a few hundred compares a lane.
__device__ float rfi_warp_median(const float* v, int L, float* mid) {
    const int lane = threadIdx.x % 32;
    for (int i = lane; i < L; i += 32) {
        const float y = v[i];
        int r = 0;
        for (int j = 0; j < L; ++j) {
            const float z = v[j];
            r += (z < y) || (z == y && j < i);
        }
        if (r == L / 2) mid[1] = y;
        if (r == L / 2 - 1) mid[0] = y;
    }
    __syncwarp();
    const float m = (L % 2) ? mid[1] : (mid[0] + mid[1]) / 2.0f;
    __syncwarp();
    return m;
}

// rfi_median_axis1: out (R, C) = the median of x (R, L, C) over its middle axis (NumPy's rule), L <= 128. A
// warp per (r, c). Launch: grid (ceil(32 R C / 256)), block (256).
extern "C" __global__ void rfi_median_axis1(const float* __restrict__ x, float* __restrict__ out, int R, int L,
                                            int C) {
    __shared__ float v[8][128];
    __shared__ float mid[8][2];
    const int w = threadIdx.x / 32, lane = threadIdx.x % 32;
    const long long k = ((long long)blockIdx.x * blockDim.x + threadIdx.x) / 32;
    if (k >= (long long)R * C) return;                         // a whole warp leaves together
    const long long r = k / C, c = k % C;
    for (int i = lane; i < L; i += 32) v[w][i] = x[((size_t)r * L + i) * (size_t)C + (size_t)c];
    __syncwarp();
    const float m = rfi_warp_median(v[w], L, mid[w]);
    if (lane == 0) out[k] = m;
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
//   words : the rows (nstand B bytes) and both arrays start on 16-byte boundaries: copied 16 bytes at a time.
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
    for (int off = 16; off > 0; off /= 2) own += __shfl_down_sync(0xffffffffu, own, off);
    if (tid % 32 == 0 && own) atomicAdd(&tot[7], own);
    __syncthreads();
    const bool wide = (float)tot[7] > spread_max;
    int n_st = 0, n_lo = 0, n_hi = 0, n_imp = 0, n_is = 0, n_sp = 0, n_any = 0, mine = 0;
    for (int s = tid; s < nstand; s += blockDim.x) {
        const unsigned char f = bad[s];
        const bool per = f & 1, l = live[s] != 0, sp = wide && !per;
        const bool any = st || per || ib || sp;
        if (l) {
            n_st += st; n_lo += (f >> 1) & 1; n_hi += (f >> 2) & 1; n_imp += ib; n_is += (f >> 3) & 1;
            n_sp += sp; n_any += any;
        }
        bad[s] = any;
        mine |= any;
    }
    // each warp's sums first, then one shared atomic per warp and counter (not one per thread)
    int cs[7] = {n_st, n_lo, n_hi, n_imp, n_is, n_sp, n_any};
    for (int r = 0; r < 7; ++r) {
        int v = cs[r];
        for (int off = 16; off > 0; off /= 2) v += __shfl_down_sync(0xffffffffu, v, off);
        if (tid % 32 == 0 && v) atomicAdd(&tot[r], v);
    }
    const bool none = !__syncthreads_or(mine);                   // no stand zeroed here: a plain copy
    if (tid < 7) cnt[((size_t)j * nchan + c) * 7 + tid] = tot[tid];
    const int t0 = j * a, t1 = min(n, t0 + a);
    const long long R = (long long)nstand * B;                   // bytes of one (frame, channel) row
    if (words) {                                                 // rows and arrays on 16-byte boundaries
        const int nq = (int)(R / 16), items = (t1 - t0) * nq;
        for (int it = tid; it < items; it += blockDim.x) {
            const int t = t0 + it / nq, q = it % nq;
            const size_t o = ((size_t)t * nchan + c) * (size_t)nq + q;
            uint4 v = reinterpret_cast<const uint4*>(x)[o];
            unsigned int* u = reinterpret_cast<unsigned int*>(&v);
            if (!none)
                for (int y = 0; y < 16; ++y)
                    if (bad[(16 * q + y) / B]) u[y / 4] &= ~(0xffu << (8 * (y % 4)));
            reinterpret_cast<uint4*>(out)[o] = v;
        }
    } else {
        for (int t = t0; t < t1; ++t) {
            const size_t base = ((size_t)t * nchan + c) * (size_t)R;
            for (long long q = tid; q < R; q += blockDim.x)
                out[base + q] = (!none && bad[q / B]) ? 0 : x[base + q];
        }
    }
}

// rfi_block_mean: ref[c, i] = the mean over the nb blocks of P[b, c, i] (float32 sums in block order):
// P (nb, nchan, nin) float32, ref (nchan, nin). A thread per (c, i). Launch: grid (ceil(nchan nin / 256)), (256).
extern "C" __global__ void rfi_block_mean(const float* __restrict__ P, float* __restrict__ ref, int nb, long long n) {
    const long long k = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (k >= n) return;
    float s = 0.0f;
    for (int b = 0; b < nb; ++b) s += P[(size_t)b * (size_t)n + (size_t)k];
    ref[k] = s / (float)nb;
}

// rfi_group_means: the impulse detector's ratios averaged over groups of channels (imaging/rfi.py's
// broadband_flags, which is their definition): means[b, q, i] = (1/g) sum over the g channels c of group q
// of (ref[c, i] > 0 ? P[b, c, i] / ref[c, i] : 1), in channel order.  P (nb, nchan, nin) float32, ref (nchan,
// nin), means (nb, ng, nin) float32. A thread per (b, q, i): consecutive threads read consecutive inputs.
// Launch: grid (ceil(nb ng nin / 256)), block (256).
extern "C" __global__ void rfi_group_means(const float* __restrict__ P, const float* __restrict__ ref,
                                           float* __restrict__ means, int nb, int nchan, int nin, int g, int ng) {
    const long long k = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (k >= (long long)nb * ng * nin) return;
    const int i = (int)(k % nin), q = (int)((k / nin) % ng), b = (int)(k / ((long long)nin * ng));
    float acc = 0.0f;
    for (int e = 0; e < g; ++e) {
        const int c = q * g + e;
        const float r = ref[(size_t)c * nin + i];
        acc += r > 0.0f ? P[((size_t)b * nchan + c) * nin + i] / r : 1.0f;
    }
    means[k] = acc / (float)g;
}

// rfi_robust_flags: flags[b, j] = 1 where stat[b, j] > med_j + kf MAD_j (med_j the median over b of column
// j, MAD_j the median of |stat[:, j] - med_j|, NumPy's rule for even nb), the product and the sum rounded
// one at a time as the array form's are.  stat (nb, C) float32, nb <= 128, flags (nb, C) uint8. A warp per
// column. Launch: grid (ceil(32 C / 256)), block (256).
extern "C" __global__ void rfi_robust_flags(const float* __restrict__ stat, unsigned char* __restrict__ flags,
                                            int nb, int C, float kf) {
    __shared__ float v[8][128];
    __shared__ float mid[8][2];
    const int w = threadIdx.x / 32, lane = threadIdx.x % 32;
    const long long j = ((long long)blockIdx.x * blockDim.x + threadIdx.x) / 32;
    if (j >= C) return;
    for (int b = lane; b < nb; b += 32) v[w][b] = stat[(size_t)b * C + j];
    __syncwarp();
    const float med = rfi_warp_median(v[w], nb, mid[w]);
    for (int b = lane; b < nb; b += 32) v[w][b] = fabsf(__fsub_rn(stat[(size_t)b * C + j], med));
    __syncwarp();
    const float lim = __fadd_rn(med, __fmul_rn(kf, rfi_warp_median(v[w], nb, mid[w])));
    for (int b = lane; b < nb; b += 32) flags[(size_t)b * C + j] = stat[(size_t)b * C + j] > lim;
}

// rfi_band_power: out[b, c] the power of block b and channel c summed over the live stands, or where fewer
// than half of the nl live stands sparked on their own in block b (own[b, i]), the sum without those stands
// times nl / (nl - k), k of them (imaging/rfi.py's band_power is the definition). P (nb, nchan, nin) float32
// (integers: the sums are exact in any order), own (nb, nin) and live (nin,) bytes, out (nb, nchan). A warp
// per (b, c), its lanes across the stands. Launch: grid (ceil(32 nb nchan / 256)), block (256).
extern "C" __global__ void rfi_band_power(const float* __restrict__ P, const unsigned char* __restrict__ own,
                                          const unsigned char* __restrict__ live, float* __restrict__ out, int nb,
                                          int nchan, int nin) {
    const long long wid = ((long long)blockIdx.x * blockDim.x + threadIdx.x) / 32;
    const int lane = threadIdx.x % 32;
    if (wid >= (long long)nb * nchan) return;
    const int b = (int)(wid / nchan);
    const float* row = P + (size_t)wid * nin;
    float total = 0.0f, kept = 0.0f;
    int k = 0, nl = 0;
    for (int i = lane; i < nin; i += 32) {
        const bool l = live[i] != 0, o = l && own[(size_t)b * nin + i] != 0;
        const float p = l ? row[i] : 0.0f;
        total += p;
        kept += o ? 0.0f : p;
        k += o;
        nl += l;
    }
    for (int off = 16; off > 0; off /= 2) {
        total += __shfl_down_sync(0xffffffffu, total, off);
        kept += __shfl_down_sync(0xffffffffu, kept, off);
        k += __shfl_down_sync(0xffffffffu, k, off);
        nl += __shfl_down_sync(0xffffffffu, nl, off);
    }
    if (lane == 0) {
        const float fl = (float)max(nl, 1), fk = (float)k;
        out[wid] = (2.0f * fk < fl) ? __fmul_rn(kept, fl / fmaxf(__fsub_rn(fl, fk), 1.0f)) : total;
    }
}
