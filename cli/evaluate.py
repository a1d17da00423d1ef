"""`splatk eval RUN`: PSNR / SSIM / LPIPS on held-out views."""
from __future__ import annotations

import json
from pathlib import Path

import click
from rich.console import Console
from rich.table import Table

from splatk.metrics.lpips import require_lpips
from splatk.stages.evaluate import run_eval


@click.command("eval")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--metrics", default="psnr,ssim", show_default=True, help="Comma-separated: psnr,ssim,lpips.")
@click.option("--lpips-net", type=click.Choice(["alex", "vgg"]), default="alex", show_default=True)
@click.option("--backend", type=click.Choice(["auto", "torch", "cpu"]), default="auto", show_default=True)
@click.option("--device", default="cpu", show_default=True,
              help="Torch device to render and measure on, e.g. cpu or cuda (cuda renders with the torch backend).")
@click.option("--scene", type=click.Path(path_type=Path), help="Scene folder, if it moved since `fit`.")
@click.option("--split", type=click.Choice(["test", "train"]), default="test", show_default=True,
              help="Views to measure; train writes RUN/metrics_train.json and leaves metrics.json as it was.")
@click.option("--save-renders", is_flag=True, help="Also write the rendered views as PNG.")
@click.option("--json", "as_json", is_flag=True, help="Print the metrics JSON to stdout.")
def command(run, metrics, lpips_net, backend, device, scene, split, save_renders, as_json):
    """Render RUN's held-out views and measure them; writes RUN/metrics.json
    (`--split train`: RUN/metrics_train.json)."""
    names = tuple(m.strip() for m in metrics.split(",") if m.strip())
    bad = [m for m in names if m not in ("psnr", "ssim", "lpips")]
    if bad:
        raise click.BadParameter(f"unknown metric(s): {', '.join(bad)}", param_hint="--metrics")
    if "lpips" in names:
        require_lpips(lpips_net)  # asked for by name: a table without it is not an answer
    res = run_eval(run, names, lpips_net=lpips_net, backend=backend, scene_path=scene, split=split,
                   save_renders=save_renders, device=device)
    console = Console(stderr=True)
    for w in res["warnings"]:
        console.print(f"[yellow]warning: {w}")
    if as_json:
        click.echo(json.dumps(res, indent=2))
        return
    table = Table(title=f"{run} ({res['split']}, {res['num_views']} views)")
    table.add_column("view")
    for m in names:
        table.add_column(m.upper(), justify="right")
    for v in res["per_view"]:
        table.add_row(v["view"], *[_fmt(v.get(m)) for m in names])
    table.add_row("[bold]mean", *[f"[bold]{_fmt(res['mean'].get(m))}" for m in names])
    Console().print(table)
    Console().print(f"{res['num_primitives']:,} primitives, {res['footprint_mb']:.2f} MB, "
                    f"render {res['render_ms']:.1f} ms/view ({res['backend']} on {res['device']}, {res['threads']} threads)")


def _fmt(x):
    return "n/a" if x is None else f"{x:.4f}"
