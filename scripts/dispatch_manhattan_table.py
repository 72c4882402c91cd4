"""Build ``cmat/envs/dispatch/data/manhattan.npz``: Manhattan ride-hailing demand and travel times.

Usage: ``python scripts/dispatch_manhattan_table.py [--wheel PATH] [--out PATH]``.

Source
------
The data files of the PyPI package ``pyhailing`` 0.0.9 (https://pypi.org/project/pyhailing/0.0.9/,
code at https://github.com/nkullman/ridehailing_package), by Nicholas Kullman, the simulator of
the ride-hailing (dynamic VRP) variant of the 12th DIMACS Implementation Challenge
(http://dimacs.rutgers.edu/programs/challenge/vrp/). Licence: Apache-2.0 (the wheel's
``pyhailing-0.0.9.dist-info/LICENSE``, copied next to the table as ``LICENSE-pyhailing``; the
wheel has no NOTICE file). pyhailing is not imported (it pins numpy<1.22): the wheel is
downloaded with ``pip download --no-deps pyhailing==0.0.9`` (or given with ``--wheel``) and
only its data files are read, with the standard library (zipfile, csv, json) and numpy.

The wheel's data files
----------------------
- ``pyhailing/data/taxizones.geojson``: 61 single polygons, ``properties.zone_id`` the NYC TLC
  taxi-zone LocationID, coordinates in km (UTM zone 18N easting/northing divided by 1000).
- ``pyhailing/data/trips.csv``: ``dow,t_15min,puzone,dozone,n_trips``; ``dow`` 0 = Monday,
  ``t_15min`` the 15-minute slot of the day (0 = 00:00–00:15), pick-up and drop-off
  LocationIDs and an integer trip count. Only ``dow`` 0–4 (Monday–Friday) occur.
- ``pyhailing/data/speeds.csv``: ``puzone,dozone,min,speed_mean,speed_stddev``; ``min`` the
  start of the 15-minute slot in minutes after midnight, speeds in km/s (pyhailing clips
  sampled speeds to 1–60 mph given in km/s). All 61 × 61 × 96 rows are present.
- ``pyhailing/data/lots.csv`` (idling locations) is not used.

Derivation
----------
1. ``zones``: the geojson's LocationIDs, sorted ascending; trips and speeds use the same 61.
2. ``demand`` (weekdays; the package has no Saturday or Sunday data): pyhailing uses the
   counts only as sampling weights (an episode draws a day of week ∝ its total, then a fixed
   number of requests ∝ ``n_trips``), and neither its code nor its documentation states the
   period they cover; its README says "based on data from business days in 2018". The counts
   are read as totals over all 2018 business days of each day of week: Monday–Friday minus the
   ten US federal holidays of 2018 (all on weekdays), i.e. 46 Mondays, 51 Tuesdays, 51
   Wednesdays, 51 Thursdays and 52 Fridays (251 days). This is an inference, not documented by
   pyhailing: with it the daily totals rise smoothly from Monday to Friday (Monday 0.90 ×
   Tuesday, the usual NYC pattern; without the holidays Monday would be 0.81 × Tuesday), and
   the ~0.44 M trips a day inside these 61 zones match 2018 yellow-taxi plus for-hire-vehicle
   volumes (yellow cabs alone carried ~0.28 M a day city-wide). Each day of week's counts are
   divided by its number of days, and the weekday table is the plain mean of the five per-day
   tables.
3. Zone centroids, as pyhailing computes them: it Delaunay-triangulates each polygon's vertices
   (which covers their convex hull) and takes the area-weighted mean of the triangles'
   centroids, i.e. the centroid of the convex hull of the vertices. Here: the hull (Andrew's
   monotone chain) and its shoelace centroid. Points are then rotated by pyhailing's
   ``_MANHATTAN_ANGLE`` = 29° (counter-clockwise), which aligns the avenues with an axis.
4. ``travel_minutes``: pyhailing's mean travel time between two points is their city-block
   (L1) distance in the rotated frame (km) divided by ``speed_mean`` of (origin zone,
   destination zone, 15-minute slot) (``RidehailGeometry.travel_time(mean=True)``; sampled
   times divide by a clipped normal speed instead). Off the diagonal: L1 distance between
   the two zones' centroids / ``speed_mean`` / 60 for each slot, then the mean of the four
   slots of each hour. Diagonal: pyhailing places a request's ends uniformly at random in the
   zone (in the hull, see 4), so the intra-zone time is the expected L1 distance between two
   independent uniform points of the hull (Monte Carlo, 20 000 pairs per zone, seed 0) /
   the zone's own ``speed_mean``, averaged over the hour in the same way. A missing or
   non-positive speed (none in 0.0.9) would be filled with the shortest path over known pairs
   of that hour (Floyd–Warshall).
5. ``coords``: the rotated hull centroids, each axis scaled to [0, 1] (min → 0, max → 1); axis 0
   runs across the island, axis 1 along it.

Output arrays (``np.savez_compressed``): ``zones`` int16 [Z]; ``demand`` float32 [96, Z, Z]
(slot, origin, destination: mean trips per 15-minute slot of one day); ``travel_minutes``
float32 [24, Z, Z] (hour, origin, destination); ``coords`` float32 [Z, 2].
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import io
import json
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import numpy.typing as npt

PACKAGE = "pyhailing"
VERSION = "0.0.9"
ROOT = Path(__file__).resolve().parent.parent
DATA_DIR = ROOT / "cmat" / "envs" / "dispatch" / "data"
TRIPS = "pyhailing/data/trips.csv"
SPEEDS = "pyhailing/data/speeds.csv"
ZONES = "pyhailing/data/taxizones.geojson"
LICENSE = f"pyhailing-{VERSION}.dist-info/LICENSE"

MANHATTAN_ANGLE_DEG = 29.0
"""pyhailing's ``RidehailGeometry._MANHATTAN_ANGLE``: points are rotated by this before L1."""
SLOTS = 96
HOURS = 24
INTRA_ZONE_PAIRS = 20_000
YEAR = 2018
US_FEDERAL_HOLIDAYS_2018 = (
    dt.date(2018, 1, 1), dt.date(2018, 1, 15), dt.date(2018, 2, 19), dt.date(2018, 5, 28),
    dt.date(2018, 7, 4), dt.date(2018, 9, 3), dt.date(2018, 10, 8), dt.date(2018, 11, 12),
    dt.date(2018, 11, 22), dt.date(2018, 12, 25),
)

