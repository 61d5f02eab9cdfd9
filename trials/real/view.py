"""The operator's live view of a trial session (``advobj trial run --view``): each camera's latest
frame with the plan's placement drawn over it, on a web page served to this machine only.

A small HTTP server (the standard library's ``http.server``, one daemon thread per client) listens
on ``127.0.0.1`` (never another interface; :data:`HOST`) at the port ``--view-port`` names
(default :data:`DEFAULT_VIEW_PORT`; 0: a free port, printed with the URL):

* ``GET /``: an HTML page with no external assets that fetches each camera's image again every
  :data:`REFRESH_MS` ms (periodic PNG, no new dependency) and says under it which trial and which
  frame it shows;
* ``GET /frame/<camera>.png``: the newest frame the runner read of that camera, as a PNG of the
  camera's size, with the placement overlay; headers ``X-Trial`` and ``X-Frame-Seq`` name the
  trial and the camera's frame counter (:attr:`robot_io.cameras.base.Frame.seq`); 503 before the
  camera's first frame;
* anything else, an unknown camera included: 404. A frame URL is looked up whole in a table of
  the session's cameras: no part of a URL ever becomes a path.

**Publishing.** The runner hands over the frames it reads anyway (:meth:`LiveView.publish`: the
wrist camera's at the placement check, the outcome and every policy step, each fixed camera's at
every step); the view never reads a camera. ``publish`` puts a reference to the frame in its
camera's slot under a lock held for that assignment only: no copy, no drawing, no encoding, no
I/O. Drawing and PNG encoding run on the client's thread, outside the lock, so a slow or stalled
client blocks only its own thread (dropped after :data:`CLIENT_TIMEOUT_S`), never the control
loop; at most :data:`MAX_CLIENTS` are served at once.

**The overlay** (:class:`PlacementOverlay`) is the trial's object layout seen through each camera:
every object's footprint outline on the table (the printed placement sheet's outlines,
:func:`trials.real.sheet.placement_outlines`, at the layout's base centre and yaw, table z = 0),
translucently filled, with a cross at its base centre and a line along its +x axis (the sheet's
heading arrow), in the role's colour (:data:`ROLE_COLORS`). Points go to pixels through the
camera's calibrated intrinsics with distortion (:meth:`calibration.intrinsics.CameraIntrinsics.project`)
from the camera's pose in the table frame at that frame: a fixed camera's ``T_table_cam``, the
wrist camera's ``T_table_tcp @ T_tcp_cam`` with the TCP pose the runner measured for that frame.
A camera without intrinsics or pose is shown without overlay (the page says so).

The server stops with the session (:meth:`LiveView.close`, also on an error or Ctrl-C): the
listening socket closes and open client connections are shut down.
"""

from __future__ import annotations

import errno
import html
import socket
import threading
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Mapping, Sequence
from urllib.parse import urlsplit

import cv2
import numpy as np

from calibration.intrinsics import CameraIntrinsics
from robot_io.cameras.base import scale_intrinsics
from robot_io.config import load_T_tcp_cam, scene_camera_pose
from robot_io.errors import MissingIntrinsicsError
from sim.errors import AdvobjError
from sim.geometry import invert_T, make_T, rot_z, transform_points
from sim.policies.contract import WRIST_CAMERA
from trials.real.plan import PLAN_ROLES
from trials.real.sheet import placement_outlines

__all__ = [
    "HOST",
    "DEFAULT_VIEW_PORT",
    "REFRESH_MS",
    "CLIENT_TIMEOUT_S",
    "MAX_CLIENTS",
    "ROLE_COLORS",
    "LiveViewError",
    "ViewCamera",
    "view_cameras",
    "PlacementOverlay",
    "LiveView",
]

HOST = "127.0.0.1"  # this machine only: the view shows the cell, it is no service for the network
DEFAULT_VIEW_PORT = 8765
REFRESH_MS = 200  # the page asks for each camera's frame again this long after the previous one came
CLIENT_TIMEOUT_S = 5.0  # a client silent (or not reading) this long is dropped
MAX_CLIENTS = 16  # connections served at once; more are closed at once
CLOSE_WAIT_S = 2.0  # close() waits this long at most for the client threads to end
ROLE_COLORS = {"goal": (0, 200, 255), "adversarial": (255, 0, 200)}  # RGB: cyan-blue and magenta
HEADING_M = 0.06  # the heading line's length along the object's +x (the placement sheet's arrow)
FILL_ALPHA = 0.3  # opacity of a footprint's fill
MIN_DEPTH_M = 0.01  # a footprint point nearer the camera's plane than this: the object is not drawn
_MAX_PX = 1 << 15  # pixel coordinates handed to OpenCV's drawing are clipped to +-this


