"""What is not known about a site: parameter ranges of a reality profile, a diagnosis' fitted
1 sigma, and the uncertainty of the machine's start state. The honest preview
(:mod:`sim_twin.preview.preview`) draws its Monte Carlo rollouts from it; the preview calibration draws
the simulated machine's true parameters from it.

A profile carries it as an optional ``uncertainty`` block (:class:`sim_twin.twin.profile.RealityProfile`)::

    "uncertainty": {
      "hydraulics.delay_s":            {"range": [0.03, 0.08]},   # uniform, drawn per joint
      "release_delay_mean_s":          {"range": [0.24, 0.28]},
      "hanging_mass.gripper_mass_kg":  {"sigma": 40.0},           # Gaussian about the profile's value
      "start.encoder_sigma_rad": 0.002, "start.imu_sigma_rad": 0.01, "start.passive_rate_max_radps": 0.05
    }

Parameter addresses:

* profile scalars ``release_delay_mean_s``, ``release_delay_std_s``, ``passive_viscous_per_s``,
  ``passive_coulomb_rad_per_s2``;
* ``hydraulics.<dead_band|delay_s|lag_s|velocity_limit>``: drawn independently per active joint;
  ``range`` bounds may be scalars or lists of 4;
* ``<effect>.<param>`` for a library effect (or ``package.module:Class.<param>`` for user code):
  the profile's entry of that effect is changed, or the effect is added when the profile lacks it
  (``sigma`` then centres on the parameter's nominal value). Effects apply after the scalars, so
  an effect that sets a value (release_delay's mean) overrides the scalar's draw.

``range`` is uniform on [lo, hi]; ``sigma`` is Gaussian about the profile's value, clipped to the
effect's prior range (:class:`sim_twin.twin.effects.Param`) or at zero. ``start.*`` set the start-state
model (:class:`StartUncertainty`); absent keys take its defaults.

Draws map points of the unit cube (scrambled Sobol points for the preview, plain uniform for the
calibration) to values by the inverse CDF, so that a few rollouts cover the box evenly.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field, replace

import numpy as np

SCALARS = ("release_delay_mean_s", "release_delay_std_s", "passive_viscous_per_s", "passive_coulomb_rad_per_s2")
HYDRAULIC = ("dead_band", "delay_s", "lag_s", "velocity_limit")
NUM_ACTIVE = 4


@dataclass(frozen=True)
class StartUncertainty:
    """How far the machine's true start state may be from the measured one.

    Attributes:
        encoder_sigma_rad: std of the active joints' encoder error (rad; telescope in m).
            CHOSEN: 0.002 (absolute encoders of ~0.1 degree resolution, HEAP class).
        imu_sigma_rad: std of the passive joints' angle estimate from the gripper IMU, rad.
            CHOSEN: 0.01 (the paper's wireless IMU, Sec. III-A, gives no figure).
        passive_rate_max_radps: residual passive swing: the executor starts a swing once both
            passive rates are below runtime.executor.ExecutorConfig.passive_still_radps
            (0.05 rad/s), so the true rate is anywhere within +-this (uniform), rad/s.
    """

    encoder_sigma_rad: float = 0.002
    imu_sigma_rad: float = 0.01
    passive_rate_max_radps: float = 0.05

    DIMS = 8  # 6 joint angles + 2 passive rates

    def perturb(self, q, qd, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The true start state for unit-cube point ``u`` (8,), given the measured (q, qd) (6,).

        Angles: q + sigma * Phi^-1(u[:6]); passive rates: qd[4:6] + max * 0.95 * (2 u[6:8] - 1)
        (inside the executor's still threshold)."""
        from scipy.stats import norm

        z = norm.ppf(np.clip(u[:6], 1e-6, 1 - 1e-6))
        sig = np.array([self.encoder_sigma_rad] * 4 + [self.imu_sigma_rad] * 2)
        q = np.asarray(q, dtype=float) + sig * z
        qd = np.array(qd, dtype=float, copy=True)
        qd[4:6] += 0.95 * self.passive_rate_max_radps * (2 * np.asarray(u[6:8]) - 1)
        return q, qd

    @property
    def active(self) -> bool:
        return self.encoder_sigma_rad > 0 or self.imu_sigma_rad > 0 or self.passive_rate_max_radps > 0


NO_START_UNCERTAINTY = StartUncertainty(0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ParamSpec:
    """One uncertain parameter.

    Attributes:
        path: its address (module doc).
        lo / hi: (dims,) uniform bounds, or None for a Gaussian.
        sigma: Gaussian std about the profile's value, or None for a uniform range.
    """

    path: str
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    sigma: float | None = None

    @property
    def dims(self) -> int:
        return NUM_ACTIVE if self.path.startswith("hydraulics.") else 1

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi), each (dims,), of a uniform parameter.

        Raises:
            ValueError: the parameter is a Gaussian (``sigma`` set, no range).
        """
        if self.lo is None or self.hi is None:
            raise ValueError(f"uncertain parameter {self.path!r} is a Gaussian (sigma), not a range")
        return self.lo, self.hi

    def at_quantiles(self, u: np.ndarray, centre) -> np.ndarray:
        """The parameter's values at quantiles ``u`` (dims,) in (0, 1): ``lo + u (hi - lo)`` for
        a uniform range, ``centre + sigma * Phi^-1(u)`` (Phi: the standard normal CDF) for a Gaussian
        about ``centre`` (the profile's value, scalar or (dims,))."""
        if self.sigma is not None:
            from scipy.stats import norm

            return centre + self.sigma * norm.ppf(u)
        lo, hi = self.bounds()
        return lo + u * (hi - lo)

    def to_dict(self) -> dict:
        if self.sigma is not None:
            return {"sigma": self.sigma}
        lo, hi = (b.tolist() for b in self.bounds())
        return {"range": [lo[0], hi[0]] if len(set(lo)) == 1 and len(set(hi)) == 1 else [lo, hi]}


@dataclass
class Uncertainty:
    """Parsed ``uncertainty`` block. Use :func:`parse`.

    Attributes:
        params: the uncertain parameters, in the block's order.
        start: the start-state model.
    """

    params: list[ParamSpec] = field(default_factory=list)
    start: StartUncertainty = field(default_factory=StartUncertainty)

    @property
    def param_dims(self) -> int:
        return sum(p.dims for p in self.params)

    def to_dict(self) -> dict:
        out = {p.path: p.to_dict() for p in self.params}
        for k in ("encoder_sigma_rad", "imu_sigma_rad", "passive_rate_max_radps"):
            out[f"start.{k}"] = getattr(self.start, k)
        return out


def _effect_param(path: str):
    """(effect class, Param) of an ``<effect>.<param>`` address. Raises ValueError."""
    from sim_twin.twin.effects import effect_class

    spec, _, pname = path.rpartition(".")
    if not spec:
        raise ValueError(f"uncertainty {path!r}: expected a profile scalar, hydraulics.<name>, <effect>.<param> or start.<name>")
    cls = effect_class(spec)
    par = next((p for p in cls.params if p.name == pname), None)
    if par is None:
        raise ValueError(f"uncertainty {path!r}: effect {cls.name!r} has no parameter {pname!r} (has {[p.name for p in cls.params]})")
    return cls, par


def parse(block: dict | None) -> Uncertainty:
    """Parse and check an ``uncertainty`` block (module doc).

    Raises:
        ValueError: unknown address, neither or both of range/sigma, lo > hi, negative or
            non-finite numbers, ranges outside an effect's prior range (the message says which).
    """
    if not block:
        return Uncertainty()
    if not isinstance(block, dict):
        raise ValueError("profile 'uncertainty' must be an object of {address: {range|sigma}}")
    start_kw, params = {}, []
    for path, spec in block.items():
        if path.startswith("start."):
            name = path[len("start."):]
            if name not in StartUncertainty.__dataclass_fields__ or name == "DIMS":
                raise ValueError(f"uncertainty {path!r}: unknown start-state key (use encoder_sigma_rad, imu_sigma_rad, passive_rate_max_radps)")
            v = float(spec)
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"uncertainty {path!r} must be finite and >= 0, got {spec!r}")
            start_kw[name] = v
            continue
        params.append(_parse_param(path, spec))
    return Uncertainty(params, StartUncertainty(**start_kw))


def _parse_param(path: str, spec) -> ParamSpec:
    if not isinstance(spec, dict) or len(set(spec) & {"range", "sigma"}) != 1 or set(spec) - {"range", "sigma"}:
        raise ValueError(f"uncertainty {path!r}: give exactly one of {{'range': [lo, hi]}} or {{'sigma': s}}")
    bounds = (0.0, math.inf)
    if path.startswith("hydraulics."):
        if path.split(".", 1)[1] not in HYDRAULIC:
            raise ValueError(f"uncertainty {path!r}: hydraulics has {list(HYDRAULIC)}")
        if path == "hydraulics.dead_band":
            bounds = (0.0, 0.99)
    elif path not in SCALARS:
        _, par = _effect_param(path)
        bounds = (par.lo, par.hi)
    dims = NUM_ACTIVE if path.startswith("hydraulics.") else 1
    if "sigma" in spec:
        s = float(spec["sigma"])
        if not math.isfinite(s) or s < 0:
            raise ValueError(f"uncertainty {path!r}: sigma must be finite and >= 0, got {spec['sigma']!r}")
        return ParamSpec(path, sigma=s)
    rng = spec["range"]
    if not isinstance(rng, (list, tuple)) or len(rng) != 2:
        raise ValueError(f"uncertainty {path!r}: range must be [lo, hi]")
    try:
        lo, hi = (np.broadcast_to(np.asarray(b, dtype=float), (dims,)).copy() for b in rng)
    except ValueError as e:
        raise ValueError(f"uncertainty {path!r}: range bounds must be numbers or lists of {dims}: {e}") from e
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))) or np.any(lo > hi):
        raise ValueError(f"uncertainty {path!r}: range needs finite lo <= hi, got {rng!r}")
    if np.any(lo < bounds[0] - 1e-12) or np.any(hi > bounds[1] + 1e-12):
        raise ValueError(f"uncertainty {path!r}: range {rng!r} outside the allowed [{bounds[0]}, {bounds[1]}]")
    return ParamSpec(path, lo=lo, hi=hi)