F64 = npt.NDArray[np.float64]


def business_days_per_weekday() -> F64:
    """Number of 2018 business days (weekdays that are not federal holidays) per Mon..Fri."""
    counts = np.zeros(5)
    day = dt.date(YEAR, 1, 1)
    while day.year == YEAR:
        if day.weekday() < 5 and day not in US_FEDERAL_HOLIDAYS_2018:
            counts[day.weekday()] += 1
        day += dt.timedelta(days=1)
    return counts


def download_wheel(directory: Path) -> Path:
    subprocess.run(
        [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
         f"{PACKAGE}=={VERSION}", "-d", str(directory)],
        check=True,
    )
    wheels = sorted(directory.glob(f"{PACKAGE}-{VERSION}-*.whl"))
    if not wheels:
        raise FileNotFoundError(f"pip download left no {PACKAGE} {VERSION} wheel in {directory}")
    return wheels[0]


def read_csv(wheel: zipfile.ZipFile, name: str, header: list[str]) -> F64:
    """The numbers of CSV file `name` in the wheel, [rows, columns], after checking its header."""
    with wheel.open(name) as raw:
        text = io.TextIOWrapper(raw, encoding="utf-8", newline="")
        found = next(csv.reader(text))
        if found != header:
            raise ValueError(f"{name}: header {found}, expected {header}")
        body: F64 = np.loadtxt(text, delimiter=",", dtype=np.float64, ndmin=2)
        return body


def convex_hull(points: F64) -> F64:
    """Counter-clockwise convex hull of [N, 2] points (Andrew's monotone chain), [H, 2]."""
    pts = sorted(set(map(tuple, points.tolist())))

    def half(seq: list[tuple[float, float]]) -> list[tuple[float, float]]:
        out: list[tuple[float, float]] = []
        for p in seq:
            while len(out) >= 2:
                (ax, ay), (bx, by) = out[-2], out[-1]
                if (bx - ax) * (p[1] - ay) - (by - ay) * (p[0] - ax) > 0:
                    break
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1], dtype=np.float64)


