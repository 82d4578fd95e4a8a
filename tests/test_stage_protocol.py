"""The stage protocol: config-derived CLI options, stage hashes, the progress mechanism."""

from dataclasses import dataclass, field
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from physavatar.cli.options import config_command
from physavatar.errors import PhysavatarError
from physavatar.progress import ProgressEvent, resolve
from physavatar.stages.base import apply_options, option, setting, stage_hash, to_argv


def _csv(s):
    return tuple(x.strip() for x in s.split(",") if x.strip())


@dataclass(frozen=True)
class _Flow:
    levels: int = option(3, "pyramid levels", flag="--flow-levels", check=lambda v: None if v >= 1 else "must be >= 1")


@dataclass(frozen=True)
class _Cfg:
    window: int = option(24, "frames fitted")
    integrator: str = option("auto", "time integrator", choices=("auto", "euler", "bdf2"))
    holdout: tuple = option((), "cameras", parse=_csv)
    fit_light: bool = option(True, "fit the light", flag="--fit-light/--fix-light")
    density: float | None = option(None, "rho")
    frames: int | None = option(None, "frames to process", hash=False)
    secret: float = setting(1.0)
    flow: _Flow = field(default_factory=_Flow)


def _app(seen):
    app = typer.Typer()

    @config_command(app, "fit", _Cfg)
    def fit(source: Path = typer.Argument(...), out: Path = typer.Option(..., "--out"), *, config: _Cfg):
        seen.append((source, out, config))

    @app.command()
    def other():
        pass

    return app


def test_options_come_from_the_config_and_round_trip_through_argv():
    seen = []
    app = _app(seen)
    args = ["--window", "12", "--holdout", "a, b", "--fix-light", "--flow-levels", "2", "--density", "0.2"]
    r = CliRunner().invoke(app, ["fit", "src", "--out", "o", *args])
    assert r.exit_code == 0, r.output
    src, out, cfg = seen[-1]
    assert (src, out) == (Path("src"), Path("o"))
    assert cfg == _Cfg(window=12, holdout=("a", "b"), fit_light=False, density=0.2, flow=_Flow(levels=2))
    # the equivalent command line gives the same config back
    r = CliRunner().invoke(app, ["fit", "src", "--out", "o", *to_argv(cfg)])
    assert r.exit_code == 0 and seen[-1][2] == cfg
    # options not given keep the config's defaults
    CliRunner().invoke(app, ["fit", "src", "--out", "o"])
    assert seen[-1][2] == _Cfg()
    help_text = CliRunner().invoke(app, ["fit", "--help"]).output
    assert "--flow-levels" in help_text and "--fix-light" in help_text and "--secret" not in help_text


def test_bad_option_values_are_one_message_naming_the_flag():
    with pytest.raises(PhysavatarError, match=r"option --integrator: 'rk4' is not auto, euler or bdf2"):
        apply_options(_Cfg(), {"integrator": "rk4"})
    with pytest.raises(PhysavatarError, match=r"option --flow-levels: must be >= 1"):
        apply_options(_Cfg(), {"flow__levels": 0})
    r = CliRunner().invoke(_app([]), ["fit", "s", "--out", "o", "--integrator", "rk4"])
    assert r.exit_code != 0 and isinstance(r.exception, PhysavatarError)


def test_stage_hash_follows_config_and_inputs(tmp_path):
    f = tmp_path / "input.txt"
    f.write_text("one")
    h = stage_hash(_Cfg(), {"capture": f})
    assert h == stage_hash(_Cfg(), {"capture": f})
    assert h != stage_hash(_Cfg(window=12), {"capture": f})          # a setting that changes outputs
    assert h != stage_hash(_Cfg(secret=2.0), {"capture": f})        # settings without a flag count too
    assert h == stage_hash(_Cfg(frames=5), {"capture": f})          # hash=False: a run can be extended
    assert h != stage_hash(_Cfg(flow=_Flow(levels=2)), {"capture": f})  # nested groups count
    f.write_text("two!")
    assert h != stage_hash(_Cfg(), {"capture": f})                  # the input changed
    assert stage_hash(_Cfg(), {"up": {"hash": "a"}}) != stage_hash(_Cfg(), {"up": {"hash": "b"}})


def test_progress_reports_to_callbacks_and_logs(caplog):
    events: list[ProgressEvent] = []
    prog = resolve(events.append)
    assert resolve(prog) is prog
    with caplog.at_level("INFO", logger="physavatar.progress"):
        with prog.task("frames", total=3) as task:
            for k in range(3):
                task.advance(loss=0.1 * k)
    assert [(e.kind, e.done) for e in events] == [("start", 0), ("advance", 1), ("advance", 2), ("advance", 3),
                                                  ("end", 3)]
    assert events[2].info == {"loss": 0.1} and events[-1].total == 3
    assert any("frames: 3/3 steps" in m for m in caplog.messages)
    silent = resolve(False)
    with silent.task("x", 2) as t:  # counts without drawing
        t.advance(2)
    assert t.done == 2
    with pytest.raises(TypeError):
        resolve(3)


def test_settings_without_a_flag_are_named_when_changed():
    from physavatar.stages.base import unflagged_changes

    assert unflagged_changes(_Cfg()) == {}
    assert unflagged_changes(_Cfg(secret=2.0, window=3, flow=_Flow(levels=2))) == {"secret": 2.0}