class LiveViewError(AdvobjError, ValueError):
    """The live view cannot listen at the port asked for; the message names ``--view-port``."""


@dataclass(frozen=True)
class ViewCamera:
    """What the overlay needs of one camera: its intrinsics (None: no overlay) and where it looks
    from: the wrist camera's mount ``T_tcp_cam``, or a fixed camera's ``T_table_cam`` (4, 4)."""

    intrinsics: CameraIntrinsics | None
    T_tcp_cam: np.ndarray | None = None
    T_table_cam: np.ndarray | None = None

    def T_table_cam_at(self, T_table_tcp: np.ndarray | None) -> np.ndarray | None:
        """The camera's pose in the table frame when the TCP was at ``T_table_tcp`` (None: unknown)."""
        if self.T_table_cam is not None:
            return self.T_table_cam
        if self.T_tcp_cam is None or T_table_tcp is None or not np.all(np.isfinite(T_table_tcp)):
            return None
        return np.asarray(T_table_tcp, dtype=np.float64) @ self.T_tcp_cam

    @property
    def note(self) -> str:
        """What the page says of this camera's overlay."""
        if self.intrinsics is None:
            return "no overlay: the camera has no intrinsics"
        if self.T_table_cam is None and self.T_tcp_cam is None:
            return "no overlay: the camera's pose is unknown (no T_tcp_cam)"
        return "overlay: the plan's placement"


def _intrinsics(camera) -> CameraIntrinsics | None:
    try:
        return camera.intrinsics
    except MissingIntrinsicsError:
        return None


def view_cameras(hw, spec, camera, fixed: Mapping) -> dict[str, ViewCamera]:
    """The overlay's geometry of a session's connected cameras: ``camera`` (the wrist camera) and
    ``fixed`` (``{name: camera}``), by the hardware config ``hw`` and the trials' scene ``spec``.

    The wrist camera's mount is the hand-eye file (``T_tcp_cam``) or, for a sim camera without one,
    its own (the scene's); a fixed camera's pose is its pose file, or for a sim camera without one
    where the scene puts it. Intrinsics are read from the connected devices (drivers may report
    them)."""
    mount = load_T_tcp_cam(hw.T_tcp_cam) if hw.T_tcp_cam is not None else getattr(camera, "T_tcp_cam", None)
    out = {WRIST_CAMERA: ViewCamera(_intrinsics(camera), T_tcp_cam=mount)}
    for name, cam in fixed.items():
        T_table_cam = scene_camera_pose(hw, name)
        if T_table_cam is None:
            T_table_cam = spec.camera_spec(name).T_table_cam
        out[name] = ViewCamera(_intrinsics(cam), T_table_cam=np.asarray(T_table_cam, dtype=np.float64))
    return out


