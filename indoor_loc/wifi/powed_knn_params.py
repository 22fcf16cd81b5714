"""Parameters of the powed k-NN positioner (:class:`indoor_loc.wifi.powed_knn.PowedKnn`; the module
docstrings of :mod:`indoor_loc.wifi.powed_knn` and :mod:`indoor_loc.wifi.powed_knn_cov` say what each does)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from indoor_loc.params import field, require

AP_WEIGHTINGS = ("idf", "none")
AGE_VIEWS = ("weighted", "both")
SMOOTH_VIEWS = ("grid", "both")
#: per-fix quantities the covariance calibration may rank the fixes by (PowedKnn fix info["features"])
COV_QUANTITIES = ("d1", "views_m", "far", "spread_m", "view_gap_m", "d_ratio", "survey_share", "n_aps")
COV_STRATA = ("factor", "tables")
MIN_BIN_SCANS = 40                                    # cross-validated scans per bin of the covariance calibration


@dataclass(frozen=True)
class PowedKnnParams:
    """Powed k-NN parameters (defaults chosen on ms_site2 B1/F7, see docs/benchmarks/wifi.md)."""
    k: int = field(4, "number of nearest map scans averaged")
    floor_dbm: float = field(-100.0, "RSS mapped to 0 in the positive representation; weaker readings are "
                                       "treated as not heard (dBm)")
    beta: float = field(math.e, "exponent of the powed representation")
    age_tau_ms: float = field(5000.0, "readings weigh exp(-age_ms / age_tau_ms); 0 = ignore ages (ms)")
    age_views: str = field("both", "'weighted': readings weigh by their age; 'both': the mean of that estimate "
                                   "and the one with ages ignored (two hypotheses on what a cached reading is worth)")
    ap_weighting: str = field("idf", "'idf' (sqrt(ln(1 + M / n_a)): APs heard everywhere weigh less) or 'none'")
    epsilon: float = field(1e-4, "epsilon in the neighbour weight 1 / (D + epsilon)")
    cov_scale: float = field(0.0, "factor on the weighted spread of the k neighbour positions added to the "
                                    "covariance (0: the cross-validated sigma already holds it)")
    cov_floor_m: float = field(1.0, "smallest isotropic standard deviation of the fix covariance (m)")
    cov_calibration: bool = field(True, "calibrate sigma(best distance) on the map by leave-walks-out "
                                          "cross-validation at fit time")
    cov_calibration_scans: int = field(1000, "at most this many map scans (evenly spaced) are cross-validated "
                                         "(bounds the fit time on large maps)")
    cov_quantile: float = field(0.95, "the ellipse of this probability is calibrated on the cross-validated errors")
    cov_folds: int = field(10, "the map's sources (walks) are dealt into at most this many folds, each left out in "
                               "turn in the calibration")
    cov_bins: int = field(5, "at most this many bins of the best-match distance in the calibration (each of at "
                             "least 40 cross-validated scans)")
    cov_recent_s: float = field(600.0, "fixes whose nearest matched map scan was recorded within this time of the scan "
                                       "(the same survey session) get a sigma calibrated on such scans only, the "
                                       "others one calibrated on the rest (s; 0 = one calibration for all)")
    cov_strata: str = field("tables", "how the recording-time strata calibrate sigma: 'tables' (one table per stratum) "
                                      "or 'factor' (one sigma table over all cross-validated scans, times a factor per "
                                      "stratum that makes its ellipse hold its own scans)")
    cov_quantities: str = field("d1", "comma-separated per-fix quantities sigma is calibrated on: 'd1' alone "
                                              "bins the best-match distance; several are combined into the "
                                              "least-squares prediction of the log cross-validated error (one of "
                                              f"{', '.join(COV_QUANTITIES)})")
    smooth_m: float = field(4.0, "bandwidth of the Gaussian kernel regression that interpolates the map's readings "
                                 "over a grid of candidate positions per floor (m); 0 = match the map scans themselves")
    smooth_grid_m: float = field(1.0, "spacing of the candidate grid (m)")
    smooth_reach_m: float = field(2.0, "grid points farther than this from every map scan of their floor are no "
                                       "candidates (m)")
    smooth_views: str = field("both", "with smooth_m > 0: 'grid' (match the interpolated grid only) or 'both' (the "
                                      "mean of the estimates against the map scans and against the grid)")
    smooth_k: int = field(20, "number of nearest grid candidates averaged (k counts the map scans)")
    field_weight: float = field(0.0, "weight of the per-AP path-loss prior in the interpolated grid, in survey "
                                     "scans at the candidate (indoor_loc.wifi.radio_field; 0 = kernel regression "
                                     "alone); with it the grid may reach farther (smooth_reach_m) and extrapolates")
    field_survey_share: bool = field(True, "with field_weight > 0 and smooth_views 'both': the estimates against the map "
                                           "scans weigh by the share of the grid estimates' weight on points within "
                                           "smooth_reach_m of a map scan (where the grid puts the user beyond the survey, "
                                           "the map scans cannot be there); False: every estimate weighs the same")
    field_reach_m: float = field(10.0, "with field_weight > 0 and a walkable area (PowedKnn.walkable, from a floor plan) "
                                       "the grid also covers the walkable points this far from the map scans (m)")
    offset_gain: float = field(0.2, "online device RSS offset: after each fix the offset moves by this fraction "
                                    "of the median residual against the neighbours (0 = off)")
    offset_max_db: float = field(20.0, "bound on the device RSS offset (dB)")
    offset_min_aps: int = field(5, "readings shared with every neighbour needed to update the offset")

    def validate(self) -> None:
        n = type(self).__name__
        require(int(self.k) >= 1, n, "k", "an integer >= 1", self.k)
        require(-120.0 <= self.floor_dbm < 0.0, n, "floor_dbm", "in [-120, 0) dBm", self.floor_dbm)
        require(math.isfinite(self.beta) and self.beta > 0, n, "beta", "> 0", self.beta)
        require(math.isfinite(self.age_tau_ms) and self.age_tau_ms >= 0, n, "age_tau_ms", ">= 0 ms",
                  self.age_tau_ms)
        require(self.age_views in AGE_VIEWS, n, "age_views", f"one of {list(AGE_VIEWS)}", self.age_views)
        require(self.ap_weighting in AP_WEIGHTINGS, n, "ap_weighting", f"one of {list(AP_WEIGHTINGS)}",
                  self.ap_weighting)
        require(math.isfinite(self.epsilon) and self.epsilon > 0, n, "epsilon", "> 0", self.epsilon)
        require(math.isfinite(self.offset_gain) and 0.0 <= self.offset_gain <= 1.0, n, "offset_gain", "in [0, 1]",
                self.offset_gain)
        require(math.isfinite(self.offset_max_db) and self.offset_max_db >= 0, n, "offset_max_db", ">= 0 dB",
                self.offset_max_db)
        require(int(self.offset_min_aps) >= 1, n, "offset_min_aps", "an integer >= 1", self.offset_min_aps)
        require(int(self.cov_calibration_scans) >= 10, n, "cov_calibration_scans", "an integer >= 10",
                self.cov_calibration_scans)
        require(math.isfinite(self.cov_quantile) and 0.0 < self.cov_quantile < 1.0, n, "cov_quantile", "in (0, 1)",
                self.cov_quantile)
        require(math.isfinite(self.smooth_m) and self.smooth_m >= 0, n, "smooth_m", ">= 0 m", self.smooth_m)
        require(math.isfinite(self.smooth_grid_m) and self.smooth_grid_m > 0, n, "smooth_grid_m", "> 0 m",
                self.smooth_grid_m)
        require(math.isfinite(self.smooth_reach_m) and self.smooth_reach_m >= 0, n, "smooth_reach_m", ">= 0 m",
                self.smooth_reach_m)
        require(self.smooth_views in SMOOTH_VIEWS, n, "smooth_views", f"one of {list(SMOOTH_VIEWS)}",
                self.smooth_views)
        require(int(self.smooth_k) >= 1, n, "smooth_k", "an integer >= 1", self.smooth_k)
        require(math.isfinite(self.field_weight) and self.field_weight >= 0, n, "field_weight", ">= 0",
                self.field_weight)
        require(math.isfinite(self.field_reach_m) and self.field_reach_m >= 0, n, "field_reach_m", ">= 0 m",
                self.field_reach_m)
        require(self.smooth_m == 0 or self.smooth_grid_m <= 10 * self.smooth_m, n, "smooth_grid_m",
                "at most 10 x smooth_m", self.smooth_grid_m)
        require(int(self.cov_folds) >= 2, n, "cov_folds", "an integer >= 2", self.cov_folds)
        require(int(self.cov_bins) >= 1, n, "cov_bins", "an integer >= 1", self.cov_bins)
        require(math.isfinite(self.cov_recent_s) and self.cov_recent_s >= 0, n, "cov_recent_s", ">= 0 s",
                self.cov_recent_s)
        require(self.cov_strata in COV_STRATA, n, "cov_strata", f"one of {list(COV_STRATA)}", self.cov_strata)
        names = cov_quantity_names(self.cov_quantities)
        require(len(names) >= 1 and len(set(names)) == len(names) and all(q in COV_QUANTITIES for q in names), n,
                "cov_quantities", f"distinct names among {list(COV_QUANTITIES)}, comma-separated", self.cov_quantities)
        require(math.isfinite(self.cov_scale) and self.cov_scale >= 0, n, "cov_scale", ">= 0", self.cov_scale)
        require(math.isfinite(self.cov_floor_m) and self.cov_floor_m > 0, n, "cov_floor_m",
                  "> 0 (a fix covariance must be invertible)", self.cov_floor_m)


def cov_quantity_names(text: str) -> list[str]:
    """The names of a ``cov_quantities`` setting."""
    return [t.strip() for t in str(text).split(",") if t.strip()]
