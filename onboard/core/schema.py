"""The one configuration system: pydantic v2 models, one YAML loader, one error format.

Every configuration object of irtrack -- the onboard daemon's sections (:mod:`onboard.app.config`
composes them; each is the config its component takes: :class:`~onboard.core.pose.PoseConfig`,
:class:`~onboard.io.mavlink_config.MavlinkConfig`, :class:`~onboard.io.record.RecordConfig` ...), the
estimator's and the image chain's (:class:`~onboard.estimation.map_estimator.MapConfig`,
:class:`~onboard.imaging.preprocess.ImagingParams` ...), the simulator's scenarios and noise cases
(:mod:`groundsim.world.scenario`) -- is a :func:`config_dataclass`: a frozen pydantic dataclass in strict
mode with ``extra="forbid"`` (a bool is not a number, ``640.0`` is not an integer, an unknown key is an
error).  A field is declared once, in a form the type checker reads::

    window_s: Annotated[float, Number(0.0, 600.0, lo_open=True)] = 20.0
    port: Annotated[int | None, Integer(1, 65535)] = None          # null allowed
    worker: Annotated[Literal["process", "thread"], Text()] = "process"  # the choices

The Python type is what mypy checks; the field type (:class:`Number`, :class:`Integer`, :class:`Flag`,
:class:`Text`, :class:`Texts`, :class:`Numbers`, :class:`Instance`) is pydantic metadata that builds
the validators and carries the one text that says what the field accepts, so an error reads the same
wherever the field is declared.  :func:`config_dataclass` is a ``dataclass_transform``: mypy sees the
fields and checks the constructor.  Cross-field rules live in the class's ``__post_init__`` and raise
:class:`Invalid` naming their field.

One error format, :class:`SchemaError` (a :class:`~onboard.core.errors.ConfigError`), one line::

    <source>: <field.path>: expected <what>, got <value>[; did you mean '<key>'?]

``<source>`` is the file, ``env IRTRACK_...``, ``--option``, ``<dict>``, or ``<ClassName>`` for a
direct construction; entry points print it and exit with :attr:`SchemaError.exit_code` (2).

One YAML loader, :func:`read_yaml`: safe, duplicate keys, aliases and nesting deeper than :data:`MAX_YAML_DEPTH`
refused, and YAML 1.2 numbers and booleans -- ``3e-1``
and ``1e-3`` are numbers (YAML 1.1, PyYAML's default, reads an exponent without a dot as a string), ``010``,
``0b11`` and ``1:30`` are strings (YAML 1.1 reads them as 8, 3 and 90), and only ``true`` / ``false`` are booleans
(``yes``, ``no``, ``on``, ``off`` are strings).

:func:`build` turns a parsed mapping into a config dataclass, descending into the fields whose type is
another config dataclass (a section), a tuple of them, or a union of them told apart by their ``model``
key; errors carry the full dotted path.  A class with ``__off_unless_enabled__ = True`` (a section that does
nothing unless its ``enabled`` is true) refuses a mapping that sets other keys without ``enabled``.  Pure: no I/O but :func:`read_yaml`'s, nothing at import time.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import re
import types
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Annotated, Any, TypeVar, dataclass_transform, overload

import pydantic
import pydantic.dataclasses
import yaml
from pydantic import BeforeValidator, ConfigDict, Field, GetCoreSchemaHandler, ValidationError, WrapValidator
from pydantic.annotated_handlers import core_schema  # pydantic's pydantic-core: the runtime list names pydantic

from onboard.core.errors import ConfigError

__all__ = [
    "SchemaError",
    "Invalid",
    "config_dataclass",
    "is_config_dataclass",
    "build",
    "NOT_A_KEY",
    "file_keys",
    "read_yaml",
    "show",
    "did_you_mean",
    "describe_range",
    "Number",
    "Integer",
    "Flag",
    "Text",
    "Texts",
    "Numbers",
    "Instance",
    "FieldType",
    "Bool",
    "NonNegativeFloat",
    "PositiveFloat",
    "NonNegativeInt",
    "PositiveInt",
    "to_plain",
    "check_value",
    "parse_yaml_text",
    "MAX_YAML_DEPTH",
    "YamlRefused",
]

MODEL_CONFIG = ConfigDict(strict=True, extra="forbid", arbitrary_types_allowed=True)
MISSING_TEXT = "nothing (the key is missing)"
SHOW_LIMIT = 120


# --------------------------------------------------------------------------- the error


def show(value: Any) -> str:
    """A value as one short line, YAML-flavoured (``true``, ``null``, strings quoted)."""
    if value is None:
        text = "null"
    elif isinstance(value, bool):
        text = str(value).lower()
    elif isinstance(value, (str, bytes, dict, list, tuple)):
        text = repr(value)
    else:
        text = str(value)
    text = " ".join(text.split())
    return text if len(text) <= SHOW_LIMIT else text[: SHOW_LIMIT - 3] + "..."


def did_you_mean(word: Any, options) -> str | None:
    """``"did you mean 'x'?"`` for the option closest to ``word`` (same letters first), or None."""
    options = [str(o) for o in options]
    same_case = [o for o in options if o.lower() == str(word).lower()]
    if same_case:
        return f"did you mean '{same_case[0]}'?"
    close = difflib.get_close_matches(str(word), options, n=1, cutoff=0.6)
    return f"did you mean '{close[0]}'?" if close else None


def _join(path: str, sub: str) -> str:
    if not sub:
        return path
    if not path:
        return sub.lstrip(".")
    return path + sub if sub.startswith("[") else f"{path}.{sub}"


class SchemaError(ConfigError):
    """One bad configuration value: ``<source>: <field>: expected <expected>, got <got>[; <hint>]``.

    Attributes: ``source``, ``field`` (dotted path; ``(document)``, ``(file)`` or ``line L, column C``),
    ``expected``, ``got`` (the text shown), ``hint``, ``line`` (1-based, YAML syntax errors only),
    ``exit_code`` 2.  Subclasses (``OnboardConfigError``, ``ScenarioError``) only rename it for their
    callers; :meth:`as_` re-issues an error as another subclass, source and path prefix changed.
    """

    exit_code = 2

    def __init__(
        self,
        source: Any,
        field: str,
        expected: str,
        got_text: str,
        hint: str | None = None,
        *,
        line: int | None = None,
        keys: tuple[str, ...] | None = None,
        owner: str | None = None,
    ):
        self.source = str(source)
        self.field = field or "(document)"
        self.expected = expected
        self.got = got_text
        self.hint = hint
        self.line = line
        self.keys = keys  # an unknown key: the keys that are allowed (the text names the section)
        self.owner = owner
        msg = f"{self.source}: {self.field}: expected {expected}, got {got_text}" + (f"; {hint}" if hint else "")
        super().__init__(" ".join(msg.split()))

    @classmethod
    def make(cls, source: Any, field: str, expected: str, got_text: str, hint: str | None = None, **kw) -> SchemaError:
        """An instance of ``cls`` whatever its own ``__init__`` signature."""
        err = cls.__new__(cls)
        SchemaError.__init__(err, source, field, expected, got_text, hint, **kw)
        return err

    def as_(self, cls: type[SchemaError], source: Any = None, prefix: str = "") -> SchemaError:
        """This error as ``cls``, from ``source`` (default: the same), its field under ``prefix``."""
        field = self.field if self.field.startswith(("(", "line ")) else _join(prefix, self.field)
        if self.field == "(document)" and prefix:
            field = prefix
        expected = self.expected
        if self.keys is not None:
            parent = field.rsplit(".", 1)[0] if "." in field else ""
            expected = f"a key of {parent or 'the document'} ({', '.join(self.keys)})"
        return cls.make(
            self.source if source is None else source,
            field,
            expected,
            self.got,
            self.hint,
            line=self.line,
            keys=self.keys,
            owner=self.owner,
        )


class Invalid(ValueError):
    """Raised by a model's own checks (``__post_init__``, field validators): ``field`` relative to the
    model (``""``: the field being validated), what was ``expected``, the value ``got``."""

    def __init__(
        self,
        field: str,
        expected: str,
        got: Any = dataclasses.MISSING,
        hint: str | None = None,
        got_text: str | None = None,
    ):
        self.field = field
        self.expected = expected
        self.got_text = (
            got_text if got_text is not None else (MISSING_TEXT if got is dataclasses.MISSING else show(got))
        )
        self.hint = hint
        super().__init__(f"{field}: expected {expected}, got {self.got_text}")


def _loc_path(loc: tuple) -> str:
    path = ""
    for part in loc:
        path = _join(path, f"[{part}]" if isinstance(part, int) else str(part))
    return path


_ERROR_PRIORITY = {
    "unexpected_keyword_argument": 0,
    "missing_argument": 1,
    "missing_keyword_only_argument": 1,
    "missing": 1,
}


def _from_validation(
    exc: ValidationError, cls: type, source: str, error: type[SchemaError] = SchemaError
) -> SchemaError:
    """The first problem of a pydantic ValidationError (unknown keys first) as a SchemaError."""
    errors = exc.errors(include_url=False)
    err = min(errors, key=lambda e: _ERROR_PRIORITY.get(e["type"], 2))
    kind, loc, ctx = err["type"], tuple(err["loc"]), err.get("ctx") or {}
    if loc and isinstance(loc[0], int) and dataclasses.is_dataclass(cls) and loc[0] < len(dataclasses.fields(cls)):
        loc = (dataclasses.fields(cls)[loc[0]].name,) + loc[1:]  # a positional argument: its field's name
    path = _loc_path(loc)
    value = err.get("input")
    keys = None
    hint = None
    if kind == "expected":
        expected, got, hint = ctx["expected"], show(value), ctx.get("hint") or None
    elif kind == "value_error" and isinstance(ctx.get("error"), Invalid):
        inv = ctx["error"]
        path, expected, got, hint = _join(path, inv.field), inv.expected, inv.got_text, inv.hint
    elif kind == "value_error":
        inner = ctx.get("error")
        expected, got = "a consistent configuration", " ".join(str(inner if inner is not None else err["msg"]).split())
    elif kind == "unexpected_keyword_argument":
        keys = file_keys(cls)
        expected = f"a key of {cls.__name__} ({', '.join(keys)})"
        got, hint = f"unknown key {loc[-1]!r}", did_you_mean(loc[-1], keys)
    elif kind.startswith("missing"):
        expected, got = "a value (required)", MISSING_TEXT
    elif kind == "unexpected_positional_argument":
        expected, got = f"at most {len(dataclasses.fields(cls))} arguments", show(value)
    elif kind in ("tuple_type", "list_type"):  # pydantic's words name its Python type: "a valid tuple"
        expected, got = "a list", show(value)
    else:  # a field without a constrained type of ours: pydantic's own words
        expected, got = err["msg"].removeprefix("Input should be ").rstrip("."), show(value)
    return error.make(source, path, expected, got, hint, keys=keys, owner=getattr(cls, "__name__", None))


# --------------------------------------------------------------------------- models


_T = TypeVar("_T")


@overload
def config_dataclass(cls: type[_T], /) -> type[_T]: ...


@overload
def config_dataclass(*, error: type[SchemaError] = ..., kw_only: bool = ...) -> Callable[[type[_T]], type[_T]]: ...


@dataclass_transform(frozen_default=True, field_specifiers=(dataclasses.field, Field))
def config_dataclass(
    cls: type[_T] | None = None, /, *, error: type[SchemaError] = SchemaError, kw_only: bool = False
) -> type[_T] | Callable[[type[_T]], type[_T]]:
    """A frozen, strict, ``extra="forbid"`` pydantic dataclass whose constructor raises ``error`` (a
    :class:`SchemaError`, source ``<ClassName>``) instead of pydantic's ValidationError; ``kw_only``: the
    fields are keyword-only."""

    def wrap(c: type[_T]) -> type[_T]:
        # the class itself, turned into a pydantic dataclass (typed by pydantic as its PydanticDataclass protocol)
        dc = typing.cast(type[_T], pydantic.dataclasses.dataclass(frozen=True, config=MODEL_CONFIG, kw_only=kw_only)(c))
        init = dc.__init__

        @functools.wraps(init)
        def __init__(self: Any, *args: Any, **kwargs: Any) -> None:
            try:
                init(self, *args, **kwargs)
            except ValidationError as exc:
                raise _from_validation(exc, dc, f"<{dc.__name__}>", error) from None

        setattr(dc, "__init__", __init__)  # noqa: B010 - mypy refuses assigning a method
        setattr(dc, "__config_dataclass__", True)  # noqa: B010
        return dc

    return wrap if cls is None else wrap(cls)


def is_config_dataclass(tp: Any) -> bool:
    return (
        isinstance(tp, type) and getattr(tp, "__config_dataclass__", False) and "__config_dataclass__" in _mro_dicts(tp)
    )


def _mro_dicts(tp: type) -> set[str]:
    return {k for c in tp.__mro__ for k in vars(c)}


def _hints(cls: type) -> dict[str, Any]:
    return _HINTS.setdefault(cls, typing.get_type_hints(cls, include_extras=True))


_HINTS: dict[type, dict[str, Any]] = {}


def _strip(tp: Any) -> Any:
    while typing.get_origin(tp) is Annotated:
        tp = typing.get_args(tp)[0]
    return tp


def _union_members(tp: Any) -> tuple[Any, ...]:
    tp = _strip(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return tuple(_strip(a) for a in typing.get_args(tp))
    return (tp,)


def _model_choice(members: tuple[type, ...]) -> dict[str, type]:
    """``{model name: class}`` of a union of sections told apart by their ``model`` field's default."""
    out = {}
    for m in members:
        f = next((f for f in dataclasses.fields(m) if f.name == "model"), None)
        if f is None or f.default is dataclasses.MISSING:
            raise TypeError(f"{m.__name__} in a section union needs a 'model' field with a default")
        out[f.default] = m
    return out


