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
