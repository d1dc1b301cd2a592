// The fused integer GEMM and power sums on Hopper (compiled for sm_90a): warpgroup MMA
// (wgmma.mma_async m64n128k32 s32.s8.s8) on 128-byte-swizzled shared memory, operands brought in by
// bulk copies (cp.async.bulk) counted on mbarriers, and each row tile's epilogue (|F|^2 summed per 16
// columns) spread over the next tile's K stages. Launched by imaging/fused.py (fused_power), which
// documents the operands and the quantisation.
//
// Compile-time constants (-D): NP int8 pieces (1, 2, 3); KD = 2 Apad bytes of a row (a multiple of 128);
// ST K stages of A in shared memory; MT row tiles a block (<= 8; B is loaded once for all of them);
// GRID 0: per-pol sums (out as the portable kernel's), 1: images placed straight onto a grid.
//
// Block: 384 threads = two MMA warpgroups (64 rows of the 128-row tile each, two sets of 64 int32
// accumulators a thread: tile t's MMAs go to one while tile t - 1's epilogue is read from the other)
// and a producer warpgroup whose one thread issues every bulk copy: the block's whole B first (KD / 128
// tiles), then A stage by stage (mbarriers full[ST], freed by the 8 MMA warps on empty[ST]).
// Shared memory (dynamic): ST + KD / 128 tiles of 16384 bytes, then 2 ST + 1 mbarriers of 8 bytes.
// A 16-KB tile holds 128 rows x 128 bytes in the swizzled order the MMA reads (chunk j of row r at
// (r / 8) 1024 + (r % 8) 128 + 16 (j ^ r % 8): soff).
//
// bf_fused_power
//   A    int8 tiles (C, PA, M / 128, NP, KD / 128, 16384) (fused.py's tile_operator of (C, PA, NP, M, KD))
//   B    int8 tiles (C, NCOL / 128, KD / 128, 16384) (fused_layout.cu's tiled output)
//   osc  float32 (C, PA, M / 2) each pixel's output scale; GRID: (C, P, M / 2) each pol's factor (scale,
//        beam pattern, product coefficient)
//   flag int32 (1,): nonzero -> every output NaN
//   out  float32 (T / 16, C, P, npix) sums over 16 samples of |F_pk|^2; GRID: (G, C, ncell) images, pol p's
//        share of pixel k added to cell cellv[k] (the caller clears the cells); a pixel whose cell is
//        ncell + j (j < nx) is one of nx directions imaged beside the grid, added to xout (G, C, nx) at j
//   M, NCOL = P T, T (samples a pol, a multiple of 128), PA (1 or 2 gain sets), base (the pieces' base),
//   npix (pixels written); GRID: cellv (npix,) int32, ncell, G (images written: g < G <= T / 16), xout, nx
// Launch: grid (ceil(M / 128 / MT), NCOL / 128, C), block 384, dynamic shared memory as above.
#include "fused_common.cuh"

#define BM 128
#define BN 128
#define NT 384
#define NACC 64                       // int32 accumulators a thread for one 64 x 128 warpgroup tile
#define TILE 16384
#define WGN 128
#define NU (WGN / 16)                 // 16-column units of a tile's epilogue
#if MT > 8
#error "the pipelined-epilogue kernel takes at most 8 row tiles a block"
#endif

#include "hopper_common.cuh"

#if GRID
// GRID: one pol's share of an image placed on the grid: lane u % 4 adds (an atomic add: the pols' shares
// meet in one cell) the sum times its factor to ob[u us + cell[pix]], for images g0 + u < G; a cell
// beyond the grid's (cell >= ncell) is a direction beside it, added to xb[u xus + cell - ncell]
__device__ __forceinline__ void put_cell(float* __restrict__ ob, const long long us, float* __restrict__ xb,
                                         const long long xus, const int ncell, const int* f0, const int* f1,
                                         const int lane, const int u, const int pix, const int cell, const float sc,
                                         const bool bad, const int npix, const int g0, const int G)
{
    const float s = quad_power(f0, f1);
    if ((lane & 3) == (u & 3) && pix < npix && g0 + u < G) {
        const float v = bad ? __int_as_float(0x7fc00000) : s * sc;
        if (cell < ncell)
            atomicAdd(ob + u * us + cell, v);
        else
            atomicAdd(xb + u * xus + (cell - ncell), v);
    }
}
#endif