def fan_triangles(hull: F64) -> tuple[F64, F64]:
    """Triangles (hull[0], hull[i], hull[i+1]) [T, 3, 2] of a convex polygon, and their areas."""
    tris = np.stack(
        [np.broadcast_to(hull[0], hull[1:-1].shape), hull[1:-1], hull[2:]], axis=1
    )
    e1, e2 = tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    return tris, 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def rotate(points: F64, degrees: float) -> F64:
    """Rotate [N, 2] points counter-clockwise about the origin (pyhailing's ``rotate_points``;
    its centre of rotation is a translation, which changes no distance)."""
    a = np.deg2rad(degrees)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    rotated: F64 = points @ rot.T
    return rotated


def sample_in(tris: F64, areas: F64, n: int, rng: np.random.Generator) -> F64:
    """`n` points uniform in the union of triangles (pyhailing's ``rand_pt_in_zone``)."""
    k = rng.choice(len(tris), size=n, p=areas / areas.sum())
    r1, r2 = np.sqrt(rng.uniform(size=(n, 1))), rng.uniform(size=(n, 1))
    t = tris[k]
    return (1 - r1) * t[:, 0] + r1 * (1 - r2) * t[:, 1] + r1 * r2 * t[:, 2]


def load_zones(wheel: zipfile.ZipFile) -> tuple[npt.NDArray[np.int64], F64, F64]:
    """Sorted LocationIDs [Z], rotated hull centroids [Z, 2] (km) and expected intra-zone L1
    distance [Z] (km) between two uniform points of each zone's hull."""
    features = json.loads(wheel.read(ZONES))["features"]
    rings: dict[int, F64] = {}
    for feature in features:
        if feature["geometry"]["type"] != "Polygon" or len(feature["geometry"]["coordinates"]) != 1:
            raise ValueError("pyhailing's zones must be single polygons without holes")
        ring = np.asarray(feature["geometry"]["coordinates"][0], dtype=np.float64)
        rings[int(feature["properties"]["zone_id"])] = rotate(ring, MANHATTAN_ANGLE_DEG)
    zones = np.array(sorted(rings), dtype=np.int64)
    rng = np.random.default_rng(0)
    centroids = np.zeros((len(zones), 2))
    intra = np.zeros(len(zones))
    for i, zone in enumerate(zones.tolist()):
        tris, areas = fan_triangles(convex_hull(rings[zone]))
        centroids[i] = (areas[:, None] * tris.mean(axis=1)).sum(axis=0) / areas.sum()
        a = sample_in(tris, areas, INTRA_ZONE_PAIRS, rng)
        b = sample_in(tris, areas, INTRA_ZONE_PAIRS, rng)
        intra[i] = np.abs(a - b).sum(axis=1).mean()
    return zones, centroids, intra


def zone_index(ids: F64, zones: npt.NDArray[np.int64], what: str) -> npt.NDArray[np.int64]:
    idx = np.searchsorted(zones, ids.astype(np.int64))
    idx = np.minimum(idx, len(zones) - 1)
    if not np.array_equal(zones[idx], ids.astype(np.int64)):
        raise ValueError(f"{what} has zones that the geojson lacks")
    return idx


def weekday_demand(wheel: zipfile.ZipFile, zones: npt.NDArray[np.int64]) -> F64:
    """Mean trips per 15-minute slot of one business day, [96, Z, Z]."""
    rows = read_csv(wheel, TRIPS, ["dow", "t_15min", "puzone", "dozone", "n_trips"])
    dow, slot = rows[:, 0].astype(np.int64), rows[:, 1].astype(np.int64)
    if dow.min() < 0 or dow.max() > 4 or slot.min() < 0 or slot.max() >= SLOTS:
        raise ValueError("trips.csv: day of week outside Monday–Friday or slot outside 0..95")
    o, d = zone_index(rows[:, 2], zones, TRIPS), zone_index(rows[:, 3], zones, TRIPS)
    z = len(zones)
    totals = np.zeros((5, SLOTS, z, z))
    np.add.at(totals, (dow, slot, o, d), rows[:, 4])
    per_day = totals / business_days_per_weekday()[:, None, None, None]
    mean: F64 = per_day.mean(axis=0)
    return mean


