"""The browser viewer (view/web.py) in a real browser: headless Chromium through Playwright.

Skipped with a message where viser, Playwright or a Chromium binary is missing
(``pip install 'whitecap[web]'`` and Debian's ``chromium``; ``make`` installs both).
Waits on the viewer's events (a frame drawn, a page connecting, a page answering
for a server picture: WebViewer.wait_until) and on the page's own (an image decoded,
an animation frame), so how long anything takes under load does not decide a result.
The few polls left (page text) have a generous limit; nothing here measures time.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
VIEWPORT = {"width": 1280, "height": 720}
WAIT_S = 120.0  # upper limit of every poll: a loaded 2-core machine can be slow to start a browser
HANG_GUARD_S = 1800.0  # event waits: only a guard against a hung viewer; each ends on its event first
STEADY_SHOTS_AT_MOST = 50  # screenshots taken for two in a row to agree (a count of page frames, not a clock)
BROWSERS = ("chromium", "chromium-browser", "google-chrome")

viser = pytest.importorskip("viser", reason="the browser viewer needs viser: pip install 'whitecap[web]'")


def _chromium() -> str | None:
    return next((p for p in map(shutil.which, BROWSERS) if p), None)


def _poll(cond, what: str, timeout: float = WAIT_S, period: float = 0.05):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = cond()
        if v:
            return v
        time.sleep(period)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip("playwright.sync_api",
                                   reason="browser tests need playwright: pip install 'whitecap[web]'")
    exe = _chromium()
    if exe is None:
        pytest.skip("no Chromium found (Debian: apt-get install chromium); browser tests skipped")
    with sync_api.sync_playwright() as p:
        from whitecap.view.web import HEADLESS_CHROMIUM_ARGS

        b = p.chromium.launch(executable_path=exe, args=list(HEADLESS_CHROMIUM_ARGS))
        yield b
        b.close()


@pytest.fixture
def page(browser):
    """A page that may load only from this machine: any other request is refused and recorded."""
    pg = browser.new_page(viewport=VIEWPORT)
    pg.foreign = []

    def route(r):
        host = r.request.url.split("/")[2].split(":")[0] if "://" in r.request.url else ""
        if r.request.url.startswith(("data:", "blob:")) or host in ("localhost", "127.0.0.1", "[::1]"):
            r.continue_()
        else:
            pg.foreign.append(r.request.url)
            r.abort()

    pg.route("**/*", route)
    yield pg
    pg.close()


def _until(viewer, predicate, what: str):
    """Wait on the viewer's events until ``predicate()`` holds; returns its value."""
    got = viewer.wait_until(predicate, HANG_GUARD_S)
    assert got, f"the viewer hung waiting for {what}"
    return got


# Counts the server pictures (viser sends them as image/jpeg blobs, the depth too) whose image
# the page is still decoding: the page revokes a blob's URL once its texture is installed.
PENDING_IMAGES_SCRIPT = """
(() => {
  const pending = new Set();
  const create = URL.createObjectURL.bind(URL), revoke = URL.revokeObjectURL.bind(URL);
  URL.createObjectURL = (o) => {
    const u = create(o);
    if (o instanceof Blob && o.type === "image/jpeg") pending.add(u);
    return u;
  };
  URL.revokeObjectURL = (u) => { pending.delete(u); return revoke(u); };
  window.__whitecapPendingImages = () => pending.size;
})();
"""


# The page has decoded every picture it was sent and runs no CSS animation (the page fades in
# when it starts: a screenshot taken meanwhile shows the picture dimmed).
PAGE_AT_REST = """() => window.__whitecapPendingImages() === 0
    && document.getAnimations().every(a => a.playState !== "running")"""


def _open(viewer, page) -> None:
    """Load the viewer's page and wait until the browser has connected and the first frame is sent."""
    page.add_init_script(PENDING_IMAGES_SCRIPT)
    page.goto(viewer.url)
    _until(viewer, lambda: viewer.pages(), "the page to connect")
    _until(viewer, lambda: viewer.drawn_frame is not None, "the first frame")


def _shot(page) -> np.ndarray:
    import io

    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB")).astype(float)


