// The fused integer GEMM and power sums with three real products a complex multiply-add (Gauss's form), on
// Hopper (compiled for sm_90a). Launched by imaging/gauss.py (gauss_power), which documents the operands and
// the quantisation; the MMA, its operands' tiles and the mbarriers are fused_hopper.cu's (hopper_common.cuh).
//
// For each pixel k and sample t, in the operator's int32 units (one scale a pixel):
//   T = sum_a Re D (Re x + Im x),  U = sum_a -(Re D + Im D) Im x,  V = sum_a (Im D - Re D) Re x
//   Re F = T + U,  Im F = T + V
// so a complex multiply-add costs three int8 products a piece instead of four. The three products are three
// K loops over the antennas (KA bytes each) into three sets of accumulators; Re F and Im F are formed in
// int32 (exact), then converted, squared and summed per 16 columns.
//
// Compile-time constants (-D): NP int8 pieces (2, 3); KA = Apad bytes of one product's row (a multiple of
// 128); ST K stages of A in shared memory; MT row tiles a block (<= 8); GRID 0: per-pol sums, 1: images
// placed straight onto a grid (as fused_hopper.cu's).
//
// Block: 384 threads = two MMA warpgroups (64 pixels of the 128-pixel tile each) and a producer warpgroup
// whose one thread issues every bulk copy (the block's whole B first, 3 KA / 128 tiles; then A stage by
// stage). An MMA thread holds three sets of 64 int32 accumulators, T, X and Y. A tile's stages run product
// by product: T's pieces, then X's (U), then Y's (V); X += T once X's MMAs are done (Y's run meanwhile) and
// Y += T at the tile's end; then the tile's epilogue (from X and Y: Re F and Im F). The epilogue runs after
// the tile's MMAs, not beside the next tile's as fused_hopper.cu's does: three sets of accumulators and the
// epilogue's values together need more registers than a thread has (232), and the spills outweigh the overlap.
// Shared memory (dynamic): ST + 3 KA / 128 tiles of 16384 bytes, then 2 ST + 1 mbarriers of 8 bytes.
//
// bf_fused_gauss
//   A    int8 tiles (C, PA, M / 128, 3, NP, KA / 128, 16384): product j = 0 (Re D), 1 (-(Re D + Im D)),
//        2 (Im D - Re D), piece i, the pixel's row (gauss.py's tile_gauss of (C, PA, 3, NP, M, KA))
//   B    int8 tiles (C, NCOL / 128, 3 KA / 128, 16384): K sections (Re x + Im x, Im x, Re x), KA bytes each
//   osc  float32 (C, PA, M) each pixel's output scale; GRID: (C, P, M) each pol's factor
//   flag int32 (1,): nonzero -> every output NaN
//   out  float32 (T / 16, C, P, npix) sums over 16 samples of |F_pk|^2; GRID: as fused_hopper.cu's
//   M (pixels, a multiple of 128), NCOL = P T, T (a multiple of 128), PA, base, npix; GRID: cellv, ncell, G,
//   xout, nx (as fused_hopper.cu's)
// Launch: grid (ceil(M / 128 / MT), NCOL / 128, C), block 384, dynamic shared memory as above.
#include "fused_common.cuh"
#include "hopper_common.cuh"

#define BM 128
#define BN 128
#define NACC 64                       // int32 accumulators a thread for one 64 x 128 warpgroup tile
#define TILE 16384
#define NU 8                          // 16-column units of a tile's epilogue
#if MT > 8
#error "the pipelined-epilogue kernel takes at most 8 row tiles a block"
#endif

// x as it is, made where it is asked for: the stages' shared-memory addresses (and so their MMA
// descriptors) are then formed at each stage, not hoisted to the kernel's start and kept in registers
// that the three sets of accumulators need
__device__ __forceinline__ unsigned opaque(unsigned x) {
    unsigned y;
    asm volatile("mov.b32 %0, %1;\n" : "=r"(y) : "r"(x));
    return y;
}

// One 16-column unit u of a lane's two pixels (rows lane / 4 and lane / 4 + 8 of the warp's 16): the sums
// of (Re F)^2 + (Im F)^2 over the unit's 16 columns, across the quad's 4 lanes
__device__ __forceinline__ void gauss_unit(const int* x, const int* y, float& pa, float& pb)
{
    float a = 0.f, b = 0.f;
#pragma unroll
    for (int h = 0; h < 2; h++) {
        const int* xr = x + 4 * h;
        const int* yi = y + 4 * h;
        const float r0 = (float)xr[0], r1 = (float)xr[1], i0 = (float)yi[0], i1 = (float)yi[1];
        const float r2 = (float)xr[2], r3 = (float)xr[3], i2 = (float)yi[2], i3 = (float)yi[3];
        a += r0 * r0 + r1 * r1 + i0 * i0 + i1 * i1;
        b += r2 * r2 + r3 * r3 + i2 * i2 + i3 * i3;
    }
    a += __shfl_xor_sync(0xffffffffu, a, 1);
    b += __shfl_xor_sync(0xffffffffu, b, 1);
    a += __shfl_xor_sync(0xffffffffu, a, 2);
    b += __shfl_xor_sync(0xffffffffu, b, 2);
    pa = a;
    pb = b;
}

