"""What every command module shares: the typer apps, the consoles and the error handler."""

from __future__ import annotations

import functools

import typer
from rich.console import Console
from rich.markup import escape

from ..errors import PhysavatarError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Physics-aware 3D avatars of dressed people from multi-view video (PhysAvatar on a CPU).",
    pretty_exceptions_enable=False,
)
motion_app = typer.Typer(no_args_is_help=True, help="Built-in and imported body motions.")
app.add_typer(motion_app, name="motion")

console = Console(stderr=False)
err_console = Console(stderr=True)


def handle_errors(fn):
    """Exit 2 with one clear line for bad input; 130 on Ctrl-C."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except PhysavatarError as e:
            err_console.print(f"[bold red]error:[/] {escape(str(e))}", highlight=False, soft_wrap=True)
            raise typer.Exit(2)
        except KeyboardInterrupt:
            err_console.print("[yellow]interrupted[/]: finished outputs are kept; run again to resume")
            raise typer.Exit(130)

    return wrapper


def bad_option(name: str, problem: str):
    raise PhysavatarError(None, f"option {name}: {problem}")


def say_clearance(summary, clearance: float, parts=None) -> None:
    """Print what arm clearance and part clearance changed (body.load.describe_clearance,
    describe_part_clearance), if anything."""
    from ..body.load import describe_clearance, describe_part_clearance

    for line in (describe_clearance(summary, clearance), describe_part_clearance(parts)):
        if line:
            console.print(line)
