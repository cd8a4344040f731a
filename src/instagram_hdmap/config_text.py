"""The text of a config: YAML read strictly and written so that it reads back the same, values
coerced to a key's declared type, nested dicts merged, and dotted keys (``model.gnn.layers``).

PyYAML reads YAML 1.1; a config is read as YAML 1.2 reads it: ``1e-3`` is a float, ``010`` is ten (not
octal 8), ``1:30`` is text (not base 60), a key written twice in one mapping is an error (PyYAML keeps
the last one silently), and ``_Dumper`` quotes text that would read back as a number. The dataclasses
these values fill are config.py's.
"""

from __future__ import annotations

import dataclasses
import datetime
import difflib
import math
import re
import reprlib
import types
import typing
from pathlib import Path
from typing import Any, Literal, Union

import yaml

from .errors import INVISIBLE, ConfigError

# Keys renamed since a release: (old dotted key, new dotted key). Old saved configs still load.
RENAMED_KEYS = (("train.max_minutes", "train.time_budget_min"),)


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if tp is type(None):
        return "null"
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list of {_type_name(args[0])}"
        return f"list of {len(args)} ({', '.join(_type_name(a) for a in args)})"
    return getattr(tp, "__name__", str(tp))


_SHORT = reprlib.Repr()  # (keyword arguments from Python 3.12 on)
_SHORT.maxlevel, _SHORT.maxlist, _SHORT.maxtuple, _SHORT.maxdict, _SHORT.maxset = 3, 6, 6, 6, 6
_SHORT.maxstring = _SHORT.maxother = 80


def _show(value: Any) -> str:
    """``repr(value)`` for a message, cut short: a list of a million items (YAML aliases) was printed whole."""
    return _SHORT.repr(value)


class _NotFinite(ConfigError):
    """A number of the right type that is NaN or infinite."""


def _hint(value: Any, tp: Any, key: str) -> str:
    """What to write instead, where YAML read the value as another type than the key's."""
    args = typing.get_args(tp) if typing.get_origin(tp) in (Union, types.UnionType) else (tp,)
    if str in args and isinstance(value, (bool, int, float, datetime.date)):  # name: 2024, version: 1.0, split: no
        where = '"..."' if "[" in key else f'{key.rpartition(".")[2]}: "..." in the YAML file'
        return f"; YAML reads yes / no / on / off, numbers and dates as such: quote the text to keep it text ({where})"
    if int in args and isinstance(value, float) and value.is_integer():  # epochs: 1e3
        return f"; write the whole number as {int(value)}"
    if any(typing.get_origin(a) is tuple for a in args) and isinstance(value, (str, int, float)):  # trainable=temporal
        return "; a list is written in brackets: [a, b] (one item: [a])"
    return ""


