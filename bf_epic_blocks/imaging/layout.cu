// Integer voltages into GEMM operands, one pass each. Launched by imaging/layout.py (gram_rows,
// direct_rhs, cov_rhs), which gives the shapes in Python terms.
//
// OUT_T, the GEMM operand's storage: i8 (int8), __half (float16), unsigned short (bfloat16 bits),
// float, double; each kernel is instantiated for each at the end of this file and asked for by name
// expression ("bf_transpose<float>").

#include <cuda_fp16.h>
typedef signed char i8;
__device__ __forceinline__ void put(double v, float* p) { *p = (float)v; }
__device__ __forceinline__ void put(double v, double* p) { *p = v; }
__device__ __forceinline__ void put(double v, __half* p) { *p = __float2half_rn((float)v); }
__device__ __forceinline__ void put(double v, i8* p) { *p = (i8)v; }
__device__ __forceinline__ float get(const float* p) { return *p; }
__device__ __forceinline__ double get(const double* p) { return *p; }
__device__ __forceinline__ float get(const __half* p) { return __half2float(*p); }
__device__ __forceinline__ float get(const i8* p) { return (float)*p; }
__device__ __forceinline__ float get(const unsigned short* p) { return __uint_as_float(((unsigned int)*p) << 16); }
__device__ __forceinline__ void put(double v, unsigned short* p) {   // bfloat16 bits, round to nearest even
    unsigned int u = __float_as_uint((float)v);
    *p = (unsigned short)((u + 0x7FFFu + ((u >> 16) & 1u)) >> 16);
}

// bf_transpose<OUT_T>: int8 (re, im) pairs x (T, Cin, Ain, P, 2) -> out, per channel a (rows, time)
// matrix. Input element (t, c, a, p, h) with c = chan[c'], a = ant[a'], p = pols[p']; r' = (a' Pp + p') 2 + h
// enumerates one channel's selected values, zero where live[c', a', p'] is 0 (uint8 (C', A', Pp)) or t >= T.
// Output element (c', a', p', h, t), t < Tout, at out[c' osc + a' osa + p' osp + h osh + t ost] (strides in
// OUT_T elements). A block of 32 x 8 threads moves a 32 (t) x 32 (r') tile through shared memory: coalesced
// reads along r', coalesced writes along t. Launch: grid (ceil(2 A Pp / 32), ceil(Tout / 32), C'), block (32, 8).
template <typename OUT_T>
__global__ void bf_transpose(
    const i8* __restrict__ x, OUT_T* __restrict__ out,
    const int T, const int Cin, const int Ain, const int P,
    const int A, const int Pp, const int Tout,
    const int* __restrict__ chan, const int* __restrict__ ant, const int* __restrict__ pols,
    const unsigned char* __restrict__ live,
    const long long osc, const long long osa, const long long osp, const long long osh, const long long ost)
{
    __shared__ float tile[32][33];
    const int R = A * Pp * 2;
    const int c = blockIdx.z;
    const int r0 = blockIdx.x * 32, t0 = blockIdx.y * 32;
    const int tx = threadIdx.x, ty = threadIdx.y;
    const long long tstride = (long long)Cin * Ain * P * 2;      // bytes between samples
    // load: this thread's column r = r0 + tx is fixed; decode it (and its gathers) once
    {
        const int r = r0 + tx;
        bool ok = r < R;
        long long base = 0;
        if (ok) {
            int h = r & 1, q = r >> 1, pp = q % Pp, a = q / Pp;
            ok = live[((long long)c * A + a) * Pp + pp] != 0;
            base = (((long long)chan[c] * Ain + ant[a]) * P + pols[pp]) * 2 + h;
        }
        for (int j = ty; j < 32; j += 8) {
            int t = t0 + j;
            tile[j][tx] = (ok && t < T) ? (float)x[(long long)t * tstride + base] : 0.f;
        }
    }
    __syncthreads();
    // store: this thread's time t = t0 + tx is fixed; rows r0 + j
    const int t = t0 + tx;
    if (t >= Tout) return;
    OUT_T* ot = out + c * osc + t * ost;
    for (int j = ty; j < 32; j += 8) {
        int r = r0 + j;
        if (r < R) {
            int h = r & 1, q = r >> 1, pp = q % Pp, a = q / Pp;
            put(tile[tx][j], ot + a * osa + pp * osp + h * osh);
        }
    }
}

