"""An accuracy target instead of a mode: pick the fastest route x precision whose error bound holds.

The package ships ``measured.json`` beside this module: for each device kind ('cpu', 'gpu'), route
('direct', 'covariance') and GEMM precision (:mod:`.gemm`), the error bound (max |I - I_exact| /
max I_exact, the worst measured over the benchmark scenes -- case P sky + noise in 4-bit, a 5 km
baseline at 88 MHz with pixels at n ~ 1e-4, a 60 dB point source -- times a safety factor) and the
effective rate (complex multiply-adds per second on case P, with :mod:`.cost`'s operation counts).
``tools/bench_dft.py --table`` measures both again on the machine at hand and rewrites the file.

:func:`choose` keeps the (route, precision) pairs that run on the device and whose bound is
<= ``tolerance``, and returns the one with the smallest predicted time. ``bf-epic plan`` prints it.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from . import cost
from ._xp import device_kind
from .gemm import precision_available

__all__ = ["Plan", "choose", "candidates", "load_table", "device_kind", "check_tolerance"]

TABLE_PATH = Path(__file__).with_name("measured.json")


@dataclass(frozen=True)
class Plan:
    """The choice: route, precision, its error bound, and the predicted seconds per image."""
    method: str
    precision: str
    bound: float
    predicted_s: float
    device: str

    def describe(self) -> str:
        return (f"{self.method} route, {self.precision}: error bound {self.bound:.1e}, predicted "
                f"{self.predicted_s * 1e3:.3g} ms per image on {self.device}")


_TABLE = None


def load_table(path=None) -> dict:
    """The measured table: {'rows': [{'device', 'method', 'precision', 'bound', 'rate_cmac_s'}, ...], ...}."""
    global _TABLE
    if path is not None:
        return json.loads(Path(path).read_text())
    if _TABLE is None:
        _TABLE = json.loads(TABLE_PATH.read_text())
    return _TABLE


def check_tolerance(tolerance) -> float:
    """``tolerance`` as a float, or a ValueError naming it unless it is a positive number."""
    try:
        tol = float(tolerance)
    except (TypeError, ValueError):
        raise ValueError(f"tolerance must be a positive number (max relative image error), got {tolerance!r}") from None
    if not tol > 0:
        raise ValueError(f"tolerance must be a positive number (max relative image error), got {tolerance!r}")
    return tol


def candidates(device, table=None) -> list[dict]:
    """Rows of the table for ``device`` ('cpu' | 'gpu', a device string such as 'gpu:1', or the numpy /
    cupy module) whose precision that device can run."""
    kind = device_kind(device)
    rows = (table or load_table())["rows"]
    return [r for r in rows if r["device"] == kind and precision_available(r["precision"], kind)]


def choose(tolerance, device="cpu", *, ntime=1024, nant=256, npix=3205, npol=2, nchan=1, products=None,
           method="auto", precision=None, table=None, sample_bits=None) -> Plan:
    """The fastest (route, precision) with a measured error bound <= ``tolerance`` on ``device``.

    device : 'cpu' | 'gpu' (or a pipeline device string: 'gpu:1', 'gpu:all'), or the array namespace
    the imaging will run in (the numpy or cupy module). Planning for a GPU needs neither CuPy nor a GPU.
    ntime : samples per image; nant, npix, npol, nchan : the problem (for the operation counts;
    the predicted time is for all ``nchan`` channels).
    method : 'auto' (either route) or 'direct' / 'covariance' to restrict the choice.
    precision : None (any) or a name to restrict the choice.
    sample_bits : bits per real voltage component when the voltages reach the imager as integers (4 for
    ci4), else None. Rows measured for one input only (``"input": "ci4"``: the fused integer modes,
    which also image no cross-pol products) are candidates only when that input is what will come.
    Raises ValueError when nothing meets the tolerance, naming the most accurate option there is.
    """
    tol = check_tolerance(tolerance)
    from .products import needs_cross, resolve_products
    names = resolve_products(npol, products)
    nblk = (npol if any(p in ("XX", "YY", "I", "Q") for p in names) else 0) + (1 if needs_cross(names) else 0)
    device = device_kind(device)
    rows = candidates(device, table)
    ints4 = sample_bits is not None and int(sample_bits) <= 4 and not needs_cross(names)
    rows = [r for r in rows if r.get("input") is None or (r["input"] == "ci4" and ints4)]
    if method != "auto":
        rows = [r for r in rows if r["method"] == method]
    if precision is not None:
        rows = [r for r in rows if r["precision"] == precision]
    if not rows:
        raise ValueError(f"no measured (route, precision) for method={method!r}, precision={precision!r} on the "
                         f"{device}; measured: {[(r['method'], r['precision']) for r in candidates(device, table)]}")
    ok = [r for r in rows if r["bound"] <= tol]
    if not ok:
        best = min(rows, key=lambda r: r["bound"])
        raise ValueError(f"no route x precision on the {device} meets tolerance {tol:.1e}: the most accurate "
                         f"({best['method']}, {best['precision']}) is bounded by {best['bound']:.1e}")
    counts = cost.route_cmacs(int(ntime), int(nant), int(npix), int(npol), max(1, nblk))

    def seconds(r):
        return int(nchan) * counts[r["method"]] / float(r["rate_cmac_s"])
    pick = min(ok, key=seconds)
    return Plan(pick["method"], pick["precision"], float(pick["bound"]), seconds(pick), device)