def unit_points(n: int, dims: int, seed: int) -> np.ndarray:
    """(n, dims) scrambled Sobol points in the unit cube (quasi Monte Carlo; scipy.stats.qmc).
    n a power of two keeps the balance properties; other n work too."""
    if dims == 0:
        return np.zeros((n, 0))
    import warnings

    from scipy.stats import qmc

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "balance properties ... n not a power of 2"
        return qmc.Sobol(dims, scramble=True, seed=seed).random(n)


def sample_profile(profile, unc: Uncertainty, u: np.ndarray):
    """The concrete profile at unit-cube point ``u`` (param_dims,) of ``unc``.

    Args:
        profile: the centre :class:`sim_twin.twin.profile.RealityProfile` (its values are the
            Gaussians' means).
        unc: its parsed uncertainty.
        u: (unc.param_dims,) point in [0, 1).

    Returns:
        a new RealityProfile without uncertainty, every listed parameter set.
    """
    from sim_twin.twin.effects import effect_class

    prof = replace(profile, uncertainty={}, effects=[copy.deepcopy(e) for e in profile.effects],
                   hydraulics=copy.deepcopy(profile.hydraulics))
    k = 0
    for p in unc.params:
        uu = np.clip(np.asarray(u[k:k + p.dims], dtype=float), 1e-6, 1 - 1e-6)
        k += p.dims
        if p.path.startswith("hydraulics."):
            name = p.path.split(".", 1)[1]
            centre = getattr(prof.hydraulics, name)
            values = p.at_quantiles(uu, centre)
            hi = 0.99 if name == "dead_band" else np.inf
            prof.hydraulics = replace(prof.hydraulics, **{name: np.clip(values, 0.0, hi)})
            continue
        if p.path in SCALARS:
            centre = getattr(prof, p.path)
            scalar = float(p.at_quantiles(uu, centre)[0])
            setattr(prof, p.path, scalar if p.sigma is None else max(0.0, scalar))
            continue
        spec, _, pname = p.path.rpartition(".")
        cls = effect_class(spec)
        par = next(x for x in cls.params if x.name == pname)
        eff = next((e for e in prof.effects if type(e) is cls), None)
        centre = eff.values[pname] if eff is not None else par.nominal
        val = float(np.clip(p.at_quantiles(uu, centre)[0], par.lo, par.hi))
        if eff is None:
            prof.effects.append(cls(**{pname: val}))
        else:
            eff.values[pname] = val
    return prof


def with_fitted_sigma(profile, fitted_sigma: dict[str, dict[str, float]]):
    """``profile`` with a diagnosis' fitted 1 sigma added to its uncertainty block.

    Args:
        profile: a RealityProfile (e.g. the diagnosis' profile_fitted.json).
        fitted_sigma: {effect name: {param: sigma}} (the diagnosis report's ``which[i].sigma``);
            non-finite or non-positive sigmas are skipped (parameters the fit pinned down or
            could not estimate).

    Returns:
        a new profile whose uncertainty has ``{"<effect>.<param>": {"sigma": s}}`` entries.
    """
    block = dict(profile.uncertainty or {})
    for eff, sig in fitted_sigma.items():
        for name, s in sig.items():
            if s is not None and math.isfinite(float(s)) and float(s) > 0:
                block[f"{eff}.{name}"] = {"sigma": float(s)}
    parse(block)
    return replace(profile, uncertainty=block)
