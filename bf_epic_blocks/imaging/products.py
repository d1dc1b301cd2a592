"""Polarisation products from beamformed fields.

Per pixel, the beamformed fields F_X, F_Y (pol 0 = X = N-S dipole, pol 1 = Y = E-W, as LSL) give
XX = |F_X|^2, YY = |F_Y|^2, XY = F_X F_Y^*, YX = F_Y F_X^*. Stokes for linear feeds, stated once:
I = XX + YY, Q = XX - YY, U = 2 Re XY, V = -2 Im XY.
Cross products are complex; images are real, so XY and YX are returned as their real parts
("XY" = Re F_X F_Y^*) and the imaginary part as "XYi" on request.
"""
from __future__ import annotations

VALID = ("XX", "YY", "XY", "YX", "XYi", "YXi", "I", "Q", "U", "V")
PRESETS = {"stokes": ("I", "Q", "U", "V"), "linear": ("XX", "YY"), "full": ("XX", "XY", "YX", "YY")}


def resolve_products(npol: int, products=None) -> tuple[str, ...]:
    """Product names for ``npol`` polarisations.

    ``products`` None -> ("XX",) for npol=1 and ("XX", "YY") for npol=2; a preset name
    ("stokes", "linear", "full") or a sequence of names from :data:`VALID`.
    """
    if npol not in (1, 2):
        raise ValueError(f"npol must be 1 or 2, got {npol}")
    if products is None:
        return ("XX",) if npol == 1 else ("XX", "YY")
    if isinstance(products, str):
        if products in PRESETS:
            names = PRESETS[products]
        else:
            names = tuple(p.strip() for p in products.split(","))
    else:
        names = tuple(products)
    for p in names:
        if p not in VALID:
            raise ValueError(f"unknown polarisation product {p!r}; expected one of {VALID} or a preset {tuple(PRESETS)}")
        if npol == 1 and p != "XX":
            raise ValueError(f"product {p!r} needs two polarisations but the data have npol=1; only 'XX' is possible")
    if not names:
        raise ValueError("products is empty")
    return names


def needs_cross(names) -> bool:
    """Whether any product needs the X-Y cross term."""
    return any(p in ("XY", "YX", "XYi", "YXi", "U", "V") for p in names)


def combine(names, xx, yy=None, xy=None):
    """Stack the requested products from time-averaged correlations.

    xx, yy: real (..., npix) powers; xy: complex (..., npix) mean of F_X F_Y^* (None if not needed).
    Returns a real array (..., nprod, npix) in the namespace of ``xx``.
    """
    from ._xp import get_xp
    xp = get_xp(xx)
    out = []
    for p in names:
        if p == "XX":
            out.append(xx)
        elif p == "YY":
            out.append(yy)
        elif p == "XY":
            out.append(xy.real)
        elif p == "YX":
            out.append(xy.real)
        elif p == "XYi":
            out.append(xy.imag)
        elif p == "YXi":
            out.append(-xy.imag)
        elif p == "I":
            out.append(xx + yy)
        elif p == "Q":
            out.append(xx - yy)
        elif p == "U":
            out.append(2.0 * xy.real)
        elif p == "V":
            out.append(-2.0 * xy.imag)
    return xp.stack(out, axis=-2)
