"""What a "no gap" means: the smallest change of the main candidates these throws could have shown.

For each main candidate (:data:`MAIN`) the throws are replayed once with its parameter moved by a
small step from nominal; the change of every channel's per-throw standardised mean residual
(:meth:`scoring.Scorer.signed`) per unit of the parameter is its sensitivity s_c. The bias test
(:func:`noise.bias_tests`) finds a change delta in channel c with probability noise.POWER when
|s_c delta| >= d_c + (z_{1 - alpha / (2 m)} + z_power) sd_c / sqrt(N) (:func:`noise.detectable_mean`;
sd_c the channel's spread over the throws, m the channels tested, d_c the test's immaterial mean,
:attr:`scoring.Scorer.bias_margin`, 0 on the impact). The detectable size is the
smallest delta over the channels; the throws needed for the reference change follow from the
same formula.

The response is not assumed linear: each candidate is replayed at SIZES times its step (up to
its prior bound), and at each size the test's probability is judged from what that replay
does to the throws: the mean shift of every channel's per-throw residual, and its spread, which
the change adds to the noise (a release delay moves near and far throws differently, so its
mean impact shift can shrink, even change sign, while its scatter grows; with no sensor noise
declared the measured noise then absorbs part of it). A size counts as detectable when some
channel's shift clears margin + (z_a + z_b) sqrt(sd^2 + spread^2) / sqrt(N); the stated size
is the smallest simulated size from which every larger simulated size up to twice it is
detectable, interpolated linearly towards the largest one that is not (so that twice the stated
size is found as the statement claims). When no simulated size qualifies, the candidate says so
(``min_change`` None).
"""

from __future__ import annotations

import numpy as np

from sim_twin.diagnosis import noise as nz
from sim_twin.diagnosis import replay as rp
from sim_twin.twin.effects import EffectStack, effect_class

MAIN = [
    # (effect, parameter, step from nominal, reference change, display unit, factor to display)
    ("release_delay", "mean_s", 0.02, 0.05, "ms", 1000.0),
    ("hanging_mass", "gripper_mass_kg", 100.0, 200.0, "kg", 1.0),
    ("passive_friction", "viscous_per_s", 0.1, 0.2, "1/s", 1.0),
    ("valve_lag", "lag_s", 0.03, 0.05, "ms", 1000.0),
    ("impact_bias", "bias_x_m", 0.05, 0.05, "cm", 100.0),
]
"""Main candidates whose detectable size a "no gap" states (reference changes CHOSEN: about the
smallest of each that moves a 20-30 m throw by a few centimetres)."""
SIZES = (1.0, 2.0, 4.0, 6.0, 8.0, 12.0)
"""Multiples of each candidate's step at which it is replayed (CHOSEN: from the step to six times
the reference changes)."""
WORDS = {"release_delay": "release delay", "hanging_mass": "hanging-mass", "passive_friction": "passive friction",
         "valve_lag": "valve lag", "impact_bias": "impact-measurement bias"}


