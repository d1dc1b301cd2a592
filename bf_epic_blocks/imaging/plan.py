"""One accuracy knob and one resolver: what the imagers run, decided in one place.

``tolerance`` is the largest acceptable relative error of an image against its float64 value,
max |I - I_exact| / max I_exact. It means the same for ``imaging.dirty_image``, every imaging block
and the YAML's ``imager.tolerance``. :func:`resolve` turns (tolerance, device, :class:`Problem`,
input kind, expert overrides, imager) into a :class:`Plan`; the pipeline runner, the blocks and
``dirty_image`` all call it, and nothing else picks a route or a precision.

The exact DFT imager ('dft')
    The package ships ``measured.json`` beside this module: for each device kind ('cpu', 'gpu'),
    route ('direct', 'covariance') and GEMM precision (:mod:`.gemm`), the error bound (the worst
    measured over the benchmark scenes -- case P sky + noise in 4-bit, a 5 km baseline at 88 MHz
    with pixels at n ~ 1e-4, a 60 dB point source -- times a safety factor) and the effective rate
    (complex multiply-adds per second on case P, with :mod:`.cost`'s operation counts).
    ``tools/bench/bench_dft.py --table`` measures both again on the machine at hand and rewrites the file.
    With a tolerance, the pick is the (route, precision) that runs on the device, whose bound is
    <= tolerance and whose predicted time is the smallest. Without one, the mode is the given
    precision (default fp32) on the cheaper route by :func:`.cost.choose_method`.

The gridded imagers ('wstack': E-field w-stacking or covariance w-gridding; 'moff')
    ``tolerance`` sets the gridder's ``epsilon`` (its kernel accuracy, :mod:`.kernels`) as
    epsilon = tolerance / 4: the tested bound of those gridders is error <= 4 epsilon
    (:mod:`.wstack`), so the image meets the tolerance. The work precision follows epsilon
    (complex64 for epsilon >= 1e-5, else complex128: :func:`.fieldgrid.work_dtype`). Without a
    tolerance the gridders use :data:`GRIDDED_DEFAULT_TOLERANCE` (epsilon 1e-4). MOFF ignores the
    antennas' heights, so its error against the exact image is not bounded by the tolerance (only
    its gridding is): its plan records no error bound.

Expert overrides
    ``precision`` and ``method`` fix the GEMM precision and the route. Given with a tolerance they
    restrict the choice (and are an error if nothing they allow meets it); the plan records them in
    ``overrides``. For the gridders ``method`` is the route ('auto', 'efield', 'covariance') and a
    precision cannot be given (epsilon decides it).

``bf-epic plan`` prints the plan of a pipeline; the imaging blocks write it to their output header
(``imager.method``, ``imager.precision``, ``imager.tolerance``, ``imager.error_bound``,
``imager.overrides``; the gridders also ``imager.epsilon``).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from . import cost
from ._xp import device_kind
from .fused import FUSED
from .gemm import check_precision, precision_available

__all__ = ["Plan", "Problem", "resolve", "choose", "candidates", "load_table", "device_kind", "check_tolerance",
           "input_kind_of", "gridded_epsilon", "IMAGERS", "INPUT_KINDS", "DFT_METHODS", "GRIDDED_METHODS", "GRIDDED_DEFAULT_TOLERANCE",
           "GRIDDED_ERROR_FACTOR"]

TABLE_PATH = Path(__file__).with_name("measured.json")

IMAGERS = ("dft", "wstack", "moff")
DFT_METHODS = ("auto", "direct", "covariance")
GRIDDED_METHODS = ("auto", "efield", "covariance")
#: what reaches the imager's operator: integers as they are (bits per real component), or complex
INPUT_KINDS = {"ci4": 4, "ci8": 8, "ci16": 16, "complex": None}
#: the tested bound of the gridders: max relative image error <= GRIDDED_ERROR_FACTOR x epsilon
GRIDDED_ERROR_FACTOR = 4.0
#: the gridders' tolerance when none is given (epsilon 1e-4)
GRIDDED_DEFAULT_TOLERANCE = 4e-4
#: the gridders' epsilon range (:func:`.kernels.es_params` takes down to 1e-14; 0.1 keeps the kernel useful)
_EPSILON_RANGE = (1e-14, 0.1)


@dataclass(frozen=True)
class Problem:
    """What is imaged, as the operation counts need it.

    npix : pixels imaged (above the horizon).   nant : antennas (stands) used.
    ntime : samples per image.   nchan : channels (the predicted time is for all of them).
    npol : 1 or 2.   products : None (npol 1: XX; npol 2: XX, YY), a preset ('stokes', 'linear',
    'full') or names; kept as the resolved tuple of names (:func:`.products.resolve_products`).
    """
    npix: int
    nant: int
    ntime: int
    nchan: int = 1
    npol: int = 2
    products: tuple = None

    def __post_init__(self):
        for name in ("npix", "nant", "ntime", "nchan", "npol"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or int(v) < 1:
                raise ValueError(f"Problem.{name} must be a positive integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        if self.npol not in (1, 2):
            raise ValueError(f"Problem.npol must be 1 or 2, got {self.npol!r}")
        from .products import resolve_products
        object.__setattr__(self, "products", tuple(resolve_products(self.npol, self.products)))

    @property
    def cross(self) -> bool:
        """Whether a product needs the cross-pol (XY) correlation."""
        from .products import needs_cross
        return needs_cross(self.products)

    @property
    def nblk(self) -> int:
        """Correlation blocks the products need (XX, YY, XY), as the DFT imager forms them."""
        own = sum([any(p in ("XX", "I", "Q") for p in self.products),
                   self.npol == 2 and any(p in ("YY", "I", "Q") for p in self.products)])
        return max(1, own + int(self.cross))


@dataclass(frozen=True)
class Plan:
    """What an imager runs, and why.

    method : the route ('direct' | 'covariance' for the DFT; 'efield' | 'covariance' | 'moff' for
             the gridders).   precision : the GEMM precision (DFT) or the gridder's work precision
             ('fp32' | 'fp64').   bound : the error bound (max relative image error) the mode is
             known to meet, or None where none is measured.   predicted_s : predicted seconds per
             image (all channels), or None.   device : 'cpu' | 'gpu'.   tolerance : the tolerance
             asked for, or None.   epsilon : the gridder's epsilon (gridders only).
             overrides : the expert overrides that restricted the choice ('method', 'precision').
             imager : 'dft' | 'wstack' | 'moff'.   problem : the :class:`Problem`.
             input_kind : what reaches the operator (a key of :data:`INPUT_KINDS`).
    """
    method: str
    precision: str
    bound: float | None
    predicted_s: float | None
    device: str
    tolerance: float | None = None
    epsilon: float | None = None
    overrides: tuple = ()
    imager: str = "dft"
    problem: Problem | None = field(default=None, compare=True)
    input_kind: str = "complex"

    def describe(self) -> str:
        bound = "no error bound measured" if self.bound is None else f"error bound {self.bound:.1e}"
        text = f"{self.imager} imager: {self.method} route, {self.precision}: {bound}"
        if self.epsilon is not None:
            text += f", gridder epsilon {self.epsilon:.1e}"
        if self.predicted_s is not None:
            text += f", predicted {self.predicted_s * 1e3:.3g} ms per image"
        text += f" on {self.device}"
        if self.overrides:
            text += f" (expert overrides: {', '.join(self.overrides)})"
        return text

    def header(self) -> dict:
        """The fields an imaging block writes to its output header's ``imager`` section."""
        out = {"method": self.method, "precision": self.precision, "tolerance": self.tolerance,
               "error_bound": self.bound, "overrides": list(self.overrides)}
        if self.epsilon is not None:
            out["epsilon"] = self.epsilon
        return out


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


