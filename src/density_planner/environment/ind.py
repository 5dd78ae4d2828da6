"""Recorded traffic in the inD format (Bock et al. 2020) -> occupancy scene.

Files of recording ``NN`` (two digits) in one folder, exactly as the inD data set ships them::

    NN_tracks.csv         one row per road user and frame: recordingId, trackId, frame, trackLifetime,
                          xCenter, yCenter [m], heading [deg], width, length [m], xVelocity, yVelocity [m/s],
                          xAcceleration, yAcceleration, lonVelocity, latVelocity, lonAcceleration,
                          latAcceleration
    NN_tracksMeta.csv     one row per road user: recordingId, trackId, initialFrame, finalFrame, numFrames,
                          width, length [m], class (car, truck_bus, pedestrian, bicycle)
    NN_recordingMeta.csv  one row: recordingId, locationId, frameRate [Hz] (25), speedLimit, weekday,
                          startTime, duration [s], numTracks, numVehicles, numVRUs, latLocation,
                          lonLocation, xUtmOrigin, yUtmOrigin, orthoPxToMeter [m per background pixel]
    NN_background.png     optional aerial image (static map, see below)

Only the columns this reader uses must be present (:data:`TRACKS_COLUMNS`, :data:`TRACKS_META_COLUMNS`,
:data:`RECORDING_META_COLUMNS`); others are ignored. Frame ``f`` is at time ``f / frameRate`` s.

Scene construction (:func:`load_ind_scene`):

1. time window ``[start_time, start_time + (n_slices - 1) dt]`` (default 10 s, 101 slices of 0.1 s); it
   must start inside the recording; where it runs past the recording's end (or past a road user's last
   frame), each road user is predicted from its last recorded slice (constant velocity and heading, position
   error growing with time: :func:`.footprints.extrapolate_tracks`), never dropped; ``scene.json`` records
   how many were predicted and from when;
2. every road user is resampled **exactly** to the slice times by linear interpolation between the two
   neighbouring frames (25 Hz -> 0.1 s = every 2.5 frames; heading along the shorter arc); a user is present
   at a slice only when both neighbouring frames exist;
3. map area: ``area`` if given, else the bounding box of the users' positions in the window grown by
   ``area_margin``, snapped outward to whole cells;
4. each user becomes the split-Gaussian footprint of :mod:`.footprints` (dimensions from ``tracksMeta``,
   class certainty, signed speed along the heading from ``xVelocity``/``yVelocity``);
   ``P_occ = clamp(static + sum)``;
5. optional static map from ``NN_background.png``: grey levels (0 black .. 1 white) below
   ``background_threshold`` (default: Otsu's threshold of the image) are occupied ("dark = occupied").
   Pixel size ``orthoPxToMeter * background_scale`` m with ``background_scale = 12``, the scale-down factor
   the inD tools use for their background images (an assumption: check it against your copy of the data
   set); pixel (col, row) is at world ``(col, -row) * pixel size`` (image top-left at the origin, y up).
   Cells outside the image are free;
6. start and goal from :func:`.sampling.sample_start_goal` (free cells 10-70 m apart, seeded).

Memory: the grid holds ``T * NX * NY`` float32 values: 101 slices of a 100 m x 80 m area at 0.1 m are
1001 x 801 cells = 324 MB (plus as much again for the cached gradient); use ``cell_size = 0.2`` (81 MB)
for larger maps. ``max_cells`` guards against accidental huge grids.
"""

from __future__ import annotations

import csv
import logging
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from density_planner.checks import check_seed
from density_planner.config import to_dict
from density_planner.errors import DataError

from .footprints import (
    ROAD_USER_CLASSES,
    FootprintConfig,
    RoadUserTracks,
    extrapolate_tracks,
    rasterise_road_users,
    resample_tracks,
)
from .grid import OccupancyGrid, lattice_size
from .sampling import StartGoalConfig, sample_start_goal
from .scene import Scene

__all__ = [
    "IndSceneConfig",
    "load_ind_scene",
    "read_tracks",
    "read_tracks_meta",
    "read_recording_meta",
    "ind_paths",
    "tracks_in_window",
    "read_background",
    "TRACKS_COLUMNS",
    "TRACKS_META_COLUMNS",
    "RECORDING_META_COLUMNS",
    "class_id",
    "map_lattice",
]

logger = logging.getLogger(__name__)

