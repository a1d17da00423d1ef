"""`splatk view RUN --port 8080`: look around a run in the browser (viser), drawn by splatk."""
from __future__ import annotations

import signal
import time
from pathlib import Path

import click
import numpy as np
from rich.console import Console

from splatk.backends import backend_names
from splatk.errors import InputError
from splatk.stages.view import FramePlanner, RunView, frame_size

VIEW_EXTRA = 'pip install "splatk[view]"'


def draw(client, view: RunView, max_size: int) -> tuple[int, int]:
    """Render ``client``'s camera (viser: OpenCV axes, vertical field of view) at most
    ``max_size`` pixels on its longest side, show it as the client's background and return its
    width and height."""
    from viser import transforms

    cam = client.camera
    width, height = frame_size(cam.image_width, cam.image_height, max_size)
    R_c2w = transforms.SO3(np.asarray(cam.wxyz)).as_matrix()
    image = view.render(RunView.camera(R_c2w, cam.position, cam.fov, width, height))
    client.scene.set_background_image(image, format="jpeg", jpeg_quality=90)
    return width, height


def jump(client, pose: dict) -> None:
    """Put ``client``'s camera at ``pose`` (`RunView.pose`)."""
    with client.atomic():
        client.camera.fov = pose["fov_y"]
        client.camera.up_direction = pose["up"]
        client.camera.position = pose["position"]
        client.camera.look_at = pose["look_at"]


def add_controls(client, view: RunView) -> dict:
    """The viewer's panel for one browser: a list of the run's cameras that jumps to the one
    picked, and the last frame's drawing time and size. Returns the handles by name."""
    names = list(view.cameras)
    start = next((n for n, c in view.cameras.items() if c is view.start), names[0])
    cameras = client.gui.add_dropdown("Camera", options=names, initial_value=start,
                                      hint="Jump to a test or train camera of the run's scene.")
    cameras.on_update(lambda _: jump(client, view.pose(view.cameras[cameras.value])))
    frame = client.gui.add_markdown("Frame: waiting for the first")
    client.gui.add_markdown("Drag: orbit · right-drag: pan · scroll: zoom · W A S D Q E: fly")
    return {"cameras": cameras, "frame": frame}


@click.command("view")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--port", type=click.IntRange(0, 65535), default=8080, show_default=True,
              help="Port to serve the viewer on (0: any free port).")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on; 0.0.0.0 lets other machines connect.")
@click.option("--camera", help="Start at this train or test camera of the run's scene (its name as the "
              "viewer's camera list shows it). Default: the first train camera.")
@click.option("--max-size", type=click.IntRange(min=16), default=960, show_default=True,
              help="Longest side of the rendered image in pixels (the browser scales it to the window).")
@click.option("--fps", type=click.FloatRange(min=0.1), default=10.0, show_default=True,
              help="Frame rate to keep while the camera moves: frames shrink until one takes 1/FPS seconds; "
              "once the camera rests, one frame at --max-size.")
@click.option("--backend", type=click.Choice(["auto", *backend_names()]), default="auto", show_default=True,
              help="Rasteriser backend.")
@click.option("--device", default="cpu", show_default=True, help="Torch device to render on, e.g. cpu or cuda.")
@click.option("--scene", type=click.Path(path_type=Path), help="Scene folder, if it moved since `fit`.")
def command(run, port, host, camera, max_size, fps, backend, device, scene):
    """Look around RUN in a web browser; every frame is rendered by splatk, as `eval` renders views.

    Drag to orbit, right-drag to pan, scroll to zoom, W A S D Q E to fly; the panel jumps to any
    train or test camera and shows each frame's drawing time and size.
    """
    try:
        import viser
    except ImportError:
        raise InputError(None, "splatk view needs the viser package", f"install it: {VIEW_EXTRA}") from None
    view = RunView(run, backend=backend, device=device, scene_path=scene, start=camera)
    start = view.start_pose()
    server = viser.ViserServer(host=host, port=port, verbose=False)
    server.scene.set_up_direction(start["up"])
    server.initial_camera.position = start["position"]
    server.initial_camera.look_at = start["look_at"]
    server.initial_camera.up = start["up"]
    server.initial_camera.fov = start["fov_y"]
    panels: dict[int, dict] = {}
    server.on_client_connect(lambda client: panels.__setitem__(client.client_id, add_controls(client, view)))
    planners: dict[int, FramePlanner] = {}
    old_term = signal.signal(signal.SIGTERM, _stop)
    try:
        # the address is printed inside the try: the page answers from viser's thread already, so
        # a Ctrl-C the moment the address shows must stop the viewer as a later one does
        Console(stderr=True).print(f"splatk view: http://{host}:{server.get_port()} (Ctrl-C to stop)",
                                   markup=False, highlight=False)
        while True:
            # one render at a time keeps the CPU for it; each browser gets a frame when its camera
            # moved, and a full-size one once it rests
            for client_id, client in list(server.get_clients().items()):
                planner = planners.setdefault(client_id, FramePlanner(max_size, 1.0 / fps))
                size = planner.next_size(client.camera.update_timestamp, time.monotonic())
                if size is None:
                    continue
                t0 = time.perf_counter()
                width, height = draw(client, view, size)
                seconds = time.perf_counter() - t0
                full = (width, height) == frame_size(client.camera.image_width, client.camera.image_height, max_size)
                planner.drawn(size, seconds, full=full)
                if client_id in panels:
                    panels[client_id]["frame"].content = f"Frame: {seconds * 1000:.0f} ms, {width}×{height}"
            time.sleep(0.02)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, old_term)
        server.stop()


def _stop(signum, frame):
    # SIGTERM (a service manager, `kill`, a background job that ignores Ctrl-C) stops the viewer
    # as Ctrl-C does: the server closes and the command exits 0
    raise KeyboardInterrupt