def detectable(throws, scorer, cache, M0: np.ndarray, D: np.ndarray, main=MAIN) -> dict:
    """Detectable sizes (module doc).

    Args:
        throws: N logged throws; scorer: their :class:`scoring.Scorer`; cache: the nominal
            dynamics (``replay.simulate(..., long=True)[0]``); M0: (N, C) nominal signed residuals.
        D: (N, C, P) degrees of freedom.

    Returns:
        {"throws": N, "alpha": ..., "power": ..., "effects": {effect: {"param", "unit", "min_change",
        "channel", "reference_change", "throws_for_reference"}}, "text": one sentence}.
    """
    N = len(throws)
    has = D.sum(axis=2) > 0
    chans = [c for c in range(M0.shape[1]) if has[:, c].sum() >= 3]
    if not chans:
        return {"throws": N, "alpha": nz.BIAS_ALPHA, "power": nz.POWER, "effects": {}, "text": ""}
    sd = np.array([np.std(M0[has[:, c], c], ddof=1) for c in chans])
    margin = np.array([np.mean(scorer.bias_margin[has[:, c], c]) for c in chans])
    unit = nz.detectable_mean(1.0, 1, len(chans))  # (z_a + z_b) for sd 1, one throw
    out = {}
    for name, param, step, ref, disp, k in main:
        cls = effect_class(name)
        # a per-joint effect's common keyword (valve_lag's lag_s) moves every joint alike
        p = next(q for q in cls.params if q.name == param or q.name.startswith(param + "_"))
        deltas = sorted({min(f * step, p.hi - p.nominal) for f in SIZES} | {min(ref, p.hi - p.nominal)})
        reps = rp.replay(throws, [EffectStack([cls(**{param: p.nominal + d})]) for d in deltas], dynamics_cache=cache)
        ok, best_ch, n_ref = [], [], np.inf
        linear: list[float] = []  # the one-step linear size from the smallest simulated change
        for d, rep in zip(deltas, reps):
            dM = scorer.signed(rep) - M0
            shift = np.array([np.mean(dM[has[:, c], c]) for c in chans])
            spread = np.array([np.std(dM[has[:, c], c], ddof=1) for c in chans])
            need = margin + unit * np.sqrt(sd**2 + spread**2) / np.sqrt(N)
            good = np.abs(shift) >= need
            if not linear:
                with np.errstate(divide="ignore", invalid="ignore"):
                    lin = np.where(np.abs(shift) > 0, (margin + unit * sd / np.sqrt(N)) * d / np.abs(shift), np.inf)
                linear.append(float(np.min(lin)))
            ok.append(bool(good.any()))
            best_ch.append(int(np.argmax(np.abs(shift) - need)))
            if abs(d - ref) < 1e-12:
                with np.errstate(divide="ignore", invalid="ignore"):
                    n_ref = float(np.min(np.where(np.abs(shift) > margin, (unit * np.sqrt(sd**2 + spread**2) / (np.abs(shift) - margin)) ** 2, np.inf)))
        size, ch = _smallest_reliable(deltas, ok, best_ch, linear[0] if linear else None)
        out[name] = {"param": param, "unit": disp, "min_change": None if size is None else float(size * k),
                     "channel": nz.CHANNELS[chans[ch]] if ch is not None else None, "simulated": [float(d * k) for d in deltas],
                     "detectable": ok, "reference_change": ref * k, "throws_for_reference": int(np.ceil(n_ref)) if np.isfinite(n_ref) else None}
    parts = [f"a {WORDS.get(n, n)} change below {v['min_change']:.3g} {v['unit']} (seen first in {v['channel']})" if v["min_change"] is not None
             else f"a {WORDS.get(n, n)} change of any simulated size up to {v['simulated'][-1]:.3g} {v['unit']}" for n, v in out.items()]
    need = [f"{v['throws_for_reference']} throws a {WORDS.get(n, n)} change of {v['reference_change']:g} {v['unit']}" for n, v in out.items()
            if v["throws_for_reference"] is not None]
    text = (f"{', '.join(parts)} would not be visible in {N} throws at this noise (bias tests at family-wise "
            f"{100 * nz.BIAS_ALPHA:g}%, {100 * nz.POWER:.0f}% power); " + ("would show: " + "; ".join(need) if need else ""))
    return {"throws": N, "alpha": nz.BIAS_ALPHA, "power": nz.POWER, "effects": out, "text": text}


def _smallest_reliable(deltas: list[float], ok: list[bool], best_ch: list[int], linear: float | None = None) -> tuple[float | None, int | None]:
    """The smallest size s such that every simulated size in [s, 2 s] is detectable (and at least
    one is), linearly interpolated from the largest undetectable size below it; (None, None) when
    none qualifies. Also the channel that shows it (at the first detectable size). ``linear``: the
    one-step linear size from the smallest simulated change; it is stated when it lies below that
    change and every simulated size up to twice it (at least the smallest) is detectable."""
    if linear is not None and np.isfinite(linear) and linear <= deltas[0] and ok[0]:
        if all(o for d, o in zip(deltas, ok) if d <= max(2 * linear, deltas[0]) + 1e-12):
            return linear, best_ch[0]
    for i, d in enumerate(deltas):
        if not ok[i]:
            continue
        upto = [j for j, e in enumerate(deltas) if d <= e <= 2 * d + 1e-12]
        if all(ok[j] for j in upto) and (2 * d <= deltas[-1] + 1e-12 or i == len(deltas) - 1 or all(ok[i:])):
            lo = deltas[i - 1] if i > 0 else 0.0
            return 0.5 * (lo + d) if i > 0 else d, best_ch[i]
    return None, None
