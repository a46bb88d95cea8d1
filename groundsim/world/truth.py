"""Ground truth of a simulator run: one CSV row per camera frame (``python -m groundsim run --truth``).

The row is what the scoring needs to judge the onboard service: where the target and the observer
really were at the frame's capture time, and where the target's centre really projects in that
frame.  Everything is computed from the flown (JSBSim) poses, never from the commanded paths.

Columns, in this order (the first ten are the interface promised by the ``run`` issue; the others
follow them and may grow at the end only)::

    time_boot_us                   capture time, vehicle boot clock (the IrFrame's stamp)
    target_lat_deg, target_lon_deg, target_alt_m          WGS84 of the target body centre
    observer_lat_deg, observer_lon_deg, observer_alt_m    WGS84 of the observer body (what #33 reports)
    target_u_px, target_v_px       projection of the target centre (``groundsim.world.render.truth_pixel``:
                                   pixel convention of ``onboard.core.frames``); NaN behind the camera
    target_visible                 1 if in front of the camera and 0 <= u < width, 0 <= v < height
    seq                            the IrFrame's sequence number
    t_s                            scenario seconds
    target_{n,e,d}_m, target_{vn,ve,vd}_mps               local NED about the scenario origin
    observer_{n,e,d}_m
    cam_{n,e,d}_m                  camera optical centre (pod lever arm applied)
    q_ned_from_cam_{w,x,y,z}       camera attitude, Hamilton, w first (``onboard.core.frames``)
    range_m                        camera to target centre
    nav_att_err_{n,e,d}_rad        navigation error injected into the telemetry at this frame's tick
                                   (``groundsim.world.nav_errors``): rotation vector of R_reported R_true^T in
                                   NED, radians (constant bias + white), applied to #31 and #285
    nav_p_err_{n,e,d}_m            reported minus true observer position, NED metres (offset + drift
                                   * t_s + white), applied to #33; the velocity error is the drift rate
                                   All six are 0 with ``--nav-noise exact``.  Every other column is the
                                   truth, never the reported value.
    time_unix_us                   capture time in UTC (us since the UNIX epoch): the simulation's one wall
                                   clock (the scenario's ``start_time_utc`` + t_s), the same instant for every
                                   vehicle of a fleet whatever its boot clock; what SYSTEM_TIME maps boot time to

Altitudes are WGS84 ellipsoidal heights (treated as AMSL, as ``onboard.core.frames`` says).  Numbers
are written with Python's shortest round-trip ``repr`` (deterministic, lossless), NaN as ``nan``.

:class:`TruthWriter` writes the header at open and flushes every row as one whole line, so a run
stopped by SIGINT/SIGTERM (or read while it runs) leaves a file of whole lines with its header.
:func:`read_truth_csv` reads it back into arrays.

Every object of a scene (a scenario with a ``scene`` section: the target, other targets, birds, aircraft,
glints; ``groundsim.world.render.scene.ObjectLabel``) goes to a second file beside it,
``<truth stem>.objects.csv``, one line per object and frame (:data:`OBJECT_COLUMNS`)::

    seq, time_boot_us, t_s         the frame (as in the truth file)
    object_id, cls                 0 is the target of the truth file's target_* columns; cls target, bird,
                                   aircraft, glint
    u_px, v_px                     sub-pixel projection of the object's centre (NaN behind the camera)
    x0_px, y0_px, x1_px, y1_px     box of the pixels holding >= 10 % of its peak signal (end exclusive;
                                   NaN when not drawn)
    visibility                     visible, occluded (its centre behind a cloud of opacity >= 0.5 that leaves it
                                   under 3 NETD of contrast, or inside a
                                   nearer object's box, or the camera's shutter closed), out_of_frame; a
                                   frozen frame (the camera repeating its last image) repeats that image's rows
    contrast_netd                  peak |signal - local background| in NETD units (0 when not drawn)
    warm                           1 when the signal at that peak is above the local background, 0 when below
                                   it or not drawn (contrast_netd is a magnitude: a cold object has it too)
    range_m                        camera to the object's centre
    n_m, e_m, d_m                  the object's centre, local NED about the scenario origin (3-D truth)

The file is opened with the first frame that has object labels (none without a scene), so a scenario
without a scene writes exactly the one truth file as before.
"""