def _camera(viewer):
    """The camera the browser reports: pixel coordinates of world points, and the image size."""
    cam = next(iter(viewer.server.get_clients().values())).camera
    R = viser.transforms.SO3(np.asarray(cam.wxyz)).as_matrix()  # columns: right, down, forward (OpenCV)
    eye, W, H = np.asarray(cam.position), cam.image_width, cam.image_height
    focal = 0.5 * H / math.tan(0.5 * cam.fov)  # fov is vertical [rad]

    def project(points):
        p = (np.asarray(points, float) - eye) @ R
        return np.c_[W / 2 + focal * p[:, 0] / p[:, 2], H / 2 + focal * p[:, 1] / p[:, 2]], p[:, 2]

    return project, focal, (W, H)


FLUID_TOL = 30.0  # RGB distance within which a pixel counts as fluid-coloured
# max - min channel below which a pixel is grey (background, panel, box); the map's colours are all above
GREY_CHROMA = 25.0


def _fluid_coloured(img: np.ndarray) -> np.ndarray:
    """Pixels within FLUID_TOL of a colour of the fluid colour map."""
    from whitecap.view.colors import colormap

    ramp = colormap(np.linspace(0.0, 1.0, 64), 0.0, 1.0) * 255.0
    out = np.zeros(img.shape[:2], bool)
    cand = np.ptp(img, axis=-1) > GREY_CHROMA
    px = img[cand].astype(np.float32)
    out[cand] = np.min(((px[:, None, :] - ramp[None]) ** 2).sum(-1), axis=1) < FLUID_TOL ** 2
    return out


def _camera_key(viewer) -> tuple:
    """The camera the page last reported, with the time it did (0 before it has)."""
    cam = next(iter(viewer.server.get_clients().values())).camera
    return (cam.update_timestamp, tuple(cam.position), tuple(cam.wxyz), float(cam.fov), cam.image_width,
            cam.image_height)


