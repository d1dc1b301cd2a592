"""The project's one set of conventions (see docs/CONVENTIONS.md for the prose).

* Antenna positions ``xyz_m``: metres East, North, Up from the station centre (LSL stand x, y, z).
* Directions: direction cosines l (East), m (North), n = sqrt(1 - l^2 - m^2) (Up = sin(altitude)).
  From azimuth (North through East) and altitude: l = cos(alt) sin(az), m = cos(alt) cos(az).
* Geometric sign SIGMA = +1 (the LSL convention): a source in direction s puts phase
  exp(+2 pi i nu (s . r_a) / c) on antenna a's voltage; the imaging operator uses
  exp(-SIGMA 2 pi i nu (s . r_a) / c) / N_A.
* Cable terms: the raw voltage carries sqrt(G_a) exp(-2 pi i nu tau_a); calibration multiplies by
  exp(+2 pi i nu tau_a) / sqrt(G_a).
* Image normalisation: I_k = (1/T) sum_t |sum_a D[k,a] x_a(t)|^2, D normalised by 1/N_A (unflagged
  antennas), so a unit-power point source gives I_k ~ 1.
* Polarisation: pol 0 = X (N-S dipole), pol 1 = Y (E-W dipole), as LSL.
  XX = |F_X|^2, YY = |F_Y|^2, XY = F_X F_Y^*, YX = F_Y F_X^*.
  Stokes (linear feeds): I = XX + YY, Q = XX - YY, U = 2 Re XY, V = -2 Im XY.
* Time tags: LWA ticks of the station's 196 MHz sampling clock since the Unix epoch (:data:`FS_HZ`).
* Dispersion: a burst of dispersion measure DM (pc cm^-3) arrives at frequency f later than at the
  reference frequency f_ref by K_DM DM (f^-2 - f_ref^-2), f in GHz (:func:`dispersion_delay_s`).
"""
import numpy as np

SPEED_OF_LIGHT_M_S = 299792458.0
SIGMA = +1
POL_NAMES = ("X", "Y")

#: The LWA station clock (Hz): time tags count its ticks, a channel's sample step is FS_HZ / bandwidth.
FS_HZ = 196_000_000

#: Dispersion constant K_DM, seconds * GHz^2 per (pc cm^-3).
DISPERSION_CONSTANT_S = 4.149e-3


def dispersion_delay_s(dm, freq_hz, ref_freq_hz):
    """Arrival delay (s) at ``freq_hz`` relative to ``ref_freq_hz`` for dispersion measure ``dm``
    (pc cm^-3); positive below the reference frequency. Broadcasts like NumPy; float64 out."""
    f = np.asarray(freq_hz, dtype=np.float64) / 1e9
    fr = np.asarray(ref_freq_hz, dtype=np.float64) / 1e9
    return DISPERSION_CONSTANT_S * np.asarray(dm, dtype=np.float64) * (f ** -2 - fr ** -2)