// bf_cov_rhs<OUT_T>: the covariance right-hand side from the integer Gram sums W int32 (C, R, R), rows
// r = (a P + p) 2 + h (all pols of the input, R = 2 A P): for block b = (bp[b], bq[b]) = (p, q) and antennas a, a2
//   R_pq[a, a2] = W[(a,p,0),(a2,q,0)] + W[(a,p,1),(a2,q,1)] + i (W[(a,p,1),(a2,q,0)] - W[(a,p,0),(a2,q,1)])
// times w_p[a] conj(w_q[a2]) (w complex128 (C, A, P) as double pairs; not read when unit) times scale,
// written at out[c osc + a osa + (b A + a2) oes] (+ o_im: imaginary part). diag (complex128 (C, nblk, A) as
// double pairs, or null): takes the same-antenna terms, weighted and unscaled, and zeros them in out.
// lo (or null): split storage, lo = value - hi in OUT_T at the same offsets. One thread per (c, a, b, a2).
// Launch: C A nblk A threads, blocks of 256.
template <typename OUT_T>
__global__ void bf_cov_rhs(
    const int* __restrict__ W, OUT_T* __restrict__ out, const double* __restrict__ w,
    const int C, const int A, const int P, const int nblk,
    const int* __restrict__ bp, const int* __restrict__ bq, const double scale, const int unit,
    const long long osc, const long long osa, const long long oes, const long long o_im,
    double* __restrict__ diag, OUT_T* __restrict__ lo)
{
    long long idx = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    long long total = (long long)C * A * nblk * A;
    if (idx >= total) return;
    int a2 = (int)(idx % A); long long r = idx / A;
    int b = (int)(r % nblk); r /= nblk;
    int a = (int)(r % A); int c = (int)(r / A);
    int p = bp[b], q = bq[b];
    long long R = (long long)A * P * 2;
    const int* Wc = W + (long long)c * R * R;
    long long ra = ((long long)a * P + p) * 2, rb = ((long long)a2 * P + q) * 2;
    // int64 sums: exact, then double (exact below 2^53)
    double re = (double)((long long)Wc[ra * R + rb] + (long long)Wc[(ra + 1) * R + rb + 1]);
    double im = (double)((long long)Wc[(ra + 1) * R + rb] - (long long)Wc[ra * R + rb + 1]);
    if (!unit) {   // w_p[a] R conj(w_q[a2]); w is complex128 (c, A, P) as double pairs
        const double* wa = w + 2 * (((long long)c * A + a) * P + p);
        const double* wb = w + 2 * (((long long)c * A + a2) * P + q);
        double xr = wa[0] * re - wa[1] * im, xi = wa[0] * im + wa[1] * re;       // w_a * R
        re = xr * wb[0] + xi * wb[1];                                            // * conj(w_b)
        im = xi * wb[0] - xr * wb[1];
    }
    if (diag != 0 && a == a2) {   // the same-antenna term leaves the GEMM; the caller adds it exactly
        double* d = diag + 2 * (((long long)c * nblk + b) * A + a);
        d[0] = re; d[1] = im;
        re = 0.0; im = 0.0;
    }
    long long off = c * osc + a * osa + ((long long)b * A + a2) * oes;
    put(re * scale, out + off);
    put(im * scale, out + off + o_im);
    if (lo != 0) {                // split storage: lo = v - hi, in the same type (fp16x3)
        put(re * scale - (double)get(out + off), lo + off);
        put(im * scale - (double)get(out + off + o_im), lo + off + o_im);
    }
}

