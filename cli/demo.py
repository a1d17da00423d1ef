"""`splatk demo`: the whole pipeline on a scene splatk generates itself (no downloads)."""
from __future__ import annotations

from pathlib import Path

import click



@click.command("demo")
@click.option("--out", "-o", type=click.Path(path_type=Path), default=Path("runs/demo"), show_default=True,
              help="Folder for the generated scene and the run.")
@click.option("--kernel", type=click.Choice(["gaussian", "beta", "student_t", "learned"]), default="gaussian", show_default=True)
@click.option("--iters", type=int, help="Training iterations (default from presets/demo.yaml).")
@click.option("--overwrite", is_flag=True, help="Replace an existing demo run.")
@click.pass_context
def command(ctx, out, kernel, iters, overwrite):
    """Generate the demo scene, fit it, evaluate it and export a PLY."""
    from splatk.data.synthetic import make_demo_scene

    from . import evaluate, export, fit

    scene = make_demo_scene(out / "scene")
    args = [str(scene), "--out", str(out / "run"), "--preset", "demo", "--kernel", kernel]
    if iters:
        args += ["--iters", str(iters)]
    if overwrite:
        args.append("--overwrite")
    for cmd, argv in ((fit.command, args),
                      (evaluate.command, [str(out / "run")]),
                      (export.command, [str(out / "run"), "--format", "ply", "--out", str(out / "model.ply")])):
        # parse as a real command line so presets and flags resolve exactly as when typed
        cmd.main(args=argv, prog_name=f"splatk {cmd.name}", standalone_mode=False, obj=ctx.obj)
