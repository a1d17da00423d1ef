"""`splatk export RUN --format ply|native|renders|kernels --out PATH`."""
from __future__ import annotations

from pathlib import Path

import click

from splatk.stages import export as export_stage


@click.command("export")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--format", "fmt", type=click.Choice(["ply", "native", "renders", "kernels"]), default="ply", show_default=True)
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True, help="File (ply, native) or folder (renders, kernels).")
@click.option("--backend", type=click.Choice(["auto", "torch", "cpu"]), default="auto", show_default=True)
def command(run, fmt, out, backend):
    """Write RUN's model as a file other tools open."""
    if fmt == "ply":
        path = export_stage.export_ply(run, out)
    elif fmt == "native":
        path = export_stage.export_native(run, out)
    elif fmt == "renders":
        path = export_stage.export_renders(run, out, backend=backend)
    else:
        from splatk.stages.kernel_plots import export_kernel_plots

        path = export_kernel_plots(run, out, backend=backend)
    click.echo(f"wrote {path}")