def shortest_paths(times: F64) -> F64:
    """Fill NaN entries of [Z, Z] with shortest paths over the known ones (Floyd–Warshall)."""
    out = np.where(np.isnan(times), np.inf, times)
    for k in range(len(out)):
        out = np.minimum(out, out[:, k : k + 1] + out[k : k + 1, :])
    filled: F64 = np.where(np.isnan(times), out, times)
    if not np.isfinite(filled).all():
        raise ValueError("travel times: some zone pairs are unreachable over known pairs")
    return filled


def travel_minutes(
    wheel: zipfile.ZipFile, zones: npt.NDArray[np.int64], centroids: F64, intra: F64
) -> F64:
    """Mean driving minutes per hour of day between zone centroids, [24, Z, Z]."""
    rows = read_csv(wheel, SPEEDS, ["puzone", "dozone", "min", "speed_mean", "speed_stddev"])
    o, d = zone_index(rows[:, 0], zones, SPEEDS), zone_index(rows[:, 1], zones, SPEEDS)
    minute = rows[:, 2].astype(np.int64)
    if (minute % 15).any() or minute.min() < 0 or minute.max() >= 24 * 60:
        raise ValueError("speeds.csv: slot starts are not multiples of 15 minutes in one day")
    z = len(zones)
    speed = np.full((SLOTS, z, z), np.nan)
    if len(np.unique((minute // 15 * z + o) * z + d)) != len(rows):
        raise ValueError("speeds.csv has duplicate (zone, zone, slot) rows")
    speed[minute // 15, o, d] = rows[:, 3]
    speed[~(speed > 0)] = np.nan
    km = np.abs(centroids[:, None, :] - centroids[None, :, :]).sum(axis=-1)
    km[np.diag_indices(z)] = intra
    slot_minutes = km / speed / 60.0
    hourly = np.full((HOURS, z, z), np.nan)
    for h in range(HOURS):
        block = slot_minutes[4 * h : 4 * h + 4]
        known = ~np.isnan(block)
        mean = np.where(known, block, 0.0).sum(axis=0) / np.maximum(known.sum(axis=0), 1)
        hourly[h] = shortest_paths(np.where(known.any(axis=0), mean, np.nan))
    return hourly


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--wheel", type=Path, help="pyhailing-0.0.9 wheel (default: download)")
    parser.add_argument("--out", type=Path, default=DATA_DIR / "manhattan.npz")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        wheel_path = args.wheel if args.wheel is not None else download_wheel(Path(tmp))
        with zipfile.ZipFile(wheel_path) as wheel:
            zones, centroids, intra = load_zones(wheel)
            demand_weekday = weekday_demand(wheel, zones)
            minutes = travel_minutes(wheel, zones, centroids, intra)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            licence = args.out.parent / "LICENSE-pyhailing"
            with wheel.open(LICENSE) as src, open(licence, "wb") as dst:
                shutil.copyfileobj(src, dst)

    lo, hi = centroids.min(axis=0), centroids.max(axis=0)
    demand = demand_weekday.astype(np.float32)
    tables = {
        "zones": zones.astype(np.int16),
        "demand": demand,
        "travel_minutes": minutes.astype(np.float32),
        "coords": ((centroids - lo) / (hi - lo)).astype(np.float32),
    }
    if not all(np.isfinite(t).all() for t in tables.values()) or not (minutes > 0).all():
        raise ValueError("non-finite values or non-positive travel times")
    np.savez_compressed(args.out, **tables)

    size = args.out.stat().st_size
    print(f"Z = {len(zones)} zones, extent {hi[0] - lo[0]:.2f} × {hi[1] - lo[1]:.2f} km")
    print(f"weekday trips per day: {demand.sum():.0f}")
    print(f"travel minutes: mean {minutes.mean():.2f}, min {minutes.min():.2f}, "
          f"max {minutes.max():.2f}")
    print(f"wrote {args.out} ({size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
