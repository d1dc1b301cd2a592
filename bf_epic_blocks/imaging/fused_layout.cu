// The voltages into the fused kernels' B operand, one pass each. Launched by imaging/fused.py
// (layout_voltages).
//
// B: int8 (Cl, Pp Tp, 2 Apad), column p' Tp + t (pol p' of the imaged pols, sample t < Tp; samples
// t >= T and antennas a >= Ain are zero), bytes 2 a + (0 re | 1 im) of a column; or, with `tiled`,
// the Hopper kernel's tiles (Cl, Pp Tp / 128, 2 Apad / 128, 16384) (b_offset).
// cmap (Cl,) int32: the input channel of each live channel; pmap (Pp,) int32: the input pol of each
// imaged pol. Apad, Tp: multiples of 64 and 128.
// Launch (all three): one thread per (c', t, 8 antennas), total = Cl Tp Apad / 8 threads, blocks of
// 256, grid ceil(total / 256).

// byte offset of the 16 bytes (16-byte chunk jj of the KD bytes) of column col of channel c in B:
// (C, NCOL, KD) row-major, or tiled (C, NCOL/128, KD/128, 128 x 128 bytes in the swizzled order of
// the warpgroup MMA: chunk j of row r at (r / 8) 1024 + (r % 8) 128 + 16 (j ^ r % 8)), for bulk copies
__device__ __forceinline__ long long b_offset(int c, int col, int jj, int ncol, int kd, int tiled) {
    if (!tiled) return ((long long)c * ncol + col) * kd + jj * 16;
    const int r = col & 127;
    return (((long long)c * (ncol >> 7) + (col >> 7)) * (kd >> 7) + (jj >> 3)) * 16384
           + (r >> 3) * 1024 + (r & 7) * 128 + (((jj & 7) ^ (r & 7)) << 4);
}

// (T, Cin, Ain, Pin, 2) int8 -> (Cl, P', T, 2 Apad) int8. One thread per (c', t, 8 antennas): it reads
// their samples of every pol (one 32-byte stretch for two pols) and writes 16 bytes per imaged pol.
extern "C" __global__ void bf_layout_i8(const signed char* __restrict__ x, signed char* __restrict__ out,
                                        const int* __restrict__ cmap, const int* __restrict__ pmap,
                                        int* __restrict__ flag, const int T, const int Tp, const int Cin,
                                        const int Ain, const int Pin, const int Pp, const int Apad, const int Cl,
                                        const int xmax, const int tiled)
{
    const int J = Apad / 8;
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    const long long total = (long long)Cl * Tp * J;
    if (i >= total) return;
    const int j = (int)(i % J); long long r = i / J;
    const int t = (int)(r % Tp); const int c = (int)(r / Tp);
    const signed char* src = x + (((long long)min(t, T - 1) * Cin + cmap[c]) * Ain) * Pin * 2;
    bool bad = false;
    for (int p = 0; p < Pp; p++) {
        const int pp = pmap[p];
        union { int4 v; signed char b[16]; } u;
#pragma unroll
        for (int e = 0; e < 8; e++) {
            const int a = j * 8 + e;
            signed char re = 0, im = 0;
            if (a < Ain && t < T) {
                re = src[((long long)a * Pin + pp) * 2];
                im = src[((long long)a * Pin + pp) * 2 + 1];
                bad |= abs((int)re) > xmax || abs((int)im) > xmax;
            }
            u.b[2 * e] = re; u.b[2 * e + 1] = im;
        }
        *reinterpret_cast<int4*>(out + b_offset(c, p * Tp + t, j, Pp * Tp, 2 * Apad, tiled)) = u.v;
    }
    if (bad) atomicOr(flag, 1);
}

