"""The operator's live view (``advobj trial run --view``, trials/real/view.py): a sim cell session
serves its cameras' latest frames with the plan's placement drawn in, on 127.0.0.1, to a real HTTP
client while it runs; unknown cameras and traversal paths are 404; the server is gone when the
session ends, by an error too; a stalled client never delays the runner's publish."""

from __future__ import annotations

import errno
import http.client
import inspect
import re
import socket
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.intrinsics import CameraIntrinsics
from robot_io.cameras.base import Frame
from sim.geometry import invert_T, look_at, make_T, so3_exp
from sim.spec import load_spec
from tests.trials.real.trial_session_helpers import REPO, sim_hardware, small_plan, tiny_onnx, two_camera_onnx
from trials.real.operator import AutoOperator
from trials.real.plan import load_plan
from trials.real.session import SessionOptions, SessionSetupError, run_session
from trials.real.store import TrialStore
from trials.real.view import (
    DEFAULT_VIEW_PORT,
    HOST,
    ROLE_COLORS,
    LiveView,
    LiveViewError,
    PlacementOverlay,
    ViewCamera,
)

TWO_CAMERAS = REPO / "scenes" / "two-cameras.yaml"
URL = re.compile(r"live view: (http://127\.0\.0\.1:(\d+)/)")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _get(url: str):
    """``(status, headers, body)`` of a GET by urllib; an HTTP error status is returned, not raised."""
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return r.status, r.headers, r.read()
    except urllib.error.HTTPError as err:
        return err.code, err.headers, err.read()


def _raw_get(port: int, path: str) -> int:
    """The status of ``GET path`` sent exactly as written (http.client: no normalisation of '..')."""
    conn = http.client.HTTPConnection(HOST, port, timeout=10)
    try:
        conn.request("GET", path)
        return conn.getresponse().status
    finally:
        conn.close()


def _refused(url: str) -> bool:
    try:
        urllib.request.urlopen(url, timeout=5)
    except urllib.error.URLError as err:
        return isinstance(err.reason, ConnectionRefusedError)
    return False


def _png_rgb(body: bytes) -> np.ndarray:
    assert body[:8] == PNG_MAGIC
    bgr = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


@pytest.fixture(scope="module")
def two_camera_cell(tmp_path_factory):
    d = tmp_path_factory.mktemp("view_cell")
    return {
        "policy": two_camera_onnx(d / "two_cameras.onnx"),
        "plan": small_plan(d / "plan.yaml", d, n_tcp=1, max_steps=3, conditions=("clean", "adv3d"), scene=TWO_CAMERAS),
        "hw": sim_hardware(d / "cell.yaml", scene_cameras={"front": {"type": "sim"}}),
    }


@pytest.fixture(scope="module")
def wrist_cell(tmp_path_factory):
    d = tmp_path_factory.mktemp("view_wrist_cell")
    return {
        "policy": tiny_onnx(d / "policy.onnx"),
        "plan": small_plan(d / "plan.yaml", d, n_tcp=1, max_steps=2, conditions=("clean",)),
        "hw": sim_hardware(d / "cell.yaml"),
    }


def _opts(cell, db, **changes) -> SessionOptions:
    values = dict(
        hardware=cell["hw"], policy=cell["policy"], plan=cell["plan"], session="s", db=db, rate_limit=False, view=True
    )
    return SessionOptions(**{**values, **changes})


def _pixel(T_table_cam: np.ndarray, K: np.ndarray, xy) -> tuple[int, int]:
    """(u, v) of the table point (x, y, 0) through a distortion-free pinhole (independent of the view)."""
    p = invert_T(T_table_cam) @ np.array([xy[0], xy[1], 0.0, 1.0])
    uv = K @ (p[:3] / p[2])
    return int(np.rint(uv[0])), int(np.rint(uv[1]))


