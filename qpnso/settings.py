"""Typed settings: one checker for every settings dataclass of qpnso.

A settings dataclass (``ControllerConfig``, ``CostWeights``, ``QPSettings``,
``SimulationConfig``, ``HandModel``, the scenario file's tables) calls
:func:`check` first thing in its ``__post_init__``: every field's value is
checked against the field's type hint and converted (NumPy scalars to Python
numbers, lists to tuples, a dict to the nested settings dataclass); its own
range checks follow and raise :func:`out_of_range`.  :func:`from_dict` builds
one from plain data (a TOML table), naming unknown keys with the valid ones.

Accepted values per type hint:

* ``float``: a finite ``int`` or ``float`` (not ``bool``, ``str`` or complex);
* ``int``: an ``int`` (not ``bool``, not ``2.5``); ``bool``: a ``bool``; ``str``: a ``str``;
* ``tuple[float, ...]`` / ``tuple[float, float, float]``: a list, tuple or 1-D array of such items;
* ``dict``: a dict (a TOML table); ``X | None``: ``None`` or an ``X``;
* a settings dataclass: an instance, or a dict built through the class's ``from_dict``.

Every error is a :class:`SettingError` (a :class:`qpnso.errors.ConfigError`)
whose message names where (the class or file), the key with its table path
(``weights.mass``), the value and what was expected::

    ControllerConfig: dt = '0.001': expected a finite number (int or float), got str
    bad.toml: weights: unknown key 'masss'; valid keys: friction_force, friction_torque, inertia, mass
"""

from __future__ import annotations

import dataclasses
import functools
import math
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeGuard

import numpy as np

from qpnso.errors import ConfigError

__all__ = ["SettingError", "check", "check_table", "from_dict", "keywords_checked", "out_of_range", "read_toml", "show"]


class SettingError(ConfigError):
    """A setting that is unknown, missing, of the wrong type or out of range.

    ``where``: the settings class or file; ``key``: the setting's dotted path
    there (``""`` for the whole table); ``problem``: what was expected;
    ``value``: :func:`show` of the value given, or None.
    """

    def __init__(self, where: str, key: str, problem: str, value: str | None = None) -> None:
        self.where, self.key, self.problem, self.value = where, key, problem, value
        head = " = ".join(part for part in (key, value) if part)
        super().__init__(": ".join(part for part in (where, head, problem) if part))

    def __reduce__(self):  # picklable (study workers)
        return type(self), (self.where, self.key, self.problem, self.value)

    def within(self, table: str = "", where: str | None = None) -> SettingError:
        """The same error seen from an enclosing table ``table`` (the key becomes
        ``table.key``) and, if given, from ``where`` (a class or file)."""
        key = ".".join(part for part in (table, self.key) if part).replace(".[", "[")
        return SettingError(self.where if where is None else where, key, self.problem, self.value)


def show(value: Any, limit: int = 80) -> str:
    """``repr`` of ``value`` as plain Python data (never ``np.float64(0.08)``), cut to ``limit`` characters."""
    text = repr(_plain(value))
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _plain(value: Any) -> Any:
    """NumPy scalars and arrays (also inside lists, tuples, dicts) as Python numbers and lists."""
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    if type(value) in (list, tuple):
        return type(value)(_plain(v) for v in value)
    if type(value) is dict:
        return {k: _plain(v) for k, v in value.items()}
    return value


def out_of_range(obj: Any, name: str, expected: str) -> SettingError:
    """The error for field ``name`` of settings ``obj``, whose value is not ``expected``
    (e.g. ``"must be > 0"``); the caller raises it."""
    return SettingError(type(obj).__name__, name, expected, show(getattr(obj, name)))