#: ``dataclasses.field(metadata=NOT_A_KEY)``: a field the program sets (e.g. a noise case's name, its key in
#: the file), not a key of the mapping :func:`build` reads
NOT_A_KEY = types.MappingProxyType({"file_key": False})


def file_keys(cls: type) -> tuple[str, ...]:
    """The keys of ``cls`` in a file: its fields but those marked :data:`NOT_A_KEY`."""
    return tuple(f.name for f in dataclasses.fields(cls) if f.metadata.get("file_key", True))


def build(
    cls: type, raw: Any, path: str = "", *, none_is_default: bool = True, given: Mapping[str, Any] | None = None
) -> Any:
    """A config dataclass ``cls`` from a parsed mapping (None: the defaults) and the ``given`` values of its
    :data:`NOT_A_KEY` fields; raises :class:`SchemaError` whose field is the full path under ``path``
    (source ``<ClassName>``; callers re-issue it with theirs)."""
    if raw is None and none_is_default:
        raw = {}
    names = list(file_keys(cls))
    if not isinstance(raw, Mapping):
        raise SchemaError.make(
            f"<{cls.__name__}>", path, f"a mapping with keys {', '.join(names)}", show(raw), owner=cls.__name__
        )
    for k in raw:
        if not isinstance(k, str):
            raise SchemaError.make(
                f"<{cls.__name__}>", path, f"string keys (one of {', '.join(names)})", show(k), owner=cls.__name__
            )
    hints = _hints(cls)
    kwargs: dict[str, Any] = {}
    for key, value in raw.items():
        sub = _join(path, key)
        if key in names:
            value = _build_value(hints[key], value, sub)
        kwargs[key] = value
    try:
        for key in kwargs:
            if key not in names and key in {f.name for f in dataclasses.fields(cls)}:  # not one the file sets
                raise SchemaError.make(
                    f"<{cls.__name__}>",
                    key,
                    f"a key of {cls.__name__} ({', '.join(names)})",
                    f"unknown key {key!r}",
                    did_you_mean(key, names),
                    keys=tuple(names),
                    owner=cls.__name__,
                )
        obj = cls(**kwargs, **(given or {}))
    except SchemaError as exc:
        if exc.owner != cls.__name__:  # raised by a library object built inside: not ours to re-path
            raise
        return _raise(exc.as_(type(exc), prefix=path))
    # after the values' own checks, which name the more specific mistake
    if getattr(cls, "__off_unless_enabled__", False) and "enabled" not in raw and raw:
        # a section drawn or sent only when enabled: its settings written without ``enabled`` would be read and
        # silently do nothing, which is never what the writer meant
        raise SchemaError.make(
            f"<{cls.__name__}>",
            _join(path, "enabled"),
            "true (or false, to keep the section off with its settings)",
            MISSING_TEXT,
            f"the section sets {', '.join(map(str, raw))} but is off unless enabled",
        )
    return obj


