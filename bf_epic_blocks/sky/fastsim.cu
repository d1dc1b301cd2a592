// The simulated sky's voltages, one pass per gulp. Launched by sky/fastsim.py (make_gulp), whose
// docstring gives the data model, the counters and the CPU twin these kernels match. Compiled with
// --use_fast_math (the hardware's log, sqrt, sin/cos).
//
// sim_gulp, sim_gulp_few: samples t0 .. t0 + n - 1 into out (n, nchan, nant, 2 pols): ci4 bytes (two a
// sample and antenna: uint16, pol 0 in the low byte, high nibble real) when ci4, else complex64 (a float4
// per sample and antenna). W complex64 (nchan, nsrc, nant, 2) the sky weights; on0, on1 int64 (nsrc, nchan)
// each source's window of samples [on0, on1); key_sky, key_noise the streams' keys; noise_amp the noise's
// rms per real part; scale the ci4 scale. sim_gulp_few is compiled for NSRC = nsrc sources (-DNSRC,
// 0 .. 16), sim_gulp takes nsrc as an argument.
// Launch: grid (ceil(n / TILE) nchan), one block per (tile of TILE samples, channel); block 64 or 256
// threads (antennas strided over the block); sim_gulp: dynamic shared memory TILE 2 nsrc float2
// (16 TILE nsrc bytes).

typedef unsigned long long u64;
__device__ __forceinline__ u64 mix64(u64 z) {
    z += 0x9E3779B97F4A7C15ULL;
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
    return z ^ (z >> 31);
}
// Box-Muller with the GPU's own log, sqrt and sin/cos (compiled with --use_fast_math): the NumPy
// twin's counters, hash and bits of u1 and u2, so the same normals to ~1e-4 (the hardware functions'
// rounding, not the IEEE-only polynomials the twin uses, which here would make the kernel much slower).
__device__ __forceinline__ float2 cnormal(u64 ctr, u64 key) {
    const u64 h = mix64(ctr ^ key);
    const float u = (float)(unsigned int)((h >> 40) + 1ULL) * (1.0f / 16777216.0f);   // (0, 1], exact
    const float r = sqrtf(fmaxf(-2.0f * __logf(u), 0.0f));
    // the angle 2 pi k2 / 2^24 taken as (2 pi k2 / 2^24 - pi) + pi: __sincosf is accurate in [-pi, pi]
    const float t = (float)(int)((h >> 16) & 0xFFFFFFULL) * (6.283185307179586f / 16777216.0f) - 3.14159265358979f;
    float sn, cs;
    __sincosf(t, &sn, &cs);
    return make_float2(-r * cs, -r * sn);
}
// one block per (channel, tile of TILE samples): the sources' signals for the tile once in shared
// memory, then one thread per antenna writes both pols of every sample (two ci4 bytes, or two
// complex64); an antenna's weights are read once per tile (from L1 after the first sample), not
// once per sample
#define TILE 32
extern "C" __global__ void sim_gulp(unsigned char* out, int ci4, const float2* W, const long long* on0,
                                    const long long* on1, long long t0, int n, int nchan, int nsrc, int nant,
                                    u64 key_sky, u64 key_noise, float noise_amp, float scale) {
    extern __shared__ float2 e[];                       // (TILE, 2 nsrc)
    const int c = blockIdx.x % nchan;
    const long long i0 = (long long)(blockIdx.x / nchan) * TILE;
    const int nt = (int)min((long long)TILE, (long long)n - i0);
    for (int i = threadIdx.x; i < nt * 2 * nsrc; i += blockDim.x) {
        const int k = i / (2 * nsrc), sp = i % (2 * nsrc), s = sp >> 1;
        const long long T = t0 + i0 + k;
        const u64 base = (u64)(T * nchan + c);
        const bool on = T >= on0[s * nchan + c] && T < on1[s * nchan + c];
        const float2 z = cnormal((base * nsrc + s) * 2 + (sp & 1), key_sky);
        e[i] = on ? z : make_float2(0.0f, 0.0f);
    }
    __syncthreads();
    for (int a = threadIdx.x; a < nant; a += blockDim.x) {
        const float2* Wa = W + ((long long)c * nsrc * nant + a) * 2;       // W[c, s, a, p] = Wa[2 nant s + p]
        for (int k = 0; k < nt; ++k) {
            const long long T = t0 + i0 + k;
            const u64 nb = ((u64)(T * nchan + c) * nant + a) * 2;           // the noise counters: nb + p
            float2 v[2];
            for (int p = 0; p < 2; ++p) {
                float vr = 0.0f, vi = 0.0f;
                for (int s = 0; s < nsrc; ++s) {
                    const float2 w = Wa[2 * nant * s + p];
                    const float2 z = e[k * 2 * nsrc + 2 * s + p];
                    vr = vr + (z.x * w.x - z.y * w.y);
                    vi = vi + (z.x * w.y + z.y * w.x);
                }
                const float2 nz = cnormal(nb + p, key_noise);
                v[p] = make_float2(vr + noise_amp * nz.x, vi + noise_amp * nz.y);
            }
            const long long o = ((i0 + k) * nchan + c) * nant + a;
            if (ci4) {
                unsigned short packed = 0;
                for (int p = 0; p < 2; ++p) {
                    int qr = max(-8, min(7, __float2int_rn(v[p].x * scale)));
                    int qi = max(-8, min(7, __float2int_rn(v[p].y * scale)));
                    packed |= (unsigned short)(((qr & 0xF) << 4) | (qi & 0xF)) << (8 * p);
                }
                reinterpret_cast<unsigned short*>(out)[o] = packed;
            } else {
                reinterpret_cast<float4*>(out)[o] = make_float4(v[0].x, v[0].y, v[1].x, v[1].y);
            }
        }
    }
}