#: columns of ``NN_tracks.csv`` the reader needs
TRACKS_COLUMNS = ("trackId", "frame", "xCenter", "yCenter", "heading", "xVelocity", "yVelocity")
#: columns of ``NN_tracksMeta.csv`` the reader needs
TRACKS_META_COLUMNS = ("trackId", "initialFrame", "finalFrame", "width", "length", "class")
#: columns of ``NN_recordingMeta.csv`` the reader needs
RECORDING_META_COLUMNS = ("recordingId", "frameRate")

#: inD class names (and a few synonyms of related data sets) -> class ids of :data:`ROAD_USER_CLASSES`
_CLASS_NAMES = {
    "car": 0,
    "van": 0,
    "truck_bus": 1,
    "truck": 1,
    "bus": 1,
    "trailer": 1,
    "pedestrian": 2,
    "bicycle": 3,
    "motorcycle": 3,
}


def class_id(name: str) -> int:
    """Class id of an inD class name (unknown names are treated as cars, with a warning)."""
    key = name.strip().lower()
    if key not in _CLASS_NAMES:
        logger.warning("unknown road-user class %r treated as a car", name)
        return 0
    return _CLASS_NAMES[key]


@dataclass(frozen=True)
class IndSceneConfig:
    """How an inD recording becomes a scene (see the module docstring). Lengths in m, times in s."""

    #: start of the time window, seconds after frame 0 of the recording
    start_time: float = 0.0
    #: number of slices (window length (n_slices - 1) * dt)
    n_slices: int = 101
    #: time between slices [s]
    dt: float = 0.1
    #: cell edge [m]
    cell_size: float = 0.1
    #: map area (xmin, xmax, ymin, ymax) [m] in the recording's frame; empty = bounding box of the users +
    #: margin
    area: tuple[float, ...] = ()
    #: margin around the users' bounding box when ``area`` is empty [m]
    area_margin: float = 10.0
    #: refuse grids with more cells than this (T * NX * NY; 4 bytes each)
    max_cells: int = 300_000_000
    #: use ``NN_background.png`` as static map when it exists
    use_background: bool = True
    #: grey level in [0, 1] separating occupied from free pixels; negative = Otsu's threshold of the image
    background_threshold: float = -1.0
    #: which pixels are occupied: "dark" (below the threshold) or "bright"
    background_occupied: Literal["dark", "bright"] = "dark"
    #: background pixel size = orthoPxToMeter * background_scale [m]
    background_scale: float = 12.0
    #: footprint model of the road users
    footprint: FootprintConfig = field(default_factory=FootprintConfig)
    #: start/goal sampler rules
    start_goal: StartGoalConfig = field(default_factory=StartGoalConfig)
    #: seed of the start/goal sampler
    seed: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.start_time) and self.start_time >= 0):
            raise ValueError(f"IndSceneConfig.start_time must be >= 0 s, got {self.start_time}")
        if self.n_slices < 1:
            raise ValueError(f"IndSceneConfig.n_slices must be >= 1, got {self.n_slices}")
        for name in ("dt", "cell_size", "background_scale"):
            if not getattr(self, name) > 0:
                raise ValueError(f"IndSceneConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.area and (
            len(self.area) != 4 or self.area[0] >= self.area[1] or self.area[2] >= self.area[3]
        ):
            raise ValueError(
                f"IndSceneConfig.area must be (xmin, xmax, ymin, ymax) with min < max, got {self.area}"
            )
        if self.area_margin < 0:
            raise ValueError(f"IndSceneConfig.area_margin must be >= 0, got {self.area_margin}")
        if self.background_threshold > 1:
            raise ValueError(
                f"IndSceneConfig.background_threshold must be <= 1, got {self.background_threshold}"
            )
        check_seed("IndSceneConfig.seed", self.seed)


# ---------------------------------------------------------------------------------------------------- CSV
# reading
def ind_paths(data_dir: str | Path, recording: int) -> dict[str, Path]:
    """Paths of the files of ``recording`` in ``data_dir`` (``tracks``, ``tracks_meta``, ``recording_meta``,
    ``background``); they need not exist."""
    if isinstance(recording, bool) or not isinstance(recording, (int, np.integer)) or recording < 0:
        raise ValueError(f"recording must be a non-negative integer, got {recording!r}")
    d = Path(data_dir)
    p = f"{int(recording):02d}"
    return {
        "tracks": d / f"{p}_tracks.csv",
        "tracks_meta": d / f"{p}_tracksMeta.csv",
        "recording_meta": d / f"{p}_recordingMeta.csv",
        "background": d / f"{p}_background.png",
    }