@functools.cache
def _field_types(cls: type) -> dict[str, Any]:
    """``{name: type hint}`` of the ``__init__`` fields of dataclass ``cls``."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if f.init}


def check(obj: Any) -> None:
    """Check every field of settings dataclass ``obj`` against its type hint and store
    the converted value (frozen dataclasses too); :class:`SettingError` if one does not fit."""
    cls: type = type(obj)
    where = cls.__name__
    for name, hint in _field_types(cls).items():
        object.__setattr__(obj, name, _field_value(hint, getattr(obj, name), name, where))


def keywords_checked(cls: type) -> type:
    """Class decorator (under ``@dataclass``): an unknown keyword given to ``cls(...)`` raises the
    :class:`SettingError` that :func:`from_dict` gives for an unknown key (the valid keys listed), instead of
    Python's ``TypeError``."""
    init = vars(cls)["__init__"]  # (the dataclass's own, from the class dict)

    @functools.wraps(init)
    def checked_init(self: Any, *args: Any, **kwargs: Any) -> None:
        _refuse_unknown(cls, kwargs, cls.__name__)
        init(self, *args, **kwargs)

    cls.__init__ = checked_init  # type: ignore[misc]
    return cls


def _refuse_unknown(cls: type, values: Mapping, where: str) -> None:
    """:class:`SettingError` naming the keys of ``values`` that are not fields of ``cls``, with the valid ones."""
    hints = _field_types(cls)
    unknown = sorted((str(k) for k in values if k not in hints))
    if unknown:
        raise SettingError(
            where,
            "",
            f"unknown key{'s' if len(unknown) > 1 else ''} "
            f"{', '.join(map(repr, unknown))}; valid keys: {', '.join(sorted(hints))}",
        )


def check_table(cls: type, values: Any, where: str = "") -> dict[str, Any]:
    """``values`` (a TOML table) checked against the fields of ``cls``, converted, without
    building ``cls`` (so without its range checks): unknown keys are listed with the valid
    ones, missing required keys named, nested tables built through their ``from_dict``."""
    where = where or cls.__name__
    if not isinstance(values, Mapping):
        raise SettingError(
            where, "", f"expected a table of {cls.__name__} settings, got {type(values).__name__}", show(values)
        )
    _refuse_unknown(cls, values, where)
    missing = [
        f.name
        for f in dataclasses.fields(cls)
        if f.init
        and f.name not in values
        and f.default is dataclasses.MISSING
        and f.default_factory is dataclasses.MISSING
    ]
    if missing:
        more = f" (and {', '.join(map(repr, missing[1:]))})" if len(missing) > 1 else ""
        raise SettingError(where, "", f"missing key {missing[0]!r}{more}")
    hints = _field_types(cls)
    return {name: _field_value(hints[name], value, name, where) for name, value in values.items()}


def from_dict(cls: type, values: Any, where: str = "") -> Any:
    """Build settings dataclass ``cls`` from plain data (a TOML table): :func:`check_table`,
    then ``cls(**values)`` and its range checks; errors name ``where`` (default: the class)."""
    checked = check_table(cls, values, where)
    try:
        return cls(**checked)
    except SettingError as exc:
        raise (exc.within(where=where) if where else exc) from None


def _field_value(hint: Any, value: Any, key: str, where: str) -> Any:
    """``value`` converted to type ``hint``, or the :class:`SettingError` naming ``key``."""
    nested = _dataclass_in(hint)
    if nested is not None and isinstance(value, Mapping):
        build = getattr(nested, "from_dict", None) or functools.partial(from_dict, nested)
        try:
            return build(value)
        except SettingError as exc:
            raise exc.within(key, where) from None
    try:
        converted = _convert(hint, value)
    except SettingError as exc:  # (an item of a list of settings tables: built by its class)
        raise exc.within(key, where) from None
    if converted is _BAD:
        raise SettingError(where, key, f"expected {_describe(hint)}, got {type(value).__name__}", show(value))
    return converted


_BAD = object()  # _convert's "does not fit"