def _raise(exc: Exception) -> Any:
    raise exc


def _build_value(tp: Any, value: Any, path: str) -> Any:
    members = _union_members(tp)
    sections = tuple(m for m in members if is_config_dataclass(m))
    if not sections:
        inner = _strip(tp)
        if typing.get_origin(inner) is tuple:
            args = typing.get_args(inner)
            if len(args) == 2 and args[1] is Ellipsis and is_config_dataclass(_strip(args[0])):
                return _build_list(_strip(args[0]), value, path)
        return value
    if value is None and type(None) in members:
        return None
    if len(sections) == 1:
        return build(sections[0], value, path)
    choice = _model_choice(sections)
    what = f"one of {', '.join(choice)}"
    if not isinstance(value, Mapping):
        raise SchemaError.make("<build>", path, f"a mapping with 'model' ({what}) and its parameters", show(value))
    if "model" not in value:
        raise SchemaError.make("<build>", _join(path, "model"), f"{what} (required)", MISSING_TEXT)
    model = value["model"]
    if not isinstance(model, str) or model not in choice:
        raise SchemaError.make(
            "<build>",
            _join(path, "model"),
            what,
            show(model),
            did_you_mean(model, choice) if isinstance(model, str) else None,
        )
    return build(choice[model], value, path)