// row tile (mt0 + tp)'s pixel of this lane, its factor and (GRID) cell: loaded a pass before its epilogue
// needs them (so that no epilogue unit waits on a load)
__device__ __forceinline__ int tile_pix(const int mt0, const int tp, const int wgi, const int wq, const int lane) {
    return (((mt0 + tp) * BM + wgi * 64 + wq * 16) >> 4) * 8 + (lane >> 2);
}
__device__ __forceinline__ void tile_load(float& sc, int& cl, const float* __restrict__ osc, const int* __restrict__ cellv,
                                          const long long orow, const int pix, const int npix) {
    sc = osc[orow + pix];
#if GRID
    cl = pix < npix ? cellv[pix] : 0;
#endif
}

// the epilogue units of tile (mt0 + tp) due at stage `it` of the next tile (all of them when it < 0)
__device__ __forceinline__ void epi_units(const int* de, const int it, float* __restrict__ ob, const long long us,
                                          float* __restrict__ xb, const long long xus, const int ncell,
                                          const float sc, const int cl, const int lane, const int tp,
                                          const int mt0, const int wgi, const int wq,
                                          const bool bad, const int npix, const int nit, const int g0, const int G)
{
    const int pix = tile_pix(mt0, tp, wgi, wq, lane);
#pragma unroll
    for (int u = 0; u < NU; u++)
        if (it < 0 || u % nit == it) {
#if GRID
            put_cell(ob, us, xb, xus, ncell, de + 8 * u, de + 8 * u + 4, lane, u, pix, cl, sc, bad, npix, g0, G);
#else
            put_unit(ob, us, de + 8 * u, de + 8 * u + 4, lane, u, pix, sc, bad, npix);
#endif
        }
}