// bf_gram_rows4: gram_rows when nothing is selected or flagged: a batched byte transpose of x int8
// (T, C, R) -> out int8 (C, R, Tp) (zero samples for t >= T), moved as 32-bit words (R4 = R / 4 words of r
// read, Tp4 = Tp / 4 words of t written) through a 64 x 64-byte shared tile (a byte per thread moves too
// little per transaction). Launch: grid (ceil(R4 / 16), ceil(Tp / 64), C), block 256.
extern "C" __global__ void bf_gram_rows4(
    const unsigned int* __restrict__ x, unsigned int* __restrict__ out,
    const int T, const int C, const int R4, const int Tp4)
{
    __shared__ unsigned char tile[64][65];           // [t][r byte]
    const int c = blockIdx.z;
    const int w0 = blockIdx.x * 16, t0 = blockIdx.y * 64;
    for (int i = threadIdx.x; i < 64 * 16; i += blockDim.x) {
        const int tt = i >> 4, w = i & 15, t = t0 + tt, r4 = w0 + w;
        unsigned int v = 0;
        if (t < T && r4 < R4) v = x[((long long)t * C + c) * R4 + r4];
        tile[tt][4 * w] = v & 0xffu;
        tile[tt][4 * w + 1] = (v >> 8) & 0xffu;
        tile[tt][4 * w + 2] = (v >> 16) & 0xffu;
        tile[tt][4 * w + 3] = v >> 24;
    }
    __syncthreads();
    const long long R = 4LL * R4;
    for (int i = threadIdx.x; i < 64 * 16; i += blockDim.x) {
        const int rr = i >> 4, w = i & 15;
        const long long r = 4LL * w0 + rr;
        const int t4 = (t0 >> 2) + w;
        if (r < R && t4 < Tp4) {
            out[((long long)c * R + r) * Tp4 + t4] = (unsigned int)tile[4 * w][rr]
                | ((unsigned int)tile[4 * w + 1][rr] << 8) | ((unsigned int)tile[4 * w + 2][rr] << 16)
                | ((unsigned int)tile[4 * w + 3][rr] << 24);
        }
    }
}

// the operand types the GEMMs take
template __global__ void bf_transpose<i8>(const i8*, i8*, int, int, int, int, int, int, int, const int*, const int*, const int*,
    const unsigned char*, long long, long long, long long, long long, long long);
template __global__ void bf_transpose<__half>(const i8*, __half*, int, int, int, int, int, int, int, const int*, const int*, const int*,
    const unsigned char*, long long, long long, long long, long long, long long);
template __global__ void bf_transpose<unsigned short>(const i8*, unsigned short*, int, int, int, int, int, int, int, const int*, const int*, const int*,
    const unsigned char*, long long, long long, long long, long long, long long);
template __global__ void bf_transpose<float>(const i8*, float*, int, int, int, int, int, int, int, const int*, const int*, const int*,
    const unsigned char*, long long, long long, long long, long long, long long);
template __global__ void bf_transpose<double>(const i8*, double*, int, int, int, int, int, int, int, const int*, const int*, const int*,
    const unsigned char*, long long, long long, long long, long long, long long);
template __global__ void bf_cov_rhs<i8>(const int*, i8*, const double*, int, int, int, int, const int*,
    const int*, double, int, long long, long long, long long, long long, double*, i8*);
template __global__ void bf_cov_rhs<__half>(const int*, __half*, const double*, int, int, int, int, const int*,
    const int*, double, int, long long, long long, long long, long long, double*, __half*);
template __global__ void bf_cov_rhs<unsigned short>(const int*, unsigned short*, const double*, int, int, int, int, const int*,
    const int*, double, int, long long, long long, long long, long long, double*, unsigned short*);
template __global__ void bf_cov_rhs<float>(const int*, float*, const double*, int, int, int, int, const int*,
    const int*, double, int, long long, long long, long long, long long, double*, float*);
template __global__ void bf_cov_rhs<double>(const int*, double*, const double*, int, int, int, int, const int*,
    const int*, double, int, long long, long long, long long, long long, double*, double*);
