"""`splatk image PHOTO --kernel learned --budget-bytes N --out DIR`: fit one photo with 2D splats."""
from __future__ import annotations

import json
from pathlib import Path

import click
from click.core import ParameterSource

from splatk.errors import InputError
from splatk.image.fit import MODES, ImageFitConfig
from splatk.image.kernels import KERNEL_CHOICES
from splatk.image.model import BACKENDS
from splatk.stages.image_fit import run_image_fit

from .progress import DEFAULT_LOG_EVERY, image_progress, stderr_console

_D = ImageFitConfig()


@click.command("image")
@click.argument("photo", type=click.Path(path_type=Path))
@click.option("--kernel", type=click.Choice(KERNEL_CHOICES), default=_D.kernel, show_default=True,
              help="2D kernel: gaussian (GaussianImage), gabor (two cosine waves per axis), gabsplat (GabSplat, "
                   "the paper's Gabor baseline), learned (planar decoder).")
@click.option("--mode", type=click.Choice(MODES), default=_D.mode, show_default=True,
              help="tuned: splatk's learned kernel (shape palette, turn, Gaussian envelope; the shared decoder paid "
                   "from the budget). paper: the paper's planar learned kernel (10-float latent per splat, sigmoid "
                   "decoder) with the budget counting the primitives only, as the paper does.")
@click.option("--budget-bytes", default=str(_D.budget_bytes), show_default=True,
              help="Bytes for all parameters (per splat float32; a learned splat's turn and palette index "
                   "take a byte each), the shared decoder and palette included at float16 (24576, 24KB, "
                   "1.5MB); sets the number of primitives.")
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True,
              help="Folder for render.png, primitives.png, kernels.png, splats.bin (the stored splats; "
                   "`splatk image-decode` redraws them) and metrics.json.")
@click.option("--iters", type=int, default=_D.iters, show_default=True, help="Optimisation steps.")
@click.option("--seed", type=int, default=_D.seed, show_default=True, help="Random seed of the init.")
@click.option("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice).")
@click.option("--downscale", type=int, default=_D.downscale, show_default=True,
              help="Box-downscale the photo by this integer factor first.")
@click.option("--grid", type=int, default=_D.grid, show_default=True,
              help="Learned kernel: decoder table nodes per axis (bilinear lookup).")
@click.option("--latent-dim", type=int, default=_D.latent_dim, show_default=True,
              help="Learned kernel: floats of each primitive's latent (fewer = more primitives per byte; "
                   "0 = one shape shared by all splats).")
@click.option("--shapes", type=click.IntRange(0, 256), default=_D.shapes, show_default=True,
              help="Learned kernel: a palette of this many shared shapes, one byte per splat naming its "
                   "shape, instead of a latent per splat (0 = a latent per splat).")
@click.option("--exact", is_flag=True, help="Learned kernel: run the decoder per pixel (slow reference).")
@click.option("--backend", type=click.Choice(BACKENDS), default=_D.backend, show_default=True,
              help="Renderer: native cpu (OpenMP), torch (reference, any device), or auto (cpu when it builds).")
@click.option("--device", default=_D.device, show_default=True,
              help="Torch device to train on, e.g. cpu or cuda (anything but cpu renders with torch).")
@click.option("--no-lpips", is_flag=True, help="Skip LPIPS.")
@click.option("--overwrite", is_flag=True, allow_from_autoenv=False,
              help="Replace --out if it holds an earlier `splatk image` result (never any other folder; not read "
                   "from the environment). Otherwise --out must be new or empty.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.option("--log-every", type=click.FloatRange(min=0), default=DEFAULT_LOG_EVERY, show_default=True,
              metavar="SECONDS", help="When stderr is not a terminal: print a plain progress line this often "
              "instead of the bar.")
@click.pass_context
def command(ctx, photo, kernel, mode, budget_bytes, out, iters, seed, threads, downscale, grid, latent_dim, shapes,
            exact, backend, device, no_lpips, overwrite, quiet, log_every):
    """Represent PHOTO with 2D splats at a byte budget and report PSNR / SSIM / LPIPS.

    The image is the plain sum of the splats (GaussianImage style); see
    `splatk.image` for the kernels and the byte accounting.
    """
    import torch

    _check_learned_flags(ctx, kernel, mode)
    if threads:
        torch.set_num_threads(threads)
    from splatk.stages.fit_config import parse_bytes

    try:
        budget_bytes = parse_bytes(budget_bytes)
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--budget-bytes") from None
    cfg = ImageFitConfig(kernel=kernel, mode=mode, budget_bytes=budget_bytes, iters=iters, seed=seed,
                         downscale=downscale, grid=grid, exact=exact, latent_dim=latent_dim,
                         shapes=shapes, backend=backend, device=device, lpips=not no_lpips)
    console = stderr_console()
    progress = None if quiet else image_progress(console, kernel, log_every)
    task = {}

    def on_step(step, total, loss, psnr):
        if progress is None:
            return
        if "id" not in task:
            task["id"] = progress.add_task("image", total=total, loss=loss, psnr=psnr)
        if step % 5 == 0 or step == total:
            progress.update(task["id"], completed=step, loss=loss, psnr=psnr)

    if progress is not None:
        progress.start()
    try:
        path = run_image_fit(photo, out, cfg, overwrite=overwrite, on_step=on_step)
    finally:
        if progress is not None:
            progress.stop()
    m = json.loads(path.read_text())
    lp = "n/a" if m["lpips"] is None else f"{m['lpips']:.4f}"
    paid = m["counted_bytes"] == m["bytes"]
    console.print(f"{m['kernel']}: {m['num_primitives']} primitives, {m['bytes']} bytes"
                  + (f" (of which {m['network_bytes']} the shared decoder"
                     + (f" and its {m['shapes']}-shape palette" if m["shapes"] else "")
                     + ("" if paid else ", not counted: the budget paid for the primitives' "
                        f"{m['counted_bytes']}") + ")"
                     if m["network_bytes"] else "")
                  + f", PSNR {m['psnr']:.2f}, SSIM {m['ssim']:.4f}, LPIPS {lp}, {m['seconds']:.1f} s")
    click.echo(f"wrote {path.parent / m['file']} ({m['file_bytes']} bytes: {m['bytes']} and a header)")
    click.echo(f"wrote {path}")


def _check_learned_flags(ctx: click.Context, kernel: str, mode: str) -> None:
    """A learned-kernel flag typed with another kernel, or one that paper mode fixes, is an error
    rather than silently dropped (`--kernel gaussian --grid 4` fitted Gaussians and said nothing)."""
    typed = [p.name for p in ctx.command.params
             if p.name in ("grid", "latent_dim", "shapes", "exact")
             and ctx.get_parameter_source(p.name) == ParameterSource.COMMANDLINE]
    flag = {name: "--" + name.replace("_", "-") for name in typed}
    if kernel != "learned" and typed:
        raise InputError(None, f"{flag[typed[0]]}: is an option of the learned kernel",
                         "add --kernel learned, or leave the flag out")
    fixed = [name for name in typed if name in ("latent_dim", "shapes")]
    if kernel == "learned" and mode == "paper" and fixed:
        raise InputError(None, f"{flag[fixed[0]]}: --mode paper fits the paper's 10-float latent per splat, "
                         "without a shape palette", "use --mode tuned, or leave the flag out")
