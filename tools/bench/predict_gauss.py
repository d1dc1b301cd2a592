"""The fused integer modes with three real products per complex multiply-add instead of four: their image
error, predicted exactly on the CPU before any kernel is written.

The fused modes (:mod:`bf_epic_blocks.imaging.fused`) form F = D X with four real int8 products per complex
multiply-add (Re D Re x - Im D Im x, Re D Im x + Im D Re x), D in ``pieces`` int8 pieces scaled per pixel
row. Gauss's form needs three:

    t1 = sum_a Re D (Re x + Im x),   t2 = sum_a Im x (Re D + Im D),   t3 = sum_a Re x (Im D - Re D)
    Re F = t1 - t2,   Im F = t1 + t3

The operator's three real rows (Re D, Re D + Im D, Im D - Re D) are written in the same int8 pieces and
base, each scaled per pixel by its own largest magnitude (``own``: three scales a pixel, the products
combined after the int32 -> float32 conversion) or all three by the largest of them (``shared``: one
scale, Re F and Im F formed in int32); the voltages' sums Re x + Im x (|.| <= 16 for 4-bit data) are the
third int8 operand. The int32 sums cannot overflow for 4-bit data at 256 antennas in either form.

Case P as ``bench_dft.py`` builds it (LWA-SV's stands, 4-bit sky and noise, 1,024 samples, 2 pols, 74 MHz),
one image per 16 samples on the 64 x 64 grid's pixels above the horizon, the error as bench_dft measures
it: max |I - I_ref| / max |I_ref| against a float64 evaluation of the definition, every pixel. The integer
products are evaluated exactly (float64 sums of integers below 2^53), then converted to float32, squared
and summed in float32 as the kernel's epilogue does. The four-product rows are this script's own
arithmetic; the package's fused mode (its quantisation and its int64 emulation of the kernel, whose
epilogue is float64) is imaged beside them: images equal to float32's rounding of the epilogue
(tests/test_bench.py) show that this script quantises as the package does.

    python tools/bench/predict_gauss.py [--nchan 4] [--json predict_gauss.json]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchlib import machine, utc_now, write_json  # noqa: E402
from cases import C, lwasv_like_layout, quantise4, reference_image, sky_efield  # noqa: E402

BASE = {2: 254, 3: 63}     # the fused modes' bases (bf_epic_blocks.imaging.fused.bases at 256 antennas)


def int_pieces(R, scale, pieces, b):
    """R float32 (..., K, A) rows, scale (..., K): the int8 pieces of R / scale * 127 in base b (as the
    package's CPU quantisation makes them: float32 residuals, rint), as float64 arrays (pieces, ..., K, A)."""
    d = (R / scale[..., None] * np.float32(127)).astype(np.float32)
    out = []
    for _ in range(pieces):
        q = np.rint(d)
        d = ((d - q) * np.float32(b)).astype(np.float32)
        out.append(q.astype(np.float64))
    q = np.stack(out)
    assert np.abs(q).max() <= 127
    return q


def exact(q, v, b):
    """sum_i b^(pieces-1-i) (q_i @ v): the kernel's int32 accumulator, exactly (float64 holds it)."""
    p = q.shape[0]
    return sum(b ** (p - 1 - i) * (q[i] @ v) for i in range(p))


def _scale(*rows):
    s = np.max([np.abs(r).max(axis=-1) for r in rows], axis=0).astype(np.float32)
    return np.where(s > 0, s, np.float32(1))


def images(D, Q, pieces, form, n=16):
    """Images (T // n, C, P, K) of 4-bit pairs Q (T, C, A, P, 2) through operator D (C, K, A) complex
    (float64 phases), each image the mean of |F|^2 over n samples, F formed in ``form``: 'four' (the
    package's fused mode), 'shared' or 'own' (three products; module docstring)."""
    b = BASE[pieces]
    T, Cn, A, P, _ = Q.shape
    K = D.shape[1]
    Dr, Di = D.real.astype(np.float32), D.imag.astype(np.float32)
    unit = np.float32(127 * b ** (pieces - 1))
    out = np.zeros((T // n, Cn, P, K), np.float32)
    for c in range(Cn):
        dr, di = Dr[c], Di[c]
        if form == "four":
            s = _scale(dr, di)
            qr, qi = int_pieces(dr, s, pieces, b), int_pieces(di, s, pieces, b)
        else:
            r1, r2 = (dr + di).astype(np.float32), (di - dr).astype(np.float32)
            if form == "shared":
                s0 = s1 = s2 = _scale(dr, r1, r2)
            else:
                s0, s1, s2 = _scale(dr), _scale(r1), _scale(r2)
            q0, q1, q2 = (int_pieces(r, s, pieces, b) for r, s in ((dr, s0), (r1, s1), (r2, s2)))
        for p in range(P):
            xr = Q[:, c, :, p, 0].T.astype(np.float64)               # (A, T)
            xi = Q[:, c, :, p, 1].T.astype(np.float64)
            if form == "four":
                re = exact(qr, xr, b) - exact(qi, xi, b)             # int32 sums, exact
                im = exact(qr, xi, b) + exact(qi, xr, b)
                fr = re.astype(np.float32) * (s / unit)[:, None]
                fi = im.astype(np.float32) * (s / unit)[:, None]
            else:
                t1, t2, t3 = exact(q0, xr + xi, b), exact(q1, xi, b), exact(q2, xr, b)
                if form == "shared":
                    fr = (t1 - t2).astype(np.float32) * (s0 / unit)[:, None]
                    fi = (t1 + t3).astype(np.float32) * (s0 / unit)[:, None]
                else:
                    a1 = t1.astype(np.float32) * (s0 / unit)[:, None]
                    fr = a1 - t2.astype(np.float32) * (s1 / unit)[:, None]
                    fi = a1 + t3.astype(np.float32) * (s2 / unit)[:, None]
            pw = (fr * fr + fi * fi).reshape(K, T // n, n).sum(axis=-1, dtype=np.float32) / np.float32(n)
            out[:, c, p] = pw.T
    return out


def package_images(xyz, freq, lm, Q, pieces, n=16):
    """The package's fused mode on the CPU (its quantisation and its int64 emulation of the kernel,
    :func:`~bf_epic_blocks.imaging.fused.reference_power`), as (T // n, C, P, K) means over n samples of the
    definition's normalisation (D / nant)."""
    from bf_epic_blocks import imaging
    from bf_epic_blocks.imaging import fused
    G = imaging.geometric_operator(xyz, freq, lm, "fp64")
    w = np.ones((len(freq), len(xyz), 2), np.complex128)
    Aq, osc, b, xmax = fused.quantise_operator(G, w, np.arange(len(xyz)), len(xyz), pieces)
    Bv = fused.layout_voltages(Q, None, [0, 1], Aq.shape[-1], xmax)
    T, Tp = Q.shape[0], fused.padded_ntime(Q.shape[0])            # B's columns are padded with zero samples
    got = fused.reference_power(Aq, osc, Bv, Tp, n=n, base=b)[:, :, :T // n, :len(lm)]  # (C, P, T/16, K)
    return got.transpose(2, 0, 1, 3) / (n * len(xyz) ** 2)


def operator(xyz, freq, lm):
    """(C, K, A) complex128: the definition's D = exp(-2 pi i nu / c (l x + m y + n z)) / nant."""
    l, m = lm[:, 0], lm[:, 1]
    nn = np.sqrt(1 - l * l - m * m)
    geo = np.outer(l, xyz[:, 0]) + np.outer(m, xyz[:, 1]) + np.outer(nn, xyz[:, 2])
    return np.stack([np.exp(-2j * np.pi * nu / C * geo) for nu in freq]) / len(xyz)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nchan", type=int, default=4)
    ap.add_argument("--ntime", type=int, default=1024)
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    from bf_epic_blocks import imaging

    xyz, layout = lwasv_like_layout(256)
    freq = 74e6 + 25e3 * np.arange(a.nchan)
    Q = quantise4(sky_efield(xyz, freq, a.ntime, npol=2, dtype=np.complex128))      # int8 (T, C, A, P, 2)
    lm = imaging.lm_grid(a.grid).lm
    D = operator(xyz, freq, lm)
    ref = reference_image(Q, xyz, freq, lm, ((0, 0), (1, 1)), accumulate=16)        # (T/16, C, P, K)

    def rel(img):
        return float(np.max(np.abs(img - ref)) / np.max(np.abs(ref)))

    print(f"# predict_gauss: case P, {len(xyz)} antennas ({layout}), {len(lm)} pixels, {a.ntime} samples, "
          f"{a.nchan} channels x 2 pols, one image per 16 samples; {machine('cpu')['hardware']}")
    print(f"{'mode':<8} {'form':<28} {'int8 MACs / complex MAC':>24} {'rel err':>9}")
    rows = []
    for mode, pieces in (("i8x2", 2), ("i8x3", 3)):
        pkg = package_images(xyz, freq, lm, Q, pieces)
        for form, label, macs, img in (("package", "four (the package, CPU)", 4 * pieces, pkg),
                                       ("four", "four (this script)", 4 * pieces, None),
                                       ("shared", "three, one scale a pixel", 3 * pieces, None),
                                       ("own", "three, a scale a product", 3 * pieces, None)):
            img = images(D, Q, pieces, form) if img is None else np.asarray(img)
            err = rel(img)
            rows.append({"mode": mode, "form": form, "int8_macs_per_cmac": macs, "rel_err": err})
            print(f"{mode:<8} {label:<28} {macs:24d} {err:9.2e}", flush=True)
    if a.json:
        write_json(a.json, {"benchmark": "predict_gauss", "date": utc_now(), "machine": machine("cpu"),
                            "case": {"nant": len(xyz), "layout": layout, "npix": len(lm), "ntime": a.ntime,
                                     "nchan": a.nchan, "npol": 2, "accumulate": 16, "data": "sky + noise, 4-bit"},
                            "rows": rows})
    return rows


if __name__ == "__main__":
    main()
