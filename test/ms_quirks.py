"""Rewrite a site of the Microsoft indoor-location format with the quirks other sites of the competition
show, losing no record: floors renamed to other conventions, lines whose end is missing (the next record
runs on), WiFi rows without frequency, headers with spaces, other key case and a byte-order mark, CRLF
line ends, plain and gzip files, a junk line and a short WiFi row per walk, a floor without
``floor_info.json``, an empty floor, a walk without waypoints and a directory that is no floor.

Every record of the source must read back equal (but the WiFi frequency, where it was removed), so
the bench on the rewritten site must print the source's figures:

    python test/ms_quirks.py ../shared/datasets/ms_site2 /tmp/ms_quirky
    indoor-loc bench wifi --site /tmp/ms_quirky --json quirky.json
"""
from __future__ import annotations

import gzip
import random
import shutil
import sys
from pathlib import Path

#: ms_site2's floors renamed to other conventions (LG1 -1, G 0, M 0.5, "Roof top" by fallback)
RENAME = {"B1": "LG1", "F3": "G", "F7": "M", "F8": "Roof top"}
JUNK = "this is not a record"
SHORT_WIFI = "1574229600000\tTYPE_WIFI\tshort"
NO_TRUTH_ID = "ffffffffffffffffffffffff"


def rewrite(src: Path, dst: Path, *, floors: dict[str, str] | None = None, seed: int = 11,
            run_on: float = 0.02, stride: int = 1) -> int:
    """Write ``src``'s floors (``floors``: {source name: new name}, default :data:`RENAME`) into ``dst``
    with the quirks (``stride`` > 1: only every stride-th walk, for a quick test); returns the number of
    lines whose end was removed."""
    rng = random.Random(seed)
    joined = 0
    for old, new in (floors or RENAME).items():
        d = dst / new
        (d / "path_data_files").mkdir(parents=True)
        for f in ("floor_image.png", "geojson_map.json", "floor_info.json"):
            if (src / old / f).is_file() and not (new == "Roof top" and f == "floor_info.json"):
                shutil.copy(src / old / f, d / f)
        files = sorted((src / old / "path_data_files").glob("*.txt.gz"))
        for i, p in enumerate(files):
            if i % stride:
                continue
            out = []
            for ln in gzip.open(p, "rt", encoding="utf-8").read().split("\n"):
                if ln.startswith("#") and i % 4 == 1:
                    ln = ln.replace("\t", " ").replace("FloorName", "floorname")
                elif "\tTYPE_WIFI\t" in ln and i % 3 == 0:
                    f = ln.split("\t")
                    ln = "\t".join(f[:5] + f[6:])                   # no frequency
                out.append(ln)
            out.insert(len(out) // 2, JUNK)
            out.insert(len(out) // 3, SHORT_WIFI)
            parts = []
            for k, ln in enumerate(out):
                end = "\r\n" if i % 5 == 0 else "\n"
                nxt = out[k + 1] if k + 1 < len(out) else ""
                if ln and not ln.startswith("#") and nxt[:1].isdigit() and rng.random() < run_on:
                    end = ""                                        # the next record runs on
                    joined += 1
                parts.append(ln + (end if k + 1 < len(out) else ""))
            text = ("\ufeff" if i % 4 == 1 else "") + "".join(parts)
            tid = p.name[: -len(".txt.gz")]
            if i % 4 == 0:
                (d / "path_data_files" / f"{tid}.txt").write_text(text, encoding="utf-8")
            else:
                (d / "path_data_files" / f"{tid}.txt.gz").write_bytes(gzip.compress(text.encode("utf-8")))
        if new == "G" and files:                                   # a walk without waypoints, sorting last
            t = gzip.open(files[-1], "rt", encoding="utf-8").read()
            t = "\n".join(ln for ln in t.split("\n") if "\tTYPE_WAYPOINT\t" not in ln)
            (d / "path_data_files" / f"{NO_TRUTH_ID}.txt").write_text(t, encoding="utf-8")
    (dst / "P1" / "path_data_files").mkdir(parents=True)
    (dst / "docs").mkdir()
    (dst / "docs" / "notes.md").write_text("not a floor\n")
    return joined


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python test/ms_quirks.py SITE_DIR OUT_DIR (OUT_DIR must not exist)")
    print(f"{rewrite(Path(sys.argv[1]), Path(sys.argv[2]))} line ends removed")