def input_kind_of(dtype) -> str:
    """The input kind of a ring dtype name or array dtype: 'ci4', 'ci8', 'ci16' (integers reaching the
    operator as they are) or 'complex' (cf16, cf32, cf64, or any complex/float array)."""
    name = str(getattr(dtype, "name", dtype)).lower()
    if name in INPUT_KINDS:
        return name
    if name in ("cf16", "cf32", "cf64", "complex64", "complex128", "float32", "float64"):
        return "complex"
    if name == "int8":
        return "ci8"          # (re, im) int8 pairs
    raise ValueError(f"input kind must be one of {tuple(INPUT_KINDS)} (or a ring dtype cf16/cf32/cf64), got {dtype!r}")


def candidates(device, table=None) -> list[dict]:
    """Rows of the table for ``device`` ('cpu' | 'gpu', a device string such as 'gpu:1', or the numpy /
    cupy module) whose precision that device can run."""
    kind = device_kind(device)
    rows = (table or load_table())["rows"]
    return [r for r in rows if r["device"] == kind and precision_available(r["precision"], kind)]


def _rows_for(device, problem, kind, table):
    """The table's rows that can image ``problem`` on ``device`` from input ``kind``: rows measured for
    one input only (``"input": "ci4"``: the fused integer modes, which image no cross-pol products)
    are candidates only when that input is what comes."""
    bits = INPUT_KINDS[kind]
    ints4 = bits is not None and bits <= 4 and not problem.cross
    return [r for r in candidates(device, table) if r.get("input") is None or (r["input"] == "ci4" and ints4)]


