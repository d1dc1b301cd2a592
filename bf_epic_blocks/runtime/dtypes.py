"""Bifrost data-type strings, their storage in ring memory, and complex pack/unpack helpers.

Bifrost names types by kind and bits: 'i8', 'u16', 'f32', 'cf32', 'ci4', 'ci8', 'ci16'...
For complex types the bits are *per component*: 'ci4' is ONE byte per complex sample
(4-bit two's-complement nibbles, high nibble = real, low nibble = imaginary), 'ci8' is two
int8, 'ci16' two int16, 'cf32' is numpy complex64.

Storage (what a span's ``data`` holds):

* 'system' / 'cuda_host' (NumPy), as real Bifrost shows them: 'ci4' -> structured
  ``[('re_im', u1)]`` (same shape as the tensor), 'ci8'/'ci16'/'ci32'/'cf16' -> structured
  ``[('re', T), ('im', T)]`` (same shape), everything else the plain NumPy dtype.
* 'cuda' (CuPy has no structured dtypes): 'ci4' -> plain uint8 (same shape); the pair types
  -> plain component dtype with one extra trailing axis of length 2 (re, im).

:func:`unpack_complex` accepts every one of these forms (and real Bifrost's ci4 with an int8
're_im' field), on NumPy or CuPy, and returns complex64.
"""
from __future__ import annotations

import numpy as np

# name -> (kind, component numpy dtype)
#   kind 'plain': stored as the numpy dtype; 'nibble': ci4; 'pair': structured (re, im)
_TYPES = {
    'i8': ('plain', np.int8), 'i16': ('plain', np.int16), 'i32': ('plain', np.int32),
    'i64': ('plain', np.int64),
    'u8': ('plain', np.uint8), 'u16': ('plain', np.uint16), 'u32': ('plain', np.uint32),
    'u64': ('plain', np.uint64),
    'f16': ('plain', np.float16), 'f32': ('plain', np.float32), 'f64': ('plain', np.float64),
    'cf32': ('plain', np.complex64), 'cf64': ('plain', np.complex128),
    'ci4': ('nibble', np.uint8),
    'ci8': ('pair', np.int8), 'ci16': ('pair', np.int16), 'ci32': ('pair', np.int32),
    'cf16': ('pair', np.float16),
}
SUPPORTED_DTYPES = tuple(_TYPES)
HOST_SPACES = ('system', 'cuda_host')
SPACES = ('system', 'cuda_host', 'cuda')


def _check_name(dtype_str):
    if not isinstance(dtype_str, str) or dtype_str not in _TYPES:
        raise ValueError(f"unknown Bifrost dtype {dtype_str!r}; expected one of "
                         f"{', '.join(SUPPORTED_DTYPES)}")
    return _TYPES[dtype_str]


def itemsize_bytes(dtype_str) -> int:
    """Bytes per element of the tensor (ci4: 1, ci8: 2, cf32: 8...)."""
    kind, comp = _check_name(dtype_str)
    return np.dtype(comp).itemsize * (2 if kind == 'pair' else 1)


def is_complex(dtype_str) -> bool:
    return dtype_str.startswith('c')


def storage_dtype(dtype_str, space='system'):
    """``(numpy_dtype, extra_trailing_shape)`` used to hold ``dtype_str`` in ``space``."""
    kind, comp = _check_name(dtype_str)
    if space not in SPACES:
        raise ValueError(f"unknown memory space {space!r}; expected one of {SPACES}")
    if kind == 'plain':
        return np.dtype(comp), ()
    if space == 'cuda':
        return np.dtype(comp), ((2,) if kind == 'pair' else ())
    if kind == 'nibble':
        return np.dtype([('re_im', np.uint8)]), ()
    return np.dtype([('re', comp), ('im', comp)]), ()


def _xp_of(a, xp=None):
    if xp is not None:
        return xp
    mod = type(a).__module__
    if mod.startswith('cupy'):
        import cupy
        return cupy
    return np


def _nibble_fields(b, xp):
    b = b.astype(xp.int16)
    return ((b >> 4) ^ 8) - 8, ((b & 0x0F) ^ 8) - 8   # sign-extend a 4-bit field: (x ^ 8) - 8


