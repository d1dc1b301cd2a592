"""Regime B in pieces, on one GPU: where the time of high-cadence imaging goes, before choosing a kernel.

Case P at the paper's cadence (256 antennas, 3,205 pixels, 16 channels x 2 pols, 1,024 samples, one
image per 16 samples: 64 per gulp), direct route, fp16 operands: 16 x [6410 x 512] . [512 x 2048] in
the real-stacked form (cuBLAS through the package's GEMM binding), then |F|^2 summed over each 16
samples by a power-and-sum kernel (vector loads, fp32 sums). Rows:

* the GEMM with fp32 output (the issue's "floor" row) and with fp16 output (half the bytes written);
* the power-and-sum kernel reading each field; the pairs for a whole gulp;
* the pair done channel by channel (one channel's fp16 field, 26 MB, fits the 50-MB L2);
* error of the fp32- and fp16-field images against a float64 evaluation (2 channels, all pixels).

usage: python tools/bench/bench_regime_b.py [--json PATH]     (needs CuPy and a CUDA device)
"""
import argparse
import sys

import numpy as np

from benchlib import machine, utc_now, write_json

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--json")
args = ap.parse_args()
try:
    import cupy as cp
    cp.cuda.runtime.getDeviceCount()
except Exception as e:  # noqa: BLE001
    sys.exit(f"bench_regime_b: needs CuPy and a CUDA device ({e})")
from bf_epic_blocks.imaging import gemm as G  # noqa: E402 - after the check that a GPU is there
C, K, A, T, P, N = 16, 3205, 256, 1024, 2, 16
rng = np.random.default_rng(1)
ang = rng.uniform(-np.pi, np.pi, (C, K, A))
D = np.cos(ang) + 1j * np.sin(ang)
X = rng.integers(-8, 8, (C, A, P * T)) + 1j * rng.integers(-8, 8, (C, A, P * T))
# stacked real form: [Re D, -Im D; Im D, Re D] (2K x 2A) . [Re X; Im X] (2A x PT) = [Re F; Im F]
Ast = np.concatenate([np.concatenate([D.real, -D.imag], 2), np.concatenate([D.imag, D.real], 2)], 1)
Bst = np.concatenate([X.real, X.imag], 1)
a = cp.asarray(Ast, cp.float16); b = cp.asarray(Bst, cp.float16)
F32 = cp.empty((C, 2 * K, P * T), cp.float32); F16 = cp.empty((C, 2 * K, P * T), cp.float16)
src = r'''
#include <cuda_fp16.h>
template <typename TIN> __device__ __forceinline__ float sq16(const TIN* re, const TIN* im);
template <> __device__ __forceinline__ float sq16<__half>(const __half* re, const __half* im) {
  const uint4* r4 = (const uint4*)re; const uint4* i4 = (const uint4*)im; float s = 0.f;
  for (int q = 0; q < 2; q++) { uint4 x = r4[q], y = i4[q]; const __half2* hx = (const __half2*)&x; const __half2* hy = (const __half2*)&y;
    for (int e = 0; e < 4; e++) { float2 u = __half22float2(hx[e]), v = __half22float2(hy[e]); s += u.x*u.x + u.y*u.y + v.x*v.x + v.y*v.y; } }
  return s; }
template <> __device__ __forceinline__ float sq16<float>(const float* re, const float* im) {
  const float4* r4 = (const float4*)re; const float4* i4 = (const float4*)im; float s = 0.f;
  for (int q = 0; q < 4; q++) { float4 x = r4[q], y = i4[q]; s += x.x*x.x + x.y*x.y + x.z*x.z + x.w*x.w + y.x*y.x + y.y*y.y + y.z*y.z + y.w*y.w; }
  return s; }
template <typename TIN> __device__ void powsum(const TIN* F, float* out, int C, int K, int T, int P) {
  const long long G = T / 16, total = (long long)C * P * K * G;
  long long i = blockIdx.x * (long long)blockDim.x + threadIdx.x; if (i >= total) return;
  const int g = i % G; long long r = i / G; const int k = r % K; r /= K; const int p = r % P; const int c = r / P;
  const TIN* re = F + ((long long)c * 2 * K + k) * (P * T) + p * T + g * 16;
  out[i] = sq16<TIN>(re, re + (long long)K * P * T); }
extern "C" __global__ void pow16_h(const __half* F, float* out, int C, int K, int T, int P) { powsum<__half>(F, out, C, K, T, P); }
extern "C" __global__ void pow16_f(const float* F, float* out, int C, int K, int T, int P) { powsum<float>(F, out, C, K, T, P); }
'''
mod = cp.RawModule(code=src, options=("-std=c++17",))
kh, kf = mod.get_function("pow16_h"), mod.get_function("pow16_f")
out = cp.empty((C, P, K, T // N), cp.float32); out2 = cp.empty_like(out)
def gemm(c_out, otype, sl=slice(None)):
    G._gemm_ex(a[sl], b[sl], c_out[sl], G._CUDA_R_16F, otype, G._COMPUTE["fp32"], np.float32, 0)
def pw(k, F, o, c=C, off=0):
    tot = c * P * K * (T // N)
    k(((tot + 255) // 256,), (256,), (F[off:off + c], o[off:off + c], np.int32(c), np.int32(K), np.int32(T), np.int32(P)))
def per_channel():
    for i in range(C):
        gemm(F16, G._CUDA_R_16F, slice(i, i + 1)); pw(kh, F16, out2, 1, i)
cases = {"gemm fp32 out (the issue's floor row)": lambda: gemm(F32, G._CUDA_R_32F),
         "gemm fp16 out": lambda: gemm(F16, G._CUDA_R_16F),
         "power+sum from fp32 field": lambda: pw(kf, F32, out),
         "power+sum from fp16 field": lambda: pw(kh, F16, out2),
         "gemm fp32 + power (whole gulp)": lambda: (gemm(F32, G._CUDA_R_32F), pw(kf, F32, out)),
         "gemm fp16 + power (whole gulp)": lambda: (gemm(F16, G._CUDA_R_16F), pw(kh, F16, out2)),
         "gemm fp16 + power, channel by channel (L2)": per_channel}
res = {}
for name, f in cases.items():
    for _ in range(3): f()
    ts = []
    for _ in range(20):
        e0, e1 = cp.cuda.Event(), cp.cuda.Event(); e0.record(); f(); e1.record(); e1.synchronize()
        ts.append(cp.cuda.get_elapsed_time(e0, e1))
    res[name] = float(np.median(ts)); print(f"{name:<46} {res[name]:.3f} ms")
gemm(F32, G._CUDA_R_32F); pw(kf, F32, out); per_channel(); cp.cuda.runtime.deviceSynchronize()
ref = out.get(); got = out2.get()
# float64 truth for 2 channels
Fr = np.matmul(D[:2], X[:2])
I = (np.abs(Fr.reshape(2, K, P, T // N, N)) ** 2).sum(-1).transpose(0, 2, 1, 3)
e32 = float(np.abs(ref[:2] - I).max() / I.max()); e16 = float(np.abs(got[:2] - I).max() / I.max())
print(f"error vs float64 (2 channels): fp32 field {e32:.2e}, fp16 field {e16:.2e}")
res.update(err_fp32_field=e32, err_fp16_field=e16, date=utc_now(), machine=machine("gpu"))
if args.json:
    write_json(args.json, res)
