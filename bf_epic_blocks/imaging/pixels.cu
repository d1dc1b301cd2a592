// Pixels to and from the grid cells they sit in. Launched by imaging/pixels.py (take_pixels,
// GridPlacement.clear).

// bf_take_pixels: out[a, b, p] = v[a sa + b sb + index[p]] (float32; v's last axis contiguous, its other
// strides sa, sb in elements), out (A, B, npix) contiguous, 32-bit index arithmetic inside a row.
// Launch: grid (ceil(npix / 256), min(A B, 65535)), block 256 (grid.y strides over the rows).
extern "C" __global__ void bf_take_pixels(const float* __restrict__ v, const int* __restrict__ index,
                                          float* __restrict__ out, const int A, const int B, const int npix,
                                          const long long sa, const long long sb)
{
    const int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= npix) return;
    const int k = index[p];
    for (int r = blockIdx.y; r < A * B; r += gridDim.y) {
        const int a = r / B, b = r - a * B;
        out[(long long)r * npix + p] = v[a * sa + b * sb + k];
    }
}

// bf_clear_rows<T>: every row of out (rows, n) set to `row` (n,); T float4 (n counted in float4, 16-byte
// stores) or float. Launch: grid (ceil(n / 128), min(rows, 65535)), block 128 (grid.y strides over the rows).
template <typename T>
__global__ void bf_clear_rows(T* __restrict__ out, const T* __restrict__ row, const long long rows, const int n)
{
    const int j = blockIdx.x * blockDim.x + threadIdx.x;
    if (j >= n) return;
    const T v = row[j];
    for (long long r = blockIdx.y; r < rows; r += gridDim.y) out[r * n + j] = v;
}

template __global__ void bf_clear_rows<float>(float*, const float*, long long, int);
template __global__ void bf_clear_rows<float4>(float4*, const float4*, long long, int);
