"""`splatk compare A.png B.png`: metrics between any two images."""
from __future__ import annotations

import json

import click


@click.command("compare")
@click.argument("image_a", type=click.Path())
@click.argument("image_b", type=click.Path())
@click.option("--metrics", default="psnr,ssim,lpips", show_default=True)
@click.option("--lpips-net", type=click.Choice(["alex", "vgg"]), default="alex", show_default=True)
@click.option("--json", "as_json", is_flag=True, help="Print JSON.")
def command(image_a, image_b, metrics, lpips_net, as_json):
    """PSNR / SSIM / LPIPS of IMAGE_A against IMAGE_B (the reference)."""
    from splatk.stages.compare import compare_images

    names = tuple(m.strip() for m in metrics.split(",") if m.strip())
    res = compare_images(image_a, image_b, names, lpips_net=lpips_net)
    for w in res.get("warnings", []):
        click.echo(f"warning: {w}", err=True)
    if as_json:
        click.echo(json.dumps(res, indent=2))
    else:
        for m in names:
            v = res.get(m)
            click.echo(f"{m}: {'n/a' if v is None else f'{v:.4f}'}")