def _build_list(cls: type, value: Any, path: str) -> Any:
    if not isinstance(value, (list, tuple)):  # a mapping is one entry written without its list, most often
        keys = ", ".join(file_keys(cls))
        raise SchemaError.make("<build>", path, f"a list of mappings with keys {keys}", show(value))
    return tuple(build(cls, v, f"{path}[{i}]", none_is_default=False) for i, v in enumerate(value))


@functools.lru_cache(maxsize=256)
def _adapter(tp: Any) -> pydantic.TypeAdapter:
    return pydantic.TypeAdapter(tp, config=MODEL_CONFIG)


def check_value(tp: Any, value: Any, path: str, source: Any, error: type[SchemaError] = SchemaError) -> Any:
    """One value against one field type (e.g. ``Integer(lo=0)``) outside a model: the clean value, or
    ``error`` naming ``source`` and ``path``."""
    try:
        return _adapter(tp).validate_python(value)
    except ValidationError as exc:
        err = _from_validation(exc, type(None), str(source), error)
        return _raise(err.as_(error, prefix=path))


def to_plain(obj: Any) -> Any:
    """Plain YAML-able data of a config (dataclasses -> dicts, tuples -> lists); :func:`build` of it gives
    the same object."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (tuple, list)):
        return [to_plain(x) for x in obj]
    if isinstance(obj, Mapping):
        return {k: to_plain(v) for k, v in obj.items()}
    return obj


# --------------------------------------------------------------------------- field types
#
# A field is declared ``name: Annotated[<Python type>, <FieldType>(...)] = default``: the Python type is
# what mypy sees (``X | None``: null is accepted; a ``Literal`` of strings: the choices of a :class:`Text`),
# the field type how pydantic checks it and the one "expected ..." text its errors show.


def _g(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def describe_range(
    noun: str, lo: float | None = None, hi: float | None = None, lo_open: bool = False, hi_open: bool = False
) -> str:
    """``"a number in (0, 1000]"``, ``"an integer >= 1"``, ``"a finite number"`` ..."""
    if lo is not None and hi is not None:
        return f"{noun} in {'(' if lo_open else '['}{_g(lo)}, {_g(hi)}{')' if hi_open else ']'}"
    if lo is not None:
        return f"{noun} {'>' if lo_open else '>='} {_g(lo)}"
    if hi is not None:
        return f"{noun} {'<' if hi_open else '<='} {_g(hi)}"
    return "a finite number" if noun == "a number" else noun


def _expect(text: str, hint: Callable[[Any], str | None] | None = None) -> WrapValidator:
    """Any failure of the wrapped type becomes one ``expected <text>`` error at the field."""

    def check(value: Any, handler: pydantic.ValidatorFunctionWrapHandler) -> Any:
        try:
            return handler(value)
        except ValidationError:
            raise Invalid("", text, value, hint(value) if hint else None) from None

    return WrapValidator(check)


def _python_scalar(value: Any) -> Any:
    """numpy scalars as Python numbers (a numpy bool stays refused: ``.item()`` gives a bool)."""
    if hasattr(value, "dtype") and hasattr(value, "item") and getattr(value, "shape", None) == ():
        return value.item()
    return value


def _split_none(tp: Any) -> tuple[Any, bool]:
    """``(X, True)`` for ``X | None``, ``(tp, False)`` otherwise."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if type(None) in args:
            rest = tuple(a for a in args if a is not type(None))
            return (rest[0] if len(rest) == 1 else typing.Union[rest]), True  # noqa: UP007 - a runtime union
    return tp, False


