// The float16 tree's input and output passes (search/tree.py: _in_half_gpu, _out_half_gpu).
//
// Launch, both: grid (ceil(ld2 / 128), min(rows, 512)), block 128 (a whole number of warps: the input
// pass's optional maximum is one atomicMax a warp); rows = nchan B (input) or D B (output).
#include <cuda_fp16.h>
// float16 storage of a pixel chunk: W[c, b, p] = (x[c, b, p0 + p] - ref[c, p0 + p]) * s for p < n, 0 in the
// row's spare pixels (rows a whole number of StreamingFDMT.HALF_VEC); each step rounded as NumPy's
// float32 does (no fused multiply-add), the float16 to nearest even (NumPy's cast). x: element (c, b, p) at c sc + b sb + k, k = p or, with a cell index,
// idx[p]; W: (nchan, B, ld2) pixel pairs. A thread per pixel pair walks rows (c, b) gridDim.y apart.
// (A thread per pixel pair, not per 8 pixels as the levels: fewer registers a thread, more threads to hide
// the gathered loads' latency.)
extern "C" __global__ void bf_fdmt_in_half(const float* __restrict__ x, const float* __restrict__ ref, const float s,
                                           __half2* __restrict__ W, const int nchan, const int B, const int n,
                                           const int ld2, const long long sc, const long long sb, const int p0,
                                           const int npix, const int* __restrict__ idx, unsigned* __restrict__ amax)
{
    // amax (optional): max |x - ref| over what this pass reads, as bf_abs_dev_max computes it (a NaN as
    // Inf), one atomic a warp
    const int q = blockIdx.x * blockDim.x + threadIdx.x;
    float m = 0.f;
    const int p = 2 * q;
    const bool has0 = q < ld2 && p < n, has1 = q < ld2 && p + 1 < n;
    const int k0 = has0 ? (idx ? idx[p0 + p] : p0 + p) : 0, k1 = has1 ? (idx ? idx[p0 + p + 1] : p0 + p + 1) : 0;
    int c = blockIdx.y / B, b = blockIdx.y - c * B;
    const int dc = gridDim.y / B, db = gridDim.y - dc * B;
#pragma unroll 4
    for (int r = blockIdx.y; r < nchan * B; r += gridDim.y) {
        const float* xr = x + c * sc + b * sb;
        const float* rr = ref + (long long)c * npix + p0 + p;
        const float d0 = has0 ? __fsub_rn(xr[k0], rr[0]) : 0.f, d1 = has1 ? __fsub_rn(xr[k1], rr[1]) : 0.f;
        if (amax) {
            m = fmaxf(m, d0 != d0 ? __int_as_float(0x7f800000) : fabsf(d0));
            m = fmaxf(m, d1 != d1 ? __int_as_float(0x7f800000) : fabsf(d1));
        }
        const float a0 = has0 ? __fmul_rn(d0, s) : 0.f;
        const float a1 = has1 ? __fmul_rn(d1, s) : 0.f;
        if (q < ld2) W[(long long)r * ld2 + q] = __floats2half2_rn(a0, a1);
        c += dc; b += db;
        if (b >= B) { b -= B; ++c; }
    }
    if (amax) {                                    // every thread of the warp here: one shuffle
#pragma unroll
        for (int o = 16; o; o >>= 1) m = fmaxf(m, __shfl_xor_sync(0xffffffffu, m, o));
        if ((threadIdx.x & 31) == 0) atomicMax(amax, __float_as_uint(m));
    }
}

// float32 rows out of float16 storage: out[r, p0 + p] = W[t0 B + r, p] a + ksum[p0 + p] bk for rows r of
// (D, B) and p < n (rounded as NumPy does). out: (D B, npix) float32; W: rows of ld2 pixel pairs.
extern "C" __global__ void bf_fdmt_out_half(const __half2* __restrict__ W, const float* __restrict__ ksum,
                                            const float a, const float bk, float* __restrict__ out, const int rows,
                                            const long long t0B, const int n, const int ld2, const int p0,
                                            const int npix)
{
    const int q = blockIdx.x * blockDim.x + threadIdx.x;
    if (q >= ld2) return;
    const int p = 2 * q;
    const bool has1 = p + 1 < n;
    if (p >= n) return;
    const float k0 = __fmul_rn(ksum[p0 + p], bk), k1 = has1 ? __fmul_rn(ksum[p0 + p + 1], bk) : 0.f;
#pragma unroll 4
    for (int r = blockIdx.y; r < rows; r += gridDim.y) {
        const float2 h = __half22float2(W[(t0B + r) * ld2 + q]);
        float* o = out + (long long)r * npix + p0 + p;
        o[0] = __fadd_rn(__fmul_rn(h.x, a), k0);
        if (has1) o[1] = __fadd_rn(__fmul_rn(h.y, a), k1);
    }
}