def _steady_shot(page) -> np.ndarray:
    """A screenshot that the next one, an animation frame later, equals (the first screenshot after a change can
    catch the page's canvas part-way)."""
    img = None
    for _ in range(STEADY_SHOTS_AT_MOST):
        page.evaluate("() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
        prev, img = img, _shot(page)
        if prev is not None and np.array_equal(img, prev):
            return img
    raise AssertionError(f"the page never showed a steady image in {STEADY_SHOTS_AT_MOST} screenshots")


def _fluid_mask_checks(viewer, page, positions):
    """Fluid-coloured pixels left of the control panel, and where the particles project; None when the page had
    not reported its camera yet or reported a new one while the screenshot was taken (the projection would be
    through another camera than the picture's)."""
    key = _camera_key(viewer)
    img = _steady_shot(page)
    if key[0] == 0.0 or _camera_key(viewer) != key:
        return None
    project, focal, (W, H) = _camera(viewer)
    assert img.shape[:2] == (H, W)
    # the control panel (its colour bar is fluid-coloured) sits at the right: judge the canvas left of it
    panel_x = int(page.get_by_text("colour by").bounding_box()["x"]) - 40
    xy, depth = project(positions)
    assert (xy[:, 0] < panel_x).all() and (xy[:, 0] > 0).all() and (xy[:, 1] > 0).all() and (xy[:, 1] < H).all()
    fluid = _fluid_coloured(img[:, :panel_x])
    return fluid, _where_projected(viewer, xy, depth, focal, (H, panel_x)), xy


def _where_projected(viewer, xy, depth, focal, shape):
    """Pixels where the fluid projects: a disc of the particle radius (plus a pixel) around each particle."""
    rad = float(viewer.source.radius) * viewer.point_scale * focal / depth + 1.5
    where = np.zeros(shape, bool)
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    for (x, y), r in zip(xy, rad):
        r0, r1, c0, c1 = int(y - r), int(y + r) + 1, int(x - r), int(x + r) + 1
        where[r0:r1, c0:c1] |= (rows[r0:r1, c0:c1] - y) ** 2 + (cols[r0:r1, c0:c1] - x) ** 2 <= r * r
    return where


def test_page_draws_the_fluid_where_it_projects(tiny_run, page):
    """Frame 0 of the tiny dam break, loaded in headless Chromium: the fluid-coloured pixels
    fall where the particles project through the browser's own camera, and cover most of that
    region; the page loads nothing from outside this machine."""
    from whitecap.view.web import WebViewer

    with WebViewer(tiny_run, port=0) as v:
        _open(v, page)
        pos = v.source.frame(0).positions

        def drawn():
            if (got := _fluid_mask_checks(v, page, pos)) is None:
                return None
            fluid, where, _ = got
            return (fluid, where) if fluid.sum() > 0.5 * where.sum() else None

        fluid, where = _poll(drawn, "the fluid to appear in the page")
        assert fluid.sum() > 2000
        assert (fluid & where).sum() / fluid.sum() > 0.97  # fluid colour only where fluid projects
        assert (fluid & where).sum() / where.sum() > 0.6  # and most of the projected region is fluid
        # the colour range is shown
        assert page.get_by_text("speed [m/s]: 0 ..").count() == 1
    assert page.foreign == []


def _drawn(handle) -> np.ndarray:
    """World positions of the points a point cloud handle last sent."""
    return np.asarray(handle.points, float) + np.asarray(handle.position, float)


def _move_slider_to_end(page) -> None:
    thumb = page.get_by_role("slider").first
    thumb.focus()
    thumb.press("End")


def test_timeline_moves_the_drawn_particles(tiny_run, page):
    """Moving the page's timeline slider to the last frame makes the viewer send that frame's
    positions (the dam has started to break: they differ from frame 0's), and the page then
    shows the fluid where frame 3's particles project."""
    from whitecap.view.web import WebViewer

    with WebViewer(tiny_run, port=0) as v:
        _open(v, page)
        first = _drawn(v.h_fluid)
        last_k = len(v.source) - 1
        _move_slider_to_end(page)
        _until(v, lambda: v.state.frame == last_k and v.drawn_frame == v.source.indices[last_k],
               "the last frame to be drawn")
        p3 = v.source.frame(last_k).positions
        drawn = _drawn(v.h_fluid)
        assert np.abs(drawn - p3).max() < 1e-6
        assert np.abs(drawn - first).max() > 0.01  # the column moved by more than a centimetre
        _poll(lambda: page.get_by_text(f"frame {v.source.indices[last_k]} ({last_k + 1} of").count(),
              "the page to show the frame")

        def shows_frame3():
            if (got := _fluid_mask_checks(v, page, p3)) is None:
                return False
            fluid, where, _ = got
            return fluid.sum() > 1000 and (fluid & where).sum() / fluid.sum() > 0.97

        _poll(shows_frame3, "the page to draw frame 3")


def test_moving_body_and_subsample_and_notebook(tiny_run, tmp_path):
    """Without a browser: a moving obstacle is placed at each frame's pose from run.json
    (geometry.obstacle_matrix); a run over the point limit draws a stable subsample and says so;
    the notebook view is an iframe of the viewer's page."""
    import trimesh

    from whitecap.geometry import pose_matrix
    from whitecap.io.record import Pose
    from whitecap.view.web import WebViewer

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    trimesh.creation.box(extents=(0.08, 0.08, 0.08)).export(run / "block.obj")
    meta = json.loads((run / "run.json").read_text())
    meta["obstacles"] = [{"mesh": "block.obj", "translate": [0.45, 0.1, 0.06]}]
    s = math.sin(math.radians(22.5))
    for f in meta["frames"]:
        f["bodies"] = [{"position": [0.0, 0.0, 0.1 * f["index"]], "quaternion": [math.sqrt(1 - s * s), 0.0, 0.0, s]}]
    (run / "run.json").write_text(json.dumps(meta))
    with WebViewer(run, port=0, max_points=500) as v:
        for k in (0, 2):
            v.seek(k)
            assert v.wait_drawn(k, HANG_GUARD_S)
            (_, h), = v.h_obstacles
            M = viser.transforms.SE3.from_rotation_and_translation(viser.transforms.SO3(np.asarray(h.wxyz)),
                                                                   np.asarray(h.position)).as_matrix()
            want = pose_matrix(Pose.model_validate(meta["frames"][k]["bodies"][0]))
            assert np.allclose(M, want, atol=1e-6)
            assert len(v.h_fluid.points) == 500
            assert "drawing 500 of 1,500 particles (subsample)" in v.g_info.content
        idx = v._sub(1500)
        assert np.abs(_drawn(v.h_fluid) - v.source.frame(2).positions[idx]).max() < 1e-6
        html = v._repr_html_()
        assert f'<iframe src="{v.url}"' in html


def test_live_scene_simulates_and_takes_solver_sliders(tmp_path):
    """A scene TOML is simulated while shown: the drawn frame advances, and the panel's
    iterations slider reaches the solver's settings."""
    import tomli_w

    from whitecap.view.web import WebViewer

    from .conftest import tiny_scene_dict

    scene = tmp_path / "tiny.toml"
    scene.write_text(tomli_w.dumps(tiny_scene_dict(foam={"enabled": False}, view={"steps_per_draw": 2})))
    with WebViewer(scene, port=0) as v:
        v.play()  # no page opens here: start the simulation from Python
        _until(v, lambda: v.source.steps >= 4 and v.frames_sent >= 2, "the live simulation to advance")
        v.g_solver["iterations"].value = 7
        _until(v, lambda: v.scene.solver.iterations == 7, "the iterations slider to reach the solver")
        steps = v.source.steps
        _until(v, lambda: v.source.steps > steps, "more steps")
    # drawn on the server, a live frame hands the solver's particles to the pages' pictures
    with WebViewer(scene, port=0, points="server") as v:
        v.play()
        _until(v, lambda: v.frames_sent >= 2 and v.spheres is not None,
               "the live simulation to reach the server's drawing")
        assert v.drawn_on_server and not v.h_fluid.visible
        P = v.spheres[2]
        assert len(P) == v.source.solver.n and np.isfinite(P).all()
        lo, hi = v.source.bounds.lower, v.source.bounds.upper
        assert (P >= lo - 1e-6).all() and (P <= hi + 1e-6).all()


def _cli(*args, **kw):
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src") + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, "-m", "whitecap.cli", "view", *map(str, args)], capture_output=True,
                          text=True, env=env, timeout=WAIT_S, **kw)


