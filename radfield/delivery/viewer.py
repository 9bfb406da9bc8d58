"""A browser viewer (viser): the model is rendered on the server as it was trained (each pixel the
mean of its own n × n rays, radfield.core.render.antialias.render_model) and streamed to each browser as the scene's background image; the cage (a wireframe toggle) and the
dataset's cameras (frustums) are drawn by the browser on top.

Each connected browser gets its own frames: while its camera moves the view is rendered at
1/`moving_downscale` of `resolution` (long side, pixels), and once the camera has rested for
`SETTLE_SECONDS` at the full `resolution`. viser's cameras use OpenCV axes, as radfield does, so a
viser camera (wxyz, position, vertical fov, aspect) is a radfield Camera without conversion.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from radfield.core.render.antialias import render_model
from radfield.core.geometry.cameras import Camera
from radfield.delivery.export import view_cameras
from radfield.core.geometry.rotations import quat_to_rotmat, rotmat_to_quat
from radfield.core.render.rasterize import render

SETTLE_SECONDS = 0.3    # camera still this long -> render at full resolution
POLL_SECONDS = 0.02
MAX_FRUSTUMS = 300      # dataset cameras drawn (evenly subsampled beyond this)
MAX_CAGE_EDGES = 60_000


@dataclass
class _ClientState:
    stamp: float = 0.0          # camera update time of the last frame sent
    full: bool = False          # whether that frame was at full resolution
    frames: int = 0


@dataclass
class ViewerScene:
    """What the viewer shows: primitives (on `device`), and optionally the cage (V, 3) + (T, 4) and
    the dataset cameras (radfield Cameras)."""

    model: object
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    cage: tuple[np.ndarray, np.ndarray] | None = None
    cameras: list[Camera] = field(default_factory=list)


def tet_edges(tets: np.ndarray) -> np.ndarray:
    """Unique edges (E, 2) of tetrahedra (T, 4)."""
    pairs = np.asarray(tets)[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
    return np.unique(np.sort(pairs, axis=1), axis=0)


def viewer_scene(target, device: str = "cpu", background: tuple[float, float, float] | None = None) -> ViewerScene:
    """What `radfield view TARGET` shows: the model of a model file or a run, and for a run its cage
    and its dataset's cameras. An edited run has no data stage of its own: its cameras (and
    background) are its source run's (radfield.run.Run.dataset_scene), since an edit keeps the
    world frame. `background` overrides the run's (default white)."""
    from pathlib import Path

    from radfield.datasets.scene import load_scene
    from radfield.delivery.content import load_content
    from radfield.run import Run, is_run_dir

    content = load_content(Path(target), device, parts=("cage", "cameras"))
    views, run_background = content.views, content.background
    if views is None and is_run_dir(target):
        scene_file = Run(target).dataset_scene()
        if scene_file is not None:
            scene = load_scene(scene_file)
            run_background = run_background or scene.background
            views = scene.splits if scene.posed else None
    return ViewerScene(content.model, background or run_background or (1.0, 1.0, 1.0), content.cage, viewer_cameras(views))


def viewer_cameras(splits: dict[str, list[dict]] | None) -> list[Camera]:
    """radfield Cameras of scene.json views (every split; the train views first)."""
    return view_cameras([v for split in sorted(splits or {}, key=lambda s: s != "train") for v in splits[split]])


def viser_camera(wxyz, position, fov: float, aspect: float, height: int) -> Camera:
    """The radfield Camera of a viser camera (OpenCV axes; `fov` vertical, radians) at `height` rows."""
    height = max(1, int(height))
    width = max(1, round(height * aspect))
    fy = 0.5 * height / math.tan(0.5 * fov)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = quat_to_rotmat(torch.as_tensor(np.asarray(wxyz), dtype=torch.float64)[None])[0]
    c2w[:3, 3] = torch.as_tensor(np.asarray(position), dtype=torch.float64)
    return Camera(fy, fy, width / 2, height / 2, width, height, c2w, "viewer")