class FieldType:
    """The base of the field types: pydantic asks it for the schema of its ``Annotated`` type."""

    def _metadata(self, tp: Any, nullable: bool) -> tuple[Any, ...]:
        raise NotImplementedError

    def _require(self, tp: Any, *allowed: Any) -> None:
        if tp not in allowed:
            raise TypeError(f"{self!r} annotates {tp!r}; it checks {' or '.join(map(repr, allowed))}")

    def __get_pydantic_core_schema__(self, source: Any, handler: GetCoreSchemaHandler) -> core_schema.CoreSchema:
        tp, nullable = _split_none(source)
        return handler.generate_schema(Annotated[(source, *self._metadata(tp, nullable))])


@dataclasses.dataclass(frozen=True)
class Number(FieldType):
    """``Annotated[float, Number(lo, hi)]``: a finite float (an int is accepted and becomes a float; a bool
    is not) within the bounds; ``what`` replaces the text built from them."""

    lo: float | None = None
    hi: float | None = None
    _: dataclasses.KW_ONLY
    lo_open: bool = False
    hi_open: bool = False
    unit: str = ""
    what: str | None = None

    def text(self) -> str:
        return self.what or describe_range("a number", self.lo, self.hi, self.lo_open, self.hi_open) + (
            f" {self.unit}" if self.unit else ""
        )

    def _metadata(self, tp: Any, nullable: bool) -> tuple[Any, ...]:
        self._require(tp, float)
        bounds = {("gt" if self.lo_open else "ge"): self.lo, ("lt" if self.hi_open else "le"): self.hi}
        given: dict[str, Any] = {k: v for k, v in bounds.items() if v is not None}
        return (
            Field(allow_inf_nan=False, **given),
            BeforeValidator(_python_scalar),
            _expect(self.text() + (" or null" if nullable else "")),
        )


