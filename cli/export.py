"""`splatk export RUN --format ply|splat|spz|native|renders|kernels --out PATH`."""
from __future__ import annotations

import json
from pathlib import Path

import click

from splatk.backends import backend_names
from splatk.stages import export as export_stage

GAUSSIAN_FORMATS = tuple(export_stage.GAUSSIAN_FORMATS)


@click.command("export")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--format", "fmt", type=click.Choice([*GAUSSIAN_FORMATS, "native", "renders", "kernels"]),
              default="ply", show_default=True,
              help="ply: 3DGS PLY; splat: antimatter15 .splat; spz: Niantic SPZ; native: splatk's model file; "
                   "renders: test views and a GIF; kernels: kernel plots.")
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True,
              help="File (ply, splat, spz, native) or folder (renders, kernels).")
@click.option("--backend", type=click.Choice(["auto", *backend_names()]), default="auto", show_default=True,
              help="Renderer for renders, kernels, and the test views that measure a Gaussian approximation.")
@click.option("--scene", type=click.Path(path_type=Path),
              help="Scene folder, if it moved since `fit` (renders; ply, splat, spz: to measure an approximation).")
@click.option("--json", "as_json", is_flag=True,
              help="Print what was written as JSON (path, format, approximation and its test PSNRs).")
@click.option("--overwrite", is_flag=True, allow_from_autoenv=False,
              help="Replace an existing --out file, or a folder of the same kind that splatk exported (never "
                   "any other folder; not read from the environment).")
def command(run, fmt, out, backend, scene, as_json, overwrite):
    """Write RUN's model as a file other tools open.

    ply, splat and spz hold Gaussians: a model they cannot hold exactly (beta, student_t or learned
    kernel, sb colour, SH bands the format lacks) is approximated, and the test views are rendered
    from the model and from the file to print the PSNR this costs. Folders (renders, kernels) must
    be new or empty unless --overwrite.
    """
    if fmt in GAUSSIAN_FORMATS:
        result = export_stage.export_gaussians(run, out, fmt, overwrite=overwrite, backend=backend,
                                               scene_path=scene)
        if result.approximation is not None:
            click.echo(f"splatk export: {result.approximation.line()}", err=True)
        path, doc = result.path, result.to_dict()
    elif fmt == "native":
        path = export_stage.export_native(run, out, overwrite=overwrite)
    elif fmt == "renders":
        path = export_stage.export_renders(run, out, backend=backend, overwrite=overwrite, scene_path=scene)
    else:
        from splatk.stages.kernel_plots import export_kernel_plots

        path = export_kernel_plots(run, out, backend=backend, overwrite=overwrite)
    if fmt not in GAUSSIAN_FORMATS:
        doc = {"path": str(path), "format": fmt, "approximation": None}
    if as_json:
        click.echo(json.dumps(doc, indent=2))
    else:
        click.echo(f"wrote {path}")
