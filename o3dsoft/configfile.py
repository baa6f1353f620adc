"""YAML config files for dataclass settings (``o3dsoft train --config train.yaml``).

Every key is checked against the dataclass: an unknown or mistyped key is an error naming the
file, the line and the closest valid key, never silently ignored.
"""

from __future__ import annotations

import dataclasses
import difflib
import typing
from pathlib import Path
from typing import Any, Dict, Optional, Tuple, Union

from .errors import InputError, UsageError

PathLike = Union[str, Path]


def read_config(path: PathLike, cls: type, lines: Optional[Dict[str, int]] = None) -> Dict[str, Any]:
    """Checked settings of dataclass `cls` from a YAML file, as keyword arguments; `lines`, where
    given, receives the line of each top-level key (for errors found once the settings are merged
    with others).

    Nested dataclass fields (e.g. ``net:``) are read as nested mappings and returned as
    instances, starting from that field's defaults.

    Raises:
        UsageError: the file does not exist.
        InputError: YAML syntax error, a top level that is not a mapping, an unknown key or one
            given twice, a value of the wrong type, a nested mapping whose dataclass's
            ``validate()`` refuses it (each with file and line).
    """
    import yaml

    path = Path(path)
    if not path.is_file():
        raise UsageError(f"{path}: no such config file")
    try:
        node = yaml.compose(path.read_text(encoding="utf-8-sig"), Loader=yaml.SafeLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        raise InputError(f"{path}{where}: not valid YAML ({getattr(e, 'problem', e)})") from None
    if node is None:
        return {}
    return _read_mapping(path, node, cls, {} if lines is None else lines)


def _read_mapping(path: Path, node, cls: type, lines: Dict[str, int]) -> Dict[str, Any]:
    """The settings of the YAML mapping `node`, each checked; the line of each key into `lines`."""
    import yaml

    if not isinstance(node, yaml.MappingNode):
        raise InputError(f"{path} line {node.start_mark.line + 1}: expected a mapping of {cls.__name__} settings")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    out: Dict[str, Any] = {}
    first_line: Dict[str, int] = {}
    for key_node, value_node in node.value:
        key, line = key_node.value, key_node.start_mark.line + 1
        if key in first_line:  # YAML keeps the last silently: a setting given twice is a mistake
            raise InputError(f"{path} line {line}: {key!r} is given twice (first on line {first_line[key]})")
        first_line[key] = lines[key] = line
        if key not in fields:
            close = difflib.get_close_matches(str(key), fields, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise InputError(f"{path} line {line}: unknown key {key!r}{hint}; valid keys: {', '.join(fields)}")
        expected = hints[key]
        if dataclasses.is_dataclass(expected):
            if isinstance(value_node, yaml.ScalarNode) and value_node.value in ("", "null", "~"):
                raise InputError(f"{path} line {line}: {key!r} must be a mapping")
            within: Dict[str, int] = {}
            nested = expected(**_read_mapping(path, value_node, expected, within))
            try:
                getattr(nested, "validate", lambda: None)()
            except InputError as e:  # its ranges, named where the file gives them
                raise InputError(f"{path} line {within.get(getattr(e, 'field', ''), line)}: {e}") from None
            out[key] = nested
            continue
        try:
            value = yaml.SafeLoader(" ").construct_object(value_node, deep=True)
        except yaml.YAMLError as e:  # e.g. a !!python/... tag, which the safe loader refuses
            raise InputError(f"{path} line {line}: {key!r}: {getattr(e, 'problem', None) or e}") from None
        out[key] = _check_type(path, line, key, value, expected)
    return out


def _check_type(path: Path, line: int, key: str, value: Any, expected: Any) -> Any:
    """`value` converted to `expected` (int -> float, list -> tuple), or an InputError."""
    args = typing.get_args(expected)
    origin = typing.get_origin(expected)
    if origin is Union:
        if value is None and type(None) in args:
            return None
        (inner,) = [a for a in args if a is not type(None)]
        return _check_type(path, line, key, value, inner)
    if origin in (tuple, Tuple):
        if not isinstance(value, list):
            raise InputError(f"{path} line {line}: {key!r} must be a list, got {value!r}")
        return tuple(_check_type(path, line, key, v, args[0]) for v in value)
    if expected is float and isinstance(value, str):
        try:  # YAML 1.1 reads exponents without a dot, such as 1e-3, as strings
            value = float(value)
        except ValueError:
            pass
    ok = {
        bool: isinstance(value, bool),
        int: isinstance(value, int) and not isinstance(value, bool),
        float: isinstance(value, (int, float)) and not isinstance(value, bool),
        str: isinstance(value, str),
    }.get(expected)
    if ok is None:
        raise TypeError(f"unsupported config type {expected!r}")  # a programming error, not bad input
    if not ok:
        names = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
        raise InputError(f"{path} line {line}: {key!r} must be {names[expected]}, got {value!r}")
    return float(value) if expected is float else value


def write_config(path: PathLike, settings: Dict[str, Any]) -> None:
    """Write settings (a dataclass's ``to_dict()``) as YAML that :func:`read_config` reads back."""
    import yaml

    Path(path).write_text(yaml.safe_dump(settings, sort_keys=False))
