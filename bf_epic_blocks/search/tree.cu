// The streaming tree dedispersion's levels and leaf rings (search/tree.py, StreamingFDMT._levels_gpu
// launches them).
//
// Compile-time define: HALF (absent: float32 values; 2, 4 or 8: float16 values, HALF pixels a load;
// the shipped float16 tree uses 8, StreamingFDMT.HALF_VEC).
// Layout: the working array W holds nwrow rows of B x pc values (row w, time t, pixel p at
// (w B + t) pc + p); the rings hold each ring row's cap slots of ld values, row r's first at rbase[r] ld.
// pc, ld and p0 count VT values (HALF pixels each for HALF).
// Launch: grid (ceil(pc / bx), rows of the level (at most 65,535 a launch)), block bx = min(128, pc).
// VT: the stored value -- float, or (HALF) HALF adjacent pixels' float16 values, each added in float32
// and rounded once (as NumPy's float16 add: the CPU's path gives the same bits).
#ifdef HALF
#include <cuda_fp16.h>
__device__ __forceinline__ __half2 hadd(__half2 a, __half2 b) {
    const float2 x = __half22float2(a), y = __half22float2(b);
    return __floats2half2_rn(x.x + y.x, x.y + y.y);
}
__device__ __forceinline__ unsigned wadd(unsigned a, unsigned b) {      // a word: two float16 values
    __half2 x = *reinterpret_cast<__half2*>(&a), y = *reinterpret_cast<__half2*>(&b);
    x = hadd(x, y);
    return *reinterpret_cast<unsigned*>(&x);
}
#if HALF == 8                   // HALF float16 values a load: one 16-, 8- or 4-byte word
typedef uint4 VT;
__device__ __forceinline__ VT vadd(VT a, VT b) {
    return make_uint4(wadd(a.x, b.x), wadd(a.y, b.y), wadd(a.z, b.z), wadd(a.w, b.w));
}
#elif HALF == 4
typedef uint2 VT;
__device__ __forceinline__ VT vadd(VT a, VT b) { return make_uint2(wadd(a.x, b.x), wadd(a.y, b.y)); }
#else
typedef unsigned VT;
__device__ __forceinline__ VT vadd(VT a, VT b) { return wadd(a, b); }
#endif
#else
typedef float VT;
__device__ __forceinline__ VT vadd(VT a, VT b) { return a + b; }
#endif

// A row's values at the block's times t (row r at time tau0 + t): in the working array W (row wrow[r] of
// B x pc, t >= 0 only), or, for a merged row that keeps a ring, in the ring itself (wrow[r] < 0): slot
// (phase[r] + t) mod cap[r] of its cap[r] = (ring length + block) rows of ld, t in [-ring length, B).
// A leaf's (channel's) older values (t < 0) are in its ring (cap = its ring length), copied there by
// bf_fdmt_ring. phase[r]: the slot of time tau0 (tau0 mod cap[r]), so the index is 32-bit.
struct Row { VT* p; int stride, ph, cap; };      // (an offset within a row's slots fits 32 bits)
__device__ __forceinline__ Row row_at(VT* W, VT* ring, const int r, const int* __restrict__ wrow,
                                      const long long* __restrict__ rbase, const int* __restrict__ cap,
                                      const int* __restrict__ phase, const int B, const int pc, const int ld,
                                      const int p0, const int p, const bool older)
{
    const int w = wrow[r];
    Row x;
    if (w >= 0 && !older) { x.p = W + (long long)w * B * pc + p; x.stride = pc; x.ph = 0; x.cap = 0x7fffffff; }
    else { x.p = ring + rbase[r] * ld + p0 + p; x.stride = ld; x.ph = phase[r]; x.cap = cap[r]; }
    return x;
}
__device__ __forceinline__ int slot(const Row& x, const int t)            // t in [-cap, cap)
{
    int m = x.ph + t;
    if (m < 0) m += x.cap; else if (m >= x.cap) m -= x.cap;
    return m * x.stride;
}

// One level of the streaming FDMT: row out[j] at t = row inL[j] at t + row inU[j] at t - o[j] (this
// block's, or older). grid (pixel blocks, rows); each thread walks the block's B times (a thread per
// element made ~230,000 short blocks per level). pc, ld, p0 count VT (HALF pixels for HALF).
extern "C" __global__ void bf_fdmt_level(VT* __restrict__ W, VT* __restrict__ ring,
                                         const int* __restrict__ out, const int* __restrict__ inL,
                                         const int* __restrict__ inU, const int* __restrict__ o,
                                         const long long* __restrict__ rbase, const int* __restrict__ cap,
                                         const int* __restrict__ phase, const int* __restrict__ wrow,
                                         const int B, const int pc, const int ld, const int p0)
{
    const int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= pc) return;
    const int j = blockIdx.y;
    const int u = inU[j], oj = o[j];
    const Row rl = row_at(W, ring, inL[j], wrow, rbase, cap, phase, B, pc, ld, p0, p, false);
    const Row ru = row_at(W, ring, u, wrow, rbase, cap, phase, B, pc, ld, p0, p, false);
    const Row rg = row_at(W, ring, u, wrow, rbase, cap, phase, B, pc, ld, p0, p, true);
    const Row ro = row_at(W, ring, out[j], wrow, rbase, cap, phase, B, pc, ld, p0, p, false);
    #pragma unroll 4
    for (int t = 0; t < B; ++t) {
        const int s = t - oj;
        const VT b = s >= 0 ? ru.p[slot(ru, s)] : rg.p[slot(rg, s)];
        ro.p[slot(ro, t)] = vadd(rl.p[slot(rl, t)], b);
    }
}

// A leaf's ring keeps its newest cap values: block times t >= B - cap go to slot (tau0 + t) % cap.
// grid (pixel blocks, leaves with a ring).
extern "C" __global__ void bf_fdmt_ring(const VT* __restrict__ W, VT* __restrict__ ring,
                                        const int* __restrict__ rows, const long long* __restrict__ rbase,
                                        const int* __restrict__ cap, const int* __restrict__ phase,
                                        const int* __restrict__ wrow, const int B, const int pc, const int ld,
                                        const int p0)
{
    const int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= pc) return;
    const int g = rows[blockIdx.y];
    const int L = cap[g];
    const VT* w = W + (long long)wrow[g] * B * pc + p;
    VT* rg = ring + rbase[g] * ld + p0 + p;
    int m = (phase[g] + max(0, B - L)) % L;
    for (int t = max(0, B - L); t < B; ++t) {
        rg[(long long)m * ld] = w[(long long)t * pc];
        if (++m == L) m = 0;
    }
}