def test_missing_run_is_a_one_line_error(tmp_path):
    r = _cli(tmp_path / "nothing", "--web", "--port", "0")
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "nothing" in lines[0], r.stderr


def test_port_in_use_is_a_one_line_error_naming_the_port(tiny_run):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = _cli(tiny_run, "--web", "--port", port)
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and f"port {port}" in lines[0], r.stderr


def test_cli_prints_the_url_and_serves_the_page(tiny_run):
    """`whitecap view RUN --web` prints the URL; the URL serves viser's page from this machine."""
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src") + os.pathsep + os.environ.get("PYTHONPATH", "")}
    p = subprocess.Popen([sys.executable, "-m", "whitecap.cli", "view", str(tiny_run), "--web", "--port", "0"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = p.stdout.readline()
        assert "http://localhost:" in line, line + p.stderr.read() if p.poll() is not None else line
        url = line.split("open ")[1].split()[0]
        html = urllib.request.urlopen(url, timeout=WAIT_S).read().decode()
        assert "<title>Viser</title>" in html and "<div id=\"root\">" in html
    finally:
        p.terminate()
        p.wait(timeout=WAIT_S)


def test_a_bad_frame_is_reported_in_the_panel_and_the_viewer_goes_on(tiny_run, tmp_path):
    """A frame with NaN positions is not drawn: the panel names the file, playback pauses,
    and the other frames still show."""
    from whitecap.io import ParticleFrame, read, write
    from whitecap.view.web import WebViewer

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    bad = run / "fluid" / "fluid_00002.ply"
    pf = read(bad)
    pf.positions[5] = np.nan
    write(bad, ParticleFrame(pf.positions, pf.velocities, pf.ids, pf.density, time=pf.time))
    with WebViewer(run, port=0) as v:
        assert v.wait_drawn(0, HANG_GUARD_S)
        v.seek(2)
        _until(v, lambda: v.error and "fluid_00002.ply" in v.error, "the error to be reported")
        assert "fluid_00002.ply" in v.g_info.content and v.state.paused
        v.seek(1)
        assert v.wait_drawn(1, HANG_GUARD_S)


def test_a_frame_with_an_empty_surface_hides_the_previous_surface(tiny_run, tmp_path):
    """Without a browser: with the surface shown, a frame whose surface mesh is empty (all
    fluid left the domain, or splashsurf found no surface) shows no surface, not the previous
    frame's; a later frame with a surface shows that frame's mesh."""
    import trimesh

    from whitecap.io import write_mesh
    from whitecap.io.mesh import SurfaceMesh
    from whitecap.view.web import WebViewer

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    (run / "mesh").mkdir()
    meta = json.loads((run / "run.json").read_text())
    boxes = {}
    for f in meta["frames"]:
        k = f["index"]
        if k == 1:
            mesh = SurfaceMesh.empty()
        else:
            b = trimesh.creation.box(extents=(0.1, 0.1, 0.1 + 0.05 * k))
            mesh = SurfaceMesh(b.vertices, b.faces)
        boxes[k] = mesh
        write_mesh(run / "mesh" / f"surface_{k:05d}.ply", mesh)
        f["files"]["mesh"] = f"mesh/surface_{k:05d}.ply"
        f["made_from"]["mesh"] = f["made_from"]["fluid"]  # made from these fluid frames: not stale
    (run / "run.json").write_text(json.dumps(meta))
    with WebViewer(run, port=0) as v:
        v._toggle("surface", True)
        shown = lambda: v.h_surface is not None and v.h_surface.visible  # noqa: E731
        for k in (0, 1, 2):
            v.seek(k)
            assert v.wait_drawn(k, HANG_GUARD_S)
            idx = v.source.indices[k]
            if len(boxes[idx].faces):  # (frame 0 may have been drawn before the surface was switched on)
                _until(v, lambda: shown() and np.allclose(np.asarray(v.h_surface.vertices), boxes[idx].vertices,
                                                          atol=1e-6),
                      f"frame {idx}'s surface to be shown")
            else:
                assert not shown()


def test_stepping_through_frames_does_not_recompile_the_point_shader(tiny_run, page):
    """Each frame's new colours make viser's client build a new point material; the page must
    reuse the compiled shader program (view/web.py's program keeper) rather than link it again
    for every frame, which in software WebGL costs a large part of a frame."""
    from whitecap.view.web import WebViewer

    page.add_init_script("""
        window.__links = 0;
        for (const C of [WebGLRenderingContext, WebGL2RenderingContext]) {
          const link = C.prototype.linkProgram;
          C.prototype.linkProgram = function (...a) { window.__links++; return link.apply(this, a); };
        }""")

    def show(v, k):
        v.seek(k)
        assert v.wait_drawn(k, HANG_GUARD_S)
        _poll(lambda: page.get_by_text(f"frame {v.source.indices[k]} ({k + 1} of").count(),
              f"the page to show frame {k}")
        page.evaluate("() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")  # drawn

    with WebViewer(tiny_run, port=0) as v:
        _open(v, page)
        n = len(v.source)
        for k in range(n):  # first pass: every kind of object has been drawn once
            show(v, k)
        links = page.evaluate("() => window.__links")
        assert links > 0  # the counter sees the page's programs
        for k in (*range(n - 2, -1, -1), *range(1, n)):  # new colours every frame
            show(v, k)
        assert page.evaluate("() => window.__links") == links


# ---------------------------------------------------------------------- pictures drawn on the server


def _look_at_wxyz(eye, target):
    """viser's camera quaternion for an eye looking at target, z up: the camera's axes are
    right, down, forward (OpenCV), built here from viser's own SO3, not from view/splat.py."""
    fwd = np.asarray(target, float) - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return viser.transforms.SO3.from_matrix(np.c_[right, np.cross(fwd, right), fwd]).wxyz


def test_splat_puts_a_particle_on_the_pixel_the_camera_projects_it_to_at_its_depth():
    """A sphere at a known world point, drawn by view/splat.py for a camera given as viser
    gives it (wxyz, position, vertical fov): its disc is centred on the pixel that viser's
    convention projects the centre to (u = W/2 + f x/z, v = H/2 + f y/z in camera axes right,
    down, forward), its radius is f r / z, and the depth at the centre is the distance along
    the view axis to the sphere's front (z - r) [m]; elsewhere the depth is far and the
    colour the background. Of two overlapping spheres the nearer one wins, whichever is
    listed first."""
    from whitecap.view.splat import FAR_DEPTH, Splatter

    W, H, fov = 320, 240, math.radians(50.0)
    eye, target = np.array([0.3, -1.0, 0.6]), np.array([0.1, 0.2, 0.1])
    wxyz = _look_at_wxyz(eye, target)
    R = viser.transforms.SO3(np.asarray(wxyz)).as_matrix()
    f = 0.5 * H / math.tan(0.5 * fov)
    x = np.array([0.18, 0.25, 0.05])  # off the image centre on both axes
    p = (x - eye) @ R
    u, v = W / 2 + f * p[0] / p[2], H / 2 + f * p[1] / p[2]
    r = 0.02
    rgb, depth = Splatter().render(x[None], [r], [[1.0, 0.0, 0.0]], wxyz, eye, fov, (W, H), background=(0.0, 0.0, 0.0))
    covered = depth < FAR_DEPTH
    rows, cols = np.nonzero(covered)
    assert abs(cols.mean() + 0.5 - u) < 0.3 and abs(rows.mean() + 0.5 - v) < 0.3  # pixel centres at +0.5
    rho = f * r / p[2]
    assert abs(math.sqrt(covered.sum() / math.pi) - rho) < 0.05 * rho + 0.5
    assert abs(depth[int(v), int(u)] - (p[2] - r)) < 0.02 * r
    assert (rgb[~covered] == 0).all() and (rgb[covered, 0] > 0).all() and (rgb[covered, 1:] == 0).all()
    # two overlapping spheres: the one 5 cm nearer the eye along the line of sight covers the centre
    near = x + 0.05 * (eye - x) / np.linalg.norm(eye - x)
    for order in ((x, near), (near, x)):
        cols_ = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]] if order[0] is x else [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]
        rgb, depth = Splatter().render(np.array(order), [r, r], cols_, wxyz, eye, fov, (W, H))
        c = rgb[int(v), int(u)]
        assert c[1] > 0 and c[0] == 0  # green: the nearer one
        pn = (near - eye) @ R
        assert abs(depth[int(v), int(u)] - (pn[2] - r)) < 0.02 * r