// the first of a lane's two pixels in row tile (mt0 + tp) (the second is 8 further on)
__device__ __forceinline__ int gauss_pix(const int mt0, const int tp, const int wgi, const int wq, const int lane) {
    return (mt0 + tp) * BM + wgi * 64 + wq * 16 + (lane >> 2);
}

struct PixelPair {                    // a lane's two pixels of a row tile: factors and (GRID) cells
    float s0, s1;
    int c0, c1;
};

__device__ __forceinline__ void pair_load(PixelPair& q, const float* __restrict__ osc, const int* __restrict__ cellv,
                                          const long long orow, const int pix, const int npix) {
    q.s0 = osc[orow + pix];
    q.s1 = osc[orow + pix + 8];
#if GRID
    q.c0 = pix < npix ? cellv[pix] : 0;
    q.c1 = pix + 8 < npix ? cellv[pix + 8] : 0;
#endif
}

// one pixel's unit: written (or, GRID, added to its cell) by lane u % 4 of the quad
__device__ __forceinline__ void put_pixel(float* __restrict__ ob, const long long us, float* __restrict__ xb,
                                          const long long xus, const int ncell, const int u, const int pix,
                                          const int cell, const float v, const bool bad, const int npix,
                                          const int g0, const int G)
{
    if (pix >= npix) return;
    const float o = bad ? __int_as_float(0x7fc00000) : v;
#if GRID
    if (g0 + u < G) {
        if (cell < ncell)
            atomicAdd(ob + u * us + cell, o);
        else
            atomicAdd(xb + u * xus + (cell - ncell), o);
    }
#else
    ob[u * us + pix] = o;
#endif
}

// the epilogue units of tile (mt0 + tp) due at stage `it` of the next tile's T (all of them when it < 0)
__device__ __forceinline__ void gauss_epi(const int* X, const int* Y, const int it, const int nit,
                                          float* __restrict__ ob, const long long us, float* __restrict__ xb,
                                          const long long xus, const int ncell, const PixelPair& q,
                                          const int lane, const int pix, const bool bad, const int npix,
                                          const int g0, const int G)
{
#pragma unroll
    for (int u = 0; u < NU; u++)
        if (it < 0 || u % nit == it) {
            float pa, pb;
            gauss_unit(X + 8 * u, Y + 8 * u, pa, pb);
            if ((lane & 3) == (u & 3)) {
                put_pixel(ob, us, xb, xus, ncell, u, pix, q.c0, pa * q.s0, bad, npix, g0, G);
                put_pixel(ob, us, xb, xus, ncell, u, pix + 8, q.c1, pb * q.s1, bad, npix, g0, G);
            }
        }
}