extern "C" __global__ void __launch_bounds__(NT, 1)
bf_fused_power(const signed char* __restrict__ A, const signed char* __restrict__ B, const float* __restrict__ osc,
               const int* __restrict__ flag, float* __restrict__ out, const int M, const int NCOL,
               const int T, const int PA, const int base, const int npix
#if GRID
               , const int* __restrict__ cellv, const int ncell, const int G, float* __restrict__ xout, const int nx
#endif
               )
{
    extern __shared__ __align__(1024) unsigned char smem[];
    constexpr int KB = KD / 128, NIT = NP * KB;
    unsigned char* sA = smem;                       // ST stages of one tile
    unsigned char* sB = smem + ST * TILE;           // B whole: KB tiles
    const unsigned bar0 = smem_u32(smem + (ST + KB) * TILE);   // full[ST], empty[ST], B's: 8 bytes each
    const unsigned fullb = bar0, emptyb = bar0 + 8 * ST, bbar = bar0 + 16 * ST;
    const int tid = threadIdx.x, lane = tid & 31, warp = tid >> 5;
    const int MTILES = M / BM, mt0 = blockIdx.x * MT, ntile = min(MT, MTILES - mt0);
    const int n0 = blockIdx.y * BN, c = blockIdx.z;
    const int pa = PA > 1 ? n0 / T : 0;
    const int NALL = ntile * NIT;
    init_stage_barriers(fullb, emptyb, bbar, tid);
    if (warp >= 8) {                                // the producer warpgroup: one thread issues every copy
        // registers go to the MMA warpgroups (allotted per warpgroup: two sets of 64 accumulators a
        // thread need more than 65536 / 384 = 170)
        asm volatile("setmaxnreg.dec.sync.aligned.u32 40;\n" ::: "memory");
        if (warp == 8 && lane == 0)                 // MT tiles, the last one repeated past the end
            produce(sA, sB, A + ((long long)(c * PA + pa) * MTILES + mt0) * NIT * TILE,
                    B + ((long long)c * (NCOL / BN) + blockIdx.y) * KB * TILE, KB, MT * NIT, NALL,
                    fullb, emptyb, bbar);
        return;
    }
    asm volatile("setmaxnreg.inc.sync.aligned.u32 232;\n" ::: "memory");
    const int wgi = warp >> 2, wq = warp & 3;
    int d0[NACC], d1[NACC];
#pragma unroll
    for (int i = 0; i < NACC; i++) { d0[i] = 0; d1[i] = 0; }
    const bool bad = flag[0] != 0;
    const int Kp = M / 2, C = gridDim.z, P = NCOL / T, TU = T / 16;
#if GRID
    const int pu = (n0 / 16) / TU, g0 = n0 / 16 - pu * TU;
    float* ob = out + ((long long)g0 * C + c) * ncell;
    const long long us = (long long)C * ncell;
    float* xb = xout + ((long long)g0 * C + c) * nx;
    const long long xus = (long long)C * nx;
    const long long orow = (long long)(c * P + pu) * Kp;
#else
    const int g0 = 0, G = 0, ncell = 0;             // the grid's arguments: unused in the per-pol sums
    const int* cellv = nullptr;
    float* xb = nullptr;
    const long long xus = 0;
    float* ob = unit_out(out, n0 / 16, c, C, P, TU, npix);
    const long long us = (long long)C * P * npix;
    const long long orow = (long long)(c * PA + pa) * Kp;
#endif
    mbar_wait(bbar, 0);

    // pass t (t = 0 .. MT, unrolled: every wgmma group and register set known to the compiler, which
    // otherwise serialises the MMAs): the MMAs of tile t into dm (t < MT) and the epilogue of tile t - 1
    // from de (t >= 1). A block past the last row tile repeats that tile's loads (the producer clamps)
    // and writes nothing for it.
#define PASS(t_, dm, de, scm, clm, sce, cle) do { \
        constexpr int tt = (t_); \
        if (tt < MT && tt < ntile) \
            tile_load(scm, clm, osc, cellv, orow, tile_pix(mt0, tt, wgi, wq, lane), npix); \
        if (tt < MT) { \
            _Pragma("unroll") for (int it = 0; it < NIT; it++) { \
                const int g = tt * NIT + it, s = g % ST; \
                mbar_wait(fullb + 8 * s, (g / ST) & 1); \
                if (NP > 1 && it % KB == 0 && it > 0) {   /* a new piece: all so far times the base */ \
                    asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory"); \
                    if (g > 0) mbar_arrive_lane0(emptyb + 8 * ((g - 1) % ST), lane); \
                    _Pragma("unroll") for (int i = 0; i < NACC; i++) dm[i] *= base; \
                } \
                const unsigned as = smem_u32(sA + s * TILE) + soff(wgi * 64, 0); \
                const unsigned bs = smem_u32(sB + (it % KB) * TILE); \
                asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory"); \
                _Pragma("unroll") for (int ks = 0; ks < 4; ks++) \
                    wg_mma(dm, mdesc(as + ks * 32, 16, 1024), mdesc(bs + ks * 32, 16, 1024), (it | ks) != 0); \
                asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory"); \
                asm volatile("wgmma.wait_group.sync.aligned 1;\n" ::: "memory");   /* all but this stage's */ \
                if (g > 0 && !(NP > 1 && it % KB == 0 && it > 0)) mbar_arrive_lane0(emptyb + 8 * ((g - 1) % ST), lane); \
                if (tt >= 1 && tt - 1 < ntile) \
                    epi_units(de, it, ob, us, xb, xus, ncell, sce, cle, lane, tt - 1, mt0, wgi, wq, bad, npix, NIT, g0, G); \
            } \
        } else { \
            asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory"); \
            if (tt - 1 < ntile) \
                epi_units(de, -1, ob, us, xb, xus, ncell, sce, cle, lane, tt - 1, mt0, wgi, wq, bad, npix, NIT, g0, G); \
        } } while (0)

    float sc0 = 0.f, sc1 = 0.f;
    int cl0 = 0, cl1 = 0;
    PASS(0, d0, d1, sc0, cl0, sc1, cl1);
#if MT >= 1
    PASS(1, d1, d0, sc1, cl1, sc0, cl0);
#endif
#if MT >= 2
    PASS(2, d0, d1, sc0, cl0, sc1, cl1);
#endif
#if MT >= 3
    PASS(3, d1, d0, sc1, cl1, sc0, cl0);
#endif
#if MT >= 4
    PASS(4, d0, d1, sc0, cl0, sc1, cl1);
#endif
#if MT >= 5
    PASS(5, d1, d0, sc1, cl1, sc0, cl0);
#endif
#if MT >= 6
    PASS(6, d0, d1, sc0, cl0, sc1, cl1);
#endif
#if MT >= 7
    PASS(7, d1, d0, sc1, cl1, sc0, cl0);
#endif
#if MT >= 8
    PASS(8, d0, d1, sc0, cl0, sc1, cl1);
#endif
#undef PASS
}