@dataclasses.dataclass(frozen=True)
class Integer(FieldType):
    """``Annotated[int, Integer(lo, hi)]``: an int (``640.0`` and ``true`` are not) within ``[lo, hi]``."""

    lo: int | None = None
    hi: int | None = None
    _: dataclasses.KW_ONLY
    what: str | None = None

    def _metadata(self, tp: Any, nullable: bool) -> tuple[Any, ...]:
        self._require(tp, int)
        text = self.what or describe_range("an integer", self.lo, self.hi)
        bounds: dict[str, Any] = {k: v for k, v in (("ge", self.lo), ("le", self.hi)) if v is not None}
        return Field(**bounds), BeforeValidator(_python_scalar), _expect(text + (" or null" if nullable else ""))


@dataclasses.dataclass(frozen=True)
class Flag(FieldType):
    """``Annotated[bool, Flag()]``: ``true`` or ``false``."""

    def _metadata(self, tp: Any, nullable: bool) -> tuple[Any, ...]:
        self._require(tp, bool)
        return (_expect("true or false" + (" or null" if nullable else "")),)


@dataclasses.dataclass(frozen=True)
class Text(FieldType):
    """``Annotated[str, Text()]``: a non-blank string (any string when ``empty``) matching ``pattern``;
    ``Annotated[Literal["a", "b"], Text()]``: one of the literal's strings, with a "did you mean"."""

    _: dataclasses.KW_ONLY
    pattern: str | None = None
    what: str | None = None
    empty: bool = False

    def _metadata(self, tp: Any, nullable: bool) -> tuple[Any, ...]:
        choices: tuple[str, ...] = ()
        if typing.get_origin(tp) is typing.Literal:
            choices = typing.get_args(tp)
            self._require(tuple(type(c) for c in choices), (str,) * len(choices))
        else:
            self._require(tp, str)
        text = (
            "one of " + ", ".join(choices)
            if choices
            else self.what or ("a string" if self.empty else "a non-empty string")
        )
        constraints: dict[str, Any] = {}
        if self.pattern is not None:
            constraints["pattern"] = self.pattern
        elif not self.empty and not choices:
            constraints["pattern"] = r"\S"
        hint = (lambda v: did_you_mean(v, choices) if isinstance(v, str) else None) if choices else None
        return Field(**constraints), _expect(text + (" or null" if nullable else ""), hint)


def _one_or_many(value: Any) -> Any:
    if isinstance(value, str):
        return (value,)
    return tuple(value) if isinstance(value, list) else value


@dataclasses.dataclass(frozen=True)
class Texts(FieldType):
    """``Annotated[tuple[str, ...], Texts()]``: a list of non-blank strings (one string is a list of one),
    held as a tuple."""

    def __get_pydantic_core_schema__(self, source: Any, handler: GetCoreSchemaHandler) -> core_schema.CoreSchema:
        self._require(source, tuple[str, ...])
        return handler.generate_schema(
            Annotated[
                tuple[Annotated[str, Field(pattern=r"\S")], ...],
                BeforeValidator(_one_or_many),
                _expect("a list of strings"),
            ]
        )


