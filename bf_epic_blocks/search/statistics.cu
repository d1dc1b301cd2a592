// The transient search's statistics, one pass per push (search/statistics.py,
// TransientSearch._push_values_gpu launches it).
//
// Compile-time defines: WMAX, the widest boxcar (images); WLIST, the boxcar widths in the search's order
// ("1,2,4,8"); RWLIST, 1 / sqrt(w) of each as float32 literals ("1.000000000e+00f,...").
// Launch: grid (ceil(npix / 128), ns), block 128: one thread per (series s = blockIdx.y, pixel p).
// Shapes (all C order): v (ns, B, npix) float32, or vh the float16 tree's rows (search/tree.py's
// HalfRows: rows of hld values, hB times a row, value i at time hfirst + i); ref, S1, S2 (ns, npix);
// hist (ns, cap, npix) float32, series s at hist + s * hstride; snr (NWL, ns, nb, npix) float32 (written
// only when write_snr); count (NWL, ns, nb) int32.
#include <cuda_fp16.h>
// One thread per (series s = blockIdx.y, pixel p): the B new values v[s, i, p] in order. Same sums as
// TransientSearch._push_chunk: the value (minus ref) into the ring; value n - wmax enters and
// n - wmax - W leaves the window's float64 sums; from value k0 on, per width w the boxcar mean of the
// newest w values against the window: snr = (box / w - mean) sqrt(w) / sigma (written only when
// write_snr: a chunk is run again, densely, only if it has a crossing), and a count per trial image of
// the pixels over the threshold.
__device__ constexpr int WL[] = {WLIST};                  // the boxcar widths, in the search's order
// 1 / sqrt(w) of each, float32 rounded to nearest (written by the host: rsqrtf of a constant is not folded
// by the compiler, and made a hardware rsqrt a width a value -- 4 of 5 a value at widths 1, 2, 4, 8)
__device__ constexpr float RW[] = {RWLIST};
#define NWL ((int)(sizeof(WL) / sizeof(WL[0])))
extern "C" __global__ void bf_search_stats(const float* __restrict__ v, const float* __restrict__ ref,
        float* __restrict__ hist, double* __restrict__ S1, double* __restrict__ S2, float* __restrict__ snr,
        int* __restrict__ count, const int B, const int npix,
        const int cap, const long long hstride, const long long n0, const int W, const int k0, const int nb,
        const float thr, const int write_snr, const __half* __restrict__ vh, const float* __restrict__ ksum,
        const float ha, const float hb, const int hB, const int hfirst, const int hld)
{
    const int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= npix) return;
    const int s = blockIdx.y, ns = gridDim.y;
    // the values: v (ns, B, npix) float32, or (vh) the float16 tree's rows where it left them, value i of
    // series s = vh[(s hB + hfirst + i) hld + p] ha + ksum[p] hb, rounded as the tree's float32 output is
    const float hk = vh ? __fmul_rn(ksum[p], hb) : 0.f;
    // the series' first value, so that a value's address is a 32-bit offset (i times a row's bytes: the
    // host checks that B rows' bytes fit)
    const char* __restrict__ vrow = vh ? (const char*)(vh + ((long long)s * hB + hfirst) * hld + p)
                                       : (const char*)(v + (long long)s * B * npix + p);
    const int vstep = vh ? 2 * hld : 4 * npix;
    // value n0 + i leaves the window from i = lfirst on, and value n0 + i - WMAX enters it from i = efirst
    // on (earlier: values before the stream's first, 0): 32-bit tests a value, not 64-bit ones
    const int lfirst = (int)max(0LL, min((long long)B, (long long)WMAX + W - n0));
    const int efirst = (int)max(0LL, min((long long)B, (long long)WMAX - n0));
    float* h = hist + s * hstride + p;                       // value n at h[(n % cap) * npix]
    const long long sp = (long long)s * npix + p;
    double s1 = S1[sp], s2 = S2[sp];
    const double invW = 1.0 / W, invW1 = 1.0 / (W - 1);
    const float r = ref[sp];
    // last[j]: value n - j (offset), j < wmax; before value n0 is shifted in, last[j] = value n0 - 1 - j
    float last[WMAX];