class PlacementOverlay:
    """Draws a trial's object layout into a camera's frame (see the module docstring).

    Args:
        plan: the session's :class:`trials.real.plan.TrialPlan`.
        spec: the scene the plan places objects of (their footprints).
        cameras: ``{camera: ViewCamera}`` (:func:`view_cameras`).
    """

    def __init__(self, plan, spec, cameras: Mapping[str, ViewCamera]):
        self.plan = plan
        self.cameras = dict(cameras)
        outlines = placement_outlines(plan, spec)  # every footprint once, before the session runs
        self._goal = next(iter(outlines["goal"].values()))
        self._adversarial = outlines["adversarial"]

    def note(self, camera: str) -> str:
        cam = self.cameras.get(camera)
        return "no overlay: no geometry for this camera" if cam is None else cam.note

    def _outline(self, role: str, trial) -> np.ndarray | None:
        if role == "goal":
            return self._goal
        # placement_outlines keys the adversarial outlines as the plan names them: by shape, and "patch"
        return self._adversarial.get("patch" if trial.condition == "patch" else trial.shape)

    def project(self, camera: str, size_hw: tuple[int, int], T_table_tcp, trial) -> list[tuple[str, np.ndarray]]:
        """``[(role, px (M + 2, 2) int32)]``: each object's footprint outline (M points), then its
        base centre and the end of its heading line, in pixels of a ``size_hw`` frame of ``camera``.
        An object with a point behind the camera (or too near its plane) or a non-finite pixel is
        left out, as is everything for a camera without intrinsics or pose."""
        cam = self.cameras.get(camera)
        if trial is None or cam is None or cam.intrinsics is None:
            return []
        T_table_cam = cam.T_table_cam_at(T_table_tcp)
        if T_table_cam is None or not np.all(np.isfinite(T_table_cam)):
            return []
        h, w = size_hw
        try:
            intr = scale_intrinsics(cam.intrinsics, w, h, f"camera {camera!r}")
        except MissingIntrinsicsError:  # frames of another aspect ratio than calibrated: no K fits them
            return []
        T_cam_table = invert_T(T_table_cam)
        layout = self.plan.object_layout(trial.object_layout).objects
        out = []
        for role in PLAN_ROLES:
            outline = self._outline(role, trial)
            if outline is None:
                continue
            p = layout[role]
            T_table_object = make_T(rot_z(p.yaw_rad), [p.xy_m[0], p.xy_m[1], 0.0])
            points_object = np.vstack(
                [np.column_stack([outline, np.zeros(len(outline))]), [0.0, 0.0, 0.0], [HEADING_M, 0.0, 0.0]]
            )
            points_cam = transform_points(T_cam_table @ T_table_object, points_object)
            if not np.all(np.isfinite(points_cam)) or np.any(points_cam[:, 2] < MIN_DEPTH_M):
                continue
            px = intr.project(points_cam)
            if not np.all(np.isfinite(px)):
                continue
            out.append((role, np.rint(np.clip(px, -_MAX_PX, _MAX_PX)).astype(np.int32)))
        return out

    def draw(self, rgb: np.ndarray, camera: str, T_table_tcp, trial) -> np.ndarray:
        """A copy of ``rgb`` (H, W, 3) uint8 with ``trial``'s placement drawn as ``camera`` saw it
        with the TCP at ``T_table_tcp`` (the table frame); ``rgb`` itself is never written."""
        out = np.array(rgb, dtype=np.uint8, copy=True)
        h, w = out.shape[:2]
        shapes = self.project(camera, (h, w), T_table_tcp, trial)
        if not shapes:
            return out
        thick = max(1, round(min(h, w) / 240))
        marker = max(5, round(min(h, w) / 16))
        for role, px in shapes:  # fills first, every line over them
            mask = np.zeros((h, w), np.uint8)
            cv2.fillPoly(mask, [px[:-2]], 1)
            sel = mask.astype(bool)
            color = np.array(ROLE_COLORS[role], np.float32)
            out[sel] = np.rint((1 - FILL_ALPHA) * out[sel] + FILL_ALPHA * color).astype(np.uint8)
        for role, px in shapes:
            cv2.polylines(out, [px[:-2]], True, ROLE_COLORS[role], thick, cv2.LINE_AA)
        for role, px in shapes:  # last: the centre's pixel is the role's colour
            centre, head = (int(px[-2, 0]), int(px[-2, 1])), (int(px[-1, 0]), int(px[-1, 1]))
            cv2.line(out, centre, head, ROLE_COLORS[role], thick)
            cv2.drawMarker(out, centre, ROLE_COLORS[role], cv2.MARKER_CROSS, marker, thick)
        return out


@dataclass(frozen=True)
class _Slot:
    """A camera's latest frame as published: the runner's own array, never written afterwards."""

    rgb: np.ndarray
    seq: int
    T_table_tcp: np.ndarray | None
    trial: object | None


class _Server(ThreadingHTTPServer):
    daemon_threads = True  # a stalled client never holds the process (or the session's end) up

    def __init__(self, port: int, view: "LiveView"):
        self.view = view
        self.clients: set[socket.socket] = set()
        self.clients_lock = threading.Condition()  # notified when a client's connection ends
        super().__init__((HOST, port), _Handler)

    def process_request(self, request, client_address):
        with self.clients_lock:
            full = len(self.clients) >= MAX_CLIENTS
            if not full:
                self.clients.add(request)
        if full:
            self.shutdown_request(request)
            return
        super().process_request(request, client_address)

    def shutdown_request(self, request):
        super().shutdown_request(request)
        with self.clients_lock:
            self.clients.discard(request)
            self.clients_lock.notify_all()

    def drop_clients(self, timeout_s: float) -> None:
        """Shut every open client connection down and wait up to ``timeout_s`` for their threads to
        let go of them (a stalled client's write fails at once; a thread still drawing a frame
        stops at its next write)."""
        with self.clients_lock:
            clients = list(self.clients)
        for sock in clients:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:  # already closed by its client
                pass
        with self.clients_lock:
            self.clients_lock.wait_for(lambda: not self.clients, timeout_s)

    def handle_error(self, request, client_address):
        pass  # a client that went away or timed out: its own business, never a traceback on the operator's terminal


