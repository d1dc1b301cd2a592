// Interference detection's power sums: 4-bit voltages into per-block sums of |x|^2 and |x|^4.
// Launched by imaging/rfi.py (block_power), which gives the shapes in Python terms.

// rfi_block_power: ci4 bytes b (T, K) (K = channels x inputs, contiguous; high nibble real, two's
// complement) -> s1, s2 (T / m, K) the sums of |x|^2 and |x|^4 over each whole block of m samples
// (exact: integers below 2^53), and sh (T / a, K) the sums of |x|^2 over each whole short block of a
// samples. One thread per column k walks down time, so that neighbouring threads read neighbouring bytes
// and the bytes are read once; the power array the NumPy form makes (4 bytes a sample) never exists.
// Launch: grid (ceil(K / 256)), block (256).
extern "C" __global__ void rfi_block_power(const unsigned char* __restrict__ b, double* __restrict__ s1,
                                           double* __restrict__ s2, float* __restrict__ sh, long long K,
                                           int T, int m, int a) {
    const long long k = (long long)blockIdx.x * blockDim.x + threadIdx.x;
    if (k >= K) return;
    long long acc1 = 0, acc2 = 0;
    int accs = 0, im_ = 0, is_ = 0;
    for (int t = 0; t < T; ++t) {
        const unsigned char v = b[(size_t)t * (size_t)K + (size_t)k];
        const int re = (int)(signed char)v >> 4;                      // arithmetic shift: the nibble's sign
        const int im = (int)(signed char)(unsigned char)(v << 4) >> 4;
        const int p = re * re + im * im;
        acc1 += p;
        acc2 += p * p;
        accs += p;
        if (++is_ == a) {
            sh[(size_t)(t / a) * (size_t)K + (size_t)k] = (float)accs;
            accs = 0;
            is_ = 0;
        }
        if (++im_ == m) {
            const size_t o = (size_t)(t / m) * (size_t)K + (size_t)k;
            s1[o] = (double)acc1;
            s2[o] = (double)acc2;
            acc1 = acc2 = 0;
            im_ = 0;
        }
    }
}