def test_a_sim_session_with_the_view_serves_each_cameras_latest_frame_with_the_placement_to_an_http_client(
    two_camera_cell, tmp_path
):
    db = tmp_path / "t.sqlite"
    lines: list[str] = []
    seen: dict = {}

    def while_running(trial):
        if seen:
            return
        ((url, port),) = [(m.group(1), int(m.group(2))) for m in map(URL.search, lines) if m]
        status, headers, page = _get(url)
        seen.update(url=url, trial=trial.trial_id, page=(status, headers["Content-Type"], page.decode()))
        for camera in ("wrist", "front"):
            status, headers, body = _get(f"{url}frame/{camera}.png")
            seen[camera] = (status, headers.get("X-Trial"), int(headers["X-Frame-Seq"]), _png_rgb(body))
        seen["unknown"] = _get(f"{url}frame/side.png")[0]
        seen["traversal"] = [
            _raw_get(port, path)
            for path in ("/frame/../frame/wrist.png", "/frame/%2e%2e/wrist.png", "/../etc/passwd", "/frame/wrist")
        ]

    summary = run_session(
        _opts(two_camera_cell, db, view_port=0),
        operator=AutoOperator(log=None),
        on_trial_end=while_running,
        log=lines.append,
    )
    assert not summary.aborted and len(summary.committed) == 2
    # The page: the session's cameras, the overlay's legend, nothing fetched from elsewhere.
    status, content_type, page = seen["page"]
    assert status == 200 and content_type.startswith("text/html")
    assert 'data-src="/frame/wrist.png"' in page and 'data-src="/frame/front.png"' in page
    assert "goal" in page and "adversarial" in page and "https://" not in page and "http://" not in page
    # Each frame: a PNG of its camera's size, the newest the runner read (on_trial_end follows the loop).
    with TrialStore(db, create=False) as store:
        steps = store.steps("s", seen["trial"])
    (s_wrist, t_wrist, seq_wrist, wrist), (s_front, t_front, seq_front, front) = seen["wrist"], seen["front"]
    assert s_wrist == s_front == 200 and t_wrist == t_front == seen["trial"]
    assert wrist.shape == (32, 32, 3) and front.shape == (128, 128, 3)
    assert seq_wrist == steps[-1]["frame_seq"] and seq_front == steps[-1]["camera_frames"]["front"]["frame_seq"]
    # 404 for a camera the session does not have, and for every path that is not a frame URL as a whole.
    assert seen["unknown"] == 404 and seen["traversal"] == [404, 404, 404, 404]
    # The overlay: the served front frame is the committed one, except around where the plan puts each
    # object; at each object's base centre (an independent pinhole projection) the role's colour.
    raw = iio.imread(db.parent / steps[-1]["camera_frames"]["front"]["frame_ref"])
    cam = load_spec(TWO_CAMERAS).camera_spec("front")
    K, T_table_cam = cam.K(128, 128), cam.T_table_cam
    plan = load_plan(two_camera_cell["plan"])
    layout = plan.object_layout(plan.trial(seen["trial"]).object_layout).objects
    changed = np.any(front != raw, axis=-1)
    near = np.zeros_like(changed)
    for role, color in ROLE_COLORS.items():
        u, v = _pixel(T_table_cam, K, layout[role].xy_m)
        assert 0 <= u < 128 and 0 <= v < 128
        assert tuple(front[v, u]) == color and tuple(raw[v, u]) != color, role
        # everything the overlay draws for this object lies within 10 cm of its base centre on the table
        ring = [
            _pixel(T_table_cam, K, np.asarray(layout[role].xy_m) + 0.1 * np.array([np.cos(a), np.sin(a)]))
            for a in np.linspace(0, 2 * np.pi, 36, endpoint=False)
        ]
        (u0, v0), (u1, v1) = np.min(ring, axis=0) - 2, np.max(ring, axis=0) + 2
        box = np.zeros_like(changed)
        box[max(v0, 0) : v1 + 1, max(u0, 0) : u1 + 1] = True
        assert changed[box].sum() > 20, role
        near |= box
    assert changed.any() and not changed[~near].any()
    # The server is gone with the session.
    assert _refused(seen["url"])


@pytest.mark.parametrize(("hook", "error"), [("on_ready", KeyboardInterrupt), ("on_trial_end", RuntimeError)])
def test_the_view_stops_when_the_session_ends_by_an_error_or_ctrl_c(wrist_cell, tmp_path, hook, error):
    lines: list[str] = []
    served = []

    def fail(*_args):
        (url,) = [m.group(1) for m in map(URL.search, lines) if m]
        served.append((url, _get(url)[0]))
        raise error("stop here")

    with pytest.raises(error, match="stop here"):
        run_session(
            _opts(wrist_cell, tmp_path / "t.sqlite", view_port=0),
            operator=AutoOperator(log=None),
            log=lines.append,
            **{hook: fail},
        )
    ((url, status),) = served
    assert status == 200 and _refused(url)