from __future__ import annotations

import csv
import dataclasses
import logging
import math
import os
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from onboard.core.errors import ConfigError, InputError, IrtrackError
from onboard.core.frames import GeodeticOrigin, PinholeIntrinsics, geodetic_from_ned, rotmat_from_quat

__all__ = [
    "OBJECT_COLUMNS",
    "objects_path",
    "TRUTH_COLUMNS",
    "REQUIRED_COLUMNS",
    "TruthRow",
    "TruthWriter",
    "TruthWriteError",
    "truth_row",
    "truth_json",
    "truth_json_schema",
    "TRUTH_JSON_VECTORS",
    "truth_objects_json",
    "read_truth_csv",
]

log = logging.getLogger(__name__)

#: The columns the issue promises, in order; extra columns come after them.
REQUIRED_COLUMNS = (
    "time_boot_us",
    "target_lat_deg",
    "target_lon_deg",
    "target_alt_m",
    "observer_lat_deg",
    "observer_lon_deg",
    "observer_alt_m",
    "target_u_px",
    "target_v_px",
    "target_visible",
)


@dataclass(frozen=True)
class TruthRow:
    """One frame's truth; field order is the CSV column order (see the module docstring).

    Integers: ``time_boot_us`` (>= 0), ``target_visible`` (0 or 1), ``seq`` (>= 0), ``time_unix_us`` (>= 0).  Every other
    field is a finite float except ``target_u_px``/``target_v_px``, which are NaN when the target
    is behind the camera.
    """

    time_boot_us: int
    target_lat_deg: float
    target_lon_deg: float
    target_alt_m: float
    observer_lat_deg: float
    observer_lon_deg: float
    observer_alt_m: float
    target_u_px: float
    target_v_px: float
    target_visible: int
    seq: int
    t_s: float
    target_n_m: float
    target_e_m: float
    target_d_m: float
    target_vn_mps: float
    target_ve_mps: float
    target_vd_mps: float
    observer_n_m: float
    observer_e_m: float
    observer_d_m: float
    cam_n_m: float
    cam_e_m: float
    cam_d_m: float
    q_ned_from_cam_w: float
    q_ned_from_cam_x: float
    q_ned_from_cam_y: float
    q_ned_from_cam_z: float
    range_m: float
    nav_att_err_n_rad: float = 0.0
    nav_att_err_e_rad: float = 0.0
    nav_att_err_d_rad: float = 0.0
    nav_p_err_n_m: float = 0.0
    nav_p_err_e_m: float = 0.0
    nav_p_err_d_m: float = 0.0
    time_unix_us: int = 0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in _INT_FIELDS:
                if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or int(v) < 0:
                    raise InputError(f"TruthRow.{f.name} must be a non-negative integer, got {v!r}")
                object.__setattr__(self, f.name, int(v))
                continue
            try:
                x = float(v)
            except (TypeError, ValueError):
                raise InputError(f"TruthRow.{f.name} must be a number, got {v!r}") from None
            if not (math.isfinite(x) or (f.name in _NAN_OK and math.isnan(x))):
                raise InputError(f"TruthRow.{f.name} must be finite, got {v!r}")
            object.__setattr__(self, f.name, x)
        if self.target_visible not in (0, 1):
            raise InputError(f"TruthRow.target_visible must be 0 or 1, got {self.target_visible}")

    def values(self) -> tuple:
        return tuple(getattr(self, name) for name in TRUTH_COLUMNS)


_INT_FIELDS = frozenset({"time_boot_us", "target_visible", "seq", "time_unix_us"})
_NAN_OK = frozenset({"target_u_px", "target_v_px"})

#: Every column, in order: :data:`REQUIRED_COLUMNS` first.
TRUTH_COLUMNS: tuple[str, ...] = tuple(f.name for f in fields(TruthRow))
if TRUTH_COLUMNS[: len(REQUIRED_COLUMNS)] != REQUIRED_COLUMNS:  # pragma: no cover - caught at import
    raise RuntimeError("TruthRow field order must start with REQUIRED_COLUMNS")


