// The reductions that follow the imager's GEMMs, one pass over the GEMM output each. Launched by
// imaging/reduce.py (block_corr, row_dot, products_from_blocks, channel_mean), which gives the shapes
// in Python terms.

// bf_block_corr: for each polarisation block b = (bp[b], bq[b]), the sums over groups of n samples of
// F_p conj(F_q). F element (row (c, k), column j) sits at F[c sc + k sk + j es] (real) and + im_off
// (imaginary), in float elements: complex (C, K, P T) has es 2, im_off 1; stacked [Re; Im] (C, 2, K, P T)
// has es 1, im_off K P T. Column j = p T + t. out: complex64 (G, C, nblk, K), times sval (*scale when
// scale is not null: a device scalar). One thread per output (c, b, k, g): consecutive threads take
// consecutive groups g of one row, so a warp reads one contiguous stretch of the row.
// Launch: C nblk K G threads, blocks of 256.
extern "C" __global__ void bf_block_corr(
    const float* __restrict__ F, float2* __restrict__ out, const float* __restrict__ scale, const float sval,
    const int C, const int K, const int T, const int n, const int G, const int nblk,
    const int* __restrict__ bp, const int* __restrict__ bq,
    const long long sc, const long long sk, const long long im_off, const int es)
{
    // output: complex64 (G, C, nblk, K), times *scale
    long long idx = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    long long total = (long long)C * nblk * K * G;
    if (idx >= total) return;
    int g = (int)(idx % G);
    long long r = idx / G;
    int k = (int)(r % K); r /= K;
    int b = (int)(r % nblk);
    int c = (int)(r / nblk);
    int p = bp[b], q = bq[b];
    const float* row = F + c * sc + k * sk;
    const float* fp = row + ((long long)p * T + (long long)g * n) * es;
    const float* fq = row + ((long long)q * T + (long long)g * n) * es;
    float sr = 0.f, si = 0.f;
    if (es == 1 && (n & 3) == 0 && (T & 3) == 0 && (im_off & 3) == 0 && (sk & 3) == 0 && (sc & 3) == 0) {
        // stacked layout, aligned: 16-byte loads (the GEMM output is 256-byte aligned)
        const float4* pr = reinterpret_cast<const float4*>(fp);
        const float4* pi = reinterpret_cast<const float4*>(fp + im_off);
        const float4* qr = reinterpret_cast<const float4*>(fq);
        const float4* qi = reinterpret_cast<const float4*>(fq + im_off);
        for (int t = 0; t < (n >> 2); ++t) {
            float4 a = pr[t], ai = pi[t];
            if (p == q) {
                sr += a.x * a.x + a.y * a.y + a.z * a.z + a.w * a.w
                    + ai.x * ai.x + ai.y * ai.y + ai.z * ai.z + ai.w * ai.w;
            } else {
                float4 b2 = qr[t], bi = qi[t];
                sr += a.x * b2.x + a.y * b2.y + a.z * b2.z + a.w * b2.w
                    + ai.x * bi.x + ai.y * bi.y + ai.z * bi.z + ai.w * bi.w;
                si += ai.x * b2.x + ai.y * b2.y + ai.z * b2.z + ai.w * b2.w
                    - a.x * bi.x - a.y * bi.y - a.z * bi.z - a.w * bi.w;
            }
        }
    } else if (es == 2 && (n & 1) == 0 && (T & 1) == 0 && (sk & 3) == 0 && (sc & 3) == 0) {
        // complex layout, aligned: 16-byte loads of two complex values
        const float4* pv = reinterpret_cast<const float4*>(fp);
        const float4* qv = reinterpret_cast<const float4*>(fq);
        for (int t = 0; t < (n >> 1); ++t) {
            float4 a = pv[t];
            if (p == q) {
                sr += a.x * a.x + a.y * a.y + a.z * a.z + a.w * a.w;
            } else {
                float4 b2 = qv[t];
                sr += a.x * b2.x + a.y * b2.y + a.z * b2.z + a.w * b2.w;
                si += a.y * b2.x - a.x * b2.y + a.w * b2.z - a.z * b2.w;
            }
        }
    } else if (p == q) {
        for (int t = 0; t < n; ++t) {
            float a = fp[(long long)t * es], ai = fp[(long long)t * es + im_off];
            sr += a * a + ai * ai;
        }
    } else {
        for (int t = 0; t < n; ++t) {
            float a = fp[(long long)t * es], ai = fp[(long long)t * es + im_off];
            float b2 = fq[(long long)t * es], bi = fq[(long long)t * es + im_off];
            sr += a * b2 + ai * bi;
            si += ai * b2 - a * bi;
        }
    }
    float s = sval * (scale ? *scale : 1.f);
    out[(((long long)g * C + c) * nblk + b) * K + k] = make_float2(sr * s, si * s);
}