def test_a_stalled_client_does_not_delay_publish_nor_the_other_clients():
    # 12 MB of noise: its PNG is larger than the socket buffers, so a client that never reads
    # stalls the thread serving it in the middle of writing.
    big = Frame(np.random.default_rng(0).integers(0, 256, (2000, 2000, 3), dtype=np.uint8), 0.0, 0)
    with LiveView(["wrist"], port=0) as view:
        view.publish("wrist", big)
        stalled = socket.socket()
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled.connect((HOST, view.port))
        stalled.sendall(b"GET /frame/wrist.png HTTP/1.0\r\n\r\n")  # and never reads
        silent = socket.create_connection((HOST, view.port))  # sends nothing at all
        deadline = time.monotonic() + 10
        while view.n_clients < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.5)  # the stalled thread is encoding or blocked in its write by now
        assert view.n_clients == 2
        small = np.full((24, 32, 3), 7, np.uint8)
        # No timing: had publish waited on a client, it would have waited for the stalled one, which
        # the server drops only after its 5 s of silence; both clients still being there after 1000
        # publishes and another client's request shows neither waited for it.
        for seq in range(1, 1001):
            view.publish("wrist", Frame(small, 0.0, seq))
        assert view.n_clients == 2
        # another client gets the newest frame while the stalled one still hangs
        status, headers, body = _get(view.url + "frame/wrist.png")
        assert status == 200 and headers["X-Frame-Seq"] == "1000" and np.array_equal(_png_rgb(body), small)
        # the served client's thread ends just after its reply is read: wait for it, not for the others
        deadline = time.monotonic() + 5
        while view.n_clients > 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert view.n_clients == 2
    assert view.n_clients == 0 and _refused(view.url)  # its connections were shut down and their threads ended
    stalled.settimeout(5)
    try:  # its connection was shut down: the rest of the stream ends (or is reset) instead of hanging
        while stalled.recv(1 << 20):
            pass
    except ConnectionResetError:
        pass
    stalled.close()
    silent.close()


def test_publish_refuses_a_camera_the_view_does_not_serve():
    with LiveView(["wrist", "front"], port=0) as view:
        with pytest.raises(KeyError, match="'side' is not one of wrist, front"):
            view.publish("side", Frame(np.zeros((4, 4, 3), np.uint8), 0.0, 0))
        assert _get(view.url + "frame/front.png")[0] == 503  # no frame yet: not an error page of the server


def test_a_port_in_use_is_one_line_naming_the_flag():
    with socket.socket() as other:
        other.bind((HOST, 0))
        other.listen()
        port = other.getsockname()[1]
        with pytest.raises(LiveViewError) as err:
            LiveView(["wrist"], port=port)
    msg = str(err.value)
    assert msg.startswith(f"--view-port: cannot listen on {HOST}:{port}: in use") and "\n" not in msg, msg


def test_the_view_listens_on_the_loopback_interface_only():
    with LiveView(["wrist"], port=0) as view:
        assert view._server.server_address[0] == "127.0.0.1" and view.url.startswith("http://127.0.0.1:")
    assert "host" not in inspect.signature(LiveView).parameters  # no way to ask for another interface


# ---------------------------------------------------------------------- the overlay's geometry
@pytest.fixture(scope="module")
def clean_plan(tmp_path_factory):
    d = tmp_path_factory.mktemp("view_plan")
    return load_plan(small_plan(d / "plan.yaml", d, n_tcp=1, conditions=("clean",))), load_spec(None)


def _down_camera(W=64, H=48, f=40.0) -> CameraIntrinsics:
    # principal point (31.75, 23.75): pixel (32, 24) here, (64, 48) at twice the size, never half-way
    return CameraIntrinsics(np.array([[f, 0, W / 2 - 0.25], [0, f, H / 2 - 0.25], [0, 0, 1.0]]), np.zeros(5), W, H)


