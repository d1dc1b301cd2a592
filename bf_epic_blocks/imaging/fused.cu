// The fused integer GEMM and power sums, portable form (compute capability 8.0 and later): four warps of
// mma.sync m16n8k32 s32.s8.s8, ldmatrix fragment loads, cp.async K stages. Launched by
// imaging/fused.py (fused_power), which documents the operands and the quantisation.
//
// Compile-time constants (-D): NP int8 pieces (1, 2, 3); KD = 2 Apad bytes of a row (a multiple of 128);
// WMW warps along M (BM = 64 WMW rows a block); WN columns a warp (BN = 128 a block, BN / WN warps
// along N); BK bytes of K a stage; ST stages (ST - 1 loaded ahead); BFULL 1: B kept whole in shared
// memory across the pieces (read from global memory once), 0: B staged with A (KD too large for that).
//
// bf_fused_power
//   A    int8 (C, PA, NP, M, KD): per channel, gain set pa and piece, M = 2 Kpad rows (each run of 16 rows:
//        8 pixels' real rows, then their imaginary rows), KD columns 2 a + (0 re | 1 im)
//   B    int8 (C, NCOL, KD): the voltages, column p Tp + t of pol p, sample t (NCOL = P Tp)
//   osc  float32 (C, PA, M / 2): each pixel's output scale
//   flag int32 (1,): nonzero -> every output NaN (a sample was beyond what int32 sums hold)
//   out  float32 (T / 16, C, P, npix): sum over 16 samples of |F_pk|^2, times osc
//   M, NCOL, T (samples a pol, Tp; a multiple of 128 when PA > 1), PA (1: gains shared by the pols,
//   2: per pol), base (the pieces' base b), npix (pixels written: k < npix)
// Launch: grid (M / BM, NCOL / BN, C), block 32 WMW (BN / WN) threads, dynamic shared memory
// ST BM (BK + 16) + (BFULL ? BN (KD + 16) : ST BN (BK + 16)) bytes (fused.py's _smem).
#include "fused_common.cuh"

__device__ __forceinline__ void cp_async16(unsigned dst, const void* src) {
    asm volatile("cp.async.cg.shared.global [%0], [%1], 16;\n" :: "r"(dst), "l"(src));
}
__device__ __forceinline__ void cp_commit() { asm volatile("cp.async.commit_group;\n" ::); }
__device__ __forceinline__ void cp_wait() { asm volatile("cp.async.wait_group %0;\n" :: "n"(ST - 2)); }

#define BM (64 * WMW)
#define BN 128
#define WNW (BN / WN)
#define NI (WN / 8)
#define NT (32 * WMW * WNW)
#define LDA (BK + 16)
#if BFULL
#define LDB (KD + 16)
#else
#define LDB (BK + 16)
#endif
#define KS (BK / 32)

__device__ __forceinline__ void ldsm_x4(unsigned addr, unsigned& r0, unsigned& r1, unsigned& r2, unsigned& r3) {
    asm volatile("ldmatrix.sync.aligned.m8n8.x4.shared.b16 {%0,%1,%2,%3}, [%4];\n"
                 : "=r"(r0), "=r"(r1), "=r"(r2), "=r"(r3) : "r"(addr));
}
__device__ __forceinline__ void mma_s8(int* d, const unsigned* a, unsigned b0, unsigned b1) {
    asm volatile("mma.sync.aligned.m16n8k32.row.col.s32.s8.s8.s32 {%0,%1,%2,%3}, {%4,%5,%6,%7}, {%8,%9}, "
                 "{%0,%1,%2,%3};\n"
                 : "+r"(d[0]), "+r"(d[1]), "+r"(d[2]), "+r"(d[3])
                 : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b0), "r"(b1));
}