@dataclasses.dataclass(frozen=True)
class Numbers(FieldType):
    """``Annotated[tuple[float, ...], Numbers(n, lo)]`` (or ``tuple[float, float, float]`` for ``n`` = 3 ...): a list of ``n`` numbers (any length >= ``min_length``
    when ``n`` is None), each within ``lo`` .. ``hi``, held as a tuple of floats.

    The wrong shape is an error of the field (``expected a list of 3 finite numbers``); a bad element
    one of ``field[i]`` (``expected a finite number``)."""

    n: int | None = None
    lo: float | None = None
    _: dataclasses.KW_ONLY
    hi: float | None = None
    lo_open: bool = False
    unit: str = ""
    what: str | None = None
    min_length: int = 0

    def __get_pydantic_core_schema__(self, source: Any, handler: GetCoreSchemaHandler) -> core_schema.CoreSchema:
        shapes = [(float, ...)] + ([] if self.n is None else [(float,) * self.n])  # e.g. tuple[float, float, float]
        if typing.get_origin(source) is not tuple or typing.get_args(source) not in shapes:
            raise TypeError(f"{self!r} annotates {source!r}; it checks tuple[float, ...] or a tuple of {self.n} floats")
        n, unit = self.n, self.unit
        element = Number(self.lo, self.hi, lo_open=self.lo_open, unit=unit)
        elem_text = element.text()
        count = f"{n}" if n is not None else f"at least {self.min_length}"
        text = self.what or f"a list of {count} finite numbers" + (
            describe_range("", self.lo, self.hi, self.lo_open) if (self.lo, self.hi) != (None, None) else ""
        ) + (f" {unit}" if unit else "")
        elem = _adapter(Annotated[float, element])
        min_length = self.min_length

        def check(value: Any) -> tuple[float, ...]:
            if hasattr(value, "tolist") and hasattr(value, "dtype"):
                value = value.tolist()
            if not isinstance(value, (list, tuple)) or (len(value) != n if n is not None else len(value) < min_length):
                raise Invalid("", text, value)
            out = []
            for i, x in enumerate(value):
                try:
                    out.append(elem.validate_python(x))
                except ValidationError:
                    raise Invalid(f"[{i}]", elem_text, x) from None
            return tuple(out)

        return handler.generate_schema(Annotated[tuple[float, ...], pydantic.PlainValidator(check)])


class Instance(FieldType):
    """``Annotated[C, Instance(C, what="a C")]``: a runtime object (an instance of one of ``classes``, or
    passing ``check``), not built from YAML; ``C | None``: None too."""

    def __init__(self, *classes: type, what: str, check: Callable[[Any], bool] | None = None) -> None:
        self.classes = classes
        self.what = what
        self.check = check

    def __repr__(self) -> str:
        return f"Instance({', '.join(c.__name__ for c in self.classes)}, what={self.what!r})"

    def __get_pydantic_core_schema__(self, source: Any, handler: GetCoreSchemaHandler) -> core_schema.CoreSchema:
        nullable = _split_none(source)[1]
        what = self.what + (" or None" if nullable else "")

        def validate(value: Any) -> Any:
            if value is None and nullable:
                return None
            ok = self.check(value) if self.check is not None else isinstance(value, self.classes)
            if not ok:
                raise Invalid("", what, value)
            return value

        return handler.generate_schema(Annotated[Any, pydantic.PlainValidator(validate)])


#: the common field types, named once
Bool = Annotated[bool, Flag()]
NonNegativeFloat = Annotated[float, Number(lo=0.0)]
PositiveFloat = Annotated[float, Number(lo=0.0, lo_open=True)]
NonNegativeInt = Annotated[int, Integer(lo=0)]
PositiveInt = Annotated[int, Integer(lo=1)]


# --------------------------------------------------------------------------- the YAML loader


#: the deepest nesting of collections the loader reads: the shipped files nest at most 6, and each level costs the
#: composer three Python frames, so this stays far below the interpreter's recursion limit (1000)
MAX_YAML_DEPTH = 64