def test_the_wrist_cameras_overlay_puts_each_object_where_the_tcp_pose_and_mount_say(clean_plan):
    plan, spec = clean_plan
    trial = plan.trials[0]
    goal = plan.object_layout(trial.object_layout).objects["goal"]
    intr = _down_camera()
    T_tcp_cam = make_T(so3_exp([0.0, 0.0, 0.3]), [0.01, -0.02, 0.03])
    # the camera 0.4 m straight above the goal's base centre: the centre is the principal point
    T_table_cam = look_at([goal.xy_m[0], goal.xy_m[1], 0.4], [goal.xy_m[0], goal.xy_m[1], 0.0], up=(1.0, 0.0, 0.0))
    T_table_tcp = T_table_cam @ invert_T(T_tcp_cam)
    overlay = PlacementOverlay(plan, spec, {"wrist": ViewCamera(intr, T_tcp_cam=T_tcp_cam)})
    rgb = np.zeros((48, 64, 3), np.uint8)
    out = overlay.draw(rgb, "wrist", T_table_tcp, trial)
    u, v = _pixel(T_table_cam, intr.K, goal.xy_m)
    assert (u, v) == (32, 24)
    assert tuple(out[v, u]) == ROLE_COLORS["goal"] and not rgb.any()  # the input is never written
    (px,) = [p for role, p in overlay.project("wrist", (48, 64), T_table_tcp, trial) if role == "goal"]
    assert tuple(px[-2]) == (u, v)
    # a frame of twice the size: the intrinsics scale with it, the centre stays in the middle
    big = overlay.draw(np.zeros((96, 128, 3), np.uint8), "wrist", T_table_tcp, trial)
    assert tuple(big[48, 64]) == ROLE_COLORS["goal"]


def test_no_overlay_without_intrinsics_pose_or_trial_and_the_page_says_so(clean_plan):
    plan, spec = clean_plan
    trial = plan.trials[0]
    cams = {
        "wrist": ViewCamera(None, T_tcp_cam=np.eye(4)),
        "front": ViewCamera(_down_camera()),  # neither mount nor pose
    }
    overlay = PlacementOverlay(plan, spec, cams)
    rgb = np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    for camera in ("wrist", "front", "side"):
        assert np.array_equal(overlay.draw(rgb, camera, np.eye(4), trial), rgb)
    assert np.array_equal(overlay.draw(rgb, "wrist", np.eye(4), None), rgb)
    # a frame of another aspect ratio than calibrated: no K describes it, so nothing is drawn
    cams["front"] = ViewCamera(_down_camera(), T_table_cam=np.eye(4))
    assert np.array_equal(PlacementOverlay(plan, spec, cams).draw(rgb[:, :48], "front", None, trial), rgb[:, :48])
    with LiveView(["wrist", "front"], port=0, title="day1", overlay=overlay) as view:
        page = _get(view.url)[2].decode()
    assert (
        "no overlay: the camera has no intrinsics" in page and "no overlay: the camera&#x27;s pose is unknown" in page
    )


finite = st.floats(-1e6, 1e6, allow_nan=False)
extreme = st.one_of(finite, st.sampled_from([0.0, 1e-12, -1e-12, 1e12, -1e12, np.nan, np.inf]))


@settings(max_examples=60, deadline=None)
@given(
    t=st.tuples(extreme, extreme, extreme),
    r=st.tuples(st.floats(-10, 10), st.floats(-10, 10), st.floats(-10, 10)),
    dist=st.sampled_from([np.zeros(5), np.array([-0.4, 0.2, 0.001, -0.001, 0.05])]),
)
def test_any_tcp_pose_draws_without_error_and_only_into_a_copy(clean_plan, t, r, dist):
    plan, spec = clean_plan
    intr = CameraIntrinsics(_down_camera().K, dist, 64, 48)
    overlay = PlacementOverlay(plan, spec, {"wrist": ViewCamera(intr, T_tcp_cam=np.eye(4))})
    T = make_T(so3_exp(np.asarray(r, dtype=np.float64)), np.asarray(t, dtype=np.float64))
    rgb = np.full((48, 64, 3), 90, np.uint8)
    out = overlay.draw(rgb, "wrist", T, plan.trials[0])
    assert out.shape == rgb.shape and out.dtype == np.uint8 and (rgb == 90).all()
    for _, px in overlay.project("wrist", (48, 64), T, plan.trials[0]):
        assert px.dtype == np.int32 and np.all(np.abs(px) <= 1 << 15)