def _seconds(row, problem):
    counts = cost.route_cmacs(problem.ntime, problem.nant, problem.npix, problem.npol, problem.nblk)
    return problem.nchan * counts[row["method"]] / float(row["rate_cmac_s"])


def _check_overrides(imager, method, precision, device):
    if imager not in IMAGERS:
        raise ValueError(f"imager must be one of {IMAGERS}, got {imager!r}")
    methods = DFT_METHODS if imager == "dft" else GRIDDED_METHODS
    if method is None:
        method = "auto"
    if method not in methods:
        raise ValueError(f"method must be one of {methods} (the {imager} imager's route), got {method!r}")
    if precision is not None:
        if imager != "dft":
            raise ValueError(f"the {imager} imager's precision follows its tolerance (epsilon); give tolerance, "
                             f"not precision={precision!r}")
        check_precision(precision, device)   # the name (one of PRECISIONS), and a tensor-core mode needs a GPU
    return method


def _fused_route(method, problem, precision):
    if method == "covariance" or problem.cross:
        raise ValueError(f"precision {precision!r} images the direct route's XX/YY powers (products XX, YY, I, Q); "
                         f"asked for method={method!r}, products {list(problem.products)}: use 'fp16x3' or 'fp32' "
                         "for the covariance route or cross-pol products")
    return "direct"


def _dft_plan(tol, kind_dev, problem, kind, method, precision, table):
    overrides = tuple(n for n, v in (("method", method != "auto"), ("precision", precision is not None)) if v)
    if tol is None:
        precision = "fp32" if precision is None else precision
        if precision in FUSED:     # a direct-route kernel for the pols' own powers
            route = _fused_route(method, problem, precision)
        elif method == "auto":
            route = cost.choose_method(problem.ntime, problem.nant, problem.npix, problem.npol, problem.nblk)
        else:
            route = method
        rows = [r for r in _rows_for(kind_dev, problem, kind, table)
                if (r["method"], r["precision"]) == (route, precision)]
        bound = float(rows[0]["bound"]) if rows else None
        predicted = _seconds(rows[0], problem) if rows else None
        return Plan(route, precision, bound, predicted, kind_dev, None, None, (), "dft", problem, kind)
    rows = _rows_for(kind_dev, problem, kind, table)
    if method != "auto":
        rows = [r for r in rows if r["method"] == method]
    if precision is not None:
        rows = [r for r in rows if r["precision"] == precision]
    if not rows:
        raise ValueError(f"no measured (route, precision) for method={method!r}, precision={precision!r} on the "
                         f"{kind_dev}; measured: {[(r['method'], r['precision']) for r in candidates(kind_dev, table)]}")
    ok = [r for r in rows if r["bound"] <= tol]
    if not ok:
        best = min(rows, key=lambda r: r["bound"])
        raise ValueError(f"no route x precision on the {kind_dev} meets tolerance {tol:.1e}: the most accurate "
                         f"({best['method']}, {best['precision']}) is bounded by {best['bound']:.1e}")
    pick = min(ok, key=lambda r: _seconds(r, problem))
    return Plan(pick["method"], pick["precision"], float(pick["bound"]), _seconds(pick, problem), kind_dev, tol,
                None, overrides, "dft", problem, kind)