def _convert(hint: Any, value: Any) -> Any:
    """``value`` as type ``hint`` (see the module doc), or ``_BAD``."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        for arm in args:
            converted = _convert(arm, value)
            if converted is not _BAD:
                return converted
        return _BAD
    if hint is Any:
        return value
    if hint is type(None):
        return None if value is None else _BAD
    if _is_dataclass_hint(hint):
        return value if isinstance(value, hint) else _BAD
    if hint is dict or origin is dict:
        return value if isinstance(value, dict) else _BAD
    if origin is tuple:
        if isinstance(value, np.ndarray) and value.ndim == 1:
            value = value.tolist()
        if not isinstance(value, (list, tuple)):
            return _BAD
        items = args[:1] * len(value) if len(args) == 2 and args[1] is Ellipsis else args
        if len(items) != len(value):
            return _BAD
        converted = tuple(_item(arm, v, i) for i, (arm, v) in enumerate(zip(items, value)))
        return _BAD if any(v is _BAD for v in converted) else converted
    if isinstance(value, np.generic):  # NumPy scalars as Python numbers (np.float64 is a float, too)
        value = value.item()
    if hint is bool or hint is str:
        return value if isinstance(value, hint) else _BAD
    if isinstance(value, bool):
        return _BAD
    if hint is int:
        return value if isinstance(value, int) else _BAD
    if hint is float and isinstance(value, (int, float)):
        try:
            converted = float(value)
        except OverflowError:  # an int beyond the float range
            return _BAD
        return converted if math.isfinite(converted) else _BAD
    if hint in (float, int):
        return _BAD
    raise TypeError(f"qpnso.settings: unsupported field type {hint!r}")


def _item(hint: Any, value: Any, i: int) -> Any:
    """Item ``i`` of a list as type ``hint``: a table built by the settings class's ``from_dict`` (a
    :class:`SettingError` names the item), else :func:`_convert`."""
    if _is_dataclass_hint(hint) and isinstance(value, Mapping) and hasattr(hint, "from_dict"):
        try:
            return hint.from_dict(value)
        except SettingError as exc:
            raise SettingError(
                exc.where, f"[{i}]" + ("." + exc.key if exc.key else ""), exc.problem, exc.value
            ) from None
    return _convert(hint, value)


def _is_dataclass_hint(hint: Any) -> TypeGuard[type]:
    """:func:`dataclasses.is_dataclass` of a type hint, which names a class (never an instance)."""
    return dataclasses.is_dataclass(hint)


def _dataclass_in(hint: Any) -> type | None:
    """The settings dataclass ``hint`` names (alone or in a union), or None."""
    arms = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
    return next((arm for arm in arms if _is_dataclass_hint(arm)), None)


def _describe(hint: Any) -> str:
    """What a value of type ``hint`` must be, in words."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return " or ".join(_describe(arm) for arm in typing.get_args(hint))
    args = typing.get_args(hint)
    if typing.get_origin(hint) is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_plural(args[0])}"
        if len(set(args)) == 1:
            return f"a list of {len(args)} {_plural(args[0])}"
        return f"a list of {len(args)} items ({', '.join(_describe(a) for a in args)})"
    if _is_dataclass_hint(hint):
        return f"a table of {hint.__name__} settings"
    return {
        float: "a finite number (int or float)",
        int: "an integer",
        bool: "true or false",
        str: "a string",
        dict: "a table",
        type(None): "None",
    }.get(hint, str(hint))


def _plural(hint: Any) -> str:
    """``_describe`` of a list's items, plural (``finite numbers``)."""
    return {float: "finite numbers", int: "integers", bool: "booleans", str: "strings"}.get(hint, _describe(hint))


def read_utf8(path: Path, error: type[Exception]) -> str:
    """The text of the file ``path``, UTF-8 (a leading byte-order mark dropped, as spreadsheets write one); an
    ``error`` names the file and why it cannot be read, or the line of its first byte that is not UTF-8."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise error(f"cannot read {path}: {exc.strerror or exc}") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line, byte = data.count(b"\n", 0, exc.start) + 1, data[exc.start]
        raise error(f"{path}: not UTF-8 text: line {line} has the byte 0x{byte:02x} ({exc.reason})") from None


def read_toml(path: str | Path, what: str = "file") -> dict:
    """The tables of the TOML file ``path``; a :class:`qpnso.errors.ConfigError` says that the ``what``
    (e.g. ``"config file"``) is not found, or names the file and TOML's own complaint."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{what} not found: {p}")
    try:
        return tomllib.loads(read_utf8(p, ConfigError))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