def truth_row(
    seq: int,
    time_boot_us: int,
    t_s: float,
    origin: GeodeticOrigin,
    intrinsics: PinholeIntrinsics,
    p_target_ned_m,
    v_target_ned_mps,
    p_observer_ned_m,
    p_cam_ned_m,
    q_ned_from_cam,
    *,
    target_lla=None,
    observer_lla=None,
    nav_error=None,
    time_unix_us: int = 0,
) -> TruthRow:
    """The truth row of one frame from true poses (pure).

    ``p_*`` (3,) local NED metres about ``origin``; ``q_ned_from_cam`` (4,) w-first.  The pixel is
    :func:`groundsim.world.render.truth_pixel` (the renderer's own projection); visibility as the module
    docstring says.  ``target_lla`` / ``observer_lla``: ``(lat_deg, lon_deg, alt_m)`` already
    computed with :func:`onboard.core.frames.geodetic_from_ned` about ``origin`` (a caller converting
    many rows at once passes them; otherwise they are computed here).  ``nav_error``: the
    :class:`groundsim.world.nav_errors.NavErrorSample` injected into the telemetry at this frame (None: zero).
    ``time_unix_us``: the frame's capture time in UTC (us since the UNIX epoch).
    """
    from groundsim.world.render import truth_pixel  # the renderer's projection; imported on first use

    p_t = np.asarray(p_target_ned_m, dtype=float)
    p_o = np.asarray(p_observer_ned_m, dtype=float)
    p_c = np.asarray(p_cam_ned_m, dtype=float)
    q_c = np.asarray(q_ned_from_cam, dtype=float)
    v_t = np.asarray(v_target_ned_mps, dtype=float)
    if target_lla is None or observer_lla is None:
        lat, lon, alt = geodetic_from_ned(np.stack([p_t, p_o]), origin)
        target_lla, observer_lla = (lat[0], lon[0], alt[0]), (lat[1], lon[1], alt[1])
    u, v = truth_pixel(intrinsics, p_c, rotmat_from_quat(q_c), p_t)
    visible = (
        math.isfinite(u) and math.isfinite(v) and 0.0 <= u < intrinsics.width_px and 0.0 <= v < intrinsics.height_px
    )
    return TruthRow(
        time_boot_us=time_boot_us,
        target_lat_deg=target_lla[0],
        target_lon_deg=target_lla[1],
        target_alt_m=target_lla[2],
        observer_lat_deg=observer_lla[0],
        observer_lon_deg=observer_lla[1],
        observer_alt_m=observer_lla[2],
        target_u_px=u,
        target_v_px=v,
        target_visible=int(visible),
        seq=seq,
        t_s=t_s,
        target_n_m=p_t[0],
        target_e_m=p_t[1],
        target_d_m=p_t[2],
        target_vn_mps=v_t[0],
        target_ve_mps=v_t[1],
        target_vd_mps=v_t[2],
        observer_n_m=p_o[0],
        observer_e_m=p_o[1],
        observer_d_m=p_o[2],
        cam_n_m=p_c[0],
        cam_e_m=p_c[1],
        cam_d_m=p_c[2],
        q_ned_from_cam_w=q_c[0],
        q_ned_from_cam_x=q_c[1],
        q_ned_from_cam_y=q_c[2],
        q_ned_from_cam_z=q_c[3],
        range_m=float(np.linalg.norm(p_t - p_c)),
        time_unix_us=time_unix_us,
        **(
            {}
            if nav_error is None
            else dict(
                nav_att_err_n_rad=nav_error.att_err_ned_rad[0],
                nav_att_err_e_rad=nav_error.att_err_ned_rad[1],
                nav_att_err_d_rad=nav_error.att_err_ned_rad[2],
                nav_p_err_n_m=nav_error.p_err_ned_m[0],
                nav_p_err_e_m=nav_error.p_err_ned_m[1],
                nav_p_err_d_m=nav_error.p_err_ned_m[2],
            )
        ),
    )


def _fmt(value) -> str:
    if isinstance(value, int):
        return str(value)
    return repr(float(value))  # shortest round-trip; 'nan' for NaN


