// What both fused-power kernels (fused.cu, fused_hopper.cu) share: the shared-memory address of a
// pointer, and the epilogue that squares and sums 16 accumulator columns per pixel and writes them.
//
// Accumulator fragments follow the mma.sync m16n8 layout per 8 columns (the Hopper warpgroup MMA's
// fragment has the same layout per 8 columns): lane l holds rows l/4 and l/4 + 8 of the 16-row run,
// columns 2 (l % 4) and 2 (l % 4) + 1; the 16 rows are 8 pixels' real rows then their imaginary rows,
// so a lane's [0], [1] are Re F and [2], [3] Im F of one pixel.

__device__ __forceinline__ unsigned smem_u32(const void* p) { return (unsigned)__cvta_generic_to_shared(p); }

// One pixel's sum of |F|^2 over 16 columns: two 8-column accumulator fragments (real rows in
// [0], [1], imaginary rows in [2], [3]) of the 4 lanes of a quad, summed in float32 and across the quad
__device__ __forceinline__ float quad_power(const int* f0, const int* f1)
{
    float s = 0.f;
#pragma unroll
    for (int h = 0; h < 2; h++) {
        const int* a = h ? f1 : f0;
        const float r0 = (float)a[0], r1 = (float)a[1], i0 = (float)a[2], i1 = (float)a[3];
        s += r0 * r0 + r1 * r1 + i0 * i0 + i1 * i1;
    }
    s += __shfl_xor_sync(0xffffffffu, s, 1);
    s += __shfl_xor_sync(0xffffffffu, s, 2);
    return s;
}

// ... which lane u % 4 writes to ob[u us + pix] (unit_out), NaN if the range flag is up
__device__ __forceinline__ void put_unit(float* __restrict__ ob, const long long us, const int* f0, const int* f1,
                                         const int lane, const int u, const int pix, const float sc, const bool bad,
                                         const int npix)
{
    const float s = quad_power(f0, f1);
    if ((lane & 3) == (u & 3) && pix < npix)
        ob[u * us + pix] = bad ? __int_as_float(0x7fc00000) : s * sc;
}

// where 16-column unit `unit0` (= p TU + g) of channel c goes: &out[g, c, p, 0]; unit unit0 + u is
// u * C P npix further on, while the units stay inside one pol (a block's columns do: T is a whole
// number of 128-column blocks)
__device__ __forceinline__ float* unit_out(float* out, const int unit0, const int c, const int C, const int P,
                                           const int TU, const int npix) {
    const int p = unit0 / TU, g = unit0 - p * TU;
    return out + (((long long)g * C + c) * P + p) * npix;
}
