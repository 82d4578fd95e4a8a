"""The ``physavatar`` command-line tool (typer): parse, call a stage, print.

Every command turns bad input (a :class:`PhysavatarError`) into one line naming the file and the
problem, and exit code 2 — never a traceback. Ctrl-C stops with exit code 130 and leaves only
finished outputs behind (all writes are atomic). Commands whose stage has a config take their
options from it (:func:`physavatar.cli.options.config_command`); each group of commands is one
module of this package.
"""

from __future__ import annotations

from ._common import app, console, err_console, handle_errors, motion_app  # noqa: F401
from . import data, importing, track, physics, appearance, avatar, batch, view  # noqa: F401,E402,I001  (registers the commands, in this order)
from . import prepare  # noqa: F401,E402  (physavatar prepare)


def main():  # console-script entry point
    import logging
    import sys

    if not sys.stderr.isatty():  # output to a log: the progress of long loops as log lines
        logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s %(message)s",
                            datefmt="%H:%M:%S")
        for noisy in ("matplotlib", "PIL", "numba", "urllib3"):
            logging.getLogger(noisy).setLevel(logging.WARNING)
    app()


if __name__ == "__main__":
    main()
