"""`splatk export RUN --format ply|native|renders|kernels --out PATH`."""
from __future__ import annotations

from pathlib import Path

import click

from splatk.backends import backend_names
from splatk.stages import export as export_stage


@click.command("export")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--format", "fmt", type=click.Choice(["ply", "native", "renders", "kernels"]), default="ply", show_default=True)
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True, help="File (ply, native) or folder (renders, kernels).")
@click.option("--backend", type=click.Choice(["auto", *backend_names()]), default="auto", show_default=True)
@click.option("--overwrite", is_flag=True, allow_from_autoenv=False,
              help="Replace an existing --out file, or a folder of the same kind that splatk exported (never "
                   "any other folder; not read from the environment).")
def command(run, fmt, out, backend, overwrite):
    """Write RUN's model as a file other tools open.

    Folders (renders, kernels) must be new or empty unless --overwrite.
    """
    if fmt == "ply":
        path = export_stage.export_ply(run, out, overwrite=overwrite)
    elif fmt == "native":
        path = export_stage.export_native(run, out, overwrite=overwrite)
    elif fmt == "renders":
        path = export_stage.export_renders(run, out, backend=backend, overwrite=overwrite)
    else:
        from splatk.stages.kernel_plots import export_kernel_plots

        path = export_kernel_plots(run, out, backend=backend, overwrite=overwrite)
    click.echo(f"wrote {path}")
