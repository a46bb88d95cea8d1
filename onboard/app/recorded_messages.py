"""The messages of a recording as :func:`onboard.app.replay.load_recording` reads them: each JSON message checked for
the fields replay and ``groundsim report`` read, and its schema for a version replay knows.  A message that fails
raises ValueError (or :class:`~onboard.core.errors.InputError` from the pose reader) saying what is wrong, which the
reader turns into one line naming the file, the message, its topic and log time (:func:`damage_text`)."""

from __future__ import annotations

import json
import math
from typing import Any

from onboard.core.track import TRACK_SCHEMA
from onboard.io.foxglove_messages import FRAME_INPUT_SCHEMA, IMAGING_POSE_SCHEMA, OBJECTS_SCHEMA, TRUTH_SCHEMA
from onboard.io.pose_json import pose_from_json
from onboard.io.record import FRAME_INPUT_TOPIC, IMAGING_POSE_TOPIC, TRUTH_TOPIC

__all__ = [
    "READ_VERSIONS",
    "TRUTH_NUMBERS",
    "TRUTH_NUMBERS_OR_NULL",
    "damage_text",
    "frame_input_row",
    "json_object",
    "track_row",
    "truth_objects_row",
    "truth_row",
    "unread_version",
]


#: the versions of the messages replay reads, by the topic or the schema family it finds them by: a later version's
#: fields may mean something else, so it is refused rather than read as this one (a track's /1 differs from /2 only
#: in when a position is published, which replay compares as recorded)
READ_VERSIONS = {
    FRAME_INPUT_TOPIC: (FRAME_INPUT_SCHEMA,),
    TRUTH_TOPIC: (TRUTH_SCHEMA,),
    IMAGING_POSE_TOPIC: (IMAGING_POSE_SCHEMA,),
    "irtrack.track/": ("irtrack.track/1", TRACK_SCHEMA),
    "irtrack.objects/": (OBJECTS_SCHEMA,),
}


def unread_version(topic: str, schema: str) -> str:
    """What is wrong when a message replay reads (by ``topic``, or by ``schema``'s family) is of a version it does
    not read; '' when nothing."""
    family = schema.split("/", 1)[0] + "/" if "/" in schema else None
    known = READ_VERSIONS.get(topic) or (READ_VERSIONS.get(family) if family else None)
    if known is None or schema in known:
        return ""
    return f"schema {schema!r}, a version this replay does not read (it reads {', '.join(known)}): a newer irtrack's?"


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _shown(value: Any) -> str:
    """``value`` as JSON, cut to a length that fits in an error line."""
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def json_object(data: bytes, ints: tuple[str, ...], pose: bool = False) -> dict:
    """``data`` as a JSON object whose fields ``ints`` are integers (replay matches frames on them) and, with
    ``pose``, whose ``pose`` field is null or a pose :func:`pose_from_json` reads; ValueError or InputError
    saying what is wrong otherwise."""
    obj = json.loads(data)
    if not isinstance(obj, dict):
        raise ValueError(f"{_shown(obj)} is not a JSON object")
    for name in ints + (("pose",) if pose else ()):
        if name not in obj:
            raise ValueError(f"no field {name!r}")
    for name in ints:
        if not _is_int(obj[name]):
            raise ValueError(f"field {name!r} is {_shown(obj[name])}, not an integer")
    if pose:
        pose_from_json(obj["pose"], "field 'pose'")
    return obj


#: the truth fields ``groundsim report`` reads: finite numbers in every row the simulator writes (TruthRow's), the
#: target's pixel a number or null (behind the camera), the injected navigation errors numbers where present
TRUTH_NUMBERS = tuple(
    f"{who}_{what}" for who in ("target", "observer") for what in ("lat_deg", "lon_deg", "alt_m")
) + tuple(f"q_ned_from_cam_{c}" for c in "wxyz")
TRUTH_NUMBERS_OR_NULL = ("target_u_px", "target_v_px") + tuple(f"nav_att_err_{c}_rad" for c in "ned")