// The same for two input pols and antennas a multiple of 8 (the stations' case): two 16-byte loads
// per thread, the pols separated by byte permutes, the range checked four bytes at a time.
extern "C" __global__ void bf_layout_i8_p2(const signed char* __restrict__ x, signed char* __restrict__ out,
                                           const int* __restrict__ cmap, const int* __restrict__ pmap,
                                           int* __restrict__ flag, const int T, const int Tp, const int Cin,
                                           const int Ain, const int Pp, const int Apad, const int Cl,
                                           const int xmax, const int tiled)
{
    const int J = Apad / 8, Jin = Ain / 8;
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    const long long total = (long long)Cl * Tp * J;
    if (i >= total) return;
    const int j = (int)(i % J); long long r = i / J;
    const int t = (int)(r % Tp); const int c = (int)(r / Tp);
    unsigned w[8] = {0, 0, 0, 0, 0, 0, 0, 0};
    if (j < Jin && t < T) {   // antennas 8j .. 8j+7: (re0, im0, re1, im1) bytes per antenna, one word each
        const int4* src = reinterpret_cast<const int4*>(x + (((long long)t * Cin + cmap[c]) * Ain + j * 8) * 4);
        const int4 u0 = src[0], u1 = src[1];
        w[0] = u0.x; w[1] = u0.y; w[2] = u0.z; w[3] = u0.w; w[4] = u1.x; w[5] = u1.y; w[6] = u1.z; w[7] = u1.w;
        if (xmax < 128) {
            const unsigned lim = 0x01010101u * (unsigned)xmax;
            unsigned over = 0;
#pragma unroll
            for (int e = 0; e < 8; e++) over |= __vcmpgtu4(__vabsss4(w[e]), lim);
            if (over) atomicOr(flag, 1);
        }
    }
    for (int p = 0; p < Pp; p++) {
        const unsigned sel = pmap[p] == 0 ? 0x5410u : 0x7632u;    // low or high halves of two words
        int4 o;
        o.x = __byte_perm(w[0], w[1], sel); o.y = __byte_perm(w[2], w[3], sel);
        o.z = __byte_perm(w[4], w[5], sel); o.w = __byte_perm(w[6], w[7], sel);
        *reinterpret_cast<int4*>(out + b_offset(c, p * Tp + t, j, Pp * Tp, 2 * Apad, tiled)) = o;
    }
}

// ci4 bytes (T, Cin, Ain, 2) uint8 (high nibble real, two's complement) -> (Cl, P', T, 2 Apad) int8, for
// antennas a multiple of 8: one 16-byte load per thread (8 antennas x 2 pols), decoded in registers, so
// the unpacked int8 pairs (twice the bytes) are never written and read back. 4-bit values need no range check.
extern "C" __global__ void bf_layout_ci4_p2(const unsigned char* __restrict__ x, signed char* __restrict__ out,
                                            const int* __restrict__ cmap, const int* __restrict__ pmap,
                                            const int T, const int Tp, const int Cin, const int Ain, const int Pp,
                                            const int Apad, const int Cl, const int tiled)
{
    const int J = Apad / 8, Jin = Ain / 8;
    long long i = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    const long long total = (long long)Cl * Tp * J;
    if (i >= total) return;
    const int j = (int)(i % J); long long r = i / J;
    const int t = (int)(r % Tp); const int c = (int)(r / Tp);
    uint4 u = make_uint4(0u, 0u, 0u, 0u);                   // padding: nibbles 0, values 0
    if (j < Jin && t < T)
        u = *reinterpret_cast<const uint4*>(x + (((long long)t * Cin + cmap[c]) * Ain + j * 8) * 2);
    const unsigned w[4] = {u.x, u.y, u.z, u.w};
    for (int p = 0; p < Pp; p++) {
        const int pp = pmap[p];
        union { int4 v; signed char b[16]; } o;
#pragma unroll
        for (int e = 0; e < 8; e++) {     // byte 2 e + pp: antenna e, pol pp
            const unsigned b = (w[e >> 1] >> (8 * (((e & 1) << 1) + pp))) & 0xFFu;
            o.b[2 * e] = (signed char)((int)((b >> 4) ^ 8u) - 8);
            o.b[2 * e + 1] = (signed char)((int)((b & 15u) ^ 8u) - 8);
        }
        *reinterpret_cast<int4*>(out + b_offset(c, p * Tp + t, j, Pp * Tp, 2 * Apad, tiled)) = o.v;
    }
}
