"""`splatk image-decode SPLATS --out PNG`: redraw the image that `splatk image` stored."""
from __future__ import annotations

from pathlib import Path

import click

from splatk.image.model import BACKENDS
from splatk.stages.image_fit import decode_image


@click.command("image-decode")
@click.argument("splats", type=click.Path(path_type=Path))
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True, help="PNG to write.")
@click.option("--backend", type=click.Choice(BACKENDS), default="auto", show_default=True,
              help="Renderer: native cpu (OpenMP), torch (reference), or auto (cpu when it builds).")
def command(splats, out, backend):
    """Redraw SPLATS (the splats.bin that `splatk image` wrote) as a PNG.

    The file holds every value the image needs and nothing else: its size is the run's
    `bytes` plus a 20-byte header.
    """
    click.echo(f"wrote {decode_image(splats, out, backend)}")
