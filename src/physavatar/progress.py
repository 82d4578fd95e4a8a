"""One progress mechanism for every long loop: stages, the simulator, parallel jobs.

Code that loops takes ``progress`` (anything :func:`resolve` accepts) and reports through the
tasks it opens::

    prog = resolve(progress)
    with prog.task("tracking", total=len(frames)) as task:
        for f in frames:
            ...
            task.advance(1, frame=f, loss=loss)

What ``progress`` may be:

- ``True``: a live bar in the terminal (rich), several tasks stacked in one display;
- ``False`` / ``None``: nothing drawn;
- a callable ``fn(event: ProgressEvent)``: called on every start, advance and end (the pipeline,
  the viewer, a batch runner or a test listen this way);
- a :class:`Progress` instance, passed on as it is (a stage hands its own to the simulator, so
  nested loops draw into the same display).

Every kind also logs to the ``physavatar.progress`` logger at INFO: a task's start, about every
tenth of its way and its end, so output going to a log file still shows how far a long run is
(the command line turns these on when its output is not a terminal).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable

log = logging.getLogger("physavatar.progress")


@dataclass
class ProgressEvent:
    """What a listener receives. ``kind``: ``"start"``, ``"advance"`` or ``"end"``."""

    kind: str
    task: str
    done: int
    total: int | None
    elapsed: float
    info: dict = field(default_factory=dict)


class Task:
    """One loop's counter; a context manager that ends the task on exit."""

    def __init__(self, owner: "Progress", name: str, total: int | None, log_every: int | None = None):
        self.owner, self.name, self.total = owner, name, total
        self.log_every = log_every  # also log every this many steps (not only every tenth)
        self.done = 0
        self.t0 = time.time()
        self._next_log = 0.1
        self._ended = False
        owner._emit(self, "start", {})
        log.info("%s: started%s", name, f" ({total} steps)" if total else "")

    def advance(self, n: int = 1, **info: Any) -> None:
        self.done += n
        self.owner._emit(self, "advance", info)
        every = self.log_every and self.done % self.log_every == 0
        if every or (self.total and self.done >= self._next_log * self.total):
            log.info("%s: %d%s after %.1f s%s", self.name, self.done, f"/{self.total}" if self.total else "",
                     time.time() - self.t0,
                     "".join(f", {k} {_fmt(v)}" for k, v in info.items()))
            if self.total:
                self._next_log = (int(10 * self.done / self.total) + 1) / 10

    def set_total(self, total: int | None) -> None:
        self.total = total
        self.owner._retotal(self)

    def end(self, **info: Any) -> None:
        if self._ended:
            return
        self._ended = True
        self.owner._emit(self, "end", info)
        log.info("%s: %d%s steps in %.1f s", self.name, self.done, f"/{self.total}" if self.total else "",
                 time.time() - self.t0)

    def __enter__(self) -> "Task":
        return self

    def __exit__(self, *exc) -> None:
        self.end()


class Progress:
    """Silent progress (the base class): tasks count and log, nothing is drawn."""

    def task(self, name: str, total: int | None = None, log_every: int | None = None) -> Task:
        """A task of ``total`` steps; its progress is logged about every tenth of the way and,
        with ``log_every``, every that many steps too (a slow loop: every few frames)."""
        return Task(self, name, total, log_every)

    def _emit(self, task: Task, kind: str, info: dict) -> None:
        pass

    def _retotal(self, task: Task) -> None:
        pass

    def close(self) -> None:
        pass


class CallbackProgress(Progress):
    """Calls ``fn(ProgressEvent)`` on every start, advance and end."""

    def __init__(self, fn: Callable[[ProgressEvent], None]):
        self.fn = fn

    def _emit(self, task: Task, kind: str, info: dict) -> None:
        self.fn(ProgressEvent(kind, task.name, task.done, task.total, time.time() - task.t0, dict(info)))


class TerminalProgress(Progress):
    """Rich bars, one per open task, in one live display that starts with the first task and stops
    when the last one ends. Extra ``info`` given to ``advance`` (e.g. ``loss=``) is shown after
    the bar."""

    def __init__(self, transient: bool = False):
        self.transient = transient
        self._bar = None
        self._ids: dict[int, Any] = {}

    def _ensure(self):
        if self._bar is None:
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress as RichProgress, TextColumn,
                                       TimeElapsedColumn, TimeRemainingColumn)

            self._bar = RichProgress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                                     TimeElapsedColumn(), TimeRemainingColumn(), TextColumn("{task.fields[info]}"),
                                     transient=self.transient)
            self._bar.start()
        return self._bar

    def _emit(self, task: Task, kind: str, info: dict) -> None:
        bar = self._ensure() if kind == "start" else self._bar
        if bar is None:
            return
        text = "  ".join(f"{k} {_fmt(v)}" for k, v in info.items())
        if kind == "start":
            self._ids[id(task)] = bar.add_task(task.name, total=task.total, info="")
            return
        tid = self._ids.get(id(task))
        if tid is None:
            return
        if kind == "advance":
            bar.update(tid, completed=task.done, **({"info": text} if text else {}))
        else:  # end: the bar stays, the live display stops with the last open task
            bar.update(tid, completed=task.done, **({"info": text} if text else {}))
            del self._ids[id(task)]
            if not self._ids:
                self.close()

    def _retotal(self, task: Task) -> None:
        tid = self._ids.get(id(task))
        if tid is not None and self._bar is not None:
            self._bar.update(tid, total=task.total)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None
            self._ids.clear()


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


ProgressLike = bool | None | Callable[[ProgressEvent], None] | Progress


def resolve(progress: ProgressLike) -> Progress:
    """The :class:`Progress` for any accepted ``progress`` argument (see the module docstring)."""
    if isinstance(progress, Progress):
        return progress
    if progress is True:
        return TerminalProgress()
    if progress is None or progress is False:
        return Progress()
    if callable(progress):
        return CallbackProgress(progress)
    raise TypeError(f"progress must be a bool, a callable or a Progress, not {type(progress).__name__}")
