"""Operation-count model for the two exact DFT routes, used by ``method="auto"`` and ``bf-epic plan``.

Counts are complex multiply-adds (CMAC, 8 real flops) per image of one channel, for ``nblk``
correlation blocks (XX, YY: one each; any cross product adds the XY block):

* direct:      F = D X            npol * npix * nant * ntime
               |F|^2 and F_X F_Y^*  nblk * npix * ntime   (elementwise, counted as CMACs)
* covariance:  R = X X^H / T      nblk * nant^2 * ntime      (only the pol blocks the products need)
               D R                nblk * npix * nant^2
               diag(D R D^H)      nblk * npix * nant        (elementwise)

``auto`` picks the route with fewer CMACs. For case P (256 antennas, 3,205 pixels, 1,024 samples,
XX+YY) that is the covariance route by about 3x; for short integrations (ntime << nant) the direct
route wins. Building the operator (npix * nant complex exponentials per channel) is common to both
and is done once per operator, not per image.
"""
from __future__ import annotations

import math


def route_cmacs(ntime: int, nant: int, npix: int, npol: int = 1, nblk: int | None = None) -> dict:
    """CMAC counts per channel for one image of ``ntime`` samples: {'direct': n, 'covariance': n}."""
    nblk = npol if nblk is None else nblk
    direct = npol * npix * nant * ntime + nblk * npix * ntime
    covariance = nblk * nant ** 2 * ntime + nblk * npix * nant * nant + nblk * npix * nant
    return {"direct": int(direct), "covariance": int(covariance)}


def route_bytes(ntime: int, nant: int, npix: int, npol: int = 1, itemsize: int = 8) -> dict:
    """Working-set bytes per channel (complex itemsize): operator + data + intermediate."""
    op = npix * nant * itemsize
    data = npol * nant * ntime * itemsize
    return {"direct": int(op + data + npol * npix * ntime * itemsize),
            "covariance": int(op + data + (npol * nant) ** 2 * itemsize + npol * npix * nant * itemsize)}


def choose_method(ntime: int, nant: int, npix: int, npol: int = 1, nblk: int | None = None) -> str:
    """'direct' or 'covariance', whichever needs fewer CMACs (ties go to covariance)."""
    c = route_cmacs(ntime, nant, npix, npol, nblk)
    return "direct" if c["direct"] < c["covariance"] else "covariance"


#: Effective complex multiply-add rates (CMAC/s) of the two routes on case P (fp32), as
#: tools/bench/bench_dft.py measures them: GPU = one NVIDIA H200 (16 channels x 2 pols), CPU = 2
#: cores of an AMD EPYC (NumPy + OpenBLAS, one channel-pol). ``bf-epic plan``
#: divides operation counts by these to predict run time; re-measure for other machines.
MEASURED_RATES_CMAC_S = {
    ("gpu", "covariance"): 4.8e12,
    ("gpu", "direct"): 4.2e12,
    ("cpu", "covariance"): 1.5e10,
    ("cpu", "direct"): 1.35e10,
}


def predict_seconds(cmacs: float, device: str, method: str) -> float:
    """Predicted run time (s) of ``cmacs`` complex multiply-adds by ``method`` on 'cpu' or 'gpu'."""
    return float(cmacs) / MEASURED_RATES_CMAC_S[(device, method)]


def operator_bytes(nchan: int, npix: int, nant: int, precision: str, *, gpu: bool, nant_in: int | None = None,
                   pols_differ: bool = True) -> dict:
    """Bytes a :class:`~.dft.DFTOperator` holds where it lives, by part, for ``nchan`` channels, ``npix``
    pixels and ``nant`` antennas kept (of ``nant_in`` in the input, default ``nant``):

    * ``phases``: the geometric operator G, complex (complex128 for 'fp64'), nchan x npix x nant; not held
      by the fused integer modes on a GPU, which form it a chunk at a time whenever they make their pieces;
    * ``operands``: the form the GEMMs take -- the stacked real halves of the tensor-core modes on a GPU
      (:func:`.gemm.stack_operator`), or the fused integer modes' int8 pieces and row scales
      (:func:`.fused.quantise_operator`: one set per pol where the pols' weights differ, ``pols_differ``);
    * ``building``: the most its construction adds while it runs (the fused modes' per-chunk working
      arrays; freed once built, but it must fit).
    """
    import numpy as np

    from .fused import PIECES, operand_bytes, reform_channels
    from .gemm import STACKED, stack_operator
    nant_in = nant if nant_in is None else int(nant_in)
    cplx = 16 if precision == "fp64" else 8
    parts = {"phases": nchan * npix * nant * cplx, "operands": 0, "building": 0}
    if gpu and precision in PIECES:
        parts["operands"] = operand_bytes(nchan, 2 if pols_differ else 1, npix, nant_in, PIECES[precision])
        # the phases of a chunk of channels at a time (FusedOperator._quantise), read by the quantising kernel
        parts["phases"] = 0
        parts["building"] = min(nchan, reform_channels(npix, nant)) * npix * nant * 8
    elif gpu and precision in STACKED:
        probe = np.zeros((1, 8, 8), np.complex64)
        per = sum(p.nbytes for p in stack_operator(probe, precision)) / probe.size
        parts["operands"] = int(nchan * npix * nant * per)
    return parts


