"""Typer commands whose options come from a stage's config dataclass (:mod:`stages.base`).

``@config_command(app, "fit-physics", PhysicsConfig)`` on ``def fit_physics(source: Path = typer.Argument(...),
out: Path = typer.Option(...), *, config: PhysicsConfig)`` gives the command the function's own
arguments plus one option per config field that carries :func:`stages.base.option` metadata. The
function receives the config with the given options applied (parsed, checked: bad values are one
``option --x: ...`` message). A setting is thus written once, in the config.
"""

from __future__ import annotations

import functools
import inspect
import types
import typing
from typing import Any, Callable, Optional

import typer

from ..stages.base import apply_options, options


def _cli_type(spec) -> Any:
    if spec.parse is not None:
        return str
    t = spec.type
    origin = typing.get_origin(t)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(t) if a is not type(None)]
        t = args[0] if len(args) == 1 else str
    if t in (bool, int, float, str):
        return t
    return str


def _shown_default(spec) -> str | bool:
    """What ``--help`` shows as the default (False: nothing)."""
    d = spec.default
    if isinstance(d, bool):
        on, _, off = spec.flag.partition("/")
        shown = on if d else (off or "--no-" + on[2:])
    elif isinstance(d, (tuple, list)):
        shown = ",".join(map(str, d)) or "none"
    else:
        shown = d
    return False if shown is None or shown == "" else str(shown)


def config_command(app: typer.Typer, name: str | None, config_cls, *, base: Callable[[], Any] | None = None,
                   skip: tuple[str, ...] = (), wrap: Callable | None = None):
    """Register ``fn`` as command ``name`` with ``config_cls``'s options (except ``skip``, dotted
    field paths). ``base()`` gives the config the options are applied to (default
    ``config_cls()``); ``wrap`` decorates the final function (the CLI's error handler)."""

    def deco(fn):
        own = [p for p in inspect.signature(fn).parameters.values() if p.name != "config"]
        hints = typing.get_type_hints(fn)
        own = [p.replace(annotation=hints.get(p.name, p.annotation), kind=inspect.Parameter.KEYWORD_ONLY) for p in own]
        specs = [s for s in options(config_cls) if s.path not in skip]
        taken = {p.name for p in own}
        params = list(own)
        for s in specs:
            if s.param in taken:
                raise TypeError(f"{fn.__name__}: option {s.param} is both an argument and a config field")
            decls = [s.flag] if "/" in s.flag or _cli_type(s) is not bool else [f"{s.flag}/--no-{s.flag[2:]}"]
            params.append(inspect.Parameter(s.param, inspect.Parameter.KEYWORD_ONLY,
                                            default=typer.Option(None, *decls, help=s.help, show_default=_shown_default(s)),
                                            annotation=Optional[_cli_type(s)]))

        @functools.wraps(fn)
        def command(**kw):
            values = {s.param: kw.pop(s.param) for s in specs}
            config = apply_options(base() if base else config_cls(), values)
            return fn(**kw, config=config)

        command.__signature__ = inspect.Signature(params)
        command.__annotations__ = {p.name: p.annotation for p in params}
        del command.__wrapped__  # typer must see the new signature, not fn's
        target = wrap(command) if wrap else command
        if wrap:
            target.__signature__ = command.__signature__
            target.__annotations__ = command.__annotations__
            if hasattr(target, "__wrapped__"):
                del target.__wrapped__
        app.command(name)(target)
        return fn

    return deco