def test_depth_png_reads_back_as_viser_reads_it():
    """The depth PNG sent with a server picture decodes, by the formula of viser's page
    (red·167.1168 + green·0.6528 + blue·0.00255 over channel values in [0, 1], i.e. 24-bit
    fixed point in 1e-5 m with red the high byte), to the depth within half a step."""
    import io

    from PIL import Image

    from whitecap.view.splat import DEPTH_STEP_UNITS, VISER_DEPTH_UNIT_M, encode_depth_png

    depth = np.array([[0.0, 0.0123, 1.5], [2.71828, 40.0, 1.0e4]], np.float32)
    a = np.asarray(Image.open(io.BytesIO(encode_depth_png(depth)))).astype(float) / 255.0
    read = a[..., 2] * 0.00255 + a[..., 1] * 0.6528 + a[..., 0] * 167.1168
    half_step = 0.5 * DEPTH_STEP_UNITS * VISER_DEPTH_UNIT_M
    assert np.all(np.abs(read.ravel()[:-1] - depth.ravel()[:-1]) <= half_step + 1e-6)
    assert read[-1, -1] > 167.0  # beyond viser's range: its largest depth


def _shaded_fluid(img: np.ndarray) -> np.ndarray:
    """Pixels that are a shade s·c of a colour c of the fluid map, s between the server
    picture's ambient and ambient + diffuse light (view/splat.py), within FLUID_TOL."""
    from whitecap.view.colors import colormap
    from whitecap.view.splat import AMBIENT, DIFFUSE

    ramp = colormap(np.linspace(0.0, 1.0, 64), 0.0, 1.0) * 255.0
    out = np.zeros(img.shape[:2], bool)
    cand = np.ptp(img, axis=-1) > GREY_CHROMA
    px = img[cand].astype(np.float32)
    s = np.clip((px @ ramp.T) / (ramp ** 2).sum(-1)[None], AMBIENT - 0.05, AMBIENT + DIFFUSE + 0.05)
    err = ((px[:, None, :] - s[..., None] * ramp[None]) ** 2).sum(-1)
    out[cand] = err.min(axis=1) < FLUID_TOL ** 2
    return out


