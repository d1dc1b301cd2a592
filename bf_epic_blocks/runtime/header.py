"""Sequence-header validation (the Bifrost header format, see docs in BIFROST.md).

A header is a JSON-serialisable dict with ``name`` (str), ``time_tag`` (int >= 0) and
``_tensor``: ``dtype`` (Bifrost type string), ``shape`` (ints, exactly one -1 = the frame
axis; axes before it are "ringlets"), and optional ``labels`` / ``scales`` / ``units``
lists, one entry per axis. Other keys pass through untouched.
"""
from __future__ import annotations

import copy
import json
import math
from numbers import Integral, Real

from .dtypes import _check_name


class HeaderError(ValueError):
    """A sequence header does not follow the Bifrost header format."""


def split_shape(shape):
    """(ringlet_shape, frame_shape) around the single -1: (2, -1, 4, 5) -> ([2], [4, 5])."""
    i = list(shape).index(-1)
    return list(shape[:i]), list(shape[i + 1:])


_SCALARS = frozenset((str, int, float, bool, type(None)))


class _NotPlain(Exception):
    """A value that only a JSON round trip can judge (a subclass, a NumPy scalar, a non-str key, a cycle)."""


def _plain(x):
    t = type(x)
    if t in _SCALARS:
        return x
    if t is list or t is tuple:
        if set(map(type, x)) <= _SCALARS:      # a flat list of numbers (a cable table's row): copied in C
            return list(x)
        return [_plain(v) for v in x]
    if t is dict:
        if not set(map(type, x)) <= {str}:
            raise _NotPlain
        return {k: _plain(v) for k, v in x.items()}
    raise _NotPlain


def plain_copy(obj):
    """A deep copy of header data: what a JSON round trip gives (tuples become lists) for plain str, int,
    float, bool, None, list, tuple and str-keyed dict values -- without the round trip, which for a
    whole-band station header (10^5-10^6 numbers) holds the interpreter for a second at each sequence's
    start; anything else is copied by :func:`copy.deepcopy`."""
    try:
        return _plain(obj)
    except (_NotPlain, RecursionError):
        return copy.deepcopy(obj)


def validate_header(header, where='header'):
    """Check ``header`` and return a JSON round-tripped deep copy (as readers will see it).

    Raises :class:`HeaderError` (a ValueError) naming the first problem found.
    """
    if not isinstance(header, dict):
        raise HeaderError(f"{where} must be a dict, got {type(header).__name__}")
    try:
        try:    # plain values copy as the round trip would give them; only the rest needs the round trip
            hdr = _plain(header)
        except (_NotPlain, RecursionError):
            hdr = json.loads(json.dumps(header, allow_nan=True))
    except (TypeError, ValueError) as exc:
        raise HeaderError(f"{where} is not JSON-serialisable ({exc}); use plain str/int/"
                          "float/list/dict values (convert NumPy scalars/arrays)") from exc
    name = hdr.get('name')
    if not isinstance(name, str) or not name:
        raise HeaderError(f"{where}['name'] must be a non-empty str, got {name!r}")
    tt = hdr.get('time_tag')
    if isinstance(tt, bool) or not isinstance(tt, Integral) or tt < 0:
        raise HeaderError(f"{where}['time_tag'] must be an int >= 0, got {tt!r}")
    tensor = hdr.get('_tensor')
    if not isinstance(tensor, dict):
        raise HeaderError(f"{where}['_tensor'] must be a dict with 'dtype' and 'shape', "
                          f"got {tensor!r}")
    try:
        _check_name(tensor.get('dtype'))
    except ValueError as exc:
        raise HeaderError(f"{where}['_tensor']['dtype']: {exc}") from None
    shape = tensor.get('shape')
    if (not isinstance(shape, list) or not shape
            or any(isinstance(s, bool) or not isinstance(s, Integral) for s in shape)):
        raise HeaderError(f"{where}['_tensor']['shape'] must be a non-empty list of ints, "
                          f"got {shape!r}")
    if shape.count(-1) != 1:
        raise HeaderError(f"{where}['_tensor']['shape'] must contain exactly one -1 (the "
                          f"frame axis), got {shape}")
    if any(s < 1 for s in shape if s != -1):
        raise HeaderError(f"{where}['_tensor']['shape'] entries other than -1 must be >= 1, "
                          f"got {shape}")
    ndim = len(shape)
    for key in ('labels', 'scales', 'units'):
        val = tensor.get(key)
        if val is None:
            continue
        if not isinstance(val, list) or len(val) != ndim:
            raise HeaderError(f"{where}['_tensor']['{key}'] must be a list with one entry per "
                              f"axis ({ndim}), got {val!r}")
        for i, v in enumerate(val):
            if v is None:
                continue
            if key in ('labels', 'units') and not isinstance(v, str):
                raise HeaderError(f"{where}['_tensor']['{key}'][{i}] must be a str or None, "
                                  f"got {v!r}")
            if key == 'scales' and not (
                    isinstance(v, list) and len(v) == 2
                    and all(isinstance(x, Real) and not isinstance(x, bool) and math.isfinite(x)
                            for x in v)):
                raise HeaderError(f"{where}['_tensor']['scales'][{i}] must be None or "
                                  f"[offset, step] (finite numbers), got {v!r}")
    labels = tensor.get('labels')
    if labels is not None:
        named = [lab for lab in labels if lab is not None]
        if len(named) != len(set(named)):
            raise HeaderError(f"{where}['_tensor']['labels'] must be unique, got {labels}")
    gulp = hdr.get('gulp_nframe')
    if gulp is not None and (isinstance(gulp, bool) or not isinstance(gulp, Integral)
                             or gulp < 0):
        raise HeaderError(f"{where}['gulp_nframe'] must be an int >= 0, got {gulp!r}")
    return hdr
