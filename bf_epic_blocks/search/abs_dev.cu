// The float16 tree's scale: the largest deviation of a push from the reference (search/tree.py,
// _abs_dev_max_gpu launches it).
//
// Launch: grid (ceil(npix / 256), min(nchan B, 512)), block 256 (a whole number of warps: each warp's
// maximum is one atomicMax). out: one uint32 word, zero before the launch.
// max |x - ref| over x (nchan, B, npix) (element (c, b, p) at c sc + b sb + k, k = p or, with a cell
// index, idx[p]) and ref (nchan, npix); a NaN counts as Inf (fmaxf would drop it). Non-negative floats
// order as their bits: atomicMax on them.
extern "C" __global__ void bf_abs_dev_max(const float* __restrict__ x, const float* __restrict__ ref,
                                          unsigned* __restrict__ out, const int nchan, const int B, const int npix,
                                          const long long sc, const long long sb, const int* __restrict__ idx)
{
    float m = 0.f;
    const int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p < npix) {
        const int k = idx ? idx[p] : p;
        int c = blockIdx.y / B, b = blockIdx.y - c * B;
        const int dc = gridDim.y / B, db = gridDim.y - dc * B;     // the row step as (c, b): no division a row
#pragma unroll 4
        for (int r = blockIdx.y; r < nchan * B; r += gridDim.y) {
            const float v = x[c * sc + b * sb + k];
            m = fmaxf(m, v != v ? __int_as_float(0x7f800000) : fabsf(__fsub_rn(v, ref[(long long)c * npix + p])));
            c += dc; b += db;
            if (b >= B) { b -= B; ++c; }
        }
    }
#pragma unroll
    for (int o = 16; o; o >>= 1) m = fmaxf(m, __shfl_xor_sync(0xffffffffu, m, o));
    if ((threadIdx.x & 31) == 0) atomicMax(out, __float_as_uint(m));
}