# the Python types a YAML value of a scalar annotation may have (an int is a valid float)
_ACCEPTS = {type(None): type(None), bool: bool, int: int, float: (int, float), str: str}


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Check ``value`` against the annotation ``tp``; return it in canonical form (tuples)."""
    origin = typing.get_origin(tp)
    bad = ConfigError(f"config key '{key}': expected {_type_name(tp)}, got {_show(value)} ({type(value).__name__})"
                      + _hint(value, tp, key))
    if origin is Literal:
        if value not in typing.get_args(tp):
            raise bad
        return value
    if origin in (Union, types.UnionType):
        for arg in typing.get_args(tp):
            try:
                return _coerce(value, arg, key)
            except _NotFinite:
                raise
            except ConfigError:
                continue
        raise bad
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise bad
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise bad
        return tuple(_coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    accepts = _ACCEPTS.get(tp)
    if accepts is None:
        raise ConfigError(f"config key '{key}': unsupported annotation {tp!r}")
    if not isinstance(value, accepts) or (isinstance(value, bool) and tp is not bool):  # True is an int in Python
        raise bad
    if tp is float:
        try:
            number = float(value)
        except OverflowError:  # an int too large for a float
            number = math.inf
        if not math.isfinite(number):
            raise _NotFinite(f"config key '{key}': expected a finite number, got {value!r}")
        return number
    if tp is str and not value.strip():  # `train.out_dir=$OUT` with OUT unset: "" would mean the working directory
        raise ConfigError(f"config key '{key}' is empty; give a value (an unset shell variable?)")
    return value


def _merge(obj: Any, updates: dict, prefix: str = "") -> Any:
    """Return a copy of dataclass ``obj`` with the nested ``updates`` applied and checked."""
    if updates is None and prefix:  # `train:` with every key below it commented out: YAML's null, an empty section
        updates = {}  # (it was refused: "must be a mapping, got None")
    if not isinstance(updates, dict):
        raise ConfigError(f"config section '{prefix.rstrip('.') or '<root>'}' must be a mapping, got {_show(updates)}")
    hints = typing.get_type_hints(type(obj))
    names = [f.name for f in dataclasses.fields(obj)]
    changes = {}
    for name, value in updates.items():
        key = prefix + str(name)
        if name not in names:
            renamed = dict(RENAMED_KEYS).get(key)  # a YAML or override of an older release: name the new key
            if renamed is not None:
                raise ConfigError(f"config key '{key}' was renamed '{renamed}'; write {renamed} (checkpoints "
                                  "saved with the old name still load)")
            dotted = "." in str(name)  # model.gnn.layers: 9 in a YAML file
            near = [] if dotted else difflib.get_close_matches(str(name).lower(), names, n=1, cutoff=0.75)  # Layers
            raise ConfigError(
                f"unknown config key '{key}'"
                + (f" (did you mean '{prefix}{near[0]}'?)" if near else "")
                + (" (YAML reads a key on / off / yes / no as true / false)" if isinstance(name, bool) else "")
                + (" (a YAML file nests the keys, model: {gnn: {layers: 9}}; the dotted form is the command line's)"
                   if dotted else "")
                + f"; valid keys of '{prefix.rstrip('.') or '<root>'}': {', '.join(names)}"
            )
        current = getattr(obj, name)
        if dataclasses.is_dataclass(current):
            changes[name] = _merge(current, value, key + ".")
        else:
            changes[name] = _coerce(value, hints[name], key)
    return dataclasses.replace(obj, **changes)


class _DuplicateKey(yaml.YAMLError):
    pass


class _StrictLoader(yaml.SafeLoader):
    """PyYAML's safe loader, except that a key written twice in one mapping is an error (PyYAML
    keeps the last one, so a section written twice silently loses the first one's keys)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            lines: dict = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *base`: its keys may be overridden
                    continue
                key = self.construct_object(key_node, deep=deep)
                try:
                    if key in lines:
                        raise _DuplicateKey(f"key {key!r} is written twice in one mapping (lines {lines[key]} and "
                                            f"{key_node.start_mark.line + 1}); YAML keeps only the last, so merge them")
                    lines[key] = key_node.start_mark.line + 1
                except TypeError:  # an unhashable key: construct_mapping names it
                    pass
        return super().construct_mapping(node, deep)

    def construct_yaml_int(self, node):
        """YAML 1.2's integers: PyYAML (YAML 1.1) reads ``010`` as octal 8 (``seed: 0123`` was 83) and ``1:30`` as
        base 60, 90 (``time_budget_min: 1:30:00`` was 5400 minutes); a leading zero is decimal here, and ``1:30``
        stays text (a number key refuses it, naming it)."""
        text = self.construct_scalar(node)
        if ":" in text:
            return text
        digits = text.replace("_", "").lstrip("+-")
        if len(digits) > 1 and digits.isdigit():
            return int(text.replace("_", ""), 10)
        return super().construct_yaml_int(node)

    def construct_yaml_float(self, node):
        text = self.construct_scalar(node)
        return text if ":" in text else super().construct_yaml_float(node)  # 1:30.5, YAML 1.1's base 60: text


_StrictLoader.add_constructor("tag:yaml.org,2002:int", _StrictLoader.construct_yaml_int)
_StrictLoader.add_constructor("tag:yaml.org,2002:float", _StrictLoader.construct_yaml_float)

