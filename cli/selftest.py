"""`splatk selftest`: every backend's images and gradients against the torch reference."""
from __future__ import annotations

import json
import math
import sys

import click


def _finite_or_none(value):
    """JSON has no infinity: an infinite error (a NaN difference) is printed as null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    return value


@click.command("selftest")
@click.option("--backend", "backend", default="all", show_default=True, metavar="NAME|all",
              help="The backend to test (torch, cpu, cuda, ...), or all: every backend that runs on this "
                   "machine (on CUDA where a backend runs there, else on the CPU).")
@click.option("--json", "as_json", is_flag=True, help="Print the full report as JSON.")
def command(backend: str, as_json: bool) -> None:
    """Render a fixed small scene through a backend and the torch reference and compare.

    Cases: the splat rasteriser for every profile kind (gaussian, beta, student_t, table), the
    planar rasteriser (gaussian_surfel, grid) and the image splats; each compares the images
    and every input's gradient under one upstream gradient. Exits 1 when any backend fails.
    """
    from splatk.stages.selftest import run_selftest

    try:
        result = run_selftest(backend)
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="--backend") from None
    if as_json:
        click.echo(json.dumps(_finite_or_none(result), indent=2, allow_nan=False))
    else:
        for name, report in result["backends"].items():
            for case, r in report["cases"].items():
                if "error" in r:
                    click.echo(f"  {name:6s} {case:24s} FAIL  {r['error']}")
                    continue
                mark = "ok  " if r["passed"] else "FAIL"
                via = "" if r["own_op"] else "  (torch op)"
                click.echo(f"  {name:6s} {case:24s} {mark}  image {r['image_error']:.1e} "
                           f"(tol {r['image_tolerance']:.0e})  grad {r['grad_error']:.1e} "
                           f"(tol {r['grad_tolerance']:.0e}){via}")
        for name, report in result["backends"].items():
            verdict = "PASS" if report["passed"] else "FAIL"
            click.echo(f"{name} ({report['device']}): {verdict}  max image error "
                       f"{report['max_image_error']:.2e}, max gradient error {report['max_grad_error']:.2e}")
        for name, reason in result["skipped"].items():
            click.echo(f"{name}: skipped ({reason})")
    if not result["passed"]:
        sys.exit(1)