class _Handler(BaseHTTPRequestHandler):
    timeout = CLIENT_TIMEOUT_S
    server_version = "advobj-live-view"
    protocol_version = "HTTP/1.0"  # one request per connection: no idle keep-alive threads

    def do_GET(self):  # noqa: N802 - http.server's name
        view: LiveView = self.server.view
        path = urlsplit(self.path).path
        if path in ("/", "/index.html"):
            self._send(200, "text/html; charset=utf-8", view.page())
            return
        camera = view.route(path)
        if camera is None:
            self.send_error(404, "no such page or camera")
            return
        try:
            got = view.frame_png(camera)
        except Exception as err:  # noqa: BLE001 - one line to the page, the session goes on
            self.send_error(500, "frame error", f"camera {camera}: {type(err).__name__}: {' '.join(str(err).split())}")
            return
        if got is None:
            self.send_error(503, f"no frame of camera {camera} yet")
            return
        data, slot = got
        headers = {"X-Frame-Seq": str(slot.seq)}
        if slot.trial is not None:
            headers["X-Trial"] = str(slot.trial.trial_id)  # a plan's safe name
        self._send(200, "image/png", data, headers)

    def _send(self, code: int, content_type: str, body: bytes, headers: Mapping[str, str] | None = None) -> None:
        self.send_response(code)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for k, v in (headers or {}).items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format, *args):  # noqa: A002 - http.server's signature
        pass  # the operator's terminal belongs to the session