#pragma unroll
    for (int j = 0; j < WMAX; j++) {
        const long long m = n0 - 1 - j;
        last[j] = m >= 0 ? h[(m % cap) * npix] : 0.f;
    }
    // Ring slots of value n (written) and n - wmax - W (leaving the window), advanced by one per value:
    // one 64-bit modulo each per thread, not per value. The value entering the window, n - wmax, is
    // last[WMAX - 1] before value n is shifted in: held, not read back. The capacity (>= W + wmax + B)
    // keeps the slots this push writes apart from those it reads, so a run of U values' loads is issued
    // before any of their stores (a load after each store would serialise every value on the memory's
    // latency).
    int in = (int)(n0 % cap);
    int il = (int)(((n0 - WMAX - W) % cap + cap) % cap);
#define U 4
    for (int i0 = 0; i0 < B; i0 += U) {
        float xv[U], lv[U];
#pragma unroll
        for (int u = 0; u < U; u++) {
            const int i = i0 + u;
            int iu = il + u;
            if (iu >= cap) iu -= cap;
            xv[u] = i >= B ? 0.f : vh ? __fadd_rn(__fmul_rn(__half2float(*(const __half*)(vrow + i * vstep)), ha), hk)
                                      : *(const float*)(vrow + i * vstep);
            lv[u] = (i < B && i >= lfirst) ? h[(long long)iu * npix] : 0.f;
        }
#pragma unroll
        for (int u = 0; u < U; u++) {
            const int i = i0 + u;
            if (i >= B) break;
            const float x = xv[u] - r;
            h[(long long)in * npix] = x;
            const double de = i >= efirst ? (double)last[WMAX - 1] : 0.0;
            const double dl = (double)lv[u];
#pragma unroll
            for (int j = WMAX - 1; j > 0; j--) last[j] = last[j - 1];
            last[0] = x;
            if (++in == cap) in = 0;
            if (++il == cap) il = 0;
            s1 += de - dl;
            s2 += de * de - dl * dl;
            if (i < k0) continue;
            // The window's sums stay float64 (they run the whole stream); what is formed from them per
            // value is float32 -- values about the reference, a few sigma wide, an S/N written as float32
            // anyway: float64 division, square root and boxes per width would make the kernel compute-bound.
            // (box / w - mean) sqrt(w) / sigma = (box - w mean) * rsqrt(w) * (1 / sigma); sigma 0 gives
            // inf or NaN.
            const double mean = s1 * invW;
            const float meanf = (float)mean;
            const double var = s2 - s1 * mean;
            const float isig = rsqrtf((float)((var > 0.0 ? var : 0.0) * invW1));   // (fmax's NaN handling: 0, as here)
            const int b = i - k0;
            // the widths known when the kernel is compiled (WLIST): each box one of the newest values' running
            // sums pre[w - 1] = last[0] + ... + last[w - 1], added in that order: WMAX - 1 adds a value for
            // every width together
            float pre[WMAX];
            pre[0] = 0.f + last[0];
#pragma unroll
            for (int j = 1; j < WMAX; j++) pre[j] = pre[j - 1] + last[j];
            float zf[NWL];
            bool over = false;
#pragma unroll
            for (int wi = 0; wi < NWL; wi++) {
                const int w = WL[wi];
                zf[wi] = (pre[w - 1] - (float)w * meanf) * RW[wi] * isig;
                over |= zf[wi] > thr;
            }
            if (write_snr) {
#pragma unroll
                for (int wi = 0; wi < NWL; wi++) snr[(((long long)wi * ns + s) * nb + b) * npix + p] = zf[wi];
            }
            // one branch a value for all the widths' crossings (rare): the kernel is bound by instruction
            // issue, and a branch per width would add ~12 of the ~100 instructions a value
            if (over) {
#pragma unroll
                for (int wi = 0; wi < NWL; wi++)
                    if (zf[wi] > thr) atomicAdd(&count[((long long)wi * ns + s) * nb + b], 1);
            }
        }
    }
#undef U
    S1[sp] = s1;
    S2[sp] = s2;
}