def _shown_picture(viewer, page, index) -> np.ndarray:
    """A screenshot of the page showing the server picture of source frame ``index`` for the
    page's camera. Every wait is on an event, not a clock: the page has answered for that
    picture (so it has it), has decoded every picture it was sent, and shows the same image
    in two screenshots in a row, an animation frame apart (the first screenshot after a new
    picture can catch the page's canvas part-way). If a newer picture was sent meanwhile
    (the page moved its camera), the wait starts over."""
    while True:
        pp = _until(viewer, lambda: viewer.picture_shown(index), f"the page to receive the picture of frame {index}")
        seq = viewer.spheres[0]
        page.wait_for_function(PAGE_AT_REST, timeout=HANG_GUARD_S * 1000)
        img = _steady_shot(page)
        if viewer.picture_shown(index) is pp and pp.settled(seq):
            return img


def _server_picture_checks(viewer, page, positions, img=None):
    project, focal, (W, H) = _camera(viewer)
    img = _shot(page) if img is None else img
    panel_x = int(page.get_by_text("colour by").bounding_box()["x"]) - 40
    xy, depth = project(positions)
    fluid = _shaded_fluid(img[:, :panel_x])
    return fluid, _where_projected(viewer, xy, depth, focal, fluid.shape), img


def test_server_pictures_show_the_fluid_where_it_projects_and_follow_the_timeline(tiny_run, page):
    """With --points server the page gets pictures, not points: the fluid-coloured (shaded)
    pixels fall where the particles project through the browser's camera and cover most of
    that region; moving the timeline to the last frame makes the page show that frame's
    particles, and the picture changes."""
    from whitecap.view.web import WebViewer

    with WebViewer(tiny_run, port=0, points="server") as v:
        _open(v, page)
        assert not v.h_fluid.visible  # the points themselves are not sent
        p0 = v.source.frame(0).positions

        def shows(pos, index):
            img = _shown_picture(v, page, index)
            fluid, where, _ = _server_picture_checks(v, page, pos, img)
            assert fluid.sum() > 2000
            assert (fluid & where).sum() / fluid.sum() > 0.97  # fluid colour only where the fluid projects
            assert (fluid & where).sum() / where.sum() > 0.6  # and most of the projected region is fluid
            return img

        img0 = shows(p0, v.source.indices[0])
        last_k = len(v.source) - 1
        _move_slider_to_end(page)
        _until(v, lambda: v.drawn_frame == v.source.indices[last_k], "the last frame to be drawn")
        p3 = v.source.frame(last_k).positions
        img3 = shows(p3, v.source.indices[last_k])
        assert (np.abs(img3 - img0).max(axis=-1) > 60).sum() > 500  # a different picture
        assert "particles drawn on the server" in v.g_info.content
        # a camera move redraws the shown frame for the new view
        client = next(iter(v.server.get_clients().values()))
        sent = v.pages()[0].sent
        client.camera.position = np.asarray(client.camera.position) + [0.15, 0.0, 0.1]
        _until(v, lambda: v.pages()[0].sent > sent, "a picture for the moved camera")
        img_moved = shows(p3, v.source.indices[last_k])
        assert (np.abs(img_moved - img3).max(axis=-1) > 60).sum() > 500