class LiveView:
    """The live view's server and the cameras' latest-frame slots (see the module docstring).

    Building it binds ``127.0.0.1:port`` (a port in use: one :class:`LiveViewError` naming
    ``--view-port``); ``with view:`` (or :meth:`start`) serves it from a daemon thread until
    :meth:`close`.

    Args:
        cameras: the session's camera names (``wrist`` and its fixed cameras); the only frame URLs.
        port: the port; None: :data:`DEFAULT_VIEW_PORT`; 0: a free one (see :attr:`url`).
        title: what the page is headed with (the session's name).
        overlay: the :class:`PlacementOverlay` (or :meth:`set_overlay` once the devices are up).
    """

    def __init__(
        self, cameras: Sequence[str], port: int | None = None, title: str = "", overlay: PlacementOverlay | None = None
    ):
        self.cameras = tuple(dict.fromkeys(cameras))
        self._routes = {f"/frame/{name}.png": name for name in self.cameras}
        self.title = str(title)
        self.overlay = overlay
        self._lock = threading.Lock()
        self._latest: dict[str, _Slot] = {}
        self._encoded: dict[str, tuple[_Slot, bytes]] = {}
        self._thread: threading.Thread | None = None
        self._closed = False
        port = DEFAULT_VIEW_PORT if port is None else int(port)
        try:
            self._server = _Server(port, self)
        except OverflowError as err:
            raise LiveViewError(f"--view-port: {port}: {err}") from None
        except OSError as err:
            why = "in use (another session's live view?)" if err.errno == errno.EADDRINUSE else err.strerror or err
            raise LiveViewError(
                f"--view-port: cannot listen on {HOST}:{port}: {why}; choose another port, or --view-port 0 for "
                "any free one"
            ) from None

    @property
    def port(self) -> int:
        return int(self._server.server_address[1])

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}/"

    def start(self) -> "LiveView":
        """Serve from a daemon thread (once)."""
        if self._closed:
            raise RuntimeError("live view: start() after close()")
        if self._thread is None:
            self._thread = threading.Thread(
                target=self._server.serve_forever, kwargs={"poll_interval": 0.1}, name="live-view", daemon=True
            )
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving: the listening socket closes, open connections are shut down (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._thread is not None:
            self._server.shutdown()
            self._thread.join()
        self._server.drop_clients(CLOSE_WAIT_S)
        self._server.server_close()
        with self._lock:
            self._latest.clear()
            self._encoded.clear()

    def __enter__(self) -> "LiveView":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def n_clients(self) -> int:
        """Client connections open now."""
        with self._server.clients_lock:
            return len(self._server.clients)

    # ------------------------------------------------------------------ the runner's side
    def set_overlay(self, overlay: PlacementOverlay | None) -> None:
        self.overlay = overlay

    def publish(self, camera: str, frame, T_table_tcp: np.ndarray | None = None, trial=None) -> None:
        """Make ``frame`` (a :class:`robot_io.cameras.base.Frame` just read) camera ``camera``'s
        latest, seen with the TCP at ``T_table_tcp`` during ``trial``: one assignment under the
        lock, nothing copied, drawn or sent here."""
        if camera not in self._routes.values():
            raise KeyError(f"live view: camera {camera!r} is not one of {', '.join(self.cameras)}")
        slot = _Slot(frame.rgb, int(frame.seq), T_table_tcp, trial)
        with self._lock:
            self._latest[camera] = slot

    # ------------------------------------------------------------------ the clients' side
    def route(self, path: str) -> str | None:
        """The camera whose frame URL ``path`` is, else None."""
        return self._routes.get(path)

    def frame_png(self, camera: str) -> tuple[bytes, _Slot] | None:
        """The PNG of ``camera``'s latest frame with the overlay, and its slot (None: no frame yet).
        Drawn and encoded outside the lock, once per frame however many clients ask."""
        with self._lock:
            slot = self._latest.get(camera)
            cached = self._encoded.get(camera)
        if slot is None:
            return None
        if cached is not None and cached[0] is slot:
            return cached[1], slot
        overlay = self.overlay
        rgb = slot.rgb if overlay is None else overlay.draw(slot.rgb, camera, slot.T_table_tcp, slot.trial)
        ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise RuntimeError(f"live view: camera {camera!r}: PNG encoding failed")
        data = buf.tobytes()
        with self._lock:
            self._encoded[camera] = (slot, data)
        return data, slot

    def page(self) -> bytes:
        """The HTML page: one refreshing image per camera, the overlay's legend, no external assets."""
        overlay = self.overlay
        figures = []
        for name in self.cameras:
            note = "no overlay" if overlay is None else overlay.note(name)
            e = html.escape(name, quote=True)
            figures.append(
                f'<figure><img data-camera="{e}" data-src="/frame/{e}.png" alt="camera {e}">'
                f'<figcaption><b>{e}</b>: <span class="info">waiting for a frame</span><br>'
                f"<small>{html.escape(note)}</small></figcaption></figure>"
            )
        legend = " ".join(
            f'<span style="color: rgb{color}">&#9632; {role}</span>' for role, color in ROLE_COLORS.items()
        )
        title = html.escape(f"advobj live view{': ' + self.title if self.title else ''}")
        return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<style>
body {{ font-family: sans-serif; background: #202020; color: #e8e8e8; margin: 1em; }}
figure {{ display: inline-block; margin: 0 1em 1em 0; vertical-align: top; }}
img {{ min-width: 320px; image-rendering: pixelated; border: 1px solid #555; background: #000; }}
img:not([src]) {{ min-height: 240px; color: transparent; }}
</style></head>
<body>
<h1>{title}</h1>
<p>{legend}: where the plan places each object (its outline on the table, a cross at its base
centre, a line along its +x axis). Frames are the ones the session reads; the view reads none.</p>
{"".join(figures)}
<script>
const REFRESH_MS = {REFRESH_MS};
for (const img of document.querySelectorAll("img[data-src]")) {{
  const info = img.parentElement.querySelector(".info");
  async function tick() {{
    let wait = REFRESH_MS;
    try {{
      const r = await fetch(img.dataset.src, {{ cache: "no-store" }});
      if (r.ok) {{
        const url = URL.createObjectURL(await r.blob());
        const old = img.src;
        img.src = url;
        if (old.startsWith("blob:")) URL.revokeObjectURL(old);
        info.textContent = "trial " + (r.headers.get("X-Trial") || "-") + ", frame " + r.headers.get("X-Frame-Seq");
      }} else {{
        info.textContent = r.status === 503 ? "waiting for a frame" : "error " + r.status;
      }}
    }} catch (e) {{
      info.textContent = "the session has ended (no server)";
      wait = 10 * REFRESH_MS;
    }}
    setTimeout(tick, wait);
  }}
  tick();
}}
</script>
</body></html>
""".encode()