def _header(path: Path, required: tuple[str, ...]) -> list[str]:
    if not path.is_file():
        raise DataError(f"inD file not found: {path}")
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            header = next(csv.reader(fh), None)
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read ({exc})") from exc
    if not header:
        raise DataError(f"{path}: empty file (expected a header line with {', '.join(required)})")
    header = [h.strip() for h in header]
    missing = [c for c in required if c not in header]
    if missing:
        raise DataError(f"{path}: missing column(s) {', '.join(missing)} (found: {', '.join(header)})")
    return header


def _bad_value(path: Path, header: list[str], columns: tuple[str, ...]) -> DataError:
    """Locate the first non-numeric entry among ``columns`` (slow path, only after a failed fast parse)."""
    wanted = [header.index(c) for c in columns]
    with path.open(newline="", encoding="utf-8-sig") as fh:
        reader = csv.reader(fh)
        next(reader)
        for line, row in enumerate(reader, start=2):
            if len(row) != len(header):
                return DataError(f"{path}: line {line} has {len(row)} fields, the header has {len(header)}")
            for i in wanted:
                try:
                    float(row[i])
                except ValueError:
                    return DataError(f"{path}: line {line}, column {header[i]!r}: {row[i]!r} is not a number")
    return DataError(f"{path}: cannot parse the numeric columns {', '.join(columns)}")


def _check_field_counts(path: Path, n_fields: int) -> None:
    """Every non-empty line of the CSV ``path`` has ``n_fields`` comma-separated fields (vectorised over the bytes;
    inD files quote nothing). A row with an extra or a missing field would otherwise be read with shifted columns."""
    try:
        buf = np.frombuffer(path.read_bytes(), dtype=np.uint8)
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc})") from exc
    if buf.size == 0:
        return
    newlines = np.flatnonzero(buf == 10)
    ends = newlines if buf[-1] == 10 else np.append(newlines, buf.size)
    starts = np.concatenate(([0], ends[:-1] + 1))
    cum = np.concatenate(([0], np.cumsum(buf == 44, dtype=np.int64)))
    commas = cum[ends] - cum[starts]
    length = ends - starts
    cr = (length > 0) & (buf[np.maximum(ends - 1, 0)] == 13)
    nonblank = (length - cr) > 0
    bad = np.flatnonzero(nonblank & (commas + 1 != n_fields))
    if bad.size:
        line = int(bad[0]) + 1
        raise DataError(
            f"{path}: line {line} has {int(commas[bad[0]]) + 1} fields, the header has {n_fields} "
            f"({bad.size} such line(s)); the file is malformed"
        )


def _read_numeric(path: Path, columns: tuple[str, ...], header: list[str]) -> dict[str, np.ndarray]:
    _check_field_counts(path, len(header))
    cols = [header.index(c) for c in columns]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": reported by the caller
            data = np.loadtxt(
                path, delimiter=",", skiprows=1, usecols=cols, dtype=np.float64, ndmin=2, encoding="utf-8-sig"
            )
    except ValueError:
        raise _bad_value(path, header, columns) from None
    return {c: data[:, i] for i, c in enumerate(columns)}


def _check_finite(path: Path, arrays: dict[str, np.ndarray], columns: tuple[str, ...]) -> None:
    for c in columns:
        bad = ~np.isfinite(arrays[c])
        if bad.any():
            row = int(np.argmax(bad))
            raise DataError(
                f"{path}: column {c!r} has {int(bad.sum())} NaN/infinite value(s) (first on line {row + 2})"
            )


def read_tracks(path: str | Path) -> dict[str, np.ndarray]:
    """The :data:`TRACKS_COLUMNS` of an ``NN_tracks.csv`` as float64 arrays (one entry per row).

    Raises :class:`DataError` for a missing file or column, a non-numeric or NaN value (naming line and
    column), or a file without rows.
    """
    path = Path(path)
    header = _header(path, TRACKS_COLUMNS)
    data = _read_numeric(path, TRACKS_COLUMNS, header)
    if data["frame"].size == 0:
        raise DataError(f"{path}: no track rows (the file has only a header)")
    _check_finite(path, data, TRACKS_COLUMNS)
    return data