extern "C" __global__ void __launch_bounds__(384, 1)
bf_fused_gauss(const signed char* __restrict__ A, const signed char* __restrict__ B, const float* __restrict__ osc,
               const int* __restrict__ flag, float* __restrict__ out, const int M, const int NCOL,
               const int T, const int PA, const int base, const int npix
#if GRID
               , const int* __restrict__ cellv, const int ncell, const int G, float* __restrict__ xout, const int nx
#endif
               )
{
    extern __shared__ __align__(1024) unsigned char smem[];
    constexpr int KB = KA / 128, NPH = NP * KB, NIT = 3 * NPH, KBB = 3 * KB;
    unsigned char* sA = smem;                       // ST stages of one tile
    unsigned char* sB = smem + ST * TILE;           // B whole: KBB tiles
    const unsigned bar0 = smem_u32(smem + (ST + KBB) * TILE);
    const unsigned fullb = bar0, emptyb = bar0 + 8 * ST, bbar = bar0 + 16 * ST;
    const int tid = threadIdx.x, lane = tid & 31, warp = tid >> 5;
    const int MTILES = M / BM, mt0 = blockIdx.x * MT, ntile = min(MT, MTILES - mt0);
    const int n0 = blockIdx.y * BN, c = blockIdx.z;
    const int pa = PA > 1 ? n0 / T : 0;
    const int NALL = ntile * NIT;
    init_stage_barriers(fullb, emptyb, bbar, tid);
    if (warp >= 8) {                                // the producer warpgroup: one thread issues every copy
        asm volatile("setmaxnreg.dec.sync.aligned.u32 40;\n" ::: "memory");
        if (warp == 8 && lane == 0)                 // MT tiles, the last one repeated past the end
            produce(sA, sB, A + ((long long)(c * PA + pa) * MTILES + mt0) * NIT * TILE,
                    B + ((long long)c * (NCOL / BN) + blockIdx.y) * KBB * TILE, KBB, MT * NIT, NALL,
                    fullb, emptyb, bbar);
        return;
    }
    // three sets of 64 accumulators a thread (more than 65536 / 384 = 170 registers: allotted per warpgroup)
    asm volatile("setmaxnreg.inc.sync.aligned.u32 232;\n" ::: "memory");
    const int wgi = warp >> 2, wq = warp & 3;
    int dT[NACC], dX[NACC], dY[NACC];
#pragma unroll
    for (int i = 0; i < NACC; i++) { dT[i] = 0; dX[i] = 0; dY[i] = 0; }
    const bool bad = flag[0] != 0;
    const int C = gridDim.z, P = NCOL / T, TU = T / 16;
#if GRID
    const int pu = (n0 / 16) / TU, g0 = n0 / 16 - pu * TU;
    float* ob = out + ((long long)g0 * C + c) * ncell;
    const long long us = (long long)C * ncell;
    float* xb = xout + ((long long)g0 * C + c) * nx;
    const long long xus = (long long)C * nx;
    const long long orow = (long long)(c * P + pu) * M;
#else
    const int g0 = 0, G = 0, ncell = 0;
    const int* cellv = nullptr;
    float* xb = nullptr;
    const long long xus = 0;
    float* ob = unit_out(out, n0 / 16, c, C, P, TU, npix);
    const long long us = (long long)C * P * npix;
    const long long orow = (long long)(c * PA + pa) * M;
#endif
    mbar_wait(bbar, 0);

    // one K stage `it` of tile tt into the product's accumulators d (product j = it / NPH): a new piece
    // first multiplies all of d so far by the base (once its MMAs are done)
#define STAGE(tt, it, d) do { \
        const int g = (tt) * NIT + (it), s = g % ST; \
        const int kb = (it) % KB, pc = ((it) / KB) % NP, j = (it) / NPH; \
        const bool piece = NP > 1 && kb == 0 && pc > 0; \
        mbar_wait(fullb + 8 * s, (g / ST) & 1); \
        if (piece) { \
            asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory"); \
            if (g > 0) mbar_arrive_lane0(emptyb + 8 * ((g - 1) % ST), lane); \
            _Pragma("unroll") for (int i = 0; i < NACC; i++) d[i] *= base; \
        } \
        const unsigned as = opaque(smem_u32(sA + s * TILE) + soff(wgi * 64, 0)); \
        const unsigned bs = opaque(smem_u32(sB + (j * KB + kb) * TILE)); \
        asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory"); \
        _Pragma("unroll") for (int ks = 0; ks < 4; ks++) { \
            if ((pc | kb | ks) == 0) wg_mma_first(d, mdesc(as, 16, 1024), mdesc(bs, 16, 1024)); \
            else wg_mma(d, mdesc(as + ks * 32, 16, 1024), mdesc(bs + ks * 32, 16, 1024), 1); \
        } \
        asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory"); \
        asm volatile("wgmma.wait_group.sync.aligned 1;\n" ::: "memory");   /* all but this stage's */ \
        if (g > 0 && !piece) mbar_arrive_lane0(emptyb + 8 * ((g - 1) % ST), lane); \
    } while (0)

    // tile t: its three products, then its epilogue from X and Y
#define TILE_PASS(t_) do { \
        constexpr int tt = (t_); \
        _Pragma("unroll") for (int it = 0; it < NPH; it++) STAGE(tt, it, dT); \
        _Pragma("unroll") for (int it = NPH; it < 2 * NPH; it++) STAGE(tt, it, dX); \
        _Pragma("unroll") for (int it = 2 * NPH; it < NIT; it++) { \
            STAGE(tt, it, dY); \
            if (it == 2 * NPH) { \
                _Pragma("unroll") for (int i = 0; i < NACC; i++) dX[i] += dT[i]; \
            } \
        } \
        asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory"); \
        _Pragma("unroll") for (int i = 0; i < NACC; i++) dY[i] += dT[i]; \
        if (tt < ntile) { \
            PixelPair q; \
            const int pix = gauss_pix(mt0, tt, wgi, wq, lane); \
            pair_load(q, osc, cellv, orow, pix, npix); \
            gauss_epi(dX, dY, -1, 1, ob, us, xb, xus, ncell, q, lane, pix, bad, npix, g0, G); \
        } } while (0)

    TILE_PASS(0);
#if MT >= 2
    TILE_PASS(1);
#endif
#if MT >= 3
    TILE_PASS(2);
#endif
#if MT >= 4
    TILE_PASS(3);
#endif
#if MT >= 5
    TILE_PASS(4);
#endif
#if MT >= 6
    TILE_PASS(5);
#endif
#if MT >= 7
    TILE_PASS(6);
#endif
#if MT >= 8
    TILE_PASS(7);
#endif
#undef TILE_PASS
#undef STAGE
}