class Viewer:
    def __init__(self, scene: ViewerScene, *, host: str = "127.0.0.1", port: int = 8080,
                 resolution: int = 512, moving_downscale: int = 4, log=print):
        import viser

        self.scene, self.resolution, self.moving_downscale, self.log = scene, resolution, moving_downscale, log
        # one tiny render first: the fused kernels load (or compile) before a browser waits on them
        render(scene.model, Camera(8.0, 8.0, 4.0, 4.0, 8, 8, torch.eye(4, dtype=torch.float64)))
        # a browser probing the port before it connects makes websockets log a handshake traceback
        logging.getLogger("websockets").setLevel(logging.CRITICAL)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.clients: dict[int, _ClientState] = {}
        self.lock = threading.Lock()
        self.centre = scene.model.means.detach().median(0).values.cpu().double().numpy()
        self._add_overlays()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(lambda client: self.clients.pop(client.client_id, None))

    # --- scene overlays ---------------------------------------------------------------------
    def _add_overlays(self) -> None:
        scene, gui = self.server.scene, self.server.gui
        if self.scene.cameras:
            # the dataset's mean "up" (−y of each camera) becomes the orbit's up direction
            up = -np.mean([c.c2w[:3, 1].numpy() for c in self.scene.cameras], axis=0)
            scene.set_up_direction(tuple(up / max(np.linalg.norm(up), 1e-12)))
        if self.scene.cage is not None:
            vertices, tets = self.scene.cage
            edges = tet_edges(tets)[:MAX_CAGE_EDGES]
            cage = scene.add_line_segments("/cage", points=np.asarray(vertices, np.float32)[edges],
                                           colors=(40, 90, 220), thickness=1.0, thickness_units="screen",
                                           visible=False)
            toggle = gui.add_checkbox("Cage wireframe", False, hint=f"{len(edges)} edges of {len(tets)} tets")
            toggle.on_update(lambda _: setattr(cage, "visible", toggle.value))
        if self.scene.cameras:
            step = max(1, math.ceil(len(self.scene.cameras) / MAX_FRUSTUMS))
            spread = np.linalg.norm([c.center.numpy() - self.centre for c in self.scene.cameras], axis=1).mean()
            frustums = []
            for i, cam in enumerate(self.scene.cameras[::step]):
                frustums.append(scene.add_camera_frustum(
                    f"/cameras/{i}", fov=2 * math.atan(0.5 * cam.height / cam.fy), aspect=cam.width / cam.height,
                    scale=0.05 * spread, thickness=1.0, thickness_units="screen", color=(230, 120, 20),
                    wxyz=rotmat_to_quat(cam.c2w[:3, :3][None])[0].numpy(), position=cam.center.numpy()))
            toggle = gui.add_checkbox("Dataset cameras", True, hint=f"{len(self.scene.cameras)} cameras")
            toggle.on_update(lambda _: [setattr(f, "visible", toggle.value) for f in frustums])
        self.res_slider = gui.add_slider("Resolution", min=64, max=2048, step=32, initial_value=self.resolution)
        self.res_slider.on_update(lambda _: self._redraw_all())
        gui.add_markdown(f"{len(self.scene.model)} {self.scene.model.kind} primitives")

    def _connect(self, client) -> None:
        if self.scene.cameras:
            start = self.scene.cameras[0]
            client.camera.fov = 2 * math.atan(0.5 * start.height / start.fy)
            # a little behind the first dataset camera, so its frustum does not fill the view
            client.camera.position = self.centre + 1.25 * (start.center.numpy() - self.centre)
            client.camera.look_at = self.centre
        else:
            extent = float(self.scene.model.means.detach().std(0).norm().cpu())
            client.camera.position = self.centre + np.array([0.0, -3.0, 1.5]) * max(extent, 1e-3)
            client.camera.look_at = self.centre
        with self.lock:
            self.clients[client.client_id] = _ClientState()
        self.log(f"viewer: client {client.client_id} connected")

    def _redraw_all(self) -> None:
        with self.lock:
            for state in self.clients.values():
                state.stamp, state.full = -1.0, False

    # --- rendering ----------------------------------------------------------------------------
    def render_frame(self, client, height: int) -> np.ndarray:
        cam = client.camera
        camera = viser_camera(cam.wxyz, cam.position, cam.fov, cam.aspect, height)
        with torch.no_grad():
            out = render_model(self.scene.model, camera, background=self.scene.background)
        return (out.color.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()

    def step(self) -> int:
        """Render one frame for every client that needs one; returns how many were rendered."""
        rendered = 0
        for client_id, client in list(self.server.get_clients().items()):
            with self.lock:
                state = self.clients.get(client_id)
            if state is None or client.camera.update_timestamp == 0.0:
                continue   # the browser has not reported its camera yet
            stamp = client.camera.update_timestamp
            moved = stamp != state.stamp
            settled = time.time() - stamp > SETTLE_SECONDS
            if not moved and (state.full or not settled):
                continue
            full = settled
            long_side = int(self.res_slider.value) // (1 if full else self.moving_downscale)
            aspect = client.camera.aspect
            height = long_side if aspect < 1 else max(1, round(long_side / aspect))
            start = time.perf_counter()
            image = self.render_frame(client, height)
            client.scene.set_background_image(image, format="jpeg", jpeg_quality=90)
            state.stamp, state.full = stamp, full
            state.frames += 1
            rendered += 1
            self.log(f"viewer: frame {state.frames} for client {client_id}: {image.shape[1]}x{image.shape[0]}"
                     f"{' (full)' if full else ''} in {1e3 * (time.perf_counter() - start):.0f} ms")
        return rendered

    def serve_forever(self) -> None:
        try:
            while True:
                if not self.step():
                    time.sleep(POLL_SECONDS)
        finally:
            self.server.stop()