# YAML 1.2 floats: PyYAML (YAML 1.1) reads "1e-3" (no dot, no exponent sign) as a string
_FLOAT_12 = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                  |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                  |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                  |[-+]?\.(?:inf|Inf|INF)
                  |\.(?:nan|NaN|NAN))$""", re.X)
_StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_12, list("-+0123456789."))


class _Dumper(yaml.SafeDumper):
    """``save_config``'s: a string that ``load_yaml`` reads as a number (``name: '3e-4'``, a YAML 1.2 float that
    PyYAML writes bare) is quoted, so that the saved config loads again (it was refused: "expected str")."""


_Dumper.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_12, list("-+0123456789."))


class _TooDeep(yaml.YAMLError):
    pass


def load_yaml(text: str):
    """YAML text -> Python values (safe types only; a key repeated in a mapping is an error)."""
    try:
        return yaml.load(text, Loader=_StrictLoader)
    except RecursionError:  # a raw RecursionError from PyYAML's composer, naming nothing
        raise _TooDeep("its lists or mappings are nested too deeply to read (hundreds of levels); a config "
                       "nests a few") from None


def _read_yaml(path: Path, seen: tuple[Path, ...] = ()) -> dict:
    # a pipe (`train <(envsubst < in.yaml)`, /dev/stdin) is read once, as a file is; it was "config file not found"
    if not path.is_file() and not (path.exists() and not path.is_dir()):
        raise ConfigError(f"config file not found: {path}" + (" (it is a folder)" if path.is_dir() else "")
                          + ("; key=value overrides go after the CONFIG file" if not seen and "=" in path.name
                             and not path.exists() else ""))
    if path.resolve() in seen:
        raise ConfigError(f"config file {path} includes itself through _base_")
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        what = "a zip archive such as a PyTorch checkpoint" if raw[:4] == b"PK\x03\x04" else "a binary file"
        raise ConfigError(f"config file {path} is not YAML text but {what}; the first argument is the experiment "
                          "YAML (a checkpoint goes with --checkpoint)") from None
    text = text.removeprefix("\ufeff")  # a byte-order mark (a Windows editor's) opens the file: read as before
    for number, line in enumerate(text.splitlines(), 1):
        chars = [c for c in INVISIBLE if c in line.split("#", 1)[0]]  # (in a comment it does no harm)
        if chars:  # YAML takes it for text: "unknown key '  epochs'", an out_dir whose name ends in it
            raise ConfigError(f"config file {path}, line {number}: {line.strip(' ')!r} holds {INVISIBLE[chars[0]]} "
                              f"(U+{ord(chars[0]):04X}), which an editor shows as a space or not at all (text copied "
                              "from a web page, a PDF or a chat?); type that line again")
    try:
        data = load_yaml(text) or {}
    except (_DuplicateKey, _TooDeep) as e:
        raise ConfigError(f"config file {path}: {e}") from None
    except yaml.YAMLError as e:
        raise ConfigError(f"config file {path} is not valid YAML: {' '.join(str(e).split())}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping at the top level")
    base = data.pop("_base_", None)
    if base is None:
        return data
    if not isinstance(base, str) or not base:
        raise ConfigError(f"config file {path}: '_base_' must name one YAML file (a path relative to {path.parent}), "
                          f"got {base!r}")
    base_path = path.parent / Path(base).expanduser()  # ~/...: the home folder, as the path keys (PATH_KEYS)
    if not base_path.is_file():
        raise ConfigError(f"config file {path}: its _base_ {base} ({base_path}) is not a file"
                          + (" but a folder" if base_path.is_dir() else "")
                          + f"; _base_ is a YAML file's path relative to {path.parent}")
    merged = _read_yaml(base_path, (*seen, path.resolve()))
    deep_update(merged, data)
    return merged


def deep_update(dst: dict, src: dict) -> None:
    """Merge the nested dict ``src`` into ``dst`` in place (``src`` wins)."""
    for k, v in src.items():
        if isinstance(v, dict) and isinstance(dst.get(k), dict):
            deep_update(dst[k], v)
        elif v is None and isinstance(dst.get(k), dict):  # an empty section (`train:`, its keys commented out)
            continue  # adds nothing to the _base_'s
        else:
            dst[k] = v


# --- dotted keys ("model.gnn.layers") of nested config dicts -----------------------------------------


def flatten(nested: dict, prefix: str = "") -> dict[str, Any]:
    """``{"model": {"gnn": {"layers": 7}}}`` -> ``{"model.gnn.layers": 7}`` (leaves in order)."""
    out: dict[str, Any] = {}
    for k, v in nested.items():
        out.update(flatten(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def get_key(nested: dict, dotted: str) -> Any:
    """The value at ``dotted`` (``"model.gnn.layers"``) of a nested dict."""
    for part in dotted.split("."):
        nested = nested[part]
    return nested


def set_key(nested: dict, dotted: str, value: Any) -> None:
    """Set the value at ``dotted`` of a nested dict (its parents must exist)."""
    *parents, last = dotted.split(".")
    for part in parents:
        nested = nested[part]
    nested[last] = value


def is_under(key: str, prefixes) -> bool:
    """``key`` is one of ``prefixes`` or lies below one: ``is_under("model.gnn.layers", ["model"])``."""
    return any(key == p or key.startswith(p + ".") for p in prefixes)