class YamlRefused(yaml.MarkedYAMLError):
    """YAML the loader refuses although PyYAML would read it; ``expected`` is what it accepts instead."""

    def __init__(self, expected: str, problem: str, mark: Any = None) -> None:
        super().__init__(None, None, problem, mark)
        self.expected = expected


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses duplicate keys, reads ``1e-3`` / ``3e-1`` as floats and only ``true`` / ``false`` as
    booleans (YAML 1.2: ``yes``, ``no``, ``on`` and ``off`` are strings, so a vehicle named ``on`` is one, and
    ``enabled: yes`` is refused by its field rather than read as true).

    Numbers are the decimal and hexadecimal integers and the decimal floats (``-5``, ``+3``, ``1_000``, ``0x1F``,
    ``0.5``, ``.5``, ``1e-3``, ``.inf``).  YAML 1.1's other integer forms are strings, refused by a number's field:
    ``010`` (octal 8 to YAML 1.1, 10 to YAML 1.2: the writer meant one of them, nobody can tell which), ``0b11`` and
    the base-60 ``1:30`` (90), which read as a number the writer did not see.

    It also refuses aliases (``*name``) and collections nested deeper than :data:`MAX_YAML_DEPTH`: a few hundred
    bytes of nested aliases expand to billions of values (memory and minutes before any field is checked), and
    a deep document exhausts the composer's recursion.  No configuration irtrack reads needs either (the
    compose files under ``deploy/`` use anchors, but Docker reads those, not this loader).  A scalar its tag
    cannot make (``!!int x``, a timestamp on 30 February) is a YAML error at its line, not a ValueError."""

    _depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent):
            raise YamlRefused(
                "YAML without aliases (write each value out)", f"the alias '*{event.anchor}'", event.start_mark
            )
        if self._depth >= MAX_YAML_DEPTH:
            raise YamlRefused(
                f"YAML nested at most {MAX_YAML_DEPTH} levels deep",
                f"a value nested deeper than {MAX_YAML_DEPTH} levels",
                event.start_mark,
            )
        self._depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_object(self, node: Any, deep: bool = False) -> Any:
        try:
            return super().construct_object(node, deep)
        except (ValueError, KeyError, TypeError, AttributeError, OverflowError) as exc:  # the tag's constructor
            tag = node.tag.replace("tag:yaml.org,2002:", "!!")
            got = show(node.value) if isinstance(node, yaml.ScalarNode) else f"a {node.id}"
            if isinstance(exc, (ValueError, OverflowError)):  # their words say what is wrong with the text
                got += f" ({' '.join(str(exc).split())})"
            raise YamlRefused(f"a value its tag {tag} can read", got, node.start_mark) from None


# the class's own copy of SafeLoader's implicit resolvers without YAML 1.1's booleans and numbers (SafeLoader's left
# as they are); the numbers and booleans this loader reads are added below
_YAML11_ONLY = {"tag:yaml.org,2002:bool", "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"}
_StrictLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag not in _YAML11_ONLY]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False):
    loader.flatten_mapping(node)
    seen: set = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=True)
        try:
            dup = key in seen
        except TypeError:  # unhashable key: the base constructor reports it
            break
        if dup:
            raise yaml.constructor.ConstructorError(
                "while constructing a mapping", node.start_mark, f"found duplicate key {key!r}", key_node.start_mark
            )
        seen.add(key)
    return yaml.SafeLoader.construct_mapping(loader, node, deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)
_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:int",
    re.compile(r"^[-+]?(?:0|[1-9][0-9_]*|0x[0-9a-fA-F_]+)$"),
    list("-+0123456789"),
)
_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+
        |[-+]?[0-9][0-9_]*\.[0-9_]*
        |[-+]?\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.VERBOSE,
    ),
    list("-+0123456789."),
)
_StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)


def parse_yaml_text(text: str) -> Any:
    """A YAML value (a file's text, an ``IRTRACK_...`` variable, a ``--set`` value) by the one loader's
    rules; raises ``yaml.YAMLError``."""
    try:
        return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - a SafeLoader subclass
    except RecursionError:  # MAX_YAML_DEPTH keeps the composer shallow; this is a caller already deep in its stack
        raise YamlRefused(f"YAML nested at most {MAX_YAML_DEPTH} levels deep", "a document too deeply nested") from None


def read_yaml(path: str | Path, error: type[SchemaError] = SchemaError) -> Any:
    """Read and parse one YAML file (None for an empty one); any problem raises ``error`` naming the file
    and, for syntax, the line and column."""
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error.make(source, "(file)", "an existing file", "no such file") from None
    except IsADirectoryError:
        raise error.make(source, "(file)", "a file", "a directory") from None
    except UnicodeDecodeError as e:
        raise error.make(source, "(file)", "UTF-8 text", f"undecodable byte at offset {e.start}") from None
    except OSError as e:
        raise error.make(source, "(file)", "a readable file", e.strerror or type(e).__name__) from None
    try:
        return parse_yaml_text(text)
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "(file)"
        problem = " ".join(f"{e.context or ''} {e.problem or ''}".split())
        expected = e.expected if isinstance(e, YamlRefused) else "valid YAML"
        raise error.make(
            source, where, expected, problem or "a syntax error", line=mark.line + 1 if mark else None
        ) from None
    except yaml.YAMLError as e:
        raise error.make(source, "(file)", "valid YAML", " ".join(str(e).split())) from None