def truth_row(data: bytes) -> dict:
    """A simulator's truth row (``irtrack.truth/1``), checked for the fields the report reads (a NaN latitude had
    made the error plot drop its frames unsaid, a missing one a traceback)."""
    obj = json_object(data, ("seq", "time_boot_us"))
    for name in TRUTH_NUMBERS + TRUTH_NUMBERS_OR_NULL:
        value = obj.get(name)
        if name in TRUTH_NUMBERS and name not in obj:
            raise ValueError(f"no field {name!r}")
        if value is None and name in TRUTH_NUMBERS_OR_NULL:
            continue
        if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)):
            raise ValueError(f"field {name!r} is {_shown(value)}, not a finite number")
    return obj


def truth_objects_row(data: bytes) -> dict:
    """A simulator's ``irtrack.truth_objects/1``, checked for the fields ``groundsim report``'s objects plot reads
    (:func:`groundsim.evaluation.mot.recorded_mot`): ``objects`` a list of objects, each with an integer ``id`` and
    its centre ``u_px``, ``v_px`` numbers or null (behind the camera)."""
    obj = json_object(data, ("seq", "time_boot_us"))
    objects = obj.get("objects")
    if not isinstance(objects, list):
        raise ValueError(f"field 'objects' is {objects!r}, not a list")
    for i, o in enumerate(objects):
        if not isinstance(o, dict):
            raise ValueError(f"objects[{i}] is {_shown(o)}, not a JSON object")
        if "id" not in o:
            raise ValueError(f"objects[{i}]: no field 'id'")
        if not _is_int(o["id"]):
            raise ValueError(f"objects[{i}]: field 'id' is {_shown(o['id'])}, not an integer")
        for name in ("u_px", "v_px"):
            value = o.get(name)
            if value is not None and not _is_number(value):
                raise ValueError(f"objects[{i}]: field {name!r} is {_shown(value)}, not a number or null")
    return obj


def frame_input_row(data: bytes) -> dict:
    """A recorded ``irtrack.frame_input/1``, checked for the fields replay reads: its frame's ``seq``,
    ``time_boot_us``, ``received_ns``, its ``pose``, and ``withheld_because`` (absent in recordings before the
    field) a list of warning codes, which the replay's pipeline withholds the frame's geometry for."""
    obj = json_object(data, ("seq", "time_boot_us", "received_ns"), pose=True)
    codes = obj.get("withheld_because", [])
    if not (isinstance(codes, list) and all(isinstance(c, str) for c in codes)):
        raise ValueError(f"field 'withheld_because' is {_shown(codes)}, not a list of strings")
    return obj


def track_row(data: bytes) -> dict:
    """A recorded track's JSON, checked for the fields :func:`compare_tracks` and :func:`compare_within_sigma` read."""
    obj = json_object(data, ("seq", "time_boot_us"))
    u, v = obj.get("u_px"), obj.get("v_px")
    if not ((u is None and v is None) or (_is_number(u) and _is_number(v))):
        raise ValueError(f"fields 'u_px', 'v_px' are {_shown(u)}, {_shown(v)}: not two numbers or two nulls")
    for name, shape in (("ned_m", (3,)), ("cov_ned_m2", (3, 3))):
        value = obj.get(name)
        if value is not None and not _numbers_of_shape(value, shape):
            raise ValueError(f"field {name!r} is {_shown(value)}, not null or {' x '.join(map(str, shape))} numbers")
    return obj


def _numbers_of_shape(value: Any, shape: tuple[int, ...]) -> bool:
    """Whether ``value`` is nested lists of numbers of ``shape``."""
    if not shape:
        return _is_number(value)
    return isinstance(value, list) and len(value) == shape[0] and all(_numbers_of_shape(v, shape[1:]) for v in value)


def damage_text(exc: BaseException) -> str:
    """What a decoding error says is wrong with a message, in words."""
    if isinstance(exc, (json.JSONDecodeError, UnicodeDecodeError)):
        return f"not JSON ({exc})"
    if isinstance(exc, KeyError):
        return f"no field {exc.args[0]!r}"
    if isinstance(exc, RecursionError):
        return "JSON nested too deeply"
    return str(exc)
