// The operator D = G w into the fused kernels' int8 pieces and row scales, in one pass. Launched by
// imaging/fused.py (quantise_operator on a GPU); the NumPy path there is the same arithmetic.
//
// g : complex64 (Cl, Kg, Ak) geometric operator of the live channels' pixels gk0 .. K - 1 (Kg = K - gk0:
// all of them, or only those that moved), as interleaved float pairs;
// w : complex64 (Cl, Ak, P) folded gains; inv : int32 (Apad,) the kept antenna at each input antenna,
// or -1 (antennas dropped or beyond the input's).
// Out: A int8 (Cl, PA, pieces, 2 Kpad, KD), or with `tiled` the Hopper kernel's tiles
// (Cl, PA, 2 Kpad / 128, pieces, KD / 128, 16384); osc float32 (Cl, PA, Kpad). Every byte of a row
// pair is written (zeros for antennas not kept and rows k >= K), so an array is refilled in place.
//
// Per row k of pixel k: s_k = max_a max(|Re D_ka|, |Im D_ka|) (1 where that is 0), then
// d = D_ka / s_k * 127 and, piece by piece, q = rint(d), d = (d - q) * b (round to nearest even, in
// float32 with no fused multiply-adds: the same numbers NumPy's complex64 arithmetic gives).
// Real row of pixel k: (q_re, -q_im) at columns 2a, 2a + 1; imaginary row: (q_im, q_re); the rows of
// each 8 pixels are 16 consecutive rows, 8 real then 8 imaginary. osc = (s_k / (127 b^(pieces-1)))^2.
//
// Launch: grid (Kpad - k0, Cl, PA), 256 threads; dynamic shared memory none, k0 >= gk0. Each block makes
// one pixel's row pair (pixel k0 + blockIdx.x: only pixels from k0 on when the others did not move): a max
// over the kept antennas, then the Apad columns.

__device__ __forceinline__ void d_of(const float2* __restrict__ g, const float2* __restrict__ w,
                                     long long grow, long long wrow, int a, int P, float& re, float& im)
{
    const float2 x = g[grow + a];
    const float2 y = w[wrow + (long long)a * P];
    re = __fsub_rn(__fmul_rn(x.x, y.x), __fmul_rn(x.y, y.y));
    im = __fadd_rn(__fmul_rn(x.x, y.y), __fmul_rn(x.y, y.x));
}

// byte offset of (piece i, row R, column j) of pol set pa of channel c
__device__ __forceinline__ long long a_offset(int c, int pa, int i, int R, int j, int PA, int pieces,
                                              int M, int KD, int tiled)
{
    if (!tiled) return ((((long long)c * PA + pa) * pieces + i) * M + R) * KD + j;
    const int r = R & 127, jj = (j & 127) >> 4;
    return (((((long long)c * PA + pa) * (M >> 7) + (R >> 7)) * pieces + i) * (KD >> 7) + (j >> 7)) * 16384
           + (r >> 3) * 1024 + (r & 7) * 128 + ((jj ^ (r & 7)) << 4) + (j & 15);
}

extern "C" __global__ void bf_quantise_operator(const float2* __restrict__ g, const float2* __restrict__ w,
                                                const int* __restrict__ inv, signed char* __restrict__ A,
                                                float* __restrict__ osc, const int K, const int Ak,
                                                const int P, const int Apad, const int pieces, const float b,
                                                const double oscale, const int tiled, const int k0,
                                                const int Kpad, const int gk0, const int Kg)
{
    const int k = k0 + blockIdx.x, c = blockIdx.y, pa = blockIdx.z;
    const int PA = gridDim.z, M = 2 * Kpad, KD = 2 * Apad;
    const long long grow = ((long long)c * Kg + (k - gk0)) * Ak;      // read only where k < K
    const long long wrow = (long long)c * Ak * P + pa;
    __shared__ float red[32];
    float m = 0.0f;
    if (k < K) {
        for (int a = threadIdx.x; a < Ak; a += blockDim.x) {
            float re, im;
            d_of(g, w, grow, wrow, a, P, re, im);
            m = fmaxf(m, fmaxf(fabsf(re), fabsf(im)));
        }
    }
    for (int o = 16; o > 0; o >>= 1) m = fmaxf(m, __shfl_xor_sync(0xffffffffu, m, o));
    if ((threadIdx.x & 31) == 0) red[threadIdx.x >> 5] = m;
    __syncthreads();
    if (threadIdx.x < 32) {
        m = threadIdx.x < (blockDim.x >> 5) ? red[threadIdx.x] : 0.0f;
        for (int o = 16; o > 0; o >>= 1) m = fmaxf(m, __shfl_xor_sync(0xffffffffu, m, o));
        if (threadIdx.x == 0) red[0] = m;
    }
    __syncthreads();
    const float s = red[0] > 0.0f ? red[0] : 1.0f;
    if (threadIdx.x == 0) {
        const double t = (double)s / oscale;
        osc[((long long)c * PA + pa) * Kpad + k] = k < K ? (float)(t * t) : 0.0f;
    }
    const int Rre = (k >> 3) * 16 + (k & 7), Rim = Rre + 8;
    for (int col = threadIdx.x; col < Apad; col += blockDim.x) {
        const int a = k < K ? inv[col] : -1;
        float dr = 0.0f, di = 0.0f;
        if (a >= 0) {
            d_of(g, w, grow, wrow, a, P, dr, di);
            dr = __fmul_rn(__fdiv_rn(dr, s), 127.0f);
            di = __fmul_rn(__fdiv_rn(di, s), 127.0f);
        }
        for (int i = 0; i < pieces; ++i) {
            const float qr = rintf(dr), qi = rintf(di);
            dr = __fmul_rn(__fsub_rn(dr, qr), b);
            di = __fmul_rn(__fsub_rn(di, qi), b);
            const signed char r8 = (signed char)(int)qr, i8 = (signed char)(int)qi;
            const signed char nr8 = (signed char)(-(int)qi);
            // real row: (q_re, -q_im); imaginary row: (q_im, q_re)
            const long long ore = a_offset(c, pa, i, Rre, 2 * col, PA, pieces, M, KD, tiled);
            const long long oim = a_offset(c, pa, i, Rim, 2 * col, PA, pieces, M, KD, tiled);
            A[ore] = r8;
            A[ore + 1] = nr8;
            A[oim] = i8;
            A[oim + 1] = r8;
        }
    }
}