// bf_row_dot: I[c, b, k] = sum_a M[c, k, b A + a] conj(D[c, k, a]), times sval (*scale when not null).
// M element (c, k, b A + a) at M[c msc + k msk + (b A + a) mes] (+ m_im for the imaginary part), complex or
// stacked as above; D complex64 (C, K, A) as float pairs. out: complex64 (C, nblk, K). One warp per (c, k):
// lanes stride over the antennas, a shuffle reduction per block b. Launch: 32 C K threads, blocks of 256.
extern "C" __global__ void bf_row_dot(
    const float* __restrict__ M, const float* __restrict__ D, float2* __restrict__ out,
    const float* __restrict__ scale, const float sval, const int C, const int K, const int A, const int nblk,
    const long long msc, const long long msk, const long long m_im, const int mes)
{
    // output: complex64 (C, nblk, K), times *scale
    long long warp = ((long long)blockIdx.x * blockDim.x + threadIdx.x) >> 5;
    int lane = threadIdx.x & 31;
    if (warp >= (long long)C * K) return;
    int c = (int)(warp / K), k = (int)(warp % K);
    const float* mrow = M + c * msc + k * msk;
    const float* drow = D + 2 * ((long long)c * K + k) * A;
    for (int b = 0; b < nblk; ++b) {
        float sr = 0.f, si = 0.f;
        for (int a = lane; a < A; a += 32) {
            long long j = ((long long)b * A + a) * mes;
            float mr = mrow[j], mi = mrow[j + m_im];
            float dr = drow[2 * a], di = drow[2 * a + 1];
            sr += mr * dr + mi * di;          // Re(m conj(d))
            si += mi * dr - mr * di;          // Im(m conj(d))
        }
        for (int o = 16; o > 0; o >>= 1) {
            sr += __shfl_down_sync(0xffffffff, sr, o);
            si += __shfl_down_sync(0xffffffff, si, o);
        }
        if (lane == 0) {
            float s = sval * (scale ? *scale : 1.f);
            out[((long long)c * nblk + b) * K + k] = make_float2(sr * s, si * s);
        }
    }
}

// bf_products, bf_products_real, bf_products_real2: polarisation products from the block correlations in
// one pass: every product is a linear combination of Re and Im of the blocks (I = Re XX + Re YY,
// V = -2 Im XY, ...): out[g, c, p, j] = sum_b s[c, b] (coef[p, b, 0] Re z + coef[p, b, 1] Im z),
// z = w[c|0, b, k] corr[g, c, b, k] at pixel k = gather[j] (j itself when gather is null; NaN `fill` where
// gather[j] < 0). corr: complex64 (bf_products) or float32 (the _real forms: the pols' own powers, Im 0)
// (G, C, nblk, K); s float32 (C, nblk); coef float32 (nprod, nblk, 2); w complex64 (Cw, nblk, K) or null;
// out float32 (G, C, nprod, Kout). nblk <= 4 (bf_products_real2: <= 2).
// Launch: grid (ceil(Kout / 256), min(C, 65535), ceil(G / 16)), block 256.
// MAXB: correlation blocks held (2: the pols' own powers; 4: XX, YY, XY at most)
__device__ __forceinline__ float2 corr_at(const float2* p, long long i) { return p[i]; }
__device__ __forceinline__ float2 corr_at(const float* p, long long i) { return make_float2(p[i], 0.f); }