def voltage_bytes(nchan: int, ntime: int, nant_in: int, precision: str, *, gpu: bool, npol: int = 2) -> int:
    """Bytes of the fused integer modes' voltage layout on a GPU (:func:`.fused.layout_voltages`: int8
    (nchan, npol x Tp, 2 Apad), Tp = ``ntime`` rounded up to 128, Apad = ``nant_in`` rounded up to 64), which
    the imager keeps from gulp to gulp; 0 for the other modes and on the CPU (the field's GEMM reads the
    voltages as they come)."""
    from .fused import PIECES, _b_shape, _pad, padded_ntime
    if not (gpu and precision in PIECES):
        return 0
    return math.prod(_b_shape(int(nchan), int(npol) * padded_ntime(int(ntime)), 2 * _pad(int(nant_in), 64), False))


#: the sky solver's own peak (:func:`~.skycal.solve_gains`) beyond the model with its fitted diffuse term
#: (one whole covariance where there is one), in covariances of one chunk of channels
#: (:func:`~.skycal.solve_chunks`): measured with tracemalloc at 16 channels and 64 antennas in one chunk,
#: 2.91 / 2.90 in complex64 (a GPU's dtype) and 2.66 / 2.64 in complex128 (the CPU's), with and without
#: the diffuse term
SOLVE_CHUNK_ARRAYS = 3.0


def solver_bytes(nchan: int, nant: int, npol: int = 2, *, gpu: bool, diffuse: bool = True) -> dict:
    """Bytes a live gain solver (:class:`~..blocks.gain_solver.GainSolverBlock`) holds where it runs, for
    ``nchan`` channels, ``nant`` stands and ``npol`` pols; one covariance array is nchan x npol x nant^2
    complex (complex64 on a GPU, complex128 on the CPU):

    * ``held``: the covariance sums (one array), the baseline weights (nchan, nant, nant) in the solve's
      real dtype (float32 on a GPU, float64 on the CPU), and the diffuse model (one array) where it is
      fitted;
    * ``working``: the most it adds, the larger of what summing adds (the integer Gram sums (npol, nchan,
      2 nant, 2 nant), int32 on a GPU, float64 on the CPU, while an integration is summed) and what forming
      a solution adds (the sums' mean and the model, one array each, and the per-chunk steps' peak,
      ``SOLVE_CHUNK_ARRAYS`` covariances of one chunk of channels, one more where the diffuse term's model
      chunk is formed, :func:`~.skycal.model_chunk`, and the per-input figures: up to eight (nchan, npol,
      nant) arrays of 16 bytes an element, the gains and the health figures); ``summing`` and ``solving``
      are the two.
    """
    from .skycal import SOLVE_CHUNK_BYTES
    cplx = 8 if gpu else 16
    per_chan = npol * nant * nant * cplx
    cov = nchan * per_chan
    chunk = min(nchan, max(1, SOLVE_CHUNK_BYTES // per_chan)) * per_chan
    held = cov + nchan * nant * nant * (4 if gpu else 8) + (cov if diffuse else 0)
    gram = npol * nchan * (2 * nant) ** 2 * (4 if gpu else 8)
    solving = 2 * cov + (SOLVE_CHUNK_ARRAYS + (1 if diffuse else 0)) * chunk + 8 * nchan * npol * nant * 16
    return {"held": int(held), "working": int(max(gram, solving)), "summing": int(gram), "solving": int(solving)}