extern "C" __global__ void __launch_bounds__(NT, 1)
bf_fused_power(const signed char* __restrict__ A, const signed char* __restrict__ B, const float* __restrict__ osc,
               const int* __restrict__ flag, float* __restrict__ out, const int M, const int NCOL,
               const int T, const int PA, const int base, const int npix)
{
    extern __shared__ __align__(16) unsigned char smem[];
    unsigned char* sA = smem;
    unsigned char* sB = smem + ST * BM * LDA;
    const int tid = threadIdx.x, lane = tid & 31, warp = tid >> 5;
    const int wm = warp / WNW, wn = warp % WNW;
    const int m0 = blockIdx.x * BM, n0 = blockIdx.y * BN, c = blockIdx.z;
    const int pa = PA > 1 ? n0 / T : 0;
    const signed char* Ab = A + ((long long)(c * PA + pa) * NP * M + m0) * KD;
    const signed char* Bb = B + ((long long)c * NCOL + n0) * KD;
    const int KB = KD / BK, NIT = NP * KB;

    int acc[4][NI][4];
#pragma unroll
    for (int i = 0; i < 4; i++)
#pragma unroll
        for (int j = 0; j < NI; j++)
#pragma unroll
            for (int e = 0; e < 4; e++) acc[i][j][e] = 0;

    // one stage: BM rows x BK bytes of A (and BN x BK of B): 16-byte chunks spread over the threads
#define CPR (BK / 16)
#define LOAD(it_, st_) do { \
        const int piece_ = (it_) / KB, kb_ = (it_) - piece_ * KB; \
        const signed char* ap_ = Ab + (long long)piece_ * M * KD + kb_ * BK; \
        const unsigned as_ = smem_u32(sA + (st_) * BM * LDA); \
        _Pragma("unroll") for (int i_ = 0; i_ < BM * CPR / NT; i_++) { \
            const int ch_ = tid + i_ * NT, row_ = ch_ / CPR, col_ = (ch_ % CPR) * 16; \
            cp_async16(as_ + row_ * LDA + col_, ap_ + (long long)row_ * KD + col_); } \
        if (!BFULL || piece_ == 0) { \
            const signed char* bp_ = Bb + kb_ * BK; \
            const unsigned bs_ = BFULL ? smem_u32(sB + kb_ * BK) : smem_u32(sB + (st_) * BN * LDB); \
            _Pragma("unroll") for (int i_ = 0; i_ < BN * CPR / NT; i_++) { \
                const int ch_ = tid + i_ * NT, row_ = ch_ / CPR, col_ = (ch_ % CPR) * 16; \
                cp_async16(bs_ + row_ * LDB + col_, bp_ + (long long)row_ * KD + col_); } \
        } } while (0)

#pragma unroll
    for (int s = 0; s < ST - 1; s++) { if (s < NIT) LOAD(s, s); cp_commit(); }

    unsigned af[2][4][4], bf[2][NI][2];   // fragments double-buffered over the k32 steps
    for (int it = 0; it < NIT; it++) {
        cp_wait();
        __syncthreads();
        { const int nx = it + ST - 1; if (nx < NIT) LOAD(nx, nx % ST); cp_commit(); }
        const int st = it % ST, kb = it % KB;
        const unsigned as = smem_u32(sA + st * BM * LDA);
        const unsigned bs = BFULL ? smem_u32(sB + kb * BK) : smem_u32(sB + st * BN * LDB);
#define FRAGS(ks_, f_) do { \
            _Pragma("unroll") for (int mi = 0; mi < 4; mi++) { \
                const int row = wm * 64 + mi * 16 + ((lane >> 3) & 1) * 8 + (lane & 7); \
                const int col = (ks_) * 32 + (lane >> 4) * 16; \
                ldsm_x4(as + row * LDA + col, af[f_][mi][0], af[f_][mi][1], af[f_][mi][2], af[f_][mi][3]); } \
            _Pragma("unroll") for (int nj = 0; nj < NI / 2; nj++) { \
                const int row = wn * WN + nj * 16 + (lane >> 4) * 8 + (lane & 7); \
                const int col = (ks_) * 32 + ((lane >> 3) & 1) * 16; \
                ldsm_x4(bs + row * LDB + col, bf[f_][2 * nj][0], bf[f_][2 * nj][1], bf[f_][2 * nj + 1][0], \
                        bf[f_][2 * nj + 1][1]); } } while (0)
        FRAGS(0, 0);
#pragma unroll
        for (int ks = 0; ks < KS; ks++) {
            const int f = ks & 1;
            if (ks + 1 < KS) FRAGS(ks + 1, (ks + 1) & 1);
#pragma unroll
            for (int mi = 0; mi < 4; mi++)
#pragma unroll
                for (int ni = 0; ni < NI; ni++) mma_s8(acc[mi][ni], af[f][mi], bf[f][ni][0], bf[f][ni][1]);
        }
#if NP > 1
        if (kb == KB - 1 && it + 1 < NIT) {
#pragma unroll
            for (int i = 0; i < 4; i++)
#pragma unroll
                for (int j = 0; j < NI; j++)
#pragma unroll
                    for (int e = 0; e < 4; e++) acc[i][j][e] *= base;
        }
#endif
    }

    const bool bad = flag[0] != 0;
    const int Kp = M / 2, C = gridDim.z, P = NCOL / T, TU = T / 16;
    float* ob = unit_out(out, (n0 + wn * WN) / 16, c, C, P, TU, npix);
    const long long us = (long long)C * P * npix;
#pragma unroll
    for (int mi = 0; mi < 4; mi++) {
        const int pix = ((m0 + wm * 64 + mi * 16) >> 4) * 8 + (lane >> 2);
        const float sc = osc[(long long)(c * PA + pa) * Kp + pix];
#pragma unroll
        for (int u = 0; u < NI / 2; u++)
            put_unit(ob, us, acc[mi][2 * u], acc[mi][2 * u + 1], lane, u, pix, sc, bad, npix);
    }
}
