"""The stage protocol: configs that describe their own command-line options, and config hashes.

Every stage is a function ``run(inputs..., config, out, progress=None) -> outputs``. Its config is a
dataclass; the fields a user may set from the command line carry their flag and help in the
field's metadata (:func:`option`), so the CLI derives its options from the config and a setting
is written once. Nested dataclass fields group settings (tracking's flow and prediction groups).

The pipeline decides whether a stage must run again from :func:`stage_hash`: the stage's config
(every field, not only the ones with flags) and the fingerprints of its inputs. A stage's own
folder keeps the config it ran with (``config.json``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import typing
from dataclasses import MISSING, dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

from ..errors import PhysavatarError


def option(default: Any = MISSING, help: str = "", flag: str | None = None, *, parse: Callable | None = None,
           choices: tuple | None = None, check: Callable[[Any], str | None] | None = None,
           default_factory: Any = MISSING, hash: bool = True) -> Any:
    """A config field that is also a command-line option.

    ``flag``: the option's name (default ``--field-name``). ``parse``: turns the option's text
    into the field's value (the option is then a string, e.g. a comma-separated camera list).
    ``choices``: the allowed values (an ``option --x: 'v' is not a, b or c`` message otherwise).
    ``check(value)``: returns a problem text, or None when the value is fine. ``hash=False``:
    the field does not change the stage's outputs (e.g. how many frames to process when a run
    can be extended), so it is left out of the stage hash.
    """
    meta = {"cli": True, "help": help, "flag": flag, "parse": parse, "choices": choices, "check": check,
            "hash": hash}
    if default_factory is not MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def camera_list(text: str) -> tuple[str, ...]:
    """An option's camera list: 'cam01, cam06' -> ('cam01', 'cam06'); '' -> () (none)."""
    return tuple(h.strip() for h in text.split(",") if h.strip())


def setting(default: Any = MISSING, *, default_factory: Any = MISSING, hash: bool = True) -> Any:
    """A config field without a command-line option (``hash=False``: left out of the stage hash)."""
    meta = {"cli": False, "hash": hash}
    if default_factory is not MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


@dataclass(frozen=True)
class OptionSpec:
    """One command-line option derived from a config field (``path``: the field's dotted name)."""

    path: str
    flag: str
    help: str
    type: Any
    default: Any
    parse: Callable | None
    choices: tuple | None
    check: Callable | None

    @property
    def param(self) -> str:
        """The keyword the CLI function receives it as."""
        return self.path.replace(".", "__")


def _hints(cls) -> dict:
    try:
        return typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001 - unresolved forward references: fall back to the raw strings
        return {f.name: f.type for f in fields(cls)}


def options(cls, prefix: str = "") -> Iterator[OptionSpec]:
    """The command-line options of config class ``cls``, nested groups flattened."""
    hints = _hints(cls)
    own = vars(cls).get("__annotations__", {})
    # a config's own options first, then those it inherits (e.g. GarmentFileOptions)
    for f in sorted(fields(cls), key=lambda f: f.name not in own):
        t = hints.get(f.name, f.type)
        if isinstance(t, type) and is_dataclass(t):
            yield from options(t, prefix + f.name + ".")
            continue
        meta = f.metadata
        if not meta.get("cli"):
            continue
        default = f.default if f.default is not MISSING else (
            f.default_factory() if f.default_factory is not MISSING else None)
        flag = meta.get("flag") or "--" + f.name.replace("_", "-")
        yield OptionSpec(prefix + f.name, flag, meta.get("help", ""), t, default, meta.get("parse"),
                         meta.get("choices"), meta.get("check"))