def read_tracks_meta(path: str | Path) -> dict[str, np.ndarray]:
    """``NN_tracksMeta.csv``: numeric :data:`TRACKS_META_COLUMNS` as float64 arrays and ``class`` as
    strings."""
    path = Path(path)
    header = _header(path, TRACKS_META_COLUMNS)
    numeric = tuple(c for c in TRACKS_META_COLUMNS if c != "class")
    data = _read_numeric(path, numeric, header)
    if data["trackId"].size == 0:
        raise DataError(f"{path}: no rows (the file has only a header)")
    _check_finite(path, data, numeric)
    for c in ("width", "length"):
        neg = data[c] < 0
        if neg.any():
            row = int(np.argmax(neg))
            raise DataError(
                f"{path}: column {c!r} must be >= 0 m, got {data[c][row]:g} on line {row + 2} "
                f"({int(neg.sum())} negative value(s))"
            )
    ci = header.index("class")
    with path.open(newline="", encoding="utf-8-sig") as fh:
        reader = csv.reader(fh)
        next(reader)
        data["class"] = np.asarray([row[ci].strip() for row in reader if row], dtype=object)
    if data["class"].size != data["trackId"].size:
        raise DataError(f"{path}: inconsistent number of rows")
    return data


def read_recording_meta(path: str | Path) -> dict[str, float | str]:
    """The first data row of ``NN_recordingMeta.csv`` as a dict (numbers as floats, other text as strings)."""
    path = Path(path)
    header = _header(path, RECORDING_META_COLUMNS)
    with path.open(newline="", encoding="utf-8-sig") as fh:
        reader = csv.reader(fh)
        next(reader)
        row = next(reader, None)
    if not row:
        raise DataError(f"{path}: no data row")
    meta: dict[str, float | str] = {}
    for key, value in zip(header, row, strict=False):
        try:
            meta[key] = float(value)
        except ValueError:
            meta[key] = value.strip()
    rate = meta.get("frameRate")
    if not isinstance(rate, float) or not math.isfinite(rate) or rate <= 0:
        raise DataError(f"{path}: column 'frameRate' must be a positive number, got {rate!r}")
    return meta


# ---------------------------------------------------------------------------------------------------- window
def tracks_in_window(
    tracks: dict[str, np.ndarray],
    frame_rate: float,
    times: np.ndarray,
) -> dict[str, np.ndarray]:
    """Resample the rows of ``tracks`` to ``times`` [s]: arrays ``(N, T)`` per user (NaN where absent).

    Returns ``ids (N,)`` and ``x, y, heading [rad], vx, vy``. Vectorised: the rows in the window are scattered
    into a dense ``(N, frames)`` array and interpolated with :func:`.footprints.resample_tracks`.
    """
    f_lo = int(math.floor(times[0] * frame_rate + 1e-9))
    f_hi = int(math.ceil(times[-1] * frame_rate - 1e-9))
    frames = np.rint(tracks["frame"]).astype(np.int64)
    rows = np.nonzero((frames >= f_lo) & (frames <= f_hi))[0]
    ids, user = np.unique(tracks["trackId"][rows], return_inverse=True)
    n_frames = f_hi - f_lo + 1
    dense = {}
    for name, col, scale in (
        ("x", "xCenter", 1.0),
        ("y", "yCenter", 1.0),
        ("heading", "heading", math.pi / 180),
        ("vx", "xVelocity", 1.0),
        ("vy", "yVelocity", 1.0),
    ):
        a = np.full((ids.size, n_frames), np.nan)
        a[user, frames[rows] - f_lo] = tracks[col][rows] * scale
        dense[name] = a
    src_times = (f_lo + np.arange(n_frames)) / frame_rate
    out = (
        resample_tracks(dense, src_times, times, angles=("heading",))
        if ids.size
        else {k: np.zeros((0, times.size)) for k in dense}
    )
    out["ids"] = ids
    return out