#: Columns of the per-object truth file (see the module docstring).
OBJECT_COLUMNS = (
    "seq",
    "time_boot_us",
    "t_s",
    "object_id",
    "cls",
    "u_px",
    "v_px",
    "x0_px",
    "y0_px",
    "x1_px",
    "y1_px",
    "visibility",
    "contrast_netd",
    "warm",
    "range_m",
    "n_m",
    "e_m",
    "d_m",
)


def objects_path(truth_path) -> Path:
    """The per-object truth file beside ``truth_path``: ``out/truth.csv`` -> ``out/truth.objects.csv``."""
    p = Path(truth_path)
    return p.with_name(f"{p.stem}.objects.csv")


def object_rows(row: TruthRow, labels) -> list[list[str]]:
    """The per-object lines of one frame (strings, :data:`OBJECT_COLUMNS` order) from its ``ObjectLabel``s."""
    out = []
    for lab in labels:
        box = (math.nan,) * 4 if lab.box_px is None else tuple(int(b) for b in lab.box_px)
        out.append(
            [
                str(row.seq),
                str(row.time_boot_us),
                _fmt(row.t_s),
                str(int(lab.object_id)),
                lab.cls,
                _fmt(lab.u_px),
                _fmt(lab.v_px),
                *map(_fmt, box),
                lab.visibility,
                _fmt(lab.contrast_netd),
                str(int(lab.warm)),
                _fmt(lab.range_m),
                *map(_fmt, lab.p_ned_m),
            ]
        )
    return out


class TruthWriteError(IrtrackError):
    """The truth file could not be written (disk full, file system gone); one line."""


