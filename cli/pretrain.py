"""`splatk pretrain --target cosine --out weights.pt`: pretrain the learned kernel's networks."""
from __future__ import annotations

from pathlib import Path

import click
from splatk.stages.pretrain import TARGETS, PretrainConfig, run_pretrain

from .progress import DEFAULT_LOG_EVERY, pretrain_progress, stderr_console


@click.command("pretrain")
@click.option("--kind", type=click.Choice(["volumetric", "planar"]), default="volumetric", show_default=True,
              help="Which learned kernel: volumetric (radial profile) or planar (general 2D, Gaussian-surfel target; --target ignored).")
@click.option("--target", type=click.Choice(TARGETS), default="cosine", show_default=True,
              help="Target profile d(r): cosine cos(pi/2 r^2), gaussian, polynomial (1-r^2)^2, linear 1-r.")
@click.option("--out", "-o", type=click.Path(path_type=Path), required=True,
              help="Weights file to write (a .json with the error is written beside it).")
@click.option("--steps", type=int, default=PretrainConfig.steps, show_default=True,
              help="Joint steps of Phi_proj and Phi_dec (after the decoder warm-up).")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@click.option("--proj-inputs", help="Volumetric: Phi_proj's inputs, a comma list of z (the latent z3D), mu (camera-"
              "space centre), s (scales), R (camera-space rotation), as paper Tab. 3. [default: z,mu,s,R]")
@click.option("--latent-dim", type=click.IntRange(1, 64), help="Volumetric: floats of z3D per primitive. [default: 5]")
@click.option("--latent2d-dim", type=click.IntRange(1, 64), help="Volumetric: floats of z2D. [default: 5]")
@click.option("--proj-width", type=click.IntRange(1, 1024), help="Volumetric: width of Phi_proj. [default: 64]")
@click.option("--dec-width", type=click.IntRange(1, 256), help="Volumetric: width of Phi_dec. [default: 4]")
@click.option("--overwrite", is_flag=True, allow_from_autoenv=False, help="Replace an existing --out file.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bar.")
@click.option("--log-every", type=click.FloatRange(min=0), default=DEFAULT_LOG_EVERY, show_default=True,
              metavar="SECONDS", help="When stderr is not a terminal: print a plain progress line this often "
              "instead of the bar.")
def command(kind, target, out, steps, seed, proj_inputs, latent_dim, latent2d_dim, proj_width, dec_width,
            overwrite, quiet, log_every):
    """Fit the learned kernel's networks to a target profile (paper Sec. 4.5).

    Use the result with `splatk fit --kernel learned --kernel-weights OUT`; the fit takes the
    network shape (--proj-inputs, --latent-dim, ...) from the file.
    """
    arch = {k: v for k, v in (("proj_inputs", proj_inputs), ("latent_dim", latent_dim),
                               ("latent2d_dim", latent2d_dim), ("proj_width", proj_width),
                               ("dec_width", dec_width)) if v is not None}
    if arch and kind == "planar":
        raise click.UsageError("--proj-inputs, --latent-dim, --latent2d-dim, --proj-width and --dec-width "
                               "shape the volumetric kernel's networks only")
    console = stderr_console()
    progress = None if quiet else pretrain_progress(console, target, log_every)
    task = {}

    def on_step(step, total, loss):
        if progress is None:
            return
        if "id" not in task:
            task["id"] = progress.add_task("pretrain", total=total, target=target, loss=loss)
        if step % 10 == 0 or step == total:
            progress.update(task["id"], completed=step, loss=loss)

    if kind == "planar":
        target = "surfel"
    if progress is not None:
        progress.start()
    try:
        if kind == "planar":
            from splatk.stages.pretrain_planar import PlanarPretrainConfig, run_pretrain_planar

            pcfg = PlanarPretrainConfig(seed=seed) if steps == PretrainConfig.steps else \
                PlanarPretrainConfig(steps=steps, seed=seed)
            path = run_pretrain_planar(out, pcfg, on_step=on_step, overwrite=overwrite)
        else:
            path = run_pretrain(target, out, steps=steps, seed=seed, kernel_options=arch, on_step=on_step,
                                overwrite=overwrite)
    finally:
        if progress is not None:
            progress.stop()
    import json

    err = json.loads(path.with_suffix(".json").read_text())["error"]
    if kind == "planar":
        console.print(f"planar (Gaussian surfel): MAE {err['mae']:.4f}, max {err['max_abs']:.4f}")
        click.echo(f"wrote {path}")
        return
    console.print(f"{target}: MAE {err['mae']:.4f}, max {err['max_abs']:.4f}, "
                  f"|d(0) err| {err['mae_r0']:.4f}, |d(1) err| {err['mae_r1']:.4f}")
    click.echo(f"wrote {path}")