# byte -> complex64 table for the host path: one gather instead of five temporaries
_CI4_LUT = None


def _nibbles_to_complex(b, xp):
    """uint8 bytes -> complex64: high nibble real, low nibble imag, two's complement."""
    global _CI4_LUT
    if xp is np:
        if _CI4_LUT is None:
            re, im = _nibble_fields(np.arange(256, dtype=np.uint8), np)
            _CI4_LUT = (re + 1j * im).astype(np.complex64)
        return _CI4_LUT[b]
    return _nibble_kernel("complex")(b)


def unpack_complex(data, dtype_str, xp=None):
    """Complex64 values of a span array of Bifrost type ``dtype_str``.

    ``data``: NumPy or CuPy array in any storage form described in the module docstring
    (structured or plain; for plain pair types the trailing axis of length 2 is (re, im) and
    is removed). Real types are simply cast. Vectorised; stays on the array's device.
    complex64 input is returned as it is (not copied): treat the result as read-only.
    """
    kind, comp = _check_name(dtype_str)
    xp = _xp_of(data, xp)
    names = getattr(data.dtype, 'names', None)
    if kind == 'nibble':
        if names:
            if len(names) != 1:
                raise TypeError(f"ci4 data has fields {names}; expected one 're_im' field")
            data = data[names[0]]
        if data.dtype.itemsize != 1:
            raise TypeError(f"ci4 data must be one byte per sample, got dtype {data.dtype}")
        return _nibbles_to_complex(data.view(xp.uint8), xp)
    if kind == 'pair':
        if names:
            if set(names) != {'re', 'im'}:
                raise TypeError(f"{dtype_str} data has fields {names}; expected 're', 'im'")
            re, im = data['re'], data['im']
        else:
            if data.ndim == 0 or data.shape[-1] != 2:
                raise TypeError(f"plain {dtype_str} data must end with an axis of length 2 "
                                f"(re, im); got shape {tuple(data.shape)}")
            re, im = data[..., 0], data[..., 1]
        out = re.astype(xp.float32) + 1j * im.astype(xp.float32)
        return out.astype(xp.complex64, copy=False)
    # complex64 input comes back as itself (no copy of a whole gulp; it may be a read-only
    # view of a ring: never write into the result)
    return data.astype(xp.complex64, copy=False)


def unpack_int8_pairs(data, dtype_str, xp=None):
    """Integer (re, im) pairs, int8 shaped ``data.shape + (2,)``, of a 'ci4' or 'ci8' span array.

    The exact form of F-engine voltages for the imager's integer paths (``imaging.DFTOperator``
    takes them directly: integer covariances, fp16 operands). Same storage forms as
    :func:`unpack_complex` (for plain 'ci8' the trailing (re, im) axis is already there). Other types
    raise TypeError: use :func:`unpack_complex`.
    """
    kind, comp = _check_name(dtype_str)
    xp = _xp_of(data, xp)
    names = getattr(data.dtype, 'names', None)
    if kind == 'nibble':
        b = ci4_bytes(data, xp)
        if xp is not np:
            out = xp.empty(b.shape + (2,), xp.int8)
            _nibble_kernel("pairs")(b, out)
            return out
        return np.stack(_nibble_fields(b, np), axis=-1).astype(np.int8)
    if kind == 'pair' and np.dtype(comp) == np.int8:
        if names:
            return xp.stack([data['re'], data['im']], axis=-1)
        return data
    raise TypeError(f"integer pairs come from 'ci4' or 'ci8' data, not {dtype_str!r}")


def ci4_bytes(data, xp=None):
    """The bytes of a 'ci4' span array, uint8 of the same shape (high nibble real, two's complement),
    whatever its storage form: for kernels that decode as they read (:mod:`..imaging.fused`)."""
    xp = _xp_of(data, xp)
    names = getattr(data.dtype, 'names', None)
    if names:
        data = data[names[0]]
    return data.view(xp.uint8)


def _pairs_ci4(data):
    return unpack_int8_pairs(data, 'ci4')