# ---------------------------------------------------------------------- options and the command line
@pytest.mark.parametrize("port", [-1, 65536])
def test_a_bad_view_port_is_one_line_naming_its_flag(port):
    with pytest.raises(SessionSetupError, match=r"^--view-port: ") as err:
        SessionOptions(hardware="hw.yaml", policy="p.onnx", plan="plan.yaml", session="s", view=True, view_port=port)
    assert "\n" not in str(err.value)


def test_view_port_without_view_is_refused_and_the_default_port_is_the_one_the_help_and_docs_give():
    import typer

    from trials.cli.trial import app

    with pytest.raises(SessionSetupError, match=r"^--view-port: only with --view"):
        SessionOptions(hardware="hw.yaml", policy="p.onnx", plan="plan.yaml", session="s", view_port=0)
    (param,) = [p for p in typer.main.get_command(app).commands["run"].params if p.name == "view_port"]
    assert f"default {DEFAULT_VIEW_PORT}" in param.help
    assert f"default {DEFAULT_VIEW_PORT}" in SessionOptions.model_fields["view_port"].description
    docs = (REPO / "docs" / "real-trials.md").read_text()
    section = docs[docs.index("## Live view") :]
    assert f"(default {DEFAULT_VIEW_PORT};" in section and f"http://127.0.0.1:{DEFAULT_VIEW_PORT}/" in section


def _trial_run(monkeypatch, cell, db: Path, *extra) -> list[str]:
    argv = ["trial", "run", "--hardware", cell["hw"], "--policy", cell["policy"], "--plan", cell["plan"]]
    argv += ["--session", "s", "--db", db, "--auto-confirm", "--no-rate-limit", *extra]
    monkeypatch.setattr(sys, "argv", ["advobj", *map(str, argv)])
    return argv


def test_trial_run_view_prints_the_url_and_the_server_is_gone_after_the_run(wrist_cell, tmp_path, monkeypatch, capsys):
    from trials.cli.main import main

    _trial_run(monkeypatch, wrist_cell, tmp_path / "t.sqlite", "--view", "--view-port", "0")
    with pytest.raises(SystemExit) as ex:
        main()
    out = capsys.readouterr().out
    assert ex.value.code == 0, out
    (url,) = [m.group(1) for m in map(URL.search, out.splitlines()) if m]
    assert _refused(url)


def test_trial_run_on_a_port_in_use_exits_2_in_one_line_before_writing_anything(
    wrist_cell, tmp_path, monkeypatch, capsys
):
    from trials.cli.main import main

    db = tmp_path / "db" / "t.sqlite"
    with socket.socket() as other:
        other.bind((HOST, 0))
        other.listen()
        port = other.getsockname()[1]
        _trial_run(monkeypatch, wrist_cell, db, "--view", "--view-port", str(port))
        with pytest.raises(SystemExit) as ex:
            main()
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert ex.value.code == 2 and len(lines) == 1 and lines[0].startswith("error: --view-port: "), lines
    assert not db.parent.exists()  # no database, no frames folder


def test_a_port_in_use_is_told_apart_from_other_bind_errors(monkeypatch):
    def refuse(self, *_a, **_k):
        raise OSError(errno.EACCES, "Permission denied")

    monkeypatch.setattr("trials.real.view._Server.server_bind", refuse)
    with pytest.raises(LiveViewError, match=r"cannot listen on 127\.0\.0\.1:80: Permission denied; choose another"):
        LiveView(["wrist"], port=80)


def test_pages_are_served_while_a_publisher_hammers_the_slot():
    """Readers and the publisher race on the slot: every frame served is one that was published whole."""
    frames = [np.full((16, 16, 3), k, np.uint8) for k in range(50)]
    with LiveView(["wrist"], port=0) as view:
        stop = threading.Event()

        def publish():
            k = 0
            while not stop.is_set():
                view.publish("wrist", Frame(frames[k % 50], 0.0, k))
                k += 1

        t = threading.Thread(target=publish)
        t.start()
        try:
            got = [_get(view.url + "frame/wrist.png") for _ in range(20)]
        finally:
            stop.set()
            t.join()
    for status, headers, body in got:
        rgb = _png_rgb(body)
        assert status == 200 and np.array_equal(rgb, frames[int(headers["X-Frame-Seq"]) % 50])
