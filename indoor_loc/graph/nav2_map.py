"""nav2 ``map_server`` maps: the YAML + image pair (``indoor-loc sim`` writes one per floor), read as
grey levels with their scale and origin, and as an occupancy grid (``nav_msgs/OccupancyGrid`` values).

Format (nav2 map_server, ``map_io``): ``image`` (relative to the YAML), ``resolution`` (m/pixel),
``origin`` [x, y, yaw] of the lower-left pixel, ``negate``, ``occupied_thresh``, ``free_thresh``,
``mode`` (``trinary`` default, ``scale``, ``raw``). A pixel's occupancy probability is
``(255 - v) / 255`` (``v / 255`` when negated): above ``occupied_thresh`` it is occupied (100), below
``free_thresh`` free (0), else unknown (-1) in trinary mode; ``scale`` maps the band in between
linearly onto 1..99; ``raw`` takes the value itself.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from indoor_loc.errors import MapError


@dataclass(frozen=True)
class Nav2Map:
    grey: np.ndarray            # (H, W) uint8, row 0 at the top of the image
    resolution_m: float         # metres per pixel
    origin: tuple[float, float, float]   # x, y (m) of the lower-left pixel's corner, yaw (rad)
    negate: bool = False
    occupied_thresh: float = 0.65
    free_thresh: float = 0.25
    mode: str = "trinary"
    floor: int | None = None    # indoor_loc's own keys (``indoor-loc sim``), when present
    height_m: float | None = None

    @property
    def px_per_m(self) -> float:
        return 1.0 / self.resolution_m

    def occupancy(self) -> np.ndarray:
        """(H, W) int8 in ``nav_msgs/OccupancyGrid`` values, rows bottom-up (row 0 at ``origin``), as
        the grid's ``data`` is laid out (row-major from the origin cell)."""
        v = self.grey[::-1].astype(np.float64)
        if self.mode == "raw":
            return np.clip(v, -1, 100).astype(np.int8)
        p = v / 255.0 if self.negate else (255.0 - v) / 255.0
        out = np.full(p.shape, -1, dtype=np.int8)
        out[p > self.occupied_thresh] = 100
        out[p < self.free_thresh] = 0
        if self.mode == "scale":
            mid = (p >= self.free_thresh) & (p <= self.occupied_thresh)
            span = max(self.occupied_thresh - self.free_thresh, 1e-9)
            out[mid] = np.clip(np.round(1 + 98 * (p[mid] - self.free_thresh) / span), 1, 99).astype(np.int8)
        return out


def is_nav2_yaml(path: str | Path) -> bool:
    return Path(path).suffix.lower() in (".yaml", ".yml")


def read_nav2_map(path: str | Path) -> Nav2Map:
    """Read a map_server YAML and its image; MapError naming the key on anything malformed."""
    import yaml
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        meta = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise MapError(f"cannot read map YAML {path}: {err}") from err
    if not isinstance(meta, dict):
        raise MapError(f"{path}: expected a nav2 map_server YAML mapping (image, resolution, origin, ...)")
    try:
        image = path.parent / str(meta["image"])
        resolution = float(meta["resolution"])
        origin = tuple(float(v) for v in meta.get("origin", [0.0, 0.0, 0.0]))
        negate = bool(int(meta.get("negate", 0)))
        occ, free = float(meta.get("occupied_thresh", 0.65)), float(meta.get("free_thresh", 0.25))
        mode = str(meta.get("mode", "trinary"))
    except (KeyError, TypeError, ValueError) as err:
        raise MapError(f"{path}: not a nav2 map_server YAML ({type(err).__name__}: {err})") from err
    if not resolution > 0 or len(origin) != 3 or mode not in ("trinary", "scale", "raw") or not 0 <= free <= occ <= 1:
        raise MapError(f"{path}: expected resolution > 0, origin [x, y, yaw], mode trinary|scale|raw and "
                       f"0 <= free_thresh <= occupied_thresh <= 1; got {resolution}, {list(origin)}, {mode}, "
                       f"{free}, {occ}")
    try:
        with Image.open(image) as im:
            grey = np.asarray(im.convert("L"))
    except (OSError, UnidentifiedImageError) as err:
        raise MapError(f"{path}: cannot read its image {image}: {err}") from err
    floor = meta.get("floor")
    height = meta.get("height_m")
    return Nav2Map(grey, resolution, (origin[0], origin[1], origin[2]), negate, occ, free, mode,
                   int(floor) if floor is not None else None, float(height) if height is not None else None)
