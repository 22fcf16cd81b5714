"""Particle filter on a building graph, vectorised over particles (struct of arrays).

Koivisto et al., "Graph-based map matching for indoor positioning" (IPIN 2014, the TLL particle
filter): particle state = (link, position on the link, direction, speed, mode); at a link end the
next link is drawn from the link-transition probabilities (:mod:`indoor_loc.graph.tll`); WLAN
positions are Gaussian measurements ``N(r | μ_k, Σ_k)`` (eq. 13) — here optionally a bivariate
Student-t of the same scale (``fix_dof``), with ``Σ_k`` calibrated against the fixes' measured
errors (``fix_cov_scale``, ``fix_sigma_extra_m``), because a fingerprint matcher's wrong matches
make the error's tails heavy; the point estimate is the
constrained mean (Algorithm 3: the link point closest to the weighted mean); resampling when
``N_eff = 1 / Σ W²`` falls below a threshold (systematic resampling).

Two motion models:

- **speed** (WiFi only, Algorithm 2 step 2): two-mode Markov chain (motion/static); in motion
  ``[s, v] ~ N([Δt v, v], σ_v² [[Δt³/3, Δt²/2], [Δt²/2, Δt]])`` with ``v`` truncated to
  ``[v_min, v_max]``; static → motion draws ``v ~ U(v_min, v_max)`` and a direction 50/50.
- **pdr**: each PDR interval gives a walked distance and a heading; the particle walks
  ``distance · scale_i + noise`` (``scale_i`` a per-particle step-length factor) along the graph.
  The heading enters as a likelihood ``exp(κ (cos Δ − 1))`` (a von Mises density; Δ the angle
  between the PDR heading, corrected by the particle's own heading offset, and the direction of
  travel on the link), mixed with a small floor so an off-graph detour does not kill the filter.
  Link choices at nodes and U-turns use this likelihood as a *guided proposal*: option ``j`` is
  drawn with probability ``P_j L_j / Z`` and the weight is multiplied by ``Z = Σ_j P_j L_j`` (the
  optimal-proposal correction), so a turn the walker really makes is followed even when its
  prior probability is ``p_min``.

Adaptive particle count (``adaptive``): at every resampling the number of particles follows the
KLD-sampling bound of Fox ("Adapting the sample size in particle filters through KLD-sampling",
IJRR 2003) over graph bins (link × ``kld_bin_m`` of position): with ``k`` occupied bins,
``n = (k−1)/(2ε) · (1 − 2/(9(k−1)) + √(2/(9(k−1))) z_{1−δ})³``, clamped to [``n_min``, ``n_max``];
a (re)initialisation from a Gaussian of covariance ``P`` draws ``n_particles · √det P / σ_ref²``
particles (Raitoharju et al., "A linear state model for PDR+WLAN positioning", 2015, eq. 63 in two
dimensions: the same particle density as ``n_particles`` over a prior of ``σ_ref`` per axis).

Time is int nanoseconds; every stochastic call takes a ``np.random.Generator``.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from enum import IntEnum

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import gammaln, logsumexp
from scipy.stats import norm

from indoor_loc import params as P
from indoor_loc.graph.model import BuildingGraph
from indoor_loc.graph.tll import Transitions
from indoor_loc.pf.floors import FloorGeometry


class Mode(IntEnum):
    STATIC = 0
    MOTION = 1


@dataclass(frozen=True)
class PfParams:
    """Particle filter parameters (units in each field's doc)."""
    n_particles: int = P.field(1000, "number of particles")
    resample_threshold: float = P.field(0.5, "resample when N_eff < this fraction of the particle count")
    # speed model (no PDR)
    sigma_v: float = P.field(0.5, "speed random-walk noise sigma_v (m/s^1.5)")
    v_min: float = P.field(0.3, "slowest walking speed in motion mode (m/s)")
    v_max: float = P.field(1.8, "fastest walking speed (m/s)")
    p_stop: float = P.field(0.05, "probability per second of motion -> static")
    p_start: float = P.field(0.3, "probability per second of static -> motion")
    # PDR model
    step_scale_sigma: float = P.field(0.12, "spread of the per-particle step-length factor at start (1 = the PDR's distance)")
    step_scale_walk: float = P.field(0.01, "random walk of the step-length factor per metre walked")
    distance_sigma: float = P.field(0.1, "distance noise per metre walked (fraction)")
    heading_sigma_rad: float = P.field(1.2, "PDR heading vs direction of travel: sigma of the von Mises likelihood (rad)")
    heading_floor: float = P.field(0.05, "floor of the heading likelihood (mixture weight of 'any direction')")
    yaw_offset_sigma_rad: float = P.field(3.2, "initial spread of the odom->map heading offset per particle (rad); >= pi means unknown")
    yaw_offset_walk_rad: float = P.field(0.02, "random walk of the heading offset per PDR interval (rad)")
    u_turn_prob: float = P.field(0.02, "prior probability of turning back on a link within one PDR interval")
    # measurements
    fix_sigma_extra_m: float = P.field(0.76, "added to each WiFi fix's standard deviation per axis (m): map and model error")
    fix_cov_scale: float = P.field(0.73, "each WiFi fix's covariance is multiplied by this (its calibration against "
                                        "measured errors) before fix_sigma_extra_m is added")
    fix_dof: float = P.field(6.0, "degrees of freedom of the WiFi fix likelihood: 0 = Gaussian, > 0 = Student-t "
                                  "(heavy tails for the fingerprint matcher's wrong matches)")
    fix_outlier_prob: float = P.field(0.05, "probability that a WiFi fix is an outlier (robust mixture)")
    init_sigma_extra_m: float = P.field(2.0, "initial cloud: fix covariance inflated by this std per axis (m)")
    reinit_mahalanobis2: float = P.field(40.0, "re-initialise around a fix when every particle's squared Mahalanobis distance exceeds this")
    reinit_fraction: float = P.field(0.5, "fraction of particles redrawn at a re-initialisation")
    inject_fraction: float = P.field(0.15, "at every WiFi fix this fraction of the lowest-weight particles is "
                                           "redrawn around the fix (sensor resetting)")
    inject_mass: float = P.field(0.15, "prior probability mass of the redrawn particles before the fix weighs them "
                                       "(the chance, per fix, that the walker is near the fix rather than where the "
                                       "particles are); the rest keep their relative weights")
    floor_jump_mass: float = P.field(0.1, "on a multi-floor graph, the redrawn particles' prior mass is inject_mass "
                                          "times this when the fix's floor is not the filter's (a floor change "
                                          "by WiFi alone needs consistent fixes); fixes without a floor redraw on "
                                          "the filter's floor")
    # adaptive particle count
    adaptive: bool = P.field(False, "adapt the particle count: KLD-sampling at resampling, the covariance rule at "
                                    "(re)initialisation; False = always n_particles")
    n_min: int = P.field(200, "fewest particles when adaptive")
    n_max: int = P.field(20000, "most particles when adaptive")
    kld_epsilon: float = P.field(0.05, "KLD-sampling bound epsilon (largest K-L divergence of the sample from the "
                                       "binned posterior)")
    kld_delta: float = P.field(0.01, "KLD-sampling bound delta (the bound holds with probability 1 - delta)")
    kld_bin_m: float = P.field(1.0, "KLD bin length along each link (m); a bin is (link, position bin)")
    count_ref_sigma_m: float = P.field(5.0, "covariance rule: n_particles suffice for a Gaussian prior of this std per "
                                            "axis (m)")

    def validate(self) -> None:
        n = type(self).__name__
        P.require(self.n_particles >= 1, n, "n_particles", ">= 1", self.n_particles)
        P.require(0 < self.resample_threshold <= 1, n, "resample_threshold", "in (0, 1]", self.resample_threshold)
        P.require(0 < self.v_min < self.v_max, n, "v_min/v_max", "0 < v_min < v_max", (self.v_min, self.v_max))
        for name in ("sigma_v", "step_scale_sigma", "step_scale_walk", "distance_sigma", "yaw_offset_walk_rad",
                     "fix_sigma_extra_m", "init_sigma_extra_m", "yaw_offset_sigma_rad"):
            P.require(getattr(self, name) >= 0, n, name, ">= 0", getattr(self, name))
        P.require(self.heading_sigma_rad > 0, n, "heading_sigma_rad", "> 0", self.heading_sigma_rad)
        for name in ("p_stop", "p_start", "heading_floor", "u_turn_prob", "fix_outlier_prob", "reinit_fraction",
                     "inject_fraction"):
            P.require(0 <= getattr(self, name) <= 1, n, name, "in [0, 1]", getattr(self, name))
        P.require(self.fix_cov_scale > 0, n, "fix_cov_scale", "> 0", self.fix_cov_scale)
        P.require(self.fix_dof >= 0, n, "fix_dof", ">= 0", self.fix_dof)
        P.require(0 < self.inject_mass < 1, n, "inject_mass", "in (0, 1)", self.inject_mass)
        P.require(0 < self.floor_jump_mass <= 1, n, "floor_jump_mass", "in (0, 1]", self.floor_jump_mass)
        P.require(self.reinit_mahalanobis2 > 0, n, "reinit_mahalanobis2", "> 0", self.reinit_mahalanobis2)
        P.require(1 <= self.n_min <= self.n_max, n, "n_min/n_max", "1 <= n_min <= n_max", (self.n_min, self.n_max))
        P.require(0 < self.kld_epsilon < 1, n, "kld_epsilon", "in (0, 1)", self.kld_epsilon)
        P.require(0 < self.kld_delta < 1, n, "kld_delta", "in (0, 1)", self.kld_delta)
        P.require(self.kld_bin_m > 0, n, "kld_bin_m", "> 0", self.kld_bin_m)
        P.require(self.count_ref_sigma_m > 0, n, "count_ref_sigma_m", "> 0", self.count_ref_sigma_m)


@dataclass
class Particles:
    """Struct of arrays, N particles: ``link (N,) int32``, ``pos (N,)`` metres from the link's
    end 0, ``direction (N,) int8`` (+1 towards end 1, -1 towards end 0), ``speed (N,)`` m/s,
    ``mode (N,) int8`` (:class:`Mode`), ``scale (N,)`` step-length factor, ``yaw_offset (N,)``
    rad (map heading = PDR heading + offset), ``log_w (N,)`` normalised log weights, ``floor_ref
    (N,) int16`` the floor the barometer expects it on (:mod:`indoor_loc.pf.floors`; -1 = its own)."""
    link: np.ndarray
    pos: np.ndarray
    direction: np.ndarray
    speed: np.ndarray
    mode: np.ndarray
    scale: np.ndarray
    yaw_offset: np.ndarray
    log_w: np.ndarray
    floor_ref: np.ndarray = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.floor_ref is None:
            self.floor_ref = np.full(len(self.link), -1, np.int16)

    def __len__(self) -> int:
        return len(self.link)

    def take(self, idx: np.ndarray) -> "Particles":
        return Particles(**{f.name: getattr(self, f.name)[idx].copy() for f in fields(self)})

    def copy(self) -> "Particles":
        return self.take(np.arange(len(self)))

    @property
    def weights(self) -> np.ndarray:
        return np.exp(self.log_w)


# ----------------------------------------------------------------------------------------------
# resampling and estimates
# ----------------------------------------------------------------------------------------------
def systematic_resample(weights: np.ndarray, rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """Indices of a systematic resampling of normalised ``weights`` (Kitagawa 1996): one uniform
    offset, ``n`` evenly spaced points; the last cumulative sum is forced to 1 (round-off guard)."""
    n = len(weights) if n is None else n
    cum = np.cumsum(weights)
    cum[-1] = 1.0
    u = (rng.random() + np.arange(n)) / n
    return np.minimum(np.searchsorted(cum, u, side="right"), len(weights) - 1)


def logsumexp_1d(a: np.ndarray) -> np.floating:
    """``scipy.special.logsumexp(a)`` of a 1-D float64 array, bit for bit: SciPy's own algorithm (the
    maxima taken out of the sum, ``log1p(s / m) + log(m) + max``) without its array-API dispatch,
    which costs more than the sum for the particles' weights (called two or three times per input).
    A non-finite maximum or result is left to SciPy's edge-case handling."""
    a = np.asarray(a)
    if a.ndim != 1 or a.dtype != np.float64 or not len(a):
        return logsumexp(a)
    a_max = np.max(a, axis=(0,), keepdims=True)
    if not np.isfinite(a_max[0]):
        return logsumexp(a)
    mask = a == a_max
    m = np.sum(mask.astype(a.dtype), axis=(0,), keepdims=True, dtype=a.dtype)
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.exp(np.where(mask, -np.inf, a) - a_max)
        s = np.sum(e, axis=(0,), keepdims=True, dtype=e.dtype)
        s = np.where(s == 0, s, s / m)
        out = np.log1p(s) + np.log(m) + a_max
    if not np.isfinite(out[0]):
        return logsumexp(a)
    return out[0]


def effective_sample_size(log_w: np.ndarray) -> float:
    """``N_eff = 1 / Σ W²`` of normalised log weights."""
    return float(np.exp(-logsumexp_1d(2.0 * log_w)))


def normalise_log(log_w: np.ndarray) -> np.ndarray:
    return log_w - logsumexp_1d(log_w)


def particle_xy(g: BuildingGraph, p: Particles) -> np.ndarray:
    """(N, 2) map positions of the particles."""
    length = g.link_len[p.link]
    return g.point_at(p.link, np.divide(p.pos, length, out=np.zeros_like(p.pos), where=length > 0))


def constrained_mean(g: BuildingGraph, xy: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, int, float]:
    """Koivisto et al. 2014, Algorithm 3: the weighted mean projected to the closest link point.
    Returns (xy (2,), link, t in [0, 1])."""
    mean = weights @ xy / weights.sum()
    link, t, _ = g.project(mean[None, :])
    return g.point_at(link, t)[0], int(link[0]), float(t[0])


def kld_bound(k: np.ndarray, epsilon: float, z: float) -> np.ndarray:
    """Fox 2003, eq. 12: particles needed so that, with probability 1 − δ (``z`` its standard
    normal quantile), the K-L divergence between the sample-based and the true binned posterior
    stays below ``epsilon`` when ``k`` bins are occupied (Wilson–Hilferty chi-square)."""
    k1 = np.maximum(np.asarray(k, float) - 1.0, 1.0)
    a = 2.0 / (9.0 * k1)
    return np.where(np.asarray(k) > 1, k1 / (2.0 * epsilon) * (1.0 - a + np.sqrt(a) * z) ** 3, 1.0)


class LinkIndex:
    """Link geometry for fast particle positions and projections: end-0 points ``a`` (L, 2), unit
    directions ``u`` (L, 2) and lengths; a k-d tree over points every ``spacing_m`` along every
    link answers "closest link" by exact projection on the links of the ``k`` nearest points (the
    result is the closest link up to half the spacing in distance; a point is never off a link).
    With ``links`` only these links answer (the level links of one floor)."""

    def __init__(self, g: BuildingGraph, spacing_m: float = 0.5, k: int = 4, *, links: np.ndarray | None = None) -> None:
        self.a = g.node_xyz[g.link_nodes[:, 0], :2].astype(float)
        ab = g.node_xyz[g.link_nodes[:, 1], :2] - self.a
        self.length = g.link_len.astype(float)
        self.u = np.divide(ab, self.length[:, None], out=np.zeros_like(ab), where=self.length[:, None] > 0)
        ids = np.arange(g.n_links) if links is None else np.asarray(links, np.int64)   # the links it answers with
        per_all = np.maximum(np.ceil(self.length / spacing_m).astype(np.int64), 1) + 1
        per = per_all[ids]
        link = np.repeat(ids, per)
        start = np.repeat(np.cumsum(per) - per, per)
        frac = (np.arange(len(link)) - start) / (per_all[link] - 1)
        self._sample_link = link
        self._tree = cKDTree(self.a[link] + (frac * self.length[link])[:, None] * self.u[link])
        self.k = int(min(k, len(link)))

    def xy(self, link: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """(N, 2) map positions at ``pos`` metres from end 0 of ``link``."""
        return self.a[link] + pos[:, None] * self.u[link]

    def project(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest link (N,) int32 and position on it (N,) metres of points (N, 2)."""
        pts = np.atleast_2d(np.asarray(pts, float))
        _, idx = self._tree.query(pts, k=self.k)
        cand = self._sample_link[np.asarray(idx).reshape(len(pts), -1)]            # (N, k)
        ap = pts[:, None, :] - self.a[cand]
        s = np.clip((ap * self.u[cand]).sum(axis=2), 0.0, self.length[cand])
        d = ap - s[..., None] * self.u[cand]
        j = np.argmin((d * d).sum(axis=2), axis=1)
        r = np.arange(len(pts))
        return cand[r, j].astype(np.int32), s[r, j]


def mahalanobis2(d: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distances of offsets ``d`` (N, 2) under a 2 × 2 ``cov`` (closed form)."""
    (a, b), (_, c) = np.linalg.inv(np.asarray(cov, float))
    x, y = d[:, 0], d[:, 1]
    return a * x * x + 2.0 * b * x * y + c * y * y


# ----------------------------------------------------------------------------------------------
class GraphParticleFilter:
    """The TLL particle filter (see the module docstring). Call :meth:`init_gaussian` (or
    :meth:`init_uniform`), then :meth:`predict_pdr` / :meth:`predict_speed` and
    :meth:`update_position` in time order; :meth:`estimate` gives the constrained mean."""

    def __init__(self, graph: BuildingGraph, transitions: Transitions, params: PfParams | None = None) -> None:
        self.g = graph
        self.tr = transitions
        self.params = params or PfParams()
        self.params.validate()
        self.p: Particles | None = None
        self.n_resample = 0
        self.n_reinit = 0
        # (N,) after a WiFi fix: the log density q(x) of the draw that put each particle there when
        # the fix redrew it (sensor resetting), -inf for the particles the motion model moved there;
        # carried through resampling. The smoother's transition density at the fix needs it.
        self.redrawn_log_q: np.ndarray | None = None
        self._heading = graph.link_heading()
        self._kappa = 1.0 / self.params.heading_sigma_rad ** 2
        self.ix = LinkIndex(graph)
        self.floors = FloorGeometry(graph)
        #: per floor, an index of its level links (sample_gaussian on a fix's floor)
        self.ix_floor = {f: LinkIndex(graph, links=np.flatnonzero(~graph.link_vertical & (graph.node_floor[graph.link_nodes[:, 0]] == f)))
                         for f in range(self.floors.n_floors)} if self.floors.n_floors > 1 else {}
        self._kld_z = float(norm.ppf(1.0 - self.params.kld_delta))

    # -- initialisation -------------------------------------------------------------------------
    def _new(self, link: np.ndarray, t: np.ndarray, rng: np.random.Generator, *, yaw_offset_mean: float = 0.0) -> Particles:
        n = len(link)
        pp = self.params
        if pp.yaw_offset_sigma_rad >= np.pi:
            off = rng.uniform(-np.pi, np.pi, n)
        else:
            off = yaw_offset_mean + pp.yaw_offset_sigma_rad * rng.standard_normal(n)
        pos = t * self.g.link_len[link]
        return Particles(link=link.astype(np.int32), pos=pos, floor_ref=self.floors.floor_of(link, pos).astype(np.int16),
                         direction=np.where(rng.random(n) < 0.5, 1, -1).astype(np.int8),
                         speed=rng.uniform(pp.v_min, pp.v_max, n), mode=np.full(n, Mode.MOTION, np.int8),
                         scale=1.0 + pp.step_scale_sigma * rng.standard_normal(n), yaw_offset=off,
                         log_w=np.full(n, -np.log(n)))

    def sample_gaussian(self, mean: np.ndarray, cov: np.ndarray, n: int, rng: np.random.Generator, *,
                        inflate: bool = True, floor: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``n`` points from N(mean, cov + extra²I) (``inflate``; else N(mean, cov): a pose given with its
        own covariance, ``initialpose``) moved to their closest link points: (link, t in [0, 1]); with
        ``floor``, the closest level links of that floor."""
        cov = np.asarray(cov, float) + (self.params.init_sigma_extra_m ** 2 if inflate else 0.0) * np.eye(2)
        pts = rng.multivariate_normal(np.asarray(mean, float), cov, size=n, method="cholesky")
        link, pos = (self.ix if floor is None or floor not in self.ix_floor else self.ix_floor[floor]).project(pts)
        length = self.ix.length[link]
        return link, np.divide(pos, length, out=np.zeros_like(pos), where=length > 0)

    def count_for(self, cov: np.ndarray) -> int:
        """Particles for a (re)initialisation from a Gaussian of covariance ``cov`` (+ extra²I):
        ``n_particles`` when not adaptive, else Raitoharju et al. 2015 eq. 63 in two dimensions,
        ``n_particles · √det P / σ_ref²`` (equal particle density over the probability ellipse), clamped to
        [n_min, n_max]."""
        pp = self.params
        if not pp.adaptive:
            return pp.n_particles
        c = np.asarray(cov, float) + pp.init_sigma_extra_m ** 2 * np.eye(2)
        n = pp.n_particles * np.sqrt(max(np.linalg.det(c), 0.0)) / pp.count_ref_sigma_m ** 2
        return int(np.clip(np.ceil(n - 1e-9), pp.n_min, pp.n_max))

    def init_gaussian(self, mean: np.ndarray, cov: np.ndarray, rng: np.random.Generator, *, inflate: bool = True,
                      floor: int | None = None) -> None:
        """Particles from a Gaussian position prior (e.g. the first WiFi fix, inflated by ``init_sigma_extra_m``;
        an ``initialpose`` as given: ``inflate`` False), projected on links (of ``floor`` when given)."""
        link, t = self.sample_gaussian(mean, cov, self.count_for(cov), rng, inflate=inflate, floor=floor)
        self.p = self._new(link, t, rng)

    def reinit_gaussian(self, mean: np.ndarray, cov: np.ndarray, keep_fraction: float, rng: np.random.Generator, *,
                        floor: int | None = None) -> None:
        """Re-initialise around a reference estimate N(mean, cov) (Raitoharju et al. 2015, Sec. 5.2):
        ``keep_fraction`` of the new set are the old particles resampled by weight (in case the
        reference is the one that is wrong), the rest are drawn from the reference and projected on
        the graph; the count follows :meth:`count_for`; weights uniform."""
        p = self.p
        assert p is not None
        n = self.count_for(cov)
        k_keep = int(round(keep_fraction * n))
        link, t = self.sample_gaussian(mean, cov, n - k_keep, rng, floor=floor)
        fresh = self._new(link, t, rng)
        if self.params.yaw_offset_sigma_rad < np.pi and len(fresh):
            fresh.yaw_offset = rng.choice(p.yaw_offset, len(fresh))          # keep the learnt heading offsets
        if k_keep:
            old = p.take(systematic_resample(p.weights, rng, k_keep))
            fresh = Particles(**{f.name: np.concatenate([getattr(old, f.name), getattr(fresh, f.name)])
                                 for f in fields(p)})
        fresh.log_w = np.full(len(fresh), -np.log(len(fresh)))
        self.p = fresh
        self.n_reinit += 1

    def min_deviance(self, mean: np.ndarray, cov: np.ndarray, weight_floor: float = 1e-3) -> float:
        """Raitoharju et al. 2015 eq. 64: the smallest squared Mahalanobis distance, under a
        reference N(mean, cov), of the particles carrying weight (above ``weight_floor / N``)."""
        p = self.p
        assert p is not None
        keep = p.log_w >= np.log(weight_floor / len(p))
        d = self.xy()[keep] - np.asarray(mean, float)
        return float(mahalanobis2(d, cov).min()) if len(d) else float("inf")

    def xy(self) -> np.ndarray:
        """(N, 2) map positions of the particles."""
        p = self.p
        assert p is not None
        return self.ix.xy(p.link, p.pos)

    def init_uniform(self, rng: np.random.Generator) -> None:
        """Particles uniform over the link length (global localisation)."""
        n = self.params.n_particles
        cum = np.cumsum(self.g.link_len)
        link = np.minimum(np.searchsorted(cum, rng.random(n) * cum[-1], side="right"), self.g.n_links - 1)
        self.p = self._new(link, rng.random(n), rng)

    @property
    def initialised(self) -> bool:
        return self.p is not None

    # -- motion ---------------------------------------------------------------------------------
    def _travel_heading(self, link: np.ndarray, direction: np.ndarray) -> np.ndarray:
        return self._heading[link] + np.where(direction > 0, 0.0, np.pi)

    def _heading_lik(self, travel: np.ndarray, heading: np.ndarray) -> np.ndarray:
        """Heading likelihood of travelling along ``travel`` when the walker's heading is ``heading``."""
        f = self.params.heading_floor
        return (1.0 - f) * np.exp(self._kappa * (np.cos(travel - heading) - 1.0)) + f

    def _move(self, dist: np.ndarray, rng: np.random.Generator, heading: np.ndarray | None) -> np.ndarray:
        """Move every particle ``dist`` (N,) metres along the graph in its direction, drawing the
        next link at every node (guided by ``heading`` when given). Returns the log-weight
        correction (N,) of the guided choices (0 without heading). Vectorised: each loop round
        handles all particles that still have distance left; rounds = most nodes any particle
        crosses in this step."""
        g, p, tr = self.g, self.p, self.tr
        assert p is not None
        remaining = np.maximum(np.asarray(dist, float), 0.0).copy()
        corr = np.zeros(len(p))
        active = np.flatnonzero(remaining > 0)
        for _ in range(10_000):
            if len(active) == 0:
                break
            lk = p.link[active]
            length = g.link_len[lk]
            d = p.direction[active]
            room = np.where(d > 0, length - p.pos[active], p.pos[active])
            step = np.minimum(room, remaining[active])
            p.pos[active] += d * step
            remaining[active] -= step
            arrive = active[remaining[active] > 1e-12]
            if len(arrive) == 0:
                break
            # node reached: which end, which adjacency slot we arrive over
            lk = p.link[arrive]
            end = (p.direction[arrive] > 0).astype(np.intp)
            node = g.link_nodes[lk, end]
            start = g.adj_ptr[node]
            deg = g.adj_ptr[node + 1] - start
            # arriving slot: the slot at `node` whose link is lk (scan the node's few slots)
            dmax = tr.probs.shape[1]
            cols = np.arange(dmax)[None, :]
            slots = np.minimum(start[:, None] + cols, len(g.adj_link) - 1)
            match = (g.adj_link[slots] == lk[:, None]) & (cols < deg[:, None])
            s_in = start + np.argmax(match, axis=1)
            probs = tr.probs[s_in]                                   # (n, D)
            cand_link = g.adj_link[slots]
            cand_end = g.adj_end[slots]
            if heading is not None:
                travel = self._heading[cand_link] + np.where(cand_end == 0, 0.0, np.pi)
                lik = self._heading_lik(travel, heading[arrive][:, None])
                q = probs * lik
                z = q.sum(axis=1)
                corr[arrive] += np.log(np.maximum(z, 1e-300))
                q /= np.maximum(z, 1e-300)[:, None]
            else:
                q = probs
            cdf = np.cumsum(q, axis=1)
            cdf[np.arange(len(arrive)), deg - 1] = 1.0
            u = rng.random(len(arrive))
            j = np.minimum((u[:, None] > cdf).sum(axis=1), deg - 1)
            new_link = cand_link[np.arange(len(arrive)), j]
            new_end = cand_end[np.arange(len(arrive)), j]            # the new link's end at `node`
            p.link[arrive] = new_link
            p.direction[arrive] = np.where(new_end == 0, 1, -1).astype(np.int8)
            p.pos[arrive] = np.where(new_end == 0, 0.0, g.link_len[new_link])
            active = arrive
        return corr

    def predict_pdr(self, distance_m: float, heading_rad: float, rng: np.random.Generator, *,
                    distance_sd_m: float | None = None, yaw_walk_rad: float | None = None) -> None:
        """One PDR interval: walked ``distance_m`` ending with walking heading ``heading_rad``
        (odom frame; each particle adds its own offset). Zero distance: nothing moves. A robot's
        odometry increment gives its own noise: ``distance_sd_m`` (m, instead of ``distance_sigma``)
        and ``yaw_walk_rad`` (the heading offset's random walk, rad, instead of ``yaw_offset_walk_rad``)."""
        p, pp = self.p, self.params
        assert p is not None
        n = len(p)
        z3 = rng.standard_normal((3, n))
        p.yaw_offset += (pp.yaw_offset_walk_rad if yaw_walk_rad is None else yaw_walk_rad) * z3[0]
        if distance_m <= 0:
            return
        p.scale += pp.step_scale_walk * np.sqrt(distance_m) * z3[1]
        np.clip(p.scale, 0.5, 1.6, out=p.scale)
        if distance_sd_m is None:
            dist = distance_m * p.scale * (1.0 + pp.distance_sigma / np.sqrt(max(distance_m, 1e-3)) * z3[2])
        else:
            dist = distance_m * p.scale + distance_sd_m * z3[2]
        heading = heading_rad + p.yaw_offset
        # U-turn on the link, guided by the heading (travelling back: cos(Δ + π) = −cos Δ)
        c = np.cos(self._travel_heading(p.link, p.direction) - heading)
        f = pp.heading_floor
        a = (1.0 - pp.u_turn_prob) * ((1.0 - f) * np.exp(self._kappa * (c - 1.0)) + f)
        b = pp.u_turn_prob * ((1.0 - f) * np.exp(self._kappa * (-c - 1.0)) + f)
        z = a + b
        turn = rng.random(n) < b / z
        p.direction = np.where(turn, -p.direction, p.direction).astype(np.int8)
        # guided choices: the direction on the current link (z) and the link at every node crossed
        log_corr = np.log(z) + self._move(dist, rng, heading)
        p.log_w = normalise_log(p.log_w + log_corr)
        p.mode[:] = Mode.MOTION

    def predict_speed(self, dt_s: float, rng: np.random.Generator) -> None:
        """Two-mode speed model over ``dt_s`` seconds (Koivisto et al. 2014, eq. 10–11, Algorithm 2)."""
        p, pp = self.p, self.params
        assert p is not None
        if dt_s <= 0:
            return
        n = len(p)
        u = rng.random(n)
        stop = (p.mode == Mode.MOTION) & (u < 1 - (1 - pp.p_stop) ** dt_s)
        start = (p.mode == Mode.STATIC) & (u < 1 - (1 - pp.p_start) ** dt_s)
        p.mode[stop] = Mode.STATIC
        p.mode[start] = Mode.MOTION
        p.speed[start] = rng.uniform(pp.v_min, pp.v_max, int(start.sum()))
        p.direction[start] = np.where(rng.random(int(start.sum())) < 0.5, 1, -1).astype(np.int8)
        moving = p.mode == Mode.MOTION
        q = pp.sigma_v ** 2 * np.array([[dt_s ** 3 / 3, dt_s ** 2 / 2], [dt_s ** 2 / 2, dt_s]])
        noise = rng.standard_normal((n, 2)) @ np.linalg.cholesky(q + 1e-12 * np.eye(2)).T
        s = np.where(moving, dt_s * p.speed + noise[:, 0], 0.0)
        p.speed = np.where(moving, np.clip(p.speed + noise[:, 1], pp.v_min, pp.v_max), 0.0)
        self._move(np.maximum(s, 0.0), rng, None)

    # -- measurement ----------------------------------------------------------------------------
    def update_position(self, mean: np.ndarray, cov: np.ndarray, rng: np.random.Generator, *,
                        floor: tuple[int, float] | None = None, inject_floor: int | None = None) -> bool:
        """WiFi position fix ``N(r | mean, cov + extra²I)`` with an outlier mixture (eq. 13).
        When every particle is far from the fix (squared Mahalanobis distance above
        ``reinit_mahalanobis2``) the filter has diverged: a ``reinit_fraction`` of the particles is
        redrawn around the fix. ``floor``: the fix's floor and the probability it is wrong
        (:meth:`FloorGeometry.fix_floor`): particles are weighed by it and redrawn on it (on
        ``inject_floor`` when given, e.g. the floor a barometer vouches for, both by sensor resetting
        and by a re-initialisation). Returns True if re-initialised."""
        p, pp = self.p, self.params
        assert p is not None
        self.redrawn_log_q = None
        mean = np.asarray(mean, float)
        S = pp.fix_cov_scale * np.asarray(cov, float) + pp.fix_sigma_extra_m ** 2 * np.eye(2)
        xy = self.xy()
        m2 = mahalanobis2(xy - mean, S)
        n = len(p)
        reinit = bool(m2.min() > pp.reinit_mahalanobis2)
        if reinit:
            self.n_reinit += 1
            k = int(round(pp.reinit_fraction * n))
            idx = rng.choice(n, size=k, replace=False)
            on = None
            if self.floors.n_floors > 1:        # the floor a barometer vouches for, else the fix's
                on = inject_floor if inject_floor is not None else (
                    floor[0] if floor is not None else self.estimate_floor()[0])
            link, t = self.sample_gaussian(mean, cov, k, rng, floor=on)
            fresh = self._new(link, t, rng)
            for f in fields(p):
                if f.name != "log_w":
                    getattr(p, f.name)[idx] = getattr(fresh, f.name)
            if self.params.yaw_offset_sigma_rad < np.pi:
                p.yaw_offset[idx] = rng.choice(p.yaw_offset, k)       # keep the learnt heading offsets
            p.log_w = np.full(n, -np.log(n))
            m2[idx] = mahalanobis2(self.ix.xy(p.link[idx], p.pos[idx]) - mean, S)
        elif pp.inject_fraction > 0:
            # sensor resetting (Lenser & Veloso 2000; the augmented MCL of Thrun et al.,
            # Probabilistic Robotics §8.3.5): the least likely particles are redrawn around the fix
            # so a filter that started from an outlier fix or fell behind the walker can jump to
            # where the WiFi says it is; the likelihood below weighs them (their prior mass is
            # inject_mass, see inject()).
            k = self.inject_count()
            if k:
                mass = pp.inject_mass
                on = None
                if self.floors.n_floors > 1:
                    current = self.estimate_floor()[0]
                    on = current if floor is None else floor[0]
                    on = on if inject_floor is None else inject_floor
                    if on != current:
                        mass *= pp.floor_jump_mass
                idx = self.inject(*self.sample_gaussian(mean, cov, k, rng, floor=on), rng, mass=mass)
                m2[idx] = mahalanobis2(self.ix.xy(p.link[idx], p.pos[idx]) - mean, S)
                # the density they were drawn from (sample_gaussian's, in the plane)
                draw = np.asarray(cov, float) + pp.init_sigma_extra_m ** 2 * np.eye(2)
                self.redrawn_log_q = np.full(n, -np.inf)
                self.redrawn_log_q[idx] = (-0.5 * mahalanobis2(self.ix.xy(p.link[idx], p.pos[idx]) - mean, draw)
                                           - np.log(2 * np.pi) - 0.5 * np.log(np.linalg.det(draw)))
        log_l = self._fix_log_likelihood(m2, S)
        if floor is not None:
            log_l = log_l + self.floors.fix_log_likelihood(self.floors.floor_of(p.link, p.pos), *floor)
        p.log_w = normalise_log(p.log_w + log_l)
        return reinit

    def _fix_log_likelihood(self, m2: np.ndarray, S: np.ndarray) -> np.ndarray:
        """Robust fix likelihood: the density below mixed with an outlier uniform over 50 m x 50 m."""
        pp = self.params
        return np.logaddexp(np.log1p(-pp.fix_outlier_prob) + self._fix_log_density(m2, S),
                            np.log(pp.fix_outlier_prob / 2500.0))

    def _fix_log_density(self, m2: np.ndarray, S: np.ndarray) -> np.ndarray:
        """Log density of a fix at squared Mahalanobis distances ``m2`` under ``S``: Gaussian, or the
        bivariate Student-t of ``fix_dof`` degrees of freedom and scale matrix ``S``."""
        nu = self.params.fix_dof
        half_logdet = 0.5 * np.log(np.linalg.det(S))
        if nu <= 0:
            return -0.5 * m2 - np.log(2 * np.pi) - half_logdet
        return (gammaln(0.5 * (nu + 2)) - gammaln(0.5 * nu) - np.log(nu * np.pi) - half_logdet
                - 0.5 * (nu + 2) * np.log1p(m2 / nu))

    def inject_count(self) -> int:
        """How many particles a sensor resetting redraws (``inject_fraction`` of them)."""
        return int(round(self.params.inject_fraction * len(self.p))) if self.p is not None else 0

    def inject(self, link: np.ndarray, t: np.ndarray, rng: np.random.Generator, *, mass: float | None = None) -> np.ndarray:
        """Sensor resetting: the ``len(link)`` lowest-weight particles move to the given link
        positions (t in [0, 1]) with a random direction, another particle's step-length factor and
        heading offset. Together they carry the prior mass ``inject_mass`` (a mixture prior:
        "tracked" with 1 − mass, "near the measurement" with mass), so one outlying measurement
        cannot move the estimate by itself: the redrawn particles win only when the measurement
        is far more likely there than at the tracked particles, and consecutive measurements that
        agree compound. Returns their indices."""
        p = self.p
        assert p is not None
        n, k = len(p), len(link)
        idx = np.argpartition(p.log_w, k - 1)[:k]
        donors = rng.integers(0, n, k)
        p.link[idx] = link
        p.pos[idx] = t * self.ix.length[link]
        p.direction[idx] = np.where(rng.random(k) < 0.5, 1, -1)
        p.scale[idx] = p.scale[donors]
        p.yaw_offset[idx] = p.yaw_offset[donors]
        p.floor_ref[idx] = self.floors.floor_of(p.link[idx], p.pos[idx])
        mass = self.params.inject_mass if mass is None else mass
        if k < n:
            kept = np.ones(n, bool)
            kept[idx] = False
            p.log_w[kept] = normalise_log(p.log_w[kept]) + np.log1p(-mass)
            p.log_w[idx] = np.log(mass / k)
        else:
            p.log_w[:] = -np.log(n)
        return idx

    def update_log_likelihood(self, log_l: np.ndarray) -> None:
        """Multiply the weights by a per-particle likelihood given as logs (N,)."""
        p = self.p
        assert p is not None
        p.log_w = normalise_log(p.log_w + np.asarray(log_l, float))

    def kld_count(self, idx: np.ndarray) -> int:
        """How many of the resampled particles ``idx`` (in random order) the KLD bound asks for:
        the first ``n`` such that ``n >= bound(k_n)``, ``k_n`` the bins occupied by the first ``n``
        (Fox 2003, Table 1, evaluated for all prefixes at once); within [n_min, n_max]."""
        p, pp = self.p, self.params
        assert p is not None
        nbin = np.ceil(self.ix.length.max() / pp.kld_bin_m) + 1
        b = p.link[idx].astype(np.int64) * int(nbin) + (p.pos[idx] / pp.kld_bin_m).astype(np.int64)
        _, first = np.unique(b, return_index=True)
        new = np.zeros(len(b), np.int64)
        new[first] = 1
        k = np.cumsum(new)
        ok = np.arange(1, len(b) + 1) >= np.maximum(kld_bound(k, pp.kld_epsilon, self._kld_z), pp.n_min)
        return int(np.argmax(ok)) + 1 if ok.any() else len(b)

    def maybe_resample(self, rng: np.random.Generator) -> bool:
        """Systematic resampling when ``N_eff`` is below the threshold; with ``adaptive`` the new
        count follows the KLD bound (:meth:`kld_count`)."""
        p, pp = self.p, self.params
        assert p is not None
        if effective_sample_size(p.log_w) >= pp.resample_threshold * len(p):
            return False
        if pp.adaptive:
            idx = rng.permutation(systematic_resample(p.weights, rng, pp.n_max))
            idx = idx[:self.kld_count(idx)]
        else:
            idx = systematic_resample(p.weights, rng)
        self.p = p.take(idx)
        self.p.log_w = np.full(len(idx), -np.log(len(idx)))
        if self.redrawn_log_q is not None:
            self.redrawn_log_q = self.redrawn_log_q[idx]
        self.n_resample += 1
        return True

    # -- estimate ---------------------------------------------------------------------------------
    def estimate(self, xy: np.ndarray | None = None, floor: int | None = None) -> tuple[np.ndarray, np.ndarray, float]:
        """Constrained mean (2,), the particle cloud's weighted covariance (2, 2) and the
        weighted circular mean of the direction of travel (rad). ``xy`` (:meth:`xy`) and ``floor``
        (:meth:`estimate_floor`'s) when the caller has them already for the particles as they are."""
        p = self.p
        assert p is not None
        w = p.weights
        xy = self.xy() if xy is None else xy
        if self.floors.n_floors > 1:               # the constrained mean on the most probable floor
            fl = self.estimate_floor()[0] if floor is None else floor
            on = self.floors.floor_of(p.link, p.pos) == fl
            mean = w[on] @ xy[on] / w[on].sum()
            link, t, _ = self.g.project(mean[None, :], floor=fl)
            mean_xy = self.g.point_at(link, t)[0]
        else:
            mean_xy, _, _ = constrained_mean(self.g, xy, w)
        d = xy - w @ xy
        cov = (w[:, None] * d).T @ d + 1e-6 * np.eye(2)
        trav = self._travel_heading(p.link, p.direction)
        yaw = float(np.arctan2(w @ np.sin(trav), w @ np.cos(trav)))
        return mean_xy, cov, yaw

    def estimate_floor(self) -> tuple[int, float, float]:
        """The most probable floor (index into the graph's floors, by summed weight), its height (m)
        and the variance of the particles' floor heights about it (m²)."""
        p = self.p
        assert p is not None
        fl = self.floors.floor_of(p.link, p.pos)
        mass = np.bincount(fl, weights=p.weights, minlength=self.floors.n_floors)
        k = int(np.argmax(mass))
        z = float(self.floors.fz[k])
        return k, z, float(mass @ (self.floors.fz - z) ** 2)
