"""What a "no gap" means: the smallest change of the main candidates these throws could have shown.

For each main candidate (:data:`MAIN`) the throws are replayed once with its parameter moved by a
small step from nominal; the change of every channel's per-throw standardised mean residual
(:meth:`scoring.Scorer.signed`) per unit of the parameter is its sensitivity s_c. The bias test
(:func:`noise.bias_tests`) finds a change delta in channel c with probability noise.POWER when
|s_c delta| >= d_c + (z_{1 - alpha / (2 m)} + z_power) sd_c / sqrt(N) (:func:`noise.detectable_mean`;
sd_c the channel's spread over the throws, m the channels tested, d_c the test's immaterial mean,
:attr:`scoring.Scorer.bias_margin`, 0 on the impact). The detectable size is the
smallest delta over the channels; the throws needed for the reference change follow from the
same formula. Linear in the parameter (one step): a statement of scale, not a guarantee.
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
        delta = min(step, p.hi - p.nominal)
        reps = rp.replay(throws, [EffectStack([cls(**{param: p.nominal + delta})])], dynamics_cache=cache)[0]
        M1 = scorer.signed(reps)
        s = np.array([np.mean((M1 - M0)[has[:, c], c]) / delta for c in chans])
        with np.errstate(divide="ignore", invalid="ignore"):
            d_min = np.where(np.abs(s) > 0, (margin + unit * sd / np.sqrt(N)) / np.abs(s), np.inf)
            n_ref = float(np.min(np.where(np.abs(s) * ref > margin, (unit * sd / (np.abs(s) * ref - margin)) ** 2, np.inf)))
        i = int(np.argmin(d_min))
        out[name] = {"param": param, "unit": disp, "min_change": float(d_min[i] * k), "channel": nz.CHANNELS[chans[i]],
                     "reference_change": ref * k, "throws_for_reference": int(np.ceil(n_ref)) if np.isfinite(n_ref) else None}
    parts = [f"a {WORDS.get(n, n)} change below {v['min_change']:.3g} {v['unit']} (seen first in {v['channel']})" for n, v in out.items()]
    need = [f"{v['throws_for_reference']} throws a {WORDS.get(n, n)} change of {v['reference_change']:g} {v['unit']}" for n, v in out.items()
            if v["throws_for_reference"] is not None]
    text = (f"{', '.join(parts)} would not be visible in {N} throws at this noise (bias tests at family-wise "
            f"{100 * nz.BIAS_ALPHA:g}%, {100 * nz.POWER:.0f}% power); " + ("would show: " + "; ".join(need) if need else ""))
    return {"throws": N, "alpha": nz.BIAS_ALPHA, "power": nz.POWER, "effects": out, "text": text}