def _pairs_ci8(data):
    return unpack_int8_pairs(data, 'ci8')


_PAIR_DECODERS = {'ci4': _pairs_ci4, 'ci8': _pairs_ci8}


def int8_pairs_decoder(dtype_str):
    """The function ``data -> unpack_int8_pairs(data, dtype_str)`` for 'ci4' or 'ci8', always the same
    object (a CUDA-graph cache can key on it: ``DFTOperator.image(..., decode=...)``)."""
    if dtype_str not in _PAIR_DECODERS:
        raise TypeError(f"integer pairs come from 'ci4' or 'ci8' data, not {dtype_str!r}")
    return _PAIR_DECODERS[dtype_str]


# ci4 decoding on the GPU in one pass each (CuPy's array form takes eight passes and four temporaries).
# These stay CuPy ElementwiseKernel snippets rather than a .cu file: each is one line per element, and
# CuPy's elementwise machinery gives them any input shape and strides (ring spans are views) for free.
_NIBBLE_SRC = {
    "complex": ("uint8 b", "complex64 out",
                "out = complex<float>((float)(((b >> 4) ^ 8) - 8), (float)(((b & 15) ^ 8) - 8));"),
    "pairs": ("uint8 b", "raw int8 out",
              "out[2 * i] = (signed char)(((b >> 4) ^ 8) - 8); out[2 * i + 1] = (signed char)(((b & 15) ^ 8) - 8);"),
}
_NIBBLE_KERNELS = {}


def _nibble_kernel(kind):
    """CuPy ElementwiseKernel decoding ci4 bytes (high nibble real, two's complement) to complex64
    ('complex') or to int8 (re, im) pairs written into a raw (..., 2) output ('pairs')."""
    if kind not in _NIBBLE_KERNELS:
        import cupy as cp
        _NIBBLE_KERNELS[kind] = cp.ElementwiseKernel(*_NIBBLE_SRC[kind], f"bf_unpack_ci4_{kind}")
    return _NIBBLE_KERNELS[kind]


def pack_ci4(values, xp=None):
    """Complex values -> ci4 bytes (uint8, same shape): round, clip to [-8, 7], high nibble =
    real, low nibble = imaginary, two's complement. NumPy or CuPy in, same module out."""
    xp = _xp_of(values, xp)
    values = xp.asarray(values)
    re = xp.clip(xp.rint(values.real), -8, 7).astype(xp.int16)
    im = xp.clip(xp.rint(values.imag), -8, 7).astype(xp.int16) if xp.iscomplexobj(values) \
        else xp.zeros(values.shape, xp.int16)
    return (((re & 0x0F) << 4) | (im & 0x0F)).astype(xp.uint8)


def pack_complex(values, dtype_str, space='system', xp=None):
    """Values -> an array in the ring storage form of ``dtype_str`` for ``space``.

    Complex integers are rounded and clipped to the component range; real types take the
    real part only if the input is complex (an error: data would be lost)."""
    kind, comp = _check_name(dtype_str)
    xp = _xp_of(values, xp)
    values = xp.asarray(values)
    sdt, extra = storage_dtype(dtype_str, space)
    if kind == 'nibble':
        packed = pack_ci4(values, xp)
        return packed if space == 'cuda' else packed.view(sdt)
    if kind == 'pair':
        cdt = np.dtype(comp)
        if cdt.kind == 'i':
            info = np.iinfo(cdt)
            def conv(v):
                return xp.clip(xp.rint(v), info.min, info.max).astype(cdt)
        else:
            def conv(v):
                return v.astype(cdt)
        re = conv(values.real)
        im = conv(values.imag) if xp.iscomplexobj(values) else xp.zeros(values.shape, cdt)
        plain = xp.stack([re, im], axis=-1)
        if space == 'cuda':
            return plain
        return xp.ascontiguousarray(plain).view(sdt)[..., 0]
    if xp.iscomplexobj(values) and not np.issubdtype(sdt, np.complexfloating):
        raise TypeError(f"complex data cannot be stored as real dtype {dtype_str!r}")
    return values.astype(sdt)
