"""`splatk compare A.png B.png`: metrics between any two images."""
from __future__ import annotations

import json
import math

import click


def _background(ctx, param, value: str) -> tuple[float, float, float]:
    try:
        rgb = tuple(float(v) for v in value.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise click.BadParameter(f"{value!r} is not three numbers in [0, 1] (e.g. 1,1,1 or 0,0,0)")
    return rgb


def _finite_or_none(value):
    """JSON has no infinity: non-finite numbers become null (nested dicts and lists too)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite_or_none(v) for v in value]
    return value


@click.command("compare")
@click.argument("image_a", type=click.Path())
@click.argument("image_b", type=click.Path())
@click.option("--metrics", default="psnr,ssim,lpips", show_default=True)
@click.option("--lpips-net", type=click.Choice(["alex", "vgg"]), default="alex", show_default=True)
@click.option("--background", default="1,1,1", show_default=True, callback=_background,
              help="R,G,B in [0, 1] that an alpha channel is composited onto, as `splatk fit` and "
                   "`splatk eval` do: 1,1,1 for transforms (NeRF-synthetic) scenes, 0,0,0 for "
                   "COLMAP scenes.")
@click.option("--json", "as_json", is_flag=True,
              help="Print JSON. Identical images have an infinite PSNR, printed as null with "
                   "\"identical\": true.")
def command(image_a, image_b, metrics, lpips_net, background, as_json):
    """PSNR / SSIM / LPIPS of IMAGE_A against IMAGE_B (the reference).

    Images are read as scene loading reads them: an alpha channel is composited onto
    --background, so an RGBA pair scores what `splatk eval` measures.
    """
    from splatk.stages.compare import compare_images

    names = tuple(m.strip() for m in metrics.split(",") if m.strip())
    res = compare_images(image_a, image_b, names, lpips_net=lpips_net, background=background)
    for w in res.get("warnings", []):
        click.echo(f"warning: {w}", err=True)
    if as_json:
        click.echo(json.dumps(_finite_or_none(res), indent=2, allow_nan=False))
    else:
        for m in names:
            v = res.get(m)
            click.echo(f"{m}: {'n/a' if v is None else f'{v:.4f}'}")