def read_background(
    path: Path, px_size: float, xs: np.ndarray, ys: np.ndarray, *, threshold: float, occupied: str
) -> np.ndarray:
    """``(NX, NY)`` float32 static occupancy (0/1) from a background image sampled at cell centres ``xs``,
    ``ys``."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            grey = np.asarray(im.convert("L"), dtype=np.float32) / 255.0
    except (OSError, UnidentifiedImageError) as exc:
        raise DataError(f"{path}: cannot read background image ({exc})") from exc
    thr = _otsu(grey) if threshold < 0 else threshold
    occ = (grey < thr) if occupied == "dark" else (grey > thr)
    rows, cols = grey.shape
    ci = np.floor(xs / px_size).astype(np.int64)
    ri = np.floor(-ys / px_size).astype(np.int64)
    ok_c = (ci >= 0) & (ci < cols)
    ok_r = (ri >= 0) & (ri < rows)
    out = occ[np.clip(ri, 0, rows - 1)[None, :], np.clip(ci, 0, cols - 1)[:, None]]
    out = out & ok_c[:, None] & ok_r[None, :]
    logger.info(
        "background %s: threshold %.3f, %.1f %% of the map occupied", path.name, thr, 100 * out.mean()
    )
    return out.astype(np.float32)


def _otsu(grey: np.ndarray) -> float:
    """Otsu's threshold of grey levels in [0, 1] (maximises the between-class variance of a 256-bin
    histogram)."""
    hist, edges = np.histogram(grey, bins=256, range=(0.0, 1.0))
    p = hist.astype(np.float64) / max(hist.sum(), 1)
    centres = (edges[:-1] + edges[1:]) / 2
    w0 = np.cumsum(p)
    m0 = np.cumsum(p * centres)
    mt = m0[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (mt * w0 - m0) ** 2 / (w0 * (1 - w0))
    between[~np.isfinite(between)] = -1
    return float(edges[int(np.argmax(between)) + 1])


def _snap_area(area: tuple[float, float, float, float], cell: float) -> tuple[float, float, float, float]:
    """Grow ``area`` outward to whole multiples of ``cell`` (so the lattice contains both ends)."""
    x0 = math.floor(area[0] / cell + 1e-9) * cell
    x1 = math.ceil(area[1] / cell - 1e-9) * cell
    y0 = math.floor(area[2] / cell + 1e-9) * cell
    y1 = math.ceil(area[3] / cell - 1e-9) * cell
    return (round(x0, 9), round(x1, 9), round(y0, 9), round(y1, 9))


def map_lattice(
    area: tuple[float, float, float, float], cell: float, n_slices: int, max_cells: int, source: str
) -> tuple[tuple[float, float, float, float], int, int]:
    """Snapped area and ``(NX, NY)`` of a map, refusing more than ``max_cells`` cells in total."""
    area = _snap_area(area, cell)
    nx, ny = lattice_size(area[0], area[1], cell), lattice_size(area[2], area[3], cell)
    total = n_slices * nx * ny
    if total > max_cells:
        raise ValueError(
            f"{source}: a {area[1] - area[0]:.0f} m x {area[3] - area[2]:.0f} m map at {cell:g} m cells and "
            f"{n_slices} slices has {total / 1e6:.0f} M cells ({4 * total / 2**30:.1f} GiB), more than "
            "max_cells="
            f"{max_cells}; use a coarser cell_size or a smaller area"
        )
    return area, nx, ny


# ---------------------------------------------------------------------------------------------------- scene
def load_ind_scene(data_dir: str | Path, recording: int, config: IndSceneConfig | None = None) -> Scene:
    """Scene of inD recording ``recording`` in ``data_dir`` (see the module docstring for every step)."""
    cfg = config or IndSceneConfig()
    paths = ind_paths(data_dir, recording)
    rec = read_recording_meta(paths["recording_meta"])
    meta_tracks = read_tracks_meta(paths["tracks_meta"])
    tracks = read_tracks(paths["tracks"])
    rate = float(rec["frameRate"])
    last_frame = float(tracks["frame"].max())
    first_frame = float(tracks["frame"].min())
    rec_end = last_frame / rate
    duration = rec.get("duration")
    if isinstance(duration, float) and math.isfinite(duration):
        rec_end = min(rec_end, duration) if duration > 0 else rec_end
    t_end = cfg.start_time + (cfg.n_slices - 1) * cfg.dt
    if cfg.start_time < first_frame / rate - 1e-9 or cfg.start_time > rec_end - 1e-9:
        raise DataError(
            f"time window [{cfg.start_time:g}, {t_end:g}] s starts outside recording {recording} "
            f"({first_frame / rate:g}-{rec_end:g} s in {paths['tracks'].name}); "
            "set --start-time (or --set ind.start_time=...) inside it"
        )
    if t_end > rec_end + 1e-9:
        logger.info(
            "inD recording %d ends at %.2f s, before the window's end %.2f s: road users are predicted past "
            "their last frame (constant velocity and heading)", recording, rec_end, t_end
        )
    times = cfg.start_time + cfg.dt * np.arange(cfg.n_slices)
    win = tracks_in_window(tracks, rate, times)
    ids = win["ids"]
    # dimensions and classes from tracksMeta
    lookup = {int(t): i for i, t in enumerate(meta_tracks["trackId"])}
    missing = [int(t) for t in ids if int(t) not in lookup]
    if missing:
        raise DataError(
            f"{paths['tracks_meta']}: no entry for trackId(s) {missing[:10]} found in {paths['tracks'].name}"
        )
    rows = np.asarray([lookup[int(t)] for t in ids], dtype=np.int64)
    cls = np.asarray([class_id(str(c)) for c in meta_tracks["class"][rows]], dtype=np.int64)
    heading = win["heading"]
    speed = win["vx"] * np.cos(heading) + win["vy"] * np.sin(heading)
    users = RoadUserTracks(
        x=win["x"],
        y=win["y"],
        heading=heading,
        speed=speed,
        length=meta_tracks["length"][rows],
        width=meta_tracks["width"][rows],
        cls=cls,
        ids=ids.astype(np.int64),
    )
    present = users.present  # recorded slices (before the prediction below)
    users = extrapolate_tracks(users, times)
    predicted = users.predicted_for is not None and bool((users.predicted_for > 0).any())
    # map area
    if cfg.area:
        a0, a1, a2, a3 = (float(v) for v in cfg.area)  # four numbers (IndSceneConfig checks)
        area = (a0, a1, a2, a3)
    else:
        if not present.any():
            raise DataError(
                f"recording {recording}: no road user in the window [{cfg.start_time:g}, {t_end:g}] s; "
                "give an "
                "explicit area to build an empty map"
            )
        px, py = users.x[present], users.y[present]
        m = cfg.area_margin
        area = (float(px.min()) - m, float(px.max()) + m, float(py.min()) - m, float(py.max()) + m)
    area, nx, ny = map_lattice(area, cfg.cell_size, cfg.n_slices, cfg.max_cells, f"inD recording {recording}")
    origin = (area[0], area[2])
    static = None
    used_background = False
    if cfg.use_background and paths["background"].is_file():
        px_m = rec.get("orthoPxToMeter")
        if not isinstance(px_m, float) or not px_m > 0:
            raise DataError(
                f"{paths['recording_meta']}: column 'orthoPxToMeter' is needed for the background image"
            )
        xs = origin[0] + cfg.cell_size * np.arange(nx)
        ys = origin[1] + cfg.cell_size * np.arange(ny)
        static = torch.from_numpy(
            read_background(
                paths["background"],
                px_m * cfg.background_scale,
                xs,
                ys,
                threshold=cfg.background_threshold,
                occupied=cfg.background_occupied,
            )
        )
        used_background = True
    probs = rasterise_road_users(
        users,
        origin=origin,
        cell_size=cfg.cell_size,
        shape=(cfg.n_slices, nx, ny),
        config=cfg.footprint,
        static=static,
    )
    grid = OccupancyGrid(probs, origin, cfg.cell_size, cfg.dt, cfg.start_time, in_range=True)
    box = (area[0] + 0.1, area[1] - 0.1, area[2] + 0.1, area[3] - 0.1)
    start, goal = sample_start_goal(grid, box, seed=cfg.seed, config=cfg.start_goal)
    n_present = present.any(axis=1)
    meta = {
        "source": "ind",
        "data_dir": str(Path(data_dir)),
        "recording": int(recording),
        "frame_rate": rate,
        "window_s": [cfg.start_time, t_end],
        "recording_end_s": rec_end,
        "road_users_predicted": int(np.any(np.asarray(users.predicted_for) > 0, axis=1).sum()) if predicted else 0,
        "prediction": "constant velocity and heading past the last recorded frame; position std grows by "
        f"{cfg.footprint.prediction_std_rate_along:g} m/s along, {cfg.footprint.prediction_std_rate_across:g} "
        "m/s across the heading",
        "background": used_background,
        "road_users": [
            {
                "track_id": int(users.ids[i]),
                "class": ROAD_USER_CLASSES[int(users.cls[i])],
                "length": float(users.length[i]),
                "width": float(users.width[i]),
                "slices_present": int(present[i].sum()),
            }
            for i in np.nonzero(n_present)[0]
        ],
        "config": to_dict(cfg),
    }
    return Scene(grid, start, goal, box, name=f"ind-rec{int(recording):02d}-t{cfg.start_time:g}", meta=meta)
