// The gain solver's covariance sums: 4-bit voltages into the rows of an exact integer Gram matrix.
// Launched by imaging/skycal.py (CovarianceSums), which gives the shapes in Python terms.

typedef signed char i8;

// skycal_rows: ci4 bytes b (T, C, A, P) (high nibble real, two's complement) -> rows (c, A, 2, Tp) int8
// for channels c0 .. c0 + nc and one polarisation p: row (a, 0) the real parts, (a, 1) the imaginary
// parts of input a over time, zero for t >= T (Tp is T padded for cuBLAS' integer GEMMs). A block of
// 32 x 8 threads moves a 32 (t) x 32 (a) tile of bytes through shared memory: reads along a (the bytes
// of one time and channel lie together), writes along t. One pass over the bytes replaces a transpose
// and two nibble passes with their temporaries.
// Launch: grid (ceil(A / 32), ceil(Tp / 32), nc), block (32, 8).
extern "C" __global__ void skycal_rows(const unsigned char* __restrict__ b, i8* __restrict__ rows, int T, int C,
                                       int A, int P, int c0, int p, int Tp) {
    __shared__ unsigned char tile[32][33];
    const int c = blockIdx.z;
    const int a0 = blockIdx.x * 32, t0 = blockIdx.y * 32;
    const int tx = threadIdx.x, ty = threadIdx.y;
    for (int j = ty; j < 32; j += 8) {
        const int t = t0 + j, a = a0 + tx;
        unsigned char v = 0;                                       // byte 0: the sample (0, 0)
        if (t < T && a < A) v = b[((size_t)t * C + (size_t)(c0 + c)) * (size_t)A * P + (size_t)a * P + p];
        tile[j][tx] = v;
    }
    __syncthreads();
    for (int j = ty; j < 32; j += 8) {
        const int a = a0 + j, t = t0 + tx;
        if (a < A && t < Tp) {
            const unsigned char v = tile[tx][j];
            const i8 re = (i8)((int)(i8)v >> 4);                      // arithmetic shift: the sign of the nibble
            const i8 im = (i8)((int)(i8)(unsigned char)(v << 4) >> 4);
            const size_t base = ((size_t)c * A + a) * 2 * (size_t)Tp;
            rows[base + t] = re;
            rows[base + Tp + t] = im;
        }
    }
}
