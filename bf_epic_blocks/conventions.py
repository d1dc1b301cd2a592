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
"""
SPEED_OF_LIGHT_M_S = 299792458.0
SIGMA = +1
POL_NAMES = ("X", "Y")
