"""Powed-representation k-NN fingerprinting with reading ages, AP weighting and floor detection.

Representation and distance (Torres-Sospedra et al., "Comprehensive analysis of distance and
similarity measures for Wi-Fi fingerprinting indoor positioning systems", Expert Systems with
Applications 42, 2015, §3.1–3.2 — the *powed* data representation with the *Sørensen* distance was
among the best on every database they compared, and needs no per-building tuning):

    pos_a   = max(r_a − floor_dbm, 0) / (−floor_dbm)          positive representation, 0 = not heard
    powed_a = pos_a ** beta                                   beta = e (their choice)
    D(x, y) = Σ_a |x_a − y_a| / Σ_a (x_a + y_a)               Sørensen (Bray–Curtis), in [0, 1]

so every AP heard by either scan counts (an AP missing on one side is a difference, not ignored),
and a strong AP weighs far more than a weak one (strong readings vary least with the phone's
orientation and body shadowing). ``D = 1 − 2 Σ_shared min(x_a, y_a) / (Σx + Σy)``: the shared sum
runs through an inverted AP → map-readings index, as in :mod:`indoor_loc.wifi.wknn`.

Two weights multiply each reading's value:

- **age** — a cached result (``age_ms`` > 0: the phone reports an older measurement taken where
  the user was seconds ago) is a weaker witness of *this* position: weight ``exp(−age / age_tau_ms)``
  on the query's readings and on the map's (the map's positions are the scans' own; an old map
  reading belongs elsewhere). Unknown ages (NaN, PUTMC) weigh 1. How much a cached reading is still
  worth depends on how fast the user walked and how often the phone sweeps, which a scan does not
  say; with ``age_views`` 'both' the position is the mean of two k-NN estimates, one with the age
  weights and one with ages ignored (an equal-weight average over the two hypotheses). On ms_site2
  the age weights alone win on some walks and lose on others (B1: the walks of the second survey
  day lose 2–5 m with them — they were walked slower, 0.95 against 1.22 m/s, so a cached reading was
  measured nearer to where the phone is; over B1's test walks the walking speed predicts the loss,
  though not on the other floors); the average is better than either on three floors of four.
- **AP informativeness** — an AP heard by nearly every map scan (a mall-wide network) says little
  about where one is: ``w_a = sqrt(ln(1 + M / n_a))`` (n_a = map scans hearing AP a; the inverse
  document frequency of text retrieval, Sparck Jones 1972). APs unknown to the map are ignored.

**Device offset**: phones differ by several dB in the RSS they report for the same signal, and
the powed representation is absolute. After each fix the median difference between the scan and
its weighted neighbours over the APs they all heard nudges a per-phone offset (``offset_gain`` of
it per scan), which corrects the next scans. On ms_site2 (one phone model) test scans shifted by
8 dB lose 1–3 m of mean error without it and recover most of it with it.

**Interpolated radio map** (``smooth_m`` > 0, the default): survey walks leave gaps between them
and every single scan is noisy (body shadowing, orientation, a cached reading repeated from the
previous scan), so the matching runs against a grid of candidate positions (``smooth_grid_m``
apart, within ``smooth_reach_m`` of a map scan of the same floor) whose values are the
Nadaraya–Watson kernel regression of the map scans' weighted powed values (Nadaraya, "On estimating
regression", 1964; Watson, "Smooth regression analysis", 1964) with a Gaussian kernel of bandwidth
``smooth_m`` over the same floor's scans — the mean of a Gaussian-process radio map with a
squared-exponential kernel in the limit of large noise (Ferris, Hähnel & Fox, "Gaussian processes
for signal strength-based location estimation", RSS 2006). Nearby walks are averaged, and a test
walk between two survey walks finds candidates between them. A bandwidth of a few metres is the
decorrelation distance of indoor shadowing. The ``smooth_k`` best grid candidates are averaged.
Interpolation also blurs: with ``smooth_views`` 'both' (the default) the fix is the equal-weight mean
of the estimates against the map scans themselves (``k`` nearest) and against the grid, for each age
view — as with the ages, two hypotheses on the right spatial scale of the map, neither of which is
best everywhere. On ms_site2 (choices made on floors B1 and F7) the mean error against the plain
WKNN's falls from 0.94 to 0.85 on B1 and from 0.61 to 0.60 on F7; on the held-out floors from 0.94
to 0.90 (F3) and stays 0.70 (F8).

**Extrapolation** (``field_weight`` > 0; 0 by default, ``indoor-loc import ms-indoor`` sets 0.05 with its floor
plans): kernel regression copies the nearest survey
scans away from the walks, so a wider grid only adds look-alikes. With a per-AP log-distance path-loss
prior (:mod:`indoor_loc.wifi.radio_field`) the grid's values tend from the kernel regression near the
walks to the propagation model's expected powed values far from them, and the grid may reach where the
survey did not go (``smooth_reach_m``). The calibration's folds fit the prior again without their
walks (a prior fitted on every scan leaks the left-out walk into its own cross-validation: on ms_site2
F3 the cross-validated mean error read 12.9 m instead of 13.9 m and the 95 % ellipse held 70 % of the
test truths instead of 79 %). The grid should extend only where people can be: given a walkable area
(``walkable``, e.g. a floor plan's free space) it covers those points up to ``field_reach_m`` from the
map scans (ms_site2 with its GeoJSON plans, against the plain WKNN: B1 0.850 → 0.822, F3 0.905 → 0.855,
F7 0.595 → 0.584, F8 0.705 → 0.703; B1/F7 tuned, F3/F8 run once per design decision). Without a plan a
wider ``smooth_reach_m`` also offers positions where nobody can be: on PUTMC, whose survey covers the
corridors, a 10 m reach costs 2.58 → 3.40 m, so the field stays off without a plan.
With the extrapolating grid the estimates against the map scans can only answer positions on the survey,
while the grid's can lie beyond it, where no map scan is: averaging the two with equal weights pulls a user
off the survey halfway back to the nearest surveyed stretch. With ``field_survey_share`` (the default) the
map scans' estimates weigh by the share of the grid estimates' weight on grid points within
``smooth_reach_m`` of a map scan (the points a grid without the field would have): 1 where the grid
agrees the user is on the survey (the equal-weight mean as before), 0 where it puts the user entirely
beyond it. On ms_site2's tuned floors with a third of the survey walks left out in turn (their scans and
the test walks' positioned against the rest), the scans more than 3 m from every remaining map scan go
from 15.34 to 14.08 m (B1) and 23.40 to 22.35 m (F7) mean error, those within 3 m from 5.52 to 5.60 m and
3.61 to 3.78 m; on the documented split B1 0.822 → 0.806 and F7 0.584 → 0.589 of the plain WKNN, and
on the held-out floors (run once) F3 0.855 → 0.830 and F8 0.703 → 0.715.

Position: the similarity-weighted mean of the k nearest map scans (or grid candidates), weights 1 / (D + epsilon)
(as WKNN, Nowicki & Skrzypczyński 2019, eq. 13). A scan that shares no AP with the map gets no fix
(reason ``no_shared_aps``); one with no usable reading ``no_usable_aps``.

**Floor detection** (a map whose scans carry several floor heights ``z_m``): every AP has a
*home floor*, the floor where the map hears it strongest (the largest weighted value among that
floor's scans) — APs are mounted on a floor and a slab attenuates them by 10–20 dB. A scan's
readings vote for their APs' home floors with their weighted values, ``s_f = Σ_{a: home(a) = f} x_a``;
the floor with the most votes is chosen and the position uses that floor's scans only.
``Fix.z`` = the floor's height, ``info["floor_p"]`` = the vote shares per height,
``info["floor"]`` the floor's name when the map names it, ``Fix.z_var`` = Σ p_f (z_f − z)².
On ms_site2 (four floors, 954 test scans) this is right for 953; the nearest map scans' vote was
right for 934–940 and a per-floor field ceiling (Σ_a min(x_a, C_f(a))) for 942 — both fail where a
test walk enters a part of its floor the survey walks did not cover but the floor above did.

"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from indoor_loc.errors import MapError
from indoor_loc.measurements import Fix
from indoor_loc.wifi.powed_knn_cov import CovarianceCalibration, fix_features
from indoor_loc.wifi.powed_knn_params import PowedKnnParams
from indoor_loc.wifi.powed_repr import age_weight, powed, scaled_columns, smoothing_grid, sorensen
from indoor_loc.wifi.radio_field import (FIELD_MIN_VALUE, Walkable, detect_level, fit_floor_models, prior_values,
                                         view_scale, walkable_mask, within_reach)
from indoor_loc.wifi.types import ApIndex, ApReadings, Positioner, RadioMap, WifiScan

@dataclass
class _View:
    """One k-NN estimate averaged into the fix: which map values, against which candidates."""
    parts: list[tuple[ApReadings, np.ndarray, np.ndarray]]   # per floor (grid) or all map scans: readings,
    #                                                  their value sums, their rows among the view's candidates
    aged: bool                                       # the query's readings weigh by their age
    values: int                                      # index of the map values (PowedKnn._vals)
    grid: bool                                       # candidates: the grid (else the map scans)
    twin: bool = False                               # ages ignored, and an aged view on the same candidates exists


class PowedKnn(CovarianceCalibration, Positioner):
    """Powed/Sørensen k-NN with ages, AP weights, an interpolated map and floor detection (see module
    docstring)."""
    name = "powed"

    def __init__(self, params: PowedKnnParams | None = None, *, walkable: Walkable | None = None) -> None:
        self.params = params or PowedKnnParams()
        self.params.validate()
        #: where people can be: (xy (N, 2) m, floor height z m) -> (N,) bool, e.g. from a floor plan; with
        #: field_weight > 0 the grid covers these points up to field_reach_m from the map scans
        self.walkable = walkable
        self.radio_map: RadioMap | None = None
        self.aps = ApIndex()
        self._w = np.zeros(0)                        # (A,) AP weights
        self._pos = np.zeros((0, 2))                # (M + C, 2) candidates: the map scans, then the grid
        self._z = np.zeros(0)
        self._n_map = 0                              # M
        self._grid_pos = np.zeros((0, 2))           # (C, 2) smoothing grid (empty without smoothing)
        self._kernel: Any = None                     # (C, M) sparse smoothing weights (None: no grid)
        self._near: Any = None                       # (C, M) sparse: map scans within smooth_reach_m
        self._kernel_den: Any = None                 # (C,) kernel row sums over all scans
        self._off: np.ndarray | None = None          # (M + C,) grid points beyond smooth_reach_m (field_survey_share)
        self._kernel_sums: list[Any] | None = None   # kernel @ values per _vals over all scans (kept while calibrating)
        self._kernel_csc: Any = None                 # the kernel by columns (map scans), for leaving scans out
        self._prior: Any = None                      # (C, A) sparse raw path-loss prior (field_weight > 0)
        self._prior_scale: list[np.ndarray] = []     # per _vals (A,) raw powed -> the values' scale
        self._prior_raw: Any = None                  # (C, A) sparse raw prior of the whole map's models
        self._field_floors = np.zeros(0)
        self._field_detect = 0.0
        self._grid_z = np.zeros(0)
        self._vals: list[np.ndarray] = []            # (M, A) weighted map values: ages weighted, ages ignored
        self._views: list[_View] = []
        self._map_views_equal = True                 # the map has no ages: its values are the same in every view
        self._floors: np.ndarray = np.zeros(0)
        self._floor_names: dict[float, str] = {}
        self._home = np.zeros(0, np.int64)           # (A,) index of each AP's home floor (-1: never heard)
        self.sigma_table = (np.zeros(1), np.full(1, self.params.cov_floor_m))   # (score bin centres, sigma per bin)
        #: cov_strata 'tables': (recent, older) tables: fixes matched to map scans recorded within cov_recent_s of
        #: the scan, the others
        self.sigma_tables: tuple[tuple[np.ndarray, np.ndarray], ...] = ()
        #: cov_strata 'factor': (recent, older) factors on sigma_table's sigma
        self.sigma_factors: tuple[float, ...] = ()
        #: the score's coefficients on (1, cov_columns(quantities)): its prediction of the log error (empty: the
        #: score is the best-match distance itself)
        self.cov_coef = np.zeros(0)
        self.calibration: dict[str, Any] = {}
        self._last_query = (np.zeros(0, np.int64), np.zeros(0))
        self._last_features: dict[str, float] = {}       # per-fix quantities of the last estimate (_features)
        self._cv_features: dict[str, np.ndarray] = {}     # the same per cross-validated scan, with its error
        self.offset_db = 0.0                          # online device RSS offset (state; reset() clears it)

    def fit(self, radio_map: RadioMap) -> "PowedKnn":
        p = self.params
        rss = np.asarray(radio_map.rssi_dbm, float)
        pos = np.asarray(radio_map.positions, float)
        if pos.ndim != 2 or pos.shape[1] != 2 or rss.shape != (len(pos), len(radio_map.bssids)):
            raise MapError(f"powed: radio map expected positions (M, 2) and rssi (M, A), got {pos.shape}, {rss.shape}")
        if len(pos) == 0:
            raise MapError("powed: the radio map has no scans")
        raw = powed(rss, p.floor_dbm, p.beta)
        aged = p.age_tau_ms > 0                      # query readings weigh by their age (map's too, when known)
        val = raw * age_weight(radio_map.age_ms, p.age_tau_ms) if radio_map.age_ms is not None else raw
        heard = val > 0
        n_a = heard.sum(axis=0)
        if p.ap_weighting == "idf":
            w = np.sqrt(np.log1p(len(pos) / np.maximum(n_a, 1)))
        else:
            w = np.ones(len(n_a))
        val = val * w[None, :]
        self._map_views_equal = radio_map.age_ms is None
        self._vals = [val]
        two = aged and p.age_views == "both"
        if two and not self._map_views_equal:
            self._vals.append(raw * w[None, :])
        # raw powed -> each view's scale, for the path-loss prior (field_weight > 0)
        self._prior_scale = [view_scale(v, raw) for v in self._vals] if p.field_weight > 0 else []
        del raw, heard                                   # (M, A) each: no longer needed
        # (aged, values index, twin) per age view
        age_views = [(aged, 0, False)] + ([(False, len(self._vals) - 1, self._map_views_equal)] if two else [])
        self.radio_map = radio_map
        self.aps = ApIndex(radio_map.bssids)
        self._w = w
        map_z = np.asarray(radio_map.z_m, float)
        self._floors = np.unique(map_z)
        self._floor_names = {float(z): str(name) for name, z in radio_map.floors.items()}
        ceiling = np.array([val[map_z == z].max(axis=0) for z in self._floors]).reshape(len(self._floors), -1)
        self._home = np.where(ceiling.max(axis=0) > 0, ceiling.argmax(axis=0), -1) if len(ceiling) else \
            np.zeros(0, np.int64)
        self._n_map = len(pos)
        self._views = []
        if p.smooth_m == 0 or p.smooth_views == "both":
            for a, j, twin in age_views:
                v = self._vals[j]
                self._views.append(_View([(ApReadings(v > 0, v), v.sum(axis=1), np.arange(len(pos)))], a, j,
                                         False, twin))
        self._grid_pos, grid_z, self._kernel, self._near = np.zeros((0, 2)), np.zeros(0), None, None
        self._kernel_den = self._kernel_csc = self._kernel_sums = None
        if p.smooth_m > 0:
            plan = p.field_weight > 0 and self.walkable is not None and p.field_reach_m > p.smooth_reach_m
            self._grid_pos, grid_z, self._kernel, self._near = smoothing_grid(
                pos, map_z, p.smooth_grid_m, p.field_reach_m if plan else p.smooth_reach_m, p.smooth_m)
            if plan:                                     # beyond smooth_reach_m only where people can be
                assert self.walkable is not None
                keep = within_reach(self._grid_pos, grid_z, pos, map_z, p.smooth_reach_m) | \
                    walkable_mask(self.walkable, self._grid_pos, grid_z)
                self._grid_pos, grid_z = self._grid_pos[keep], grid_z[keep]
                self._kernel, self._near = self._kernel[keep], self._near[keep]
            # --- extrapolating radio map: the path-loss prior of the grid (indoor_loc.wifi.radio_field) ---
            self._prior, self._grid_z = None, grid_z
            if p.field_weight > 0:
                self._prior_raw = None
                self._prior = self._field_prior(np.ones(len(pos), bool))
            # the grid views' readings are filled after the calibration, which interpolates its own per fold
            for a, j, twin in age_views:
                self._views.append(_View([], a, j, True, twin))
        self._pos = np.vstack([pos, self._grid_pos])
        self._z = np.concatenate([map_z, grid_z])
        self._off = self._off_survey(np.ones(len(pos), bool))
        self.sigma_table = (np.zeros(1), np.full(1, p.cov_floor_m))
        self.sigma_tables, self.sigma_factors, self.cov_coef = (), (), np.zeros(0)
        self.calibration = {}
        if p.cov_calibration:
            self._calibrate(list(radio_map.source), map_z)
        if self._kernel is not None:
            # one floor at a time (the grid's values are row by row): no whole-grid temporaries
            for zf in np.unique(grid_z):
                rd, sm, rows = self._smoothed(np.ones(len(pos), bool), float(zf))
                for view in self._views:
                    if view.grid:
                        view.parts.append((rd[view.values], sm[view.values], rows))
        self._last_features = {}
        return self

    def _off_survey(self, keep: np.ndarray) -> np.ndarray | None:
        """(M + C,) bool: the grid points farther than ``smooth_reach_m`` from every map scan ``keep`` of their
        floor (None unless ``field_survey_share``)."""
        p = self.params
        if not (p.field_survey_share and p.field_weight > 0 and len(self._grid_pos)):
            return None
        assert self.radio_map is not None
        near = within_reach(self._grid_pos, self._grid_z, np.asarray(self.radio_map.positions, float)[keep],
                            np.asarray(self.radio_map.z_m, float)[keep], p.smooth_reach_m)
        return np.concatenate([np.zeros(self._n_map, bool), ~near])

    def _smoothed(self, keep: np.ndarray, floor: float | None = None
                  ) -> tuple[list[Any], list[Any], np.ndarray]:
        """The grid interpolated from the map scans ``keep`` (M,) bool: per map values (``_vals``) the
        readings and their sums over the grid points within reach of a kept scan (of floor height ``floor``
        only, if given), and those points' rows. Leaving scans out subtracts their kernel terms from the
        sums over all scans. With ``field_weight`` > 0 the path-loss prior is added, fitted again without
        the left-out scans. Every step is row by row, so a floor's rows get the values they have in the
        whole grid; one floor and one map values at a time keep the temporaries small."""
        from scipy import sparse
        if self._kernel_den is None:
            self._kernel_den = np.asarray(self._kernel.sum(axis=1)).ravel()
        keep = np.asarray(keep, bool)
        drop = ~keep
        reach = self._near @ keep.astype(np.float64) > 0
        if floor is not None:
            reach &= self._grid_z == floor
        rows = np.flatnonzero(reach)
        whole = len(rows) == len(self._grid_pos)
        kern = self._kernel if whole else self._kernel[rows]
        den = self._kernel_den if whole else self._kernel_den[rows]
        drops: list[Any] = [None] * len(self._vals)
        if drop.any():
            if self._kernel_csc is None:
                self._kernel_csc = sparse.csc_matrix(self._kernel)
            k_drop = self._kernel_csc[:, drop]
            den = den - np.asarray(k_drop.sum(axis=1)).ravel()[rows]
            drops = [sparse.csr_matrix(k_drop @ sparse.csr_matrix(v[drop]))[rows] for v in self._vals]
            del k_drop
        prior = None
        lam = self.params.field_weight
        if self._prior is not None:                      # the path-loss prior: field_weight pseudo-scans at each point
            if drop.any():
                prior = self._field_prior(keep, rows)
            else:
                prior = self._prior if whole else self._prior[rows]
            den = den + lam
        inv = 1.0 / np.maximum(den, 1e-300)
        readings: list[Any] = []
        sums: list[Any] = []
        for j, (v, dr) in enumerate(zip(self._vals, drops)):
            if self._kernel_sums is None:                # the kernel sums over all scans
                g = sparse.csr_matrix(kern @ sparse.csr_matrix(v))
            else:                                        # (a copy: scaled in place below)
                g = self._kernel_sums[j].copy() if whole else self._kernel_sums[j][rows]
            if dr is not None:
                g = g - dr
            if prior is not None:
                g = g + scaled_columns(prior, self._prior_scale[j], lam)
            g.data *= np.repeat(inv, np.diff(g.indptr))
            g.data[g.data < 1e-12] = 0.0                 # what only the left-out scans heard (rounding residue)
            g.eliminate_zeros()
            sums.append(np.asarray(g.sum(axis=1)).ravel())
            readings.append(ApReadings.from_sparse(g))
            del g
        return readings, sums, rows

    def _field_prior(self, keep: np.ndarray, rows: np.ndarray | None = None) -> Any:
        """The (len(rows), A) sparse raw path-loss prior (powed values) at the grid points ``rows`` (all if None),
        the models fitted on the map scans ``keep`` (M,) bool (:mod:`indoor_loc.wifi.radio_field`).
        The first call fits every AP on all scans; a fold then refits, per floor, only the APs its
        left-out scans heard there (every other AP's readings, hence its model, are unchanged) and
        keeps the other APs' values. The detection level is the whole map's (a property of the phones)."""
        assert self.radio_map is not None
        p = self.params
        rm = self.radio_map
        n_aps = len(rm.bssids)
        if self._prior_raw is None:
            self._field_floors = np.unique(self._grid_z)
            level = detect_level(rm)
            self._field_detect = level if math.isfinite(level) else p.floor_dbm
            models = fit_floor_models(rm, self._field_floors)
            self._prior_raw = prior_values(models, self._grid_pos, self._grid_z, n_aps,
                                           detect_dbm=self._field_detect,
                                           floor_dbm=p.floor_dbm, beta=p.beta, min_value=FIELD_MIN_VALUE)
        keep = np.asarray(keep, bool)
        grid, gz = (self._grid_pos, self._grid_z) if rows is None else (self._grid_pos[rows], self._grid_z[rows])
        if keep.all():
            prior = self._prior_raw if rows is None else self._prior_raw[rows]
        else:
            rss = np.asarray(rm.rssi_dbm, float)
            map_z = np.asarray(rm.z_m, float)
            drop = ~keep
            floors = self._field_floors
            changed = np.array([np.any(np.isfinite(rss[drop & (map_z == zf)]), axis=0) for zf in floors]
                               ).reshape(len(floors), n_aps)
            on = np.searchsorted(floors, np.unique(gz))            # refit the floors of these points only
            models = fit_floor_models(rm, floors[on], keep=keep, aps=changed[on])
            fresh = prior_values(models, grid, gz, n_aps, detect_dbm=self._field_detect,
                                 floor_dbm=p.floor_dbm, beta=p.beta, min_value=FIELD_MIN_VALUE)
            kept = self._prior_raw.copy() if rows is None else self._prior_raw[rows]
            # the APs the fold did not refit keep their values: the refitted ones' entries are zeroed and dropped
            # (every stored prior value is >= FIELD_MIN_VALUE > 0); the grid points are in floor order, so a
            # floor's entries are one run
            f_row = np.searchsorted(floors, gz)
            data = kept.data
            if np.all(np.diff(f_row) >= 0):
                bounds = kept.indptr[np.searchsorted(f_row, np.arange(len(floors) + 1))]
                for f in range(len(floors)):
                    seg = slice(bounds[f], bounds[f + 1])
                    data[seg][changed[f][kept.indices[seg]]] = 0.0
            else:
                data[changed[np.repeat(f_row, np.diff(kept.indptr)), kept.indices]] = 0.0
            kept.eliminate_zeros()
            prior = kept + fresh
        return prior

    # ------------------------------------------------------------------------------------------
    def distances(self, scan: WifiScan) -> tuple[np.ndarray, int, int]:
        """(D (M + C,) Sørensen distance of the first view to every candidate, usable readings, readings
        known to the map)."""
        ds, _, n_usable, n_known = self.view_distances(scan)
        return ds[0], n_usable, n_known

    def view_distances(self, scan: WifiScan) -> tuple[list[np.ndarray], list[_View], int, int]:
        """Distances (M + C,) per view, 1 for the candidates a view does not use (the map scans, then
        the grid points; ages weighted first, ages ignored second with ``age_views`` 'both' unless
        neither the map nor the scan has ages), the views, usable readings, readings known to the map."""
        p = self.params
        v = powed(scan.rssi_dbm, p.floor_dbm, p.beta)
        usable = v > 0
        cols = self.aps.columns(scan.bssid)
        keep = usable & (cols >= 0)
        n = len(self._pos)
        if not keep.any():
            return [np.ones(n) for _ in self._views], list(self._views), int(usable.sum()), 0
        c = cols[keep]
        raw = v[keep] * self._w[c]
        ages = age_weight(None if scan.age_ms is None else np.asarray(scan.age_ms, float)[keep], p.age_tau_ms)
        no_ages = bool(np.all(ages == 1.0))
        ds: list[np.ndarray] = []
        used: list[_View] = []
        for j, view in enumerate(self._views):
            if view.twin and no_ages:
                continue                             # no ages on either side: the same as its aged twin
            q = raw * ages if view.aged else raw
            if j == 0:
                self._last_query = (c, q)
            ds.append(self._dist_cols(c, q, j))
            used.append(view)
        return ds, used, int(usable.sum()), int(keep.sum())

    def _dist_cols(self, c: np.ndarray, q: np.ndarray, view: int = 0) -> np.ndarray:
        """Sørensen distance (M + C,) of a query given as map columns c (q,) and weighted values q (q,)
        to the candidates of view ``view`` (1 for the others)."""
        v = self._views[view]
        d = np.ones(len(self._pos))
        off = self._n_map if v.grid else 0
        for rd, sums, rows in v.parts:
            d[off + rows] = sorensen(c, q, rd, sums, len(rows))
        return d

    def _estimate(self, ds: list[np.ndarray], allowed: np.ndarray, pos: np.ndarray | None = None,
                  views: list[_View] | None = None, off: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray] | None:
        """Per view the k nearest allowed candidates with D < 1 (``k`` map scans, ``smooth_k`` grid
        points), weights 1 / (D + epsilon); the position is the mean of the views' weighted means. ``off``
        (M + C,) bool, the grid points beyond the survey (``field_survey_share``): the map scans' views then
        weigh by the grid views' share of weight on the others.
        (xy, rows, weights summing to 1, D1 of the first view, D of the rows) or None when no view has
        a candidate."""
        p = self.params
        views = self._views if views is None else views
        parts = []                                   # (rows, weights, D, view) of the views with a candidate
        for d, v in zip(ds, views):
            cand = np.flatnonzero(allowed & (d < 1.0))
            if len(cand) == 0:
                continue
            k = int(p.smooth_k) if v.grid else int(p.k)
            best = cand[np.argsort(d[cand], kind="stable")[:min(k, len(cand))]]
            s = 1.0 / (d[best] + p.epsilon)
            parts.append((best, s / s.sum(), d[best], v))
        if not parts:
            return None
        rows = np.concatenate([b for b, _, _, _ in parts])
        share = np.ones(len(parts))
        if off is not None:
            g_w = [(b, x) for b, x, _, v in parts if v.grid]
            if g_w and len(g_w) < len(parts) and any(off[b].any() for b, _ in g_w):
                on = float(np.mean([x @ ~off[b] for b, x in g_w]))        # the grid estimates' weight on the survey
                share = np.array([1.0 if v.grid else on for _, _, _, v in parts])
        if np.all(share == 1.0):
            w = np.concatenate([x for _, x, _, _ in parts]) / len(parts)
        else:
            w = np.concatenate([x * f for (_, x, _, _), f in zip(parts, share)]) / share.sum()
        p_all = self._pos if pos is None else pos
        xy = w @ p_all[rows]
        self._last_features = fix_features(xy, p_all, parts, float(share.min()))
        return (xy, rows, w, float(parts[0][2][0]), np.concatenate([x for _, _, x, _ in parts]))

    def reset(self) -> None:
        """Forget the learnt device offset (a new phone)."""
        self.offset_db = 0.0

    def locate(self, scan: WifiScan) -> Fix:
        """A fix (xy, cov, z = the detected floor's height) or ok=False with a reason. With
        ``offset_gain`` > 0 the scan is first corrected by the learnt device offset, and the fix
        updates it (so a sequence of scans from one phone is stateful; ``reset()`` per phone)."""
        if self.radio_map is None:
            raise MapError("powed: fit() a radio map before locating")
        if self.params.offset_gain > 0 and self.offset_db != 0.0:
            scan = replace(scan, rssi_dbm=np.clip(np.asarray(scan.rssi_dbm, float) - self.offset_db, -120.0, 0.0))
        fix = self._locate(scan)
        if fix.ok and self.params.offset_gain > 0:
            self._update_offset(scan, fix)
        fix.info["offset_db"] = self.offset_db
        return fix

    def _update_offset(self, scan: WifiScan, fix: Fix) -> None:
        """Median residual of the (corrected) scan against the weighted neighbours over the APs
        every neighbour heard; the offset moves by ``offset_gain`` of it (Laoudias et al., "Device
        self-calibration in location systems using signal strength histograms", J. Location Based
        Services 7(3), 2013, calibrate a device offset online; this estimates it from the matches)."""
        p = self.params
        rm = self.radio_map
        assert rm is not None
        cols = self.aps.columns(scan.bssid)
        k = cols >= 0
        if k.sum() < p.offset_min_aps:
            return
        wm = self.map_weights(fix.info["rows"], fix.info["weights"])
        if not wm.max() > 0:
            return                                           # a fix on extrapolated candidates only: no map scans behind it
        support = np.flatnonzero(wm >= 0.01 * wm.max())      # the map scans behind the fix
        m = np.asarray(rm.rssi_dbm, float)[np.ix_(support, cols[k])]
        shared = ~np.isnan(m).any(axis=0)
        if shared.sum() < p.offset_min_aps:
            return
        wts = wm[support] / wm[support].sum()
        ref = wts @ m[:, shared]
        r = float(np.median(np.asarray(scan.rssi_dbm, float)[k][shared] - ref))
        self.offset_db = float(np.clip(self.offset_db + p.offset_gain * r, -p.offset_max_db, p.offset_max_db))

    def map_weights(self, rows: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """(M,) weights of the map scans behind a fix of candidate ``rows`` with ``weights``: the map
        scans among them when there are any (the direct neighbours), else the grid points' weights
        spread over the scans each interpolates."""
        out = np.zeros(self._n_map)
        direct = rows < self._n_map
        if direct.any() or self._kernel is None:
            np.add.at(out, rows[direct], weights[direct])
            return out
        k = self._kernel[rows - self._n_map]
        k = k.multiply(1.0 / np.maximum(np.asarray(k.sum(axis=1)), 1e-300))
        return np.asarray(k.T @ weights).ravel()

    def _locate(self, scan: WifiScan) -> Fix:
        p = self.params
        nan_fix = (np.full(2, np.nan), np.full((2, 2), np.nan))
        ds, views, n_usable, n_known = self.view_distances(scan)
        if n_usable == 0:
            return Fix(scan.stamp_ns, *nan_fix, ok=False, reason="no_usable_aps")
        if n_known == 0 or not any(np.any(d < 1.0) for d in ds):
            return Fix(scan.stamp_ns, *nan_fix, ok=False, reason="no_shared_aps")
        floor_p: dict[float, float] = {}
        allowed = np.ones(len(self._pos), bool)
        if len(self._floors) > 1:
            c, q = self._last_query
            h = self._home[c]
            score = np.bincount(h[h >= 0], weights=q[h >= 0], minlength=len(self._floors))
            share = score / max(float(score.sum()), 1e-300)
            floor_p = {float(z): float(x) for z, x in zip(self._floors, share)}
            z_best = float(self._floors[int(np.argmax(score))])
            on_floor = self._z == z_best
            if any(np.any(on_floor & (d < 1.0)) for d in ds):
                allowed = on_floor
        else:
            z_best = float(self._floors[0]) if len(self._floors) else 0.0
            floor_p[z_best] = 1.0
        est = self._estimate(ds, allowed, None, views, self._off)
        assert est is not None                       # some view has a map scan with D < 1 among `allowed`
        xy, best, w, d1, dist = est
        f = self._pos[best]
        dev = f - xy
        spread = (w[:, None] * dev).T @ dev
        lag = self._lag_s(best, scan.stamp_ns)
        feats = {**self._last_features, "n_aps": float(n_known)}
        sigma = self.sigma_m(d1, lag, feats)
        cov = p.cov_scale * spread + sigma ** 2 * np.eye(2)
        info = {"rows": best, "weights": w, "distance": dist, "positions": f,
                "candidates": int(sum(np.count_nonzero(allowed & (d < 1.0)) for d in ds[:1])),
                "sigma_m": sigma, "d1": d1, "lag_s": lag,
                "floor_p": floor_p, "floor": self._floor_names.get(z_best, ""), "features": feats}
        z_best = float(self._z[best[0]])
        return Fix(scan.stamp_ns, xy, cov, ok=True, info=info, z=z_best,
                   z_var=float(sum(pp * (z - z_best) ** 2 for z, pp in floor_p.items())))

    # -- fitted state: save / load (indoor_loc.wifi.fit_store) and memory after the fit ------------
    def release_fit_data(self) -> None:
        """Drop what only :meth:`fit` uses: the map values (M, A), the reach matrix, the kernel by columns
        and its row sums, the path-loss prior, the cross-validated scans' quantities. :meth:`locate` needs none of them, so the fixes do not
        change; a later :meth:`fit` builds them again. (The kernel by rows stays: a fix on grid points
        only spreads its weights over the map scans with it, for the device offset.)"""
        self._vals = []
        self._near = self._kernel_den = self._kernel_csc = self._kernel_sums = None
        self._prior = self._prior_raw = None
        self._prior_scale = []
        self._field_floors, self._field_detect = np.zeros(0), 0.0
        self._cv_features, self._last_features = {}, {}

    def fitted_state(self) -> dict[str, np.ndarray]:
        """Everything :meth:`locate` needs after :meth:`fit`, as named arrays (no Python objects), for
        :meth:`load_fitted_state` on the same radio map. Map values shared by two views are stored once."""
        if self.radio_map is None:
            raise MapError("powed: fit() a radio map before saving its fitted state")
        out: dict[str, np.ndarray] = {
            "w": self._w, "pos": self._pos, "z": self._z, "n_map": np.array(self._n_map, np.int64),
            "floors": self._floors, "home": self._home, "map_views_equal": np.array(self._map_views_equal),
            "sigma_d1": self.sigma_table[0], "sigma_s": self.sigma_table[1],
            "n_sigma_tables": np.array(len(self.sigma_tables), np.int64),
            "sigma_factors": np.array(self.sigma_factors, float), "cov_coef": np.asarray(self.cov_coef, float),
            "calibration": np.array(json.dumps(self.calibration)),
            "views": np.array([[v.aged, v.values, v.grid, v.twin] for v in self._views], np.int64).reshape(-1, 4)}
        for i, (d1, sig) in enumerate(self.sigma_tables):
            out[f"sigma{i}_d1"], out[f"sigma{i}_s"] = d1, sig
        if self._off is not None:                        # the grid points beyond the survey (field_survey_share)
            out["off"] = self._off
        parts: dict[int, int] = {}                       # id(readings) -> part number
        for j, view in enumerate(self._views):
            ids = []
            for rd, sums, rows in view.parts:
                if id(rd) not in parts:
                    n = parts[id(rd)] = len(parts)
                    out.update({f"part{n}_ptr": rd.ptr, f"part{n}_row": rd.row, f"part{n}_val": rd.val,
                                f"part{n}_sums": np.asarray(sums), f"part{n}_rows": np.asarray(rows)})
                ids.append(parts[id(rd)])
            out[f"view{j}_parts"] = np.array(ids, np.int64)
        if self._kernel is not None:
            from scipy import sparse
            k = sparse.csr_matrix(self._kernel)
            out.update(kernel_data=k.data, kernel_indices=k.indices, kernel_indptr=k.indptr,
                       kernel_shape=np.array(k.shape, np.int64))
        return out

    def load_fitted_state(self, radio_map: RadioMap, state: Any) -> "PowedKnn":
        """This positioner as :meth:`fit` (then :meth:`release_fit_data`) leaves it on ``radio_map``, from the
        arrays of :meth:`fitted_state` (a mapping, e.g. an opened ``.npz``; the caller checks that they were
        made for this map and these parameters). MapError when they are inconsistent with the map."""
        from scipy import sparse
        n_scans, n_aps = len(radio_map.positions), len(radio_map.bssids)
        try:
            w, pos, z = (np.asarray(state[k]) for k in ("w", "pos", "z"))
            n_map = int(state["n_map"])
            home = np.asarray(state["home"])
            views = np.asarray(state["views"]).reshape(-1, 4)
            n_c = len(pos) - n_map
            ok = (n_map == n_scans and w.shape == (n_aps,) and home.shape == (n_aps,) and pos.ndim == 2
                  and pos.shape[1] == 2 and z.shape == (len(pos),) and n_c >= 0)
            if not ok:
                raise MapError(f"arrays of {n_map} map scans, {len(w)} APs, {len(pos)} candidates do not fit a map "
                               f"of {n_scans} scans and {n_aps} APs")
            parts: dict[int, tuple[ApReadings, np.ndarray, np.ndarray]] = {}
            built: list[_View] = []
            for j, (aged, values, grid, twin) in enumerate(views.tolist()):
                view_parts = []
                for n in np.asarray(state[f"view{j}_parts"]).tolist():
                    if n not in parts:
                        rd = ApReadings.__new__(ApReadings)
                        rd.ptr, rd.row, rd.val = (np.asarray(state[f"part{n}_{k}"]) for k in ("ptr", "row", "val"))
                        sums, rows = np.asarray(state[f"part{n}_sums"]), np.asarray(state[f"part{n}_rows"])
                        limit = n_c if grid else n_map
                        if not (len(rd.ptr) == n_aps + 1 and len(rd.row) == len(rd.val) == int(rd.ptr[-1])
                                and sums.shape == rows.shape and (len(rows) == 0 or
                                                                  (rows.min() >= 0 and rows.max() < limit))
                                and (len(rd.row) == 0 or (rd.row.min() >= 0 and rd.row.max() < len(rows)))):
                            raise MapError(f"part {n} of view {j} is inconsistent")
                        parts[n] = (rd, sums, rows)
                    view_parts.append(parts[n])
                built.append(_View(view_parts, bool(aged), int(values), bool(grid), bool(twin)))
            kernel = None
            if "kernel_data" in state:
                shape = tuple(int(s) for s in np.asarray(state["kernel_shape"]))
                if shape != (n_c, n_scans):
                    raise MapError(f"kernel of shape {shape}, expected {(n_c, n_scans)}")
                kernel = sparse.csr_matrix((np.asarray(state["kernel_data"]), np.asarray(state["kernel_indices"]),
                                            np.asarray(state["kernel_indptr"])), shape=shape)
            tables = tuple((np.asarray(state[f"sigma{i}_d1"]), np.asarray(state[f"sigma{i}_s"]))
                           for i in range(int(state["n_sigma_tables"])))
            sigma_table = (np.asarray(state["sigma_d1"]), np.asarray(state["sigma_s"]))
            factors = tuple(float(x) for x in np.asarray(state["sigma_factors"], float).ravel())
            coef = np.asarray(state["cov_coef"], float).ravel()
            calibration = json.loads(str(state["calibration"]))
            floors = np.asarray(state["floors"])
            map_views_equal = bool(state["map_views_equal"])
            off = np.asarray(state["off"], bool) if "off" in state else None
            if off is not None and off.shape != (len(pos),):
                raise MapError(f"off-survey flags of shape {off.shape}, expected {(len(pos),)}")
        except (KeyError, ValueError, TypeError, IndexError) as err:
            raise MapError(f"powed: fitted state unreadable: {type(err).__name__}: {err}") from err
        self.release_fit_data()
        self.radio_map = radio_map
        self.aps = ApIndex(radio_map.bssids)
        self._w, self._pos, self._z, self._n_map, self._home = w, pos, z, n_map, home
        self._grid_pos, self._grid_z = pos[n_map:], z[n_map:]
        self._kernel = kernel
        self._views = built
        self._floors = floors
        self._floor_names = {float(zf): str(name) for name, zf in radio_map.floors.items()}
        self._map_views_equal = map_views_equal
        self._off = off
        self.sigma_table, self.sigma_tables, self.calibration = sigma_table, tables, calibration
        self.sigma_factors, self.cov_coef = factors, coef
        return self