def gridded_epsilon(tolerance=None, imager="wstack") -> float:
    """The gridder's epsilon for ``tolerance`` (None: :data:`GRIDDED_DEFAULT_TOLERANCE`):
    tolerance / :data:`GRIDDED_ERROR_FACTOR`, or a ValueError naming the tolerances allowed."""
    tol = GRIDDED_DEFAULT_TOLERANCE if tolerance is None else check_tolerance(tolerance)
    eps = tol / GRIDDED_ERROR_FACTOR
    lo, hi = _EPSILON_RANGE
    if not lo <= eps <= hi:
        raise ValueError(f"the {imager} imager's tolerance must lie in [{lo * GRIDDED_ERROR_FACTOR:g}, "
                         f"{hi * GRIDDED_ERROR_FACTOR:g}] (its gridder's epsilon = tolerance / "
                         f"{GRIDDED_ERROR_FACTOR:g} in [{lo:g}, {hi:g}]), got {tolerance!r}")
    return eps


def _gridded_plan(tol, kind_dev, problem, kind, method, imager):
    asked = tol
    eps = gridded_epsilon(tol, imager)
    if imager == "moff":
        route = "moff"
    elif method == "auto":
        # covariance when the integration is at least as long as the array has antennas: then the
        # cheaper by far (tools/bench/bench_wstack.py)
        route = "covariance" if problem.ntime >= problem.nant else "efield"
    else:
        route = method
    # .fieldgrid.work_dtype's rule (complex64 for epsilon >= 1e-5), not imported: fieldgrid imports
    # the DFT module, which imports this one; tests/test_resolver.py holds the two equal
    precision = "fp32" if eps >= 1e-5 else "fp64"
    bound = None if imager == "moff" else GRIDDED_ERROR_FACTOR * eps
    overrides = ("method",) if method != "auto" and imager != "moff" else ()
    return Plan(route, precision, bound, None, kind_dev, asked, eps, overrides, imager, problem, kind)


def resolve(tolerance=None, *, device, problem: Problem, input_kind="complex", precision=None, method="auto",
            imager="dft", table=None) -> Plan:
    """The plan for imaging ``problem`` on ``device`` to ``tolerance`` (see the module docstring).

    tolerance : None (DFT: the given precision, default fp32, on the cheaper route; gridders:
                :data:`GRIDDED_DEFAULT_TOLERANCE`) or the largest acceptable max |I - I_exact| /
                max I_exact, a positive number.
    device : 'cpu' | 'gpu' (or a pipeline device string 'gpu:1', 'gpu:all'), or the numpy / cupy
             module. Planning for a GPU needs neither CuPy nor a GPU.
    problem : a :class:`Problem`.
    input_kind : what the operator is handed (a key of :data:`INPUT_KINDS`, or a ring dtype name):
             'ci4' when 4-bit integers reach one GPU's DFT operator as they are, which makes the fused
             integer modes (i8x1, i8x2, i8x3) candidates.
    precision, method : expert overrides (module docstring); precision one of
             :data:`.gemm.PRECISIONS` (fp64, fp32, tf32x3, fp16x3, tf32, fp16, bf16, i8x1, i8x2,
             i8x3).
    imager : 'dft' | 'wstack' | 'moff'.
    table : a measured table in :func:`load_table`'s form (default: measured.json).
    Raises ValueError for a bad tolerance, override or input kind (naming what is allowed), and
    when nothing meets the tolerance (naming the most accurate option there is).
    """
    tol = None if tolerance is None else check_tolerance(tolerance)
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a Problem (npix, nant, ntime, nchan, npol, products), got {problem!r}")
    kind_dev = device_kind(device)
    kind = input_kind_of(input_kind)
    method = _check_overrides(imager, method, precision, kind_dev)
    if imager == "dft":
        return _dft_plan(tol, kind_dev, problem, kind, method, precision, table)
    return _gridded_plan(tol, kind_dev, problem, kind, method, imager)


def choose(tolerance, device="cpu", *, ntime=1024, nant=256, npix=3205, npol=2, nchan=1, products=None,
           method="auto", precision=None, table=None, sample_bits=None) -> Plan:
    """The DFT imager's fastest (route, precision) with a measured error bound <= ``tolerance``:
    :func:`resolve` for a problem given by its sizes (defaults: case P) and ``sample_bits`` (bits per
    real voltage component when integers reach the operator, else None)."""
    tol = check_tolerance(tolerance)
    kind = "complex" if sample_bits is None else ("ci4" if int(sample_bits) <= 4 else "ci8" if int(sample_bits) <= 8
                                                  else "ci16")
    return resolve(tol, device=device, problem=Problem(npix, nant, ntime, nchan, npol, products), input_kind=kind,
                   precision=precision, method=method, table=table)