class TruthWriter:
    """Writes :class:`TruthRow` lines to ``path`` (parent directories created; an existing file
    is replaced).  The header is written and flushed at open; every :meth:`write` appends one
    whole line and flushes it.  A path that cannot be written raises :class:`ConfigError`
    naming ``option`` (the command's option that gave the path; none for a file a command places itself, as
    ``groundsim dataset`` its sequences' truth.csv) and the path."""

    def __init__(self, path, option: str = "--truth") -> None:
        self.path = Path(path)
        self._named = f"{option} {self.path}" if option else str(self.path)
        self.rows_written = 0
        self._objects = None  # the per-object file, opened with the first labelled frame
        try:
            if self.path.parent and not self.path.parent.exists():
                self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = open(self.path, "w", encoding="ascii", newline="")
            self._f.write(",".join(TRUTH_COLUMNS) + "\n")
            self._f.flush()
        except OSError as exc:
            raise ConfigError(f"{self._named}: cannot write: {exc.strerror or exc}") from None
        log.info("truth: writing %s", self.path)

    def write(self, row: TruthRow, labels=()) -> None:
        """One frame: its truth row, and its objects' lines (``labels``: ObjectLabel, see the module docstring)."""
        if self._f is None:
            raise InputError(f"truth writer for {self.path} is closed")
        if not isinstance(row, TruthRow):
            raise InputError(f"TruthWriter.write expects a TruthRow, got {type(row).__name__}")
        try:
            self._f.write(",".join(_fmt(v) for v in row.values()) + "\n")  # one write: one whole line
            self._f.flush()
            if labels:
                if self._objects is None:
                    self._objects = open(objects_path(self.path), "w", encoding="ascii", newline="")
                    self._objects.write(",".join(OBJECT_COLUMNS) + "\n")
                self._objects.write("".join(",".join(r) + "\n" for r in object_rows(row, labels)))
                self._objects.flush()
        except OSError as exc:
            raise TruthWriteError(f"{self._named}: write failed: {exc.strerror or exc}") from None
        self.rows_written += 1

    def close(self) -> None:
        objects, self._objects = self._objects, None
        if objects is not None:
            objects.close()
        f, self._f = self._f, None
        if f is not None:
            try:
                f.flush()
                os.fsync(f.fileno())
            except OSError as exc:  # a full disk at the very end: say so, the rows so far stay
                log.warning("truth: final flush of %s failed: %s", self.path, exc)
            finally:
                f.close()

    def __enter__(self) -> TruthWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_truth_csv(path) -> dict[str, np.ndarray]:
    """A truth CSV as ``{column: (N,) array}`` (int64 for integer columns, float64 otherwise).

    Raises :class:`InputError` naming the file and line when the header lacks a required column
    or a row has the wrong number of fields or a non-number.  Extra columns are kept.
    """
    p = Path(path)
    try:
        with open(p, encoding="ascii", newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read truth CSV: {exc}") from None
    if not rows:
        raise InputError(f"{p}: empty truth CSV (no header)")
    header = rows[0]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise InputError(f"{p}: line 1: header lacks {', '.join(missing)}")
    cols: dict[str, list] = {name: [] for name in header}
    for n, r in enumerate(rows[1:], start=2):
        if len(r) != len(header):
            raise InputError(f"{p}: line {n}: expected {len(header)} fields, got {len(r)}")
        for name, text in zip(header, r):
            try:
                cols[name].append(int(text) if name in _INT_FIELDS else float(text))
            except ValueError:
                raise InputError(f"{p}: line {n}: {name}: expected a number, got {text!r}") from None
    return {name: np.asarray(vals, dtype=np.int64 if name in _INT_FIELDS else float) for name, vals in cols.items()}


#: the vectors :func:`truth_json` adds to a row's columns, for viewers: key -> the columns it repeats
TRUTH_JSON_VECTORS: dict[str, tuple[str, str, str]] = {
    "target_ned_m": ("target_n_m", "target_e_m", "target_d_m"),
    "target_vel_ned_mps": ("target_vn_mps", "target_ve_mps", "target_vd_mps"),
    "camera_ned_m": ("cam_n_m", "cam_e_m", "cam_d_m"),
}


def truth_json(row: TruthRow) -> dict:
    """A truth row as ``irtrack.truth/1``: every CSV column (NaN as null) plus vectors for viewers."""
    out = {
        k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in dataclasses.asdict(row).items()
    }
    for name, columns in TRUTH_JSON_VECTORS.items():
        out[name] = [getattr(row, c) for c in columns]
    return out


def truth_json_schema(title: str) -> dict:
    """The JSON Schema (named ``title``: ``irtrack.truth/1``) of :func:`truth_json`'s message, made from
    :class:`TruthRow`'s fields, so that it names every key the message has: integers as the row's, numbers
    elsewhere (null where the row may hold NaN), and :data:`TRUTH_JSON_VECTORS`; every key always present."""
    props: dict[str, dict] = {}
    for name in TRUTH_COLUMNS:
        if name in _INT_FIELDS:
            props[name] = {"type": "integer", "minimum": 0}
        else:
            props[name] = {"type": ["number", "null"] if name in _NAN_OK else "number"}
    for name, columns in TRUTH_JSON_VECTORS.items():
        props[name] = {
            "type": "array",
            "items": {"type": "number"},
            "minItems": 3,
            "maxItems": 3,
            "description": ", ".join(columns),
        }
    return {
        "title": title,
        "description": "The simulator's exact state at one rendered frame (groundsim run --record; columns: "
        "groundsim/world/truth.py).",
        "type": "object",
        "properties": props,
        "required": list(props),
    }


def truth_objects_json(row: TruthRow, labels) -> dict:
    """A frame's object labels as ``irtrack.truth_objects/1`` (``groundsim run --record``): the lines
    :func:`object_rows` writes to ``<truth>.objects.csv``, with the box as ``[x, y, w, h]`` pixels (the CSV's
    end-exclusive ``x0, y0, x1, y1``; null when not drawn) and NaN as null."""

    def num(x: float):
        return float(x) if math.isfinite(x) else None

    objects = []
    for lab in labels:
        box = None if lab.box_px is None else [int(b) for b in lab.box_px]
        objects.append(
            {
                "id": int(lab.object_id),
                "cls": lab.cls,
                "u_px": num(lab.u_px),
                "v_px": num(lab.v_px),
                "box_px": None if box is None else [box[0], box[1], box[2] - box[0], box[3] - box[1]],
                "visibility": lab.visibility,
                "contrast_netd": num(lab.contrast_netd),
                "warm": bool(lab.warm),
                "range_m": num(lab.range_m),
                "p_ned_m": [num(c) for c in lab.p_ned_m],
            }
        )
    return {"seq": int(row.seq), "time_boot_us": int(row.time_boot_us), "t_s": num(row.t_s), "objects": objects}
