"""A browser viewer (viser): the model is rendered on the server as it was trained (each pixel the
mean of its own n × n rays, radfield.core.render.antialias.render_model) and streamed to each browser as the scene's background image; the cage (a wireframe toggle) and the
dataset's cameras (frustums) are drawn by the browser on top.

Each connected browser gets its own frames: while its camera moves the view is rendered at
1/`moving_downscale` of `resolution` (long side, pixels), and once the camera has rested for
`SETTLE_SECONDS` at the full `resolution`. viser's cameras use OpenCV axes, as radfield does, so a
viser camera (wxyz, position, vertical fov, aspect) is a radfield Camera without conversion.

A dynamic model (a time-conditioned kind, core/kinds/dynamic.py) gets a "Time" slider in [0, 1]:
every frame is drawn at its moment (Camera.time), and moving it redraws every browser's view. A
dynamic dataset photographs each camera at many moments: its frustums are drawn once a pose.
Its "Play" button (then "Pause") runs the Time slider: one pass over [0, 1] in `PLAY_SECONDS`,
then from 0 again, and every browser's slider and view follow; dragging the slider while it plays
continues from there. The server advances the slider by the wall time the last round of frames
took, once per round (serve_forever): a pass takes `PLAY_SECONDS` however fast frames are drawn,
slower drawing shows fewer moments instead of a slower clip, and the slider never moves more often
than frames are drawn. (A fixed step per drawn frame would tie the clip's speed to the model's
size, the resolution, the device and the number of browsers.) While it plays the frames are drawn
at the moving resolution, as while the camera moves, so that more moments are shown; paused, the
view is drawn at full resolution.

A relightable model (core/kinds/relight.py) gets a light control: "Light azimuth" and "Light
elevation" sliders (degrees about the model's centre and the dataset's up) and, for a point light,
"Light distance"; every frame is drawn under that light (Camera.light), and moving one redraws
every browser's view. The light starts where `--light` / `--light-dir` puts it, else at the mean
distance and elevation of the dataset's lights (conditions/light.py: orbit_lights), else (a model
file) at 45 degrees and three times the model's spread, of intensity distance², which lights the
centre with irradiance 1 as the olat demo scene's lights do.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from radfield.core.render.antialias import render_model
from radfield.core.geometry.cameras import Camera
from radfield.core.geometry.rotations import quat_to_rotmat, rotmat_to_quat
from radfield.core.render.rasterize import render
from radfield import conditions
from radfield.conditions.light import light_angles, light_at
from radfield.delivery.view_scene import ViewerScene

SETTLE_SECONDS = 0.3    # camera still this long -> render at full resolution
POLL_SECONDS = 0.02
MAX_FRUSTUMS = 300      # dataset cameras drawn (evenly subsampled beyond this)
MAX_CAGE_EDGES = 60_000
LIGHT_DISTANCES = (0.25, 4.0)   # the distance slider's range, times the starting light's distance
TIME_STEP = 0.01        # the time slider's resolution: the model is continuous in time, the data's moments need not be k/100
PLAY_SECONDS = 4.0      # one pass of Play over [0, 1]: a few seconds, slow enough to follow a change


@dataclass
class _ClientState:
    stamp: float = 0.0          # camera update time of the last frame sent
    full: bool = False          # whether that frame was at full resolution
    frames: int = 0
    moment: float | None = None  # the time a dynamic model's last frame showed
    light: object = None         # the light a relightable model's last frame was drawn under


def tet_edges(tets: np.ndarray) -> np.ndarray:
    """Unique edges (E, 2) of tetrahedra (T, 4)."""
    pairs = np.asarray(tets)[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
    return np.unique(np.sort(pairs, axis=1), axis=0)


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
        # the viewer's own controls: a Time slider and Play, light sliders (its conditions, conditions/)
        taken = {condition.name for condition in conditions.taken(scene.model)}
        self.dynamic, self.relightable = "time" in taken, "light" in taken
        self.time_slider = self.play_button = None
        self.playing = False
        self.play_phase = 0.0        # Play's position in [0, 1), finer than the slider's step
        self.play_clock = 0.0        # time.monotonic() of Play's last advance
        self.play_shown = 0.0        # the slider value Play last set (another one: the user moved it)
        self.centre, self.up = scene.centre, scene.up
        self.start_light = scene.start_light() if self.relightable else None
        # one tiny render first: the fused kernels load (or compile) before a browser waits on them
        render(scene.model, Camera(8.0, 8.0, 4.0, 4.0, 8, 8, torch.eye(4, dtype=torch.float64)).at(
            time=scene.time if self.dynamic else None, light=self.start_light))
        # a browser probing the port before it connects makes websockets log a handshake traceback
        logging.getLogger("websockets").setLevel(logging.CRITICAL)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.clients: dict[int, _ClientState] = {}
        self.lock = threading.Lock()
        self._add_overlays()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(lambda client: self.clients.pop(client.client_id, None))

    # --- scene overlays ---------------------------------------------------------------------
    def _add_overlays(self) -> None:
        scene, gui = self.server.scene, self.server.gui
        if self.scene.cameras:
            # the dataset's mean "up" (−y of each camera) becomes the orbit's up direction
            scene.set_up_direction(tuple(self.up))
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
        if self.dynamic:
            # no redraw callback: step() compares each client's last moment with the slider's
            self.time_slider = gui.add_slider("Time", min=0.0, max=1.0, step=TIME_STEP, initial_value=self.scene.time,
                                              hint="the moment shown, in [0, 1]")
            # gray, not viser's default blue: the panel stays colourless, so a saturated colour on
            # the page is the model's (the browser tests read a screenshot's colours)
            self.play_button = gui.add_button("Play", icon="player-play", color="gray",
                                              hint=f"runs the Time slider: one pass over [0, 1] in {PLAY_SECONDS:g} s, looping")
            self.play_button.on_click(lambda _: self.set_playing(not self.playing))
        if self.relightable:
            self._add_light_control(gui)
        gui.add_markdown(f"{len(self.scene.model)} {self.scene.model.kind} primitives")

    def _add_light_control(self, gui) -> None:
        """Azimuth, elevation (and a point light's distance) sliders; no redraw callback: step()
        compares each client's last light with the sliders'."""
        azimuth, elevation, distance = light_angles(self.centre, self.up, self.start_light)
        self.light_sliders = [gui.add_slider("Light azimuth", min=-180.0, max=180.0, step=1.0,
                                             initial_value=azimuth, hint="degrees about the up direction"),
                              gui.add_slider("Light elevation", min=-89.0, max=89.0, step=1.0,
                                             initial_value=elevation, hint="degrees above the horizon")]
        if distance is not None:
            low, high = (distance * f for f in LIGHT_DISTANCES)
            self.light_sliders.append(gui.add_slider("Light distance", min=low, max=high, step=(high - low) / 200,
                                                     initial_value=distance, hint="from the model's centre"))
        self.light_start_values = [slider.value for slider in self.light_sliders]

    def set_playing(self, playing: bool) -> None:
        """Start or pause Play (module docstring); the button then offers the other."""
        if playing and not self.playing:
            self.play_phase = self.play_shown = float(self.time_slider.value)
            self.play_clock = time.monotonic()
        self.playing = playing
        self.play_button.label = "Pause" if playing else "Play"
        self.play_button.icon = "player-pause" if playing else "player-play"

    def advance_play(self, now: float | None = None) -> None:
        """While Play is on, move the Time slider on by the wall time since its last advance (one
        pass in PLAY_SECONDS, from 1 back to 0); the slider shows the moment rounded to its step."""
        if not self.playing:
            return
        now = time.monotonic() if now is None else now
        if self.time_slider.value != self.play_shown:
            self.play_phase = float(self.time_slider.value)   # the user moved the slider: play on from there
        self.play_phase = (self.play_phase + (now - self.play_clock) / PLAY_SECONDS) % 1.0
        self.play_clock = now
        shown = round(round(self.play_phase / TIME_STEP) * TIME_STEP, 6)
        if shown != self.time_slider.value:
            self.time_slider.value = self.play_shown = shown

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
    @property
    def time(self) -> float | None:
        """The moment a dynamic model is drawn at (the Time slider's), None for a static model."""
        return float(self.time_slider.value) if self.time_slider is not None else None

    @property
    def light(self):
        """The light a relightable model is drawn under (the light sliders'), None for other models."""
        if not self.relightable:
            return None
        if [slider.value for slider in self.light_sliders] == self.light_start_values:
            return self.start_light   # exactly the light asked for, not its round trip through the angles
        azimuth, elevation, *distance = (float(slider.value) for slider in self.light_sliders)
        return light_at(self.centre, self.up, azimuth, elevation, distance[0] if distance else None,
                        self.start_light.intensity)

    def render_view(self, camera: Camera, moment: float | None = None, light=None) -> np.ndarray:
        """`camera`'s frame (H, W, 3) uint8; a dynamic model's at `moment` (default: the slider's), a
        relightable model's under `light` (default: the light sliders')."""
        moment = self.time if moment is None else moment
        light = self.light if light is None else light
        with torch.no_grad():
            out = render_model(self.scene.model, camera.at(time=moment, light=light),
                               background=self.scene.background)
        return (out.color.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()

    def render_frame(self, client, height: int, moment: float | None = None, light=None) -> np.ndarray:
        cam = client.camera
        return self.render_view(viser_camera(cam.wxyz, cam.position, cam.fov, cam.aspect, height), moment, light)

    def step(self) -> int:
        """Render one frame for every client that needs one; returns how many were rendered."""
        rendered = 0
        for client_id, client in list(self.server.get_clients().items()):
            with self.lock:
                state = self.clients.get(client_id)
            if state is None or client.camera.update_timestamp == 0.0:
                continue   # the browser has not reported its camera yet
            stamp = client.camera.update_timestamp
            moment, light = self.time, self.light   # read once: a slider may move while this frame renders
            moved = stamp != state.stamp or moment != state.moment or light != state.light
            # a playing clip is motion too: its frames are drawn small (module docstring)
            settled = time.time() - stamp > SETTLE_SECONDS and not self.playing
            if not moved and (state.full or not settled):
                continue
            full = settled
            long_side = int(self.res_slider.value) // (1 if full else self.moving_downscale)
            aspect = client.camera.aspect
            height = long_side if aspect < 1 else max(1, round(long_side / aspect))
            start = time.perf_counter()
            image = self.render_frame(client, height, moment, light)
            client.scene.set_background_image(image, format="jpeg", jpeg_quality=90)
            state.stamp, state.full, state.moment, state.light = stamp, full, moment, light
            state.frames += 1
            rendered += 1
            at = f" at time {moment:.2f}" if moment is not None else ""
            at += f" under a light at {', '.join(f'{x:.2f}' for x in light.position)}" if light and light.position else ""
            at += f" under a light along {', '.join(f'{x:.2f}' for x in light.direction)}" if light and light.direction else ""
            self.log(f"viewer: frame {state.frames} for client {client_id}: {image.shape[1]}x{image.shape[0]}"
                     f"{' (full)' if full else ''}{at} in {1e3 * (time.perf_counter() - start):.0f} ms")
        return rendered

    def serve_forever(self) -> None:
        try:
            while True:
                self.advance_play()   # once per round of frames: never faster than they are drawn
                if not self.step():
                    time.sleep(POLL_SECONDS)
        finally:
            self.server.stop()
