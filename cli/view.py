"""`splatk view RUN --port 8080`: look around a run in the browser (viser), drawn by splatk."""
from __future__ import annotations

import time
from pathlib import Path

import click
import numpy as np
from rich.console import Console

from splatk.backends import backend_names
from splatk.errors import InputError
from splatk.stages.view import RunView

VIEW_EXTRA = 'pip install "splatk[view]"'


def draw(client, view: RunView, max_size: int) -> None:
    """Render ``client``'s camera (viser: OpenCV axes, vertical field of view) at most
    ``max_size`` pixels on its longest side and show it as the client's background."""
    from viser import transforms

    cam = client.camera
    scale = min(1.0, max_size / max(cam.image_width, cam.image_height))
    width, height = max(2, round(cam.image_width * scale)), max(2, round(cam.image_height * scale))
    R_c2w = transforms.SO3(np.asarray(cam.wxyz)).as_matrix()
    image = view.render(RunView.camera(R_c2w, cam.position, cam.fov, width, height))
    client.scene.set_background_image(image, format="jpeg", jpeg_quality=90)


@click.command("view")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--port", type=click.IntRange(0, 65535), default=8080, show_default=True,
              help="Port to serve the viewer on (0: any free port).")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on; 0.0.0.0 lets other machines connect.")
@click.option("--max-size", type=click.IntRange(min=16), default=960, show_default=True,
              help="Longest side of the rendered image in pixels (the browser scales it to the window).")
@click.option("--backend", type=click.Choice(["auto", *backend_names()]), default="auto", show_default=True,
              help="Rasteriser backend.")
@click.option("--device", default="cpu", show_default=True, help="Torch device to render on, e.g. cpu or cuda.")
@click.option("--scene", type=click.Path(path_type=Path), help="Scene folder, if it moved since `fit`.")
def command(run, port, host, max_size, backend, device, scene):
    """Look around RUN in a web browser; every frame is rendered by splatk, as `eval` renders views."""
    try:
        import viser
    except ImportError:
        raise InputError(None, "splatk view needs the viser package", f"install it: {VIEW_EXTRA}") from None
    view = RunView(run, backend=backend, device=device, scene_path=scene)
    start = view.start_pose()
    server = viser.ViserServer(host=host, port=port, verbose=False)
    server.scene.set_up_direction(start["up"])
    server.initial_camera.position = start["position"]
    server.initial_camera.look_at = start["look_at"]
    server.initial_camera.up = start["up"]
    server.initial_camera.fov = start["fov_y"]
    Console(stderr=True).print(f"splatk view: http://{host}:{server.get_port()} (Ctrl-C to stop)",
                               markup=False, highlight=False)
    drawn: dict[int, float] = {}
    try:
        while True:
            # redraw a client when its camera moved; one render at a time keeps the CPU for it
            for client_id, client in list(server.get_clients().items()):
                stamp = client.camera.update_timestamp
                if stamp and drawn.get(client_id) != stamp:
                    drawn[client_id] = stamp
                    draw(client, view, max_size)
            time.sleep(0.02)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