// The same samples for a few sources (NSRC <= MAX_REG_SRC, fixed when compiled): an antenna's
// weights held in registers for the whole tile and the sources' signals read from shared memory as
// one float4 (both pols) per source, the noise counter and the output index stepped, not
// recomputed. Every float operation is the generic kernel's, in its order (same bits, tested).
extern "C" __global__ void sim_gulp_few(unsigned char* __restrict__ out, int ci4, const float2* __restrict__ W,
                                        const long long* __restrict__ on0, const long long* __restrict__ on1,
                                        long long t0, int n, int nchan, int nant,
                                        u64 key_sky, u64 key_noise, float noise_amp, float scale) {
    const int c = blockIdx.x % nchan;
    const long long i0 = (long long)(blockIdx.x / nchan) * TILE;
    const int nt = (int)min((long long)TILE, (long long)n - i0);
#if NSRC > 0
    __shared__ float4 e[TILE * NSRC];                   // (TILE, NSRC): pol 0 in .x .y, pol 1 in .z .w
    for (int i = threadIdx.x; i < nt * NSRC; i += blockDim.x) {
        const int k = i / NSRC, s = i % NSRC;
        const long long T = t0 + i0 + k;
        const u64 base = ((u64)(T * nchan + c) * NSRC + s) * 2;
        const bool on = T >= on0[s * nchan + c] && T < on1[s * nchan + c];
        const float2 z0 = cnormal(base, key_sky), z1 = cnormal(base + 1, key_sky);
        e[i] = on ? make_float4(z0.x, z0.y, z1.x, z1.y) : make_float4(0.0f, 0.0f, 0.0f, 0.0f);
    }
    __syncthreads();
#endif
    const u64 nstep = (u64)nchan * nant * 2;
    const long long ostep = (long long)nchan * nant;
    for (int a = threadIdx.x; a < nant; a += blockDim.x) {
#if NSRC > 0
        float4 w[NSRC];                                 // W[c, s, a, 0:2] for each source
#pragma unroll
        for (int s = 0; s < NSRC; ++s) w[s] = reinterpret_cast<const float4*>(W)[((long long)c * NSRC + s) * nant + a];
#endif
        u64 nb = ((u64)((t0 + i0) * nchan + c) * nant + a) * 2;
        long long o = (i0 * nchan + c) * nant + a;
        for (int k = 0; k < nt; ++k, nb += nstep, o += ostep) {
            float vr0 = 0.0f, vi0 = 0.0f, vr1 = 0.0f, vi1 = 0.0f;
#if NSRC > 0
#pragma unroll
            for (int s = 0; s < NSRC; ++s) {
                const float4 z = e[k * NSRC + s];
                vr0 = vr0 + (z.x * w[s].x - z.y * w[s].y);
                vi0 = vi0 + (z.x * w[s].y + z.y * w[s].x);
                vr1 = vr1 + (z.z * w[s].z - z.w * w[s].w);
                vi1 = vi1 + (z.z * w[s].w + z.w * w[s].z);
            }
#endif
            const float2 n0 = cnormal(nb, key_noise), n1 = cnormal(nb + 1, key_noise);
            const float ar = vr0 + noise_amp * n0.x, ai = vi0 + noise_amp * n0.y;
            const float br = vr1 + noise_amp * n1.x, bi = vi1 + noise_amp * n1.y;
            if (ci4) {
                const int q0 = max(-8, min(7, __float2int_rn(ar * scale))), q1 = max(-8, min(7, __float2int_rn(ai * scale)));
                const int q2 = max(-8, min(7, __float2int_rn(br * scale))), q3 = max(-8, min(7, __float2int_rn(bi * scale)));
                reinterpret_cast<unsigned short*>(out)[o] =
                    (unsigned short)(((q0 & 0xF) << 4) | (q1 & 0xF) | ((q2 & 0xF) << 12) | ((q3 & 0xF) << 8));
            } else {
                reinterpret_cast<float4*>(out)[o] = make_float4(ar, ai, br, bi);
            }
        }
    }
}