def apply_options(config, values: dict[str, Any]):
    """``config`` with the given option values (keyed by :attr:`OptionSpec.param`; None = not
    given) parsed, checked and set. Bad values raise one :class:`PhysavatarError` naming the flag."""
    specs = {s.param: s for s in options(type(config))}
    for param, value in values.items():
        if value is None:
            continue
        s = specs[param]
        if s.parse is not None:
            try:
                value = s.parse(value)
            except (TypeError, ValueError) as e:
                raise PhysavatarError(None, f"option {s.flag}: {e}") from None
        if s.choices is not None and value not in s.choices:
            allowed = ", ".join(map(str, s.choices[:-1])) + f" or {s.choices[-1]}" if len(s.choices) > 1 else str(s.choices[0])
            raise PhysavatarError(None, f"option {s.flag}: {value!r} is not {allowed}")
        if s.check is not None:
            problem = s.check(value)
            if problem:
                raise PhysavatarError(None, f"option {s.flag}: {problem}")
        config = set_path(config, s.path, value)
    return config


def set_path(config, path: str, value):
    """A copy of dataclass ``config`` with the (dotted) field ``path`` set to ``value``."""
    head, _, rest = path.partition(".")
    if rest:
        return dataclasses.replace(config, **{head: set_path(getattr(config, head), rest, value)})
    return dataclasses.replace(config, **{head: value})


def to_dict(config) -> dict:
    """The config as JSON-ready data (tuples as lists, paths as strings)."""
    return _jsonable(dataclasses.asdict(config))


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, Path):
        return str(x)
    if hasattr(x, "tolist"):
        return x.tolist()
    return x


def _hashed(config) -> dict:
    """The config's fields that change outputs (``hash=False`` fields left out), nested."""
    out = {}
    for f in fields(config):
        if not f.metadata.get("hash", True):
            continue
        v = getattr(config, f.name)
        out[f.name] = _hashed(v) if is_dataclass(v) and not isinstance(v, type) else _jsonable(v)
    return out


def fingerprint(path: str | Path) -> list:
    """What identifies an input on disk without reading it whole: for every file (a folder's,
    recursively) its relative path, size and modification time. A missing path is ``[]``."""
    p = Path(path)
    if p.is_file():
        st = p.stat()
        return [[p.name, st.st_size, st.st_mtime_ns]]
    if not p.is_dir():
        return []
    rows = []
    for q in sorted(p.rglob("*")):
        if q.is_file():
            st = q.stat()
            rows.append([str(q.relative_to(p)), st.st_size, st.st_mtime_ns])
    return rows


def stage_hash(config, inputs: dict[str, Any] | None = None) -> str:
    """A short hash of a stage's config (fields that change outputs) and inputs. An input is a
    path (fingerprinted with :func:`fingerprint`) or any JSON-able value (e.g. the hash of the
    stage that made it)."""
    data = {"config": _hashed(config) if is_dataclass(config) else _jsonable(config), "inputs": {}}
    for k, v in sorted((inputs or {}).items()):
        data["inputs"][k] = fingerprint(v) if isinstance(v, Path) else _jsonable(v)
    blob = json.dumps(data, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def to_argv(config) -> list[str]:
    """The command-line options that give ``config`` from its class's defaults (options whose
    value differs from the default; settings without a flag cannot be shown and are left out)."""
    base = type(config)()
    argv = []
    for s in options(type(config)):
        v, d = get_path(config, s.path), get_path(base, s.path)
        if v == d or v is None:
            continue
        if isinstance(v, bool):  # "--on/--off" flags, or a single flag that turns the default over
            on, _, off = s.flag.partition("/")
            argv.append((on if v else off) if off else s.flag)
        elif isinstance(v, (tuple, list)):
            argv += [s.flag, ",".join(map(str, v))]
        else:
            argv += [s.flag, str(v)]
    return argv


def get_path(config, path: str):
    for part in path.split("."):
        config = getattr(config, part)
    return config


def unflagged_changes(config) -> dict:
    """Settings without a command-line option whose value differs from the class default (dotted
    names), e.g. what a preset such as fit-appearance's ``--quick`` sets beyond its flags."""
    base = type(config)()
    flagged = {s.path for s in options(type(config))}
    out = {}

    def walk(c, b, prefix):
        for f in fields(c):
            v, d = getattr(c, f.name), getattr(b, f.name)
            path = prefix + f.name
            if is_dataclass(v) and not isinstance(v, type):
                walk(v, d, path + ".")
            elif path not in flagged and v != d:
                out[path] = _jsonable(v)

    walk(config, base, "")
    return out