// One thread per output cell j of a channel c (grid.y strides over the channels) and a run of RUN
// groups g (grid.z): the pixel, the channel's scales and the weights are read once for the run, every
// block's value once for all products (a thread per (g, c) row, re-reading the weights per row, runs
// latency-bound, well below the memory's speed).
#define RUN 16
template <int MAXB, typename TC>
__device__ void products(const TC* __restrict__ corr, const float* __restrict__ s, const float* __restrict__ coef,
                         const float2* __restrict__ w, const int Cw, const int* __restrict__ gather,
                         float* __restrict__ out, const long long G, const int C, const int nblk, const int nprod,
                         const int K, const int Kout, const float fill)
{
    // SUB groups' values are requested before any is used: SUB x nblk loads in flight a thread
    constexpr int SUB = MAXB <= 2 ? 8 : 4;
    const int j = blockIdx.x * blockDim.x + threadIdx.x;
    if (j >= Kout) return;
    const int k = gather ? gather[j] : j;
    const long long g0 = (long long)blockIdx.z * RUN, g1 = min(G, g0 + RUN);
    for (int c = blockIdx.y; c < C; c += gridDim.y) {
        if (k < 0) {
            for (long long g = g0; g < g1; ++g)
                for (int p = 0; p < nprod; ++p) out[((g * C + c) * nprod + p) * Kout + j] = fill;
            continue;
        }
        float2 wb[MAXB];
        float sb[MAXB];
#pragma unroll
        for (int b = 0; b < MAXB; ++b) {
            wb[b] = make_float2(0.f, 0.f);
            sb[b] = 0.f;
            if (b < nblk) {
                wb[b] = w ? w[((long long)(Cw == 1 ? 0 : c) * nblk + b) * K + k] : make_float2(1.f, 0.f);
                sb[b] = s[c * nblk + b];
            }
        }
        for (long long ga = g0; ga < g1; ga += SUB) {
            // every value of SUB groups requested first (the loads' latency overlapped), then used
            float2 z[SUB][MAXB];
#pragma unroll
            for (int u = 0; u < SUB; ++u)
#pragma unroll
                for (int b = 0; b < MAXB; ++b)
                    z[u][b] = (b < nblk && ga + u < g1)
                              ? corr_at(corr + ((ga + u) * C + c) * nblk * K + k, (long long)b * K)
                              : make_float2(0.f, 0.f);
#pragma unroll
            for (int u = 0; u < SUB; ++u) {
                if (ga + u >= g1) break;
                const long long row = (ga + u) * C + c;
                float zr[MAXB], zi[MAXB];
#pragma unroll
                for (int b = 0; b < MAXB; ++b) {
                    const float2 v = wb[b], q = z[u][b];
                    zr[b] = sb[b] * (q.x * v.x - q.y * v.y); zi[b] = sb[b] * (q.x * v.y + q.y * v.x);
                }
                for (int p = 0; p < nprod; ++p) {
                    float v = 0.f;
#pragma unroll
                    for (int b = 0; b < MAXB; ++b)
                        if (b < nblk) v += coef[(p * nblk + b) * 2] * zr[b] + coef[(p * nblk + b) * 2 + 1] * zi[b];
                    out[(row * nprod + p) * Kout + j] = v;
                }
            }
        }
    }
}

// complex block correlations; real ones (the fused integer modes' |F_p|^2: Im = 0)
extern "C" __global__ void bf_products(const float2* corr, const float* s, const float* coef, const float2* w,
                                       const int Cw, const int* gather, float* out, const long long G, const int C,
                                       const int nblk, const int nprod, const int K, const int Kout, const float fill)
{ products<4>(corr, s, coef, w, Cw, gather, out, G, C, nblk, nprod, K, Kout, fill); }
extern "C" __global__ void bf_products_real(const float* corr, const float* s, const float* coef, const float2* w,
                                            const int Cw, const int* gather, float* out, const long long G,
                                            const int C, const int nblk, const int nprod, const int K,
                                            const int Kout, const float fill)
{ products<4>(corr, s, coef, w, Cw, gather, out, G, C, nblk, nprod, K, Kout, fill); }
// the same for one or two blocks (the registers of two: more threads a SM, more loads in flight)
extern "C" __global__ void bf_products_real2(const float* corr, const float* s, const float* coef, const float2* w,
                                             const int Cw, const int* gather, float* out, const long long G,
                                             const int C, const int nblk, const int nprod, const int K,
                                             const int Kout, const float fill)
{ products<2>(corr, s, coef, w, Cw, gather, out, G, C, nblk, nprod, K, Kout, fill); }

// bf_channel_mean: out[i, j] = (sum_c x[i, c, j]) / C in float64, c in order: x (n, C, inner) float32
// contiguous, out (n, inner) float64. A thread per (i, j): a warp reads 128 contiguous bytes a channel.
// Launch: grid (ceil(inner / 256), n), block 256.
extern "C" __global__ void bf_channel_mean(const float* __restrict__ x, double* __restrict__ out, const int C,
                                           const long long inner)
{
    const long long j = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (j >= inner) return;
    const float* p = x + (long long)blockIdx.y * C * inner + j;
    double s = 0.0;
#pragma unroll 8
    for (int c = 0; c < C; ++c) s += (double)p[(long long)c * inner];
    out[(long long)blockIdx.y * inner + j] = s / C;
}

// bf_rows_nonzero: out[r] = 1 where row r of x (rows, len) float32 contiguous holds any value that is neither
// zero nor NaN (x > 0 || x < 0), else 0. One thread block per row, reading it 256 values at a time and
// stopping at the first stretch that holds such a value: an imaged channel's first pixels do, so a gulp of
// images costs about a 256th of reading it; a wholly flagged channel (zeros) is read to its end.
// Launch: grid (rows), block (256).
extern "C" __global__ void bf_rows_nonzero(const float* __restrict__ x, unsigned char* __restrict__ out,
                                           const long long len)
{
    const float* row = x + (size_t)blockIdx.x * (size_t)len;
    int found = 0;
    for (long long j0 = 0; j0 < len; j0 += blockDim.x) {
        const long long j = j0 + threadIdx.x;
        const float v = j < len ? row[j] : 0.0f;
        if (__syncthreads_or(v > 0.0f || v < 0.0f)) {
            found = 1;
            break;
        }
    }
    if (threadIdx.x == 0) out[blockIdx.x] = (unsigned char)found;
}