def test_auto_draws_on_the_server_above_the_threshold(tiny_run, monkeypatch):
    """Without a browser: --points auto sends the points of a run under SERVER_POINTS_ABOVE
    particles to the page, and draws a run over it on the server (the points are hidden)."""
    import importlib

    web = importlib.import_module("whitecap.view.web")  # the module (the package's `web` is the function)
    with web.WebViewer(tiny_run, port=0) as v:  # 1,500 particles, [view] web_points = auto
        assert v.points == "auto" and v.wait_drawn(0, HANG_GUARD_S)
        assert v.drawn_on_server is False and v.h_fluid.visible and v.spheres is None
    monkeypatch.setattr(web, "SERVER_POINTS_ABOVE", 1000)
    with web.WebViewer(tiny_run, port=0) as v:
        assert v.wait_drawn(0, HANG_GUARD_S)
        assert v.drawn_on_server is True and not v.h_fluid.visible and len(v.spheres[2]) == 1500
        assert "1,500 particles drawn on the server (more than 1,000: --points auto)" in v.g_info.content


def test_server_pictures_are_depth_composited_with_obstacles(tiny_run, tmp_path, page):
    """The server picture carries depth: an obstacle between the camera and the fluid hides
    the fluid behind it, and the fluid hides an obstacle behind it (viser's page composites
    the picture with the meshes it draws itself by that depth)."""
    import trimesh

    from whitecap.config import View
    from whitecap.view.app import initial_camera
    from whitecap.view.web import WebViewer

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    from whitecap.view.app import open_source

    src, _ = open_source(run, "cpu", "z")
    cam = initial_camera(View(), src.bounds)
    eye = np.asarray(cam.eye, float)
    centre = src.frame(0).positions.mean(axis=0)
    low, high = centre - [0.0, 0.0, 0.07], centre + [0.0, 0.0, 0.07]  # two points inside the column
    front = eye + 0.6 * (low - eye)  # well in front of the fluid, on the line of sight to `low`
    behind = high + 0.3 * (high - eye) / np.linalg.norm(high - eye)  # beyond the far side of the 0.2 m column
    trimesh.creation.box(extents=(0.03, 0.03, 0.03)).export(run / "front.obj")
    trimesh.creation.box(extents=(0.05, 0.05, 0.05)).export(run / "behind.obj")
    meta = json.loads((run / "run.json").read_text())
    meta["obstacles"] = [{"mesh": "front.obj", "translate": front.tolist()},
                         {"mesh": "behind.obj", "translate": behind.tolist()}]
    (run / "run.json").write_text(json.dumps(meta))
    with WebViewer(run, port=0, points="server") as v:
        _open(v, page)
        img = _shown_picture(v, page, v.source.indices[0])
        project, focal, _ = _camera(v)

        def square(point, half_m):
            (x, y), z = (a[0] for a in project(np.asarray(point)[None]))
            h = max(int(0.6 * half_m * focal / z), 2)  # inside the cube's projection
            return slice(int(y) - h, int(y) + h), slice(int(x) - h, int(x) + h)

        fs, bs = square(front, 0.015), square(behind, 0.025)
        fluid, where, _ = _server_picture_checks(v, page, v.source.frame(0).positions, img)
        # both cubes lie inside the fluid's projection; in front, no fluid shows; behind, only fluid
        assert where[fs].all() and where[bs].all()
        assert fluid[fs].mean() < 0.05 and fluid[bs].mean() > 0.9


