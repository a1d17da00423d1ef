"""The `splatk` command: a click group; each sub-command lives in its own module."""
from __future__ import annotations

import signal
import sys
import traceback

import click

from splatk.errors import BackendUnavailable, InputError, TrainingStalled

#: exit codes: 2 bad input (a one-line message naming the file and the fix), 3 training stalled
#: (the run folder keeps its last healthy checkpoint), 128 + N stopped by signal N (130 Ctrl-C,
#: 143 SIGTERM) after saving a checkpoint
EXIT_INPUT_ERROR, EXIT_STALLED = 2, 3


class SplatkGroup(click.Group):
    """Turns input errors into one line and exit code 2, a stalled fit into one line and exit
    code 3; tracebacks only with -v."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except InputError as e:
            if ctx.obj and ctx.obj.get("verbose"):
                traceback.print_exc()
            click.echo(f"splatk: error: {e.message()}", err=True)
            sys.exit(EXIT_INPUT_ERROR)
        except TrainingStalled as e:
            if ctx.obj and ctx.obj.get("verbose"):
                traceback.print_exc()
            click.echo(f"splatk: error: {e.message()}", err=True)
            sys.exit(EXIT_STALLED)
        except BackendUnavailable as e:
            click.echo(f"splatk: error: {e}", err=True)
            sys.exit(2)
        except OSError as e:
            if ctx.obj and ctx.obj.get("verbose"):
                traceback.print_exc()
            where = f"{e.filename}: " if getattr(e, "filename", None) else ""
            click.echo(f"splatk: error: {where}{e.strerror or e}", err=True)
            sys.exit(2)


@click.group(cls=SplatkGroup, context_settings={"help_option_names": ["-h", "--help"],
                                                 "auto_envvar_prefix": "SPLATK"})
@click.option("-v", "--verbose", is_flag=True, help="Show full tracebacks on errors.")
@click.version_option(package_name="splatk")
@click.pass_context
def cli(ctx: click.Context, verbose: bool) -> None:
    """splatk: splatting-based novel view synthesis with learned, view-dependent kernels.

    Typical use: `splatk fit SCENE --out RUN`, then `splatk eval RUN` and
    `splatk export RUN --format ply --out model.ply`.
    """
    ctx.ensure_object(dict)
    ctx.obj["verbose"] = verbose


def _register() -> None:
    import importlib

    for name in ("fit", "evaluate", "export", "compare", "pretrain", "image", "image_decode", "sfm", "bench", "demo",
                 "render", "view", "selftest"):
        try:
            mod = importlib.import_module(f"splatk_cli.{name}")
        except ModuleNotFoundError as e:
            if e.name == f"splatk_cli.{name}":
                continue
            raise
        cli.add_command(mod.command)


_register()


def main() -> None:
    """The `splatk` entry point. Tunes glibc's malloc for training first (``splatk._malloc``):
    a process-wide setting, so the command makes it, not ``import splatk``."""
    from splatk._malloc import tune_malloc

    tune_malloc()
    # pycolmap, imported with splatk.data, installs glog's SIGTERM handler: a stack dump, then
    # death. A command with no stop logic of its own (fit and bench have theirs) ends as Python
    # ends on Ctrl-C instead: `finally` blocks run, partial files stay temporary, exit 128 + 15.
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    cli(prog_name="splatk")


def _exit_on_sigterm(signum, frame):
    print("splatk: stopped by SIGTERM", file=sys.stderr)
    raise SystemExit(128 + signum)


if __name__ == "__main__":
    main()
