"""Chosen corruptions of a simulated station's voltages: the truth a gain solver is tested against.

Data model (docs/CONVENTIONS.md's, with a direction-independent gain g per input a = (stand, pol))::

    X_a(t) = cable_a(nu) * g_a(nu, t) * sky_a(t) + noise_a(t) [+ extra_a(t) for a noisy input]

* ``g_a(nu, t) = amp_a(t) exp(i (phase_a(t) - 2 pi nu tau_a))`` multiplies the sky signal only, before
  the receiver noise; the cable terms (sqrt(G) exp(-2 pi i nu tau_cable)) stay separate and are still
  applied by the simulator. A solver that removes the cable terms first should find g (its table
  holds 1 / g).
* ``amp_a(0)``: log-normal with mean 1 and fractional rms ``amplitude_rms`` (exp(s N - s^2 / 2),
  s^2 = log(1 + amplitude_rms^2): never negative, the scatter of |g| exactly as asked).
* ``phase_a(0)``: uniform in [0, 2 pi) with ``random_phase``, else 0. ``tau_a``: normal, rms
  ``delay_ns_rms`` ns.
* Drift: ``amp_a(t) = amp_a(0) (1 + s_a drift_amplitude_frac t / drift_over_s)`` (clipped at 0) and
  ``phase_a(t) = phase_a(0) + s'_a radians(drift_phase_deg) t / drift_over_s``, with random signs
  s_a, s'_a = +-1 per input: a linear drift reaching the given values after ``drift_over_s`` seconds
  (and going on at that rate).
* Deaf inputs see no sky (g = 0): only receiver noise. Noisy inputs get an extra independent noise
  of power ``noisy_power`` times the median input's total power, as their own simulator column
  (:meth:`GainCorruption.noisy_weights`), so the CUDA kernel needs nothing new.
* ``deaf`` / ``noisy``: a number of inputs the seed picks (among ``usable`` ones, deaf first, the two
  sets disjoint), or explicit ``(stand_index, pol)`` pairs (stand_index counted from 0, the row of
  the station table; pol 0 = X, 1 = Y).

Everything is a function of ``seed`` and the array's shape: one ``numpy.random.SeedSequence(seed)``
spawns separate streams for amplitudes, phases, delays, drift signs and the choice of inputs, so
asking for deaf inputs leaves the gains of the others as they were.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Mapping

import numpy as np

__all__ = ["GainCorruption"]


def _inputs(v, what):
    """An int >= 0 or a tuple of (stand_index, pol) pairs."""
    if isinstance(v, bool):
        raise TypeError(f"{what}: expected a number of inputs or a list of (stand_index, pol) pairs, got {v!r}")
    if isinstance(v, (int, np.integer)):
        if v < 0:
            raise ValueError(f"{what}: expected a number >= 0, got {v}")
        return int(v)
    try:
        pairs = tuple((int(s), int(p)) for s, p in v)
    except (TypeError, ValueError):
        raise TypeError(f"{what}: expected a number of inputs or a list of (stand_index, pol) pairs, "
                        f"got {v!r}") from None
    for s, p in pairs:
        if s < 0 or p not in (0, 1):
            raise ValueError(f"{what}: pairs are (stand_index >= 0, pol 0 or 1), got {(s, p)}")
    return pairs


@dataclass(frozen=True)
class GainCorruption:
    """Per-input complex gains, deaf and noisy inputs, drawn from ``seed`` (module docstring).

    Parameters
    ----------
    amplitude_rms : fractional rms of |g| about 1 (log-normal).
    delay_ns_rms : rms of the per-input delay, ns.
    random_phase : a uniform phase per input (else 0).
    drift_amplitude_frac, drift_phase_deg, drift_over_s : the linear drift of amplitude (fraction)
        and phase (deg) reached after drift_over_s seconds, with a random sign per input.
    deaf, noisy : a number of inputs picked by the seed, or (stand_index, pol) pairs.
    noisy_power : extra noise power of a noisy input, in units of the median input's total power.
    seed : the random seed.
    """
    amplitude_rms: float = 0.25
    delay_ns_rms: float = 30.0
    random_phase: bool = True
    drift_amplitude_frac: float = 0.0
    drift_phase_deg: float = 0.0
    drift_over_s: float = 600.0
    deaf: int | tuple = 0
    noisy: int | tuple = 0
    noisy_power: float = 10.0
    seed: int = 0
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self):
        for name in ("amplitude_rms", "delay_ns_rms", "drift_amplitude_frac", "noisy_power"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: expected a finite number >= 0, got {v!r}")
        if not (isinstance(self.drift_phase_deg, (int, float)) and math.isfinite(self.drift_phase_deg)):
            raise ValueError(f"drift_phase_deg: expected a finite number, got {self.drift_phase_deg!r}")
        if not (isinstance(self.drift_over_s, (int, float)) and math.isfinite(self.drift_over_s)
                and self.drift_over_s > 0):
            raise ValueError(f"drift_over_s: expected a finite number > 0, got {self.drift_over_s!r}")
        object.__setattr__(self, "deaf", _inputs(self.deaf, "deaf"))
        object.__setattr__(self, "noisy", _inputs(self.noisy, "noisy"))
        object.__setattr__(self, "random_phase", bool(self.random_phase))
        object.__setattr__(self, "seed", int(self.seed))

    @classmethod
    def from_config(cls, cfg: Mapping | None, *, seed: int | None = None) -> "GainCorruption":
        """From the YAML mapping ``{amplitude_rms, delay_ns_rms, random_phase, drift: {amplitude_frac,
        phase_deg, over_s}, deaf, noisy, noisy_power, seed}``; absent or null keys take the defaults,
        and a null ``seed`` takes ``seed`` (the source's)."""
        cfg = dict(cfg or {})
        drift = dict(cfg.pop("drift", None) or {})
        known = {"amplitude_rms", "delay_ns_rms", "random_phase", "deaf", "noisy", "noisy_power", "seed"}
        unknown = set(cfg) - known
        bad_drift = set(drift) - {"amplitude_frac", "phase_deg", "over_s"}
        if unknown or bad_drift:
            raise ValueError(f"corrupt: unknown key(s) {sorted(unknown) + ['drift.' + k for k in sorted(bad_drift)]}")
        kw = {k: v for k, v in cfg.items() if v is not None}
        kw.update({f"drift_{k}": v for k, v in (("amplitude_frac", drift.get("amplitude_frac")),
                                                ("phase_deg", drift.get("phase_deg")),
                                                ("over_s", drift.get("over_s"))) if v is not None})
        if kw.get("seed") is None and seed is not None:
            kw["seed"] = seed
        return cls(**kw)

    def to_dict(self) -> dict:
        """The settings as plain values (for a header)."""
        d = asdict(self)
        d.pop("_cache", None)
        for k in ("deaf", "noisy"):
            if not isinstance(d[k], int):
                d[k] = [list(p) for p in d[k]]
        return d

    # -------------------------------------------------------------- draws
    def _draws(self, nstand: int, npol: int) -> dict:
        key = (int(nstand), int(npol))
        if key not in self._cache:
            amp_ss, ph_ss, tau_ss, drift_ss, pick_ss = np.random.SeedSequence(self.seed).spawn(5)
            shape = key
            s2 = math.log1p(self.amplitude_rms ** 2)
            amp = np.exp(math.sqrt(s2) * np.random.default_rng(amp_ss).standard_normal(shape) - s2 / 2)
            phase = np.random.default_rng(ph_ss).uniform(0.0, 2 * np.pi, shape)
            if not self.random_phase:
                phase = np.zeros(shape)
            tau = 1e-9 * self.delay_ns_rms * np.random.default_rng(tau_ss).standard_normal(shape)
            signs = np.where(np.random.default_rng(drift_ss).random((2,) + shape) < 0.5, -1.0, 1.0)
            self._cache[key] = {"amp": amp, "phase": phase, "tau": tau, "sign_amp": signs[0],
                                "sign_phase": signs[1], "perm": np.random.default_rng(pick_ss).permutation(
                                    nstand * npol)}
        return self._cache[key]

    def _masks(self, nstand, npol, usable=None):
        """(deaf, noisy) bool (nstand, npol)."""
        d = self._draws(nstand, npol)
        ok = np.ones((nstand, npol), bool) if usable is None else np.asarray(usable, bool)
        if ok.shape != (nstand, npol):
            raise ValueError(f"usable: expected a bool mask of shape {(nstand, npol)}, got {ok.shape}")
        masks = []
        taken = np.zeros((nstand, npol), bool)
        for what, spec in (("deaf", self.deaf), ("noisy", self.noisy)):
            m = np.zeros((nstand, npol), bool)
            if isinstance(spec, int):
                pool = [i for i in d["perm"] if ok.flat[i] and not taken.flat[i]]
                if spec > len(pool):
                    raise ValueError(f"{what}: {spec} inputs asked for, only {len(pool)} usable ones left")
                m.flat[pool[:spec]] = True
            else:
                for s, p in spec:
                    if s >= nstand or p >= npol:
                        raise ValueError(f"{what}: input {(s, p)} is outside the array ({nstand} stands, {npol} pols)")
                    m[s, p] = True
            taken |= m
            masks.append(m)
        return masks[0], masks[1]

    def deaf_mask(self, nstand: int, npol: int, *, usable=None) -> np.ndarray:
        """bool (nstand, npol): the deaf inputs (chosen among ``usable``, a bool mask, where a number is asked)."""
        return self._masks(nstand, npol, usable)[0]

    def noisy_mask(self, nstand: int, npol: int, *, usable=None) -> np.ndarray:
        """bool (nstand, npol): the noisy inputs (chosen among ``usable`` minus the deaf ones)."""
        return self._masks(nstand, npol, usable)[1]

    # -------------------------------------------------------------- gains
    def gains(self, nstand: int, npol: int, freq_hz, t_s: float = 0.0, *, usable=None) -> np.ndarray:
        """The true gains g, complex128 (nchan, nstand, npol), at ``t_s`` seconds (module docstring).

        Deaf inputs have g = 0. ``usable``: as :meth:`deaf_mask` (which inputs a number of deaf ones
        is picked from)."""
        f = np.atleast_1d(np.asarray(freq_hz, np.float64))
        d = self._draws(nstand, npol)
        x = float(t_s) / self.drift_over_s
        amp = np.clip(d["amp"] * (1.0 + d["sign_amp"] * self.drift_amplitude_frac * x), 0.0, None)
        phase = d["phase"] + d["sign_phase"] * math.radians(self.drift_phase_deg) * x
        g = amp[None] * np.exp(1j * (phase[None] - 2 * np.pi * f[:, None, None] * d["tau"][None]))
        g[:, self.deaf_mask(nstand, npol, usable=usable)] = 0.0
        return g

    def noisy_weights(self, nstand: int, npol: int, nchan: int, median_power, *, usable=None) -> np.ndarray:
        """Extra simulator columns for the noisy inputs, complex128 (nchan, nnoisy, nstand, npol).

        Column k is seen by the k-th noisy input alone, with power ``noisy_power * median_power[c]``
        (``median_power``: scalar or (nchan,), the median input's total power in the simulator's
        units); fastsim drives it with a complex normal of variance 1 per real part, so its weight is
        sqrt(that power / 2)."""
        mask = self.noisy_mask(nstand, npol, usable=usable)
        mp = np.broadcast_to(np.asarray(median_power, np.float64), (nchan,))
        idx = np.argwhere(mask)
        w = np.zeros((nchan, len(idx), nstand, npol), np.complex128)
        for k, (s, p) in enumerate(idx):
            w[:, k, s, p] = np.sqrt(self.noisy_power * mp / 2.0)
        return w