# ---------------------------------------------------------------------- issue 30: the viewer as users meet it


@pytest.mark.parametrize("port", ["70000", "-5", "65536"])
def test_a_port_out_of_range_is_refused_in_one_line(tiny_run, port, capsys):
    """--port 70000 is not "already in use" and --port -5 is not a host that cannot be
    resolved: the line says what a port is."""
    from whitecap.cli import main

    assert main(["view", str(tiny_run), "--web", "--port", port]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--port must be a number from 1 to 65535" in err and port in err, err
    assert "in use" not in err and "resolve" not in err


def test_live_scene_waits_for_the_first_page(tmp_path, page):
    """A live scene does not simulate while nobody looks: the loop runs (it has drawn frame 0
    and gone round many times) but the solver has made no step, and the panel says why; the
    first page to connect starts it."""
    import tomli_w

    from whitecap.view.web import WebViewer

    from .conftest import tiny_scene_dict

    scene = tmp_path / "tiny.toml"
    scene.write_text(tomli_w.dumps(tiny_scene_dict(foam={"enabled": False}, view={"steps_per_draw": 2})))
    with WebViewer(scene, port=0) as v:
        _until(v, lambda: v.passes >= 20 and v.drawn_frame is not None, "the loop to go round")
        assert v.source.steps == 0 and v.state.paused
        assert "waiting for a page to open" in v.g_info.content
        _open(v, page)
        _until(v, lambda: v.source.steps >= 4 and v.frames_sent >= 2, "the simulation to start with the page")
        assert not v.state.paused


def test_auto_keeps_one_place_for_a_run_whose_count_crosses_the_threshold(tiny_run, tmp_path, monkeypatch):
    """Without a browser: a run whose frames hold 1,500, 1,560, 1,570 and 1,580 particles,
    with the threshold at 1,550: --points auto draws every frame in the same place, going back
    and forth over the frames (it used to flip between the page and the server)."""
    import importlib

    from .test_surface_export import synthetic_diffuse

    web = importlib.import_module("whitecap.view.web")
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    synthetic_diffuse(run)  # frame k > 0 gets 50 + 10 k diffuse particles
    monkeypatch.setattr(web, "SERVER_POINTS_ABOVE", 1550)
    with web.WebViewer(run, port=0) as v:
        counts = [sum(v.source.frame(k).counts().values()) for k in range(4)]
        assert counts == [1500, 1560, 1570, 1580]
        places = []
        for k in (0, 1, 2, 3, 2, 0, 3):
            v.seek(k)
            assert v.wait_drawn(k, HANG_GUARD_S)
            places.append(v.drawn_on_server)
        assert places == [False] * len(places)
