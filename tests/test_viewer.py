"""``unibody view`` (issue 39): the viser viewer, its panels, offscreen recording, and a real
headless-Chromium check that the body and a labelled marker are drawn and the frame slider
changes the picture.

The browser test needs Debian's ``chromium`` and ``chromium-driver`` and the ``selenium``
package; it skips with the reason where one is missing.
"""

from __future__ import annotations

import io
import math
import os
import shutil
import socket
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from unibody.cli import main
from unibody.viz.viewer.tracks import (
    GHOST,
    GHOST_COLOR,
    LABELLED,
    UNLABELLED,
    UNLABELLED_COLOR,
    MarkerTrack,
    SceneItem,
    local_frame,
    marker_color,
    marker_colors,
)

needs_viser = pytest.mark.skipif(
    __import__("importlib").util.find_spec("viser") is None, reason="viser not installed (pip install '.[viewer]')"
)


class BoxBody:
    """A BodySource: a 0.4 x 1.6 x 0.3 m box that slides +X by 2 cm a frame, 3 joints."""

    def __init__(self, num_frames: int = 30, fps: float = 30.0) -> None:
        x, y, z = np.meshgrid([-0.2, 0.2], [0.0, 1.6], [-0.15, 0.15], indexing="ij")
        self.rest = np.stack([x.ravel(), y.ravel(), z.ravel()], 1).astype(np.float32)
        q = [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]  # fmt: skip
        self.faces = np.array(q, np.uint32)
        self.name, self.num_frames, self.fps, self.identity = "box", num_frames, fps, None
        self.joint_names, self.parents = ("Root", "Hips", "Head"), (-1, 0, 1)
        self.asked: list[int] = []

    def frames(self, index):
        index = np.asarray(index)
        self.asked += index.tolist()
        shift = np.zeros((len(index), 1, 3), np.float32)
        shift[:, 0, 0] = 0.02 * index
        joints = np.array([[0, 0, 0], [0, 0.9, 0], [0, 1.5, 0]], np.float32)
        return self.rest[None] + shift, joints[None] + shift

    def set_identity(self, values):
        pass

    def set_joint_rotation(self, joint, axis_angle):
        pass


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --------------------------------------------------------------------------- tracks


def test_marker_colours_tell_kinds_apart_and_stay_fixed_per_label():
    labels = ("LFHD", "RFHD", "C7", "*3")
    kinds = np.array([[LABELLED, LABELLED, LABELLED, UNLABELLED], [LABELLED, LABELLED, GHOST, GHOST]])
    c = marker_colors(labels, kinds)
    assert c.shape == (2, 4, 3) and c.dtype == np.uint8
    assert tuple(c[0, 0]) == marker_color("LFHD") == tuple(c[1, 0])
    assert tuple(c[0, 3]) == UNLABELLED_COLOR and tuple(c[1, 2]) == GHOST_COLOR == tuple(c[1, 3])
    many = np.array([marker_color(f"M{i}") for i in range(200)], np.int64)
    # Labelled colours are saturated: never the unlabelled grey, never near the ghosts' magenta.
    assert (many.max(1) - many.min(1) >= 150).all()
    assert np.abs(many - GHOST_COLOR).sum(1).min() > 60


def test_local_frame_follows_time_across_rates():
    assert [local_frame(g, 120.0, 30.0, 100) for g in (0, 3, 4, 8, 10_000)] == [0, 0, 1, 2, 99]
    assert local_frame(7, 30.0, 30.0, 10) == 7


def test_marker_track_checks_its_arrays():
    with pytest.raises(ValueError, match=r"take: kinds: expected \(2, 3\)"):
        MarkerTrack("take", np.zeros((2, 3, 3)), ("a", "b", "c"), np.zeros((2, 2)), 100.0)
    with pytest.raises(ValueError, match="take: labels: expected 3"):
        MarkerTrack("take", np.zeros((2, 3, 3)), ("a",), np.zeros((2, 3)), 100.0)


# --------------------------------------------------------------------------- server


@needs_viser
def test_frames_stream_into_the_same_mesh_node():
    from unibody.viz.viewer.app import Viewer

    body = BoxBody()
    with Viewer([SceneItem("box", bodies=(body,))], port=0) as viewer:
        nodes = set(viewer.server.scene._handle_from_node_name)
        mesh = viewer._bodies[0].mesh
        for g in (5, 17, 29, 3):
            viewer.show(g)
            np.testing.assert_array_equal(mesh.vertices, body.frames([g])[0][0])
        assert set(viewer.server.scene._handle_from_node_name) == nodes  # no node added per frame
        assert viewer._bodies[0].mesh is mesh
        body.asked.clear()
        viewer.show(3)  # already shown: nothing posed or sent
        assert body.asked == []


@needs_viser
def test_taken_port_gives_the_next_free_one_and_says_so():
    from unibody.viz.viewer.app import Viewer

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with Viewer([SceneItem("box", bodies=(BoxBody(),))], port=port) as viewer:
            assert viewer.port != port
            assert viewer.port_note == f"port {port} is in use; serving on port {viewer.port}"


@needs_viser
def test_playback_runs_on_the_clock_and_loops():
    from unibody.viz.viewer.app import Viewer

    with Viewer([SceneItem("box", bodies=(BoxBody(num_frames=10, fps=20.0),))], port=0) as viewer:
        viewer.speed = 2.0
        viewer.play()
        seen = set()
        t = time.perf_counter()
        while time.perf_counter() - t < 1.5 and len(seen) < 10:
            seen.add(viewer.frame)
            time.sleep(0.01)
        viewer.play(False)
        assert len(seen) >= 5  # 10 frames at 40 frames/s in at most 1.5 s, looping
        assert viewer.gui.frame.value == viewer.frame
        frozen = viewer.frame
        time.sleep(0.2)
        assert viewer.frame == frozen


@pytest.fixture(scope="module")
def pca_body():
    from unibody.body import BodyLayer
    from unibody.cli.view_sources import LayerBody, _controls

    layer = BodyLayer.from_pca(num_components=16)
    params = np.zeros(16, np.float32)
    pose = np.zeros((8, 77, 3), np.float32)
    pose[:, 0, 1] = np.linspace(0, 1.5, 8)  # Hips turn about Y
    transl = np.tile(np.array([[0.0, 0.95, 0.0]], np.float32), (8, 1))
    return LayerBody("pca", layer, params, pose, transl, 30.0, _controls(layer, "pca", params))


@needs_viser
def test_identity_and_pose_panels_repose_the_body(pca_body):
    from unibody.rig import joint_index
    from unibody.viz.viewer.app import Viewer

    with Viewer([SceneItem("pca", bodies=(pca_body,))], port=0) as viewer:
        panels, mesh = viewer.gui, viewer._bodies[0].mesh
        before = mesh.vertices.copy()
        height = np.ptp(before[:, 1])
        panels.identity[0].value = 2.5  # pc000 is size
        taller = mesh.vertices.copy()
        assert abs(np.ptp(taller[:, 1]) - height) > 0.02
        panels.joint.value = "LeftForeArm"
        panels.rotation[1].value = 90
        bent = mesh.vertices.copy()
        moved = np.linalg.norm(bent - taller, axis=1)
        # The forearm and hand move; the legs do not.
        feet = taller[:, 1] < 0.3
        assert moved.max() > 0.1 and moved[feet].max() < 1e-5
        _, joints = pca_body.frames([0])
        hand = joints[0, joint_index("LeftHand")]
        assert np.linalg.norm(bent - hand, axis=1).min() < 0.05
        panels.rotation[1].value = 0
        np.testing.assert_allclose(mesh.vertices, taller, atol=1e-5)
        panels.identity[0].value = 0.0
        np.testing.assert_allclose(mesh.vertices, before, atol=1e-5)


# --------------------------------------------------------------------------- command line


def test_view_unreadable_file_is_one_line(tmp_path, capsys):
    bad = tmp_path / "take.c3d"
    bad.write_bytes(b"not a c3d at all" * 4)
    assert main(["view", str(bad), "--record", str(tmp_path / "x.png")]) == 3
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(bad) in err and err.startswith("unibody: error:")
    assert main(["view", str(tmp_path / "missing.npz")]) == 3
    assert "missing.npz: no such file" in capsys.readouterr().err


def test_view_bad_arguments(tmp_path, capsys):
    assert main(["view", "--port", "http"]) == 2
    assert "--port: expected a port number 0..65535, got 'http'" in capsys.readouterr().err
    assert main(["view", "--record", str(tmp_path / "x.gif")]) == 4
    assert "--record: expected a .mp4 or .png file" in capsys.readouterr().err
    assert main(["view", "--record", str(tmp_path / "x.png"), "--size", "big"]) == 2
    assert main(["view", "--turntable", "3"]) == 2
    for spacing in ("0", "-1", "1e20", "nan"):  # 1e20 drew an empty floor, 1e300 overflowed the camera
        assert main(["view", "--spacing", spacing, "--record", str(tmp_path / "x.png")]) == 2
        assert f"--spacing: expected metres in (0, 100], got {spacing!r}" in capsys.readouterr().err
    take = tmp_path / "take.npz"
    from unibody.mocap.c3d import MarkerSequence, write_npz

    write_npz(take, MarkerSequence(np.zeros((2, 1, 3)), ("LFHD",), ("",), 100.0))
    assert main(["view", str(take), "--solve", "pig99", "--record", str(tmp_path / "x.png")]) == 2
    assert "--solve: layout: unknown layout 'pig99'" in capsys.readouterr().err


def test_spacing_is_checked_by_the_recorder_and_the_viewer():
    from unibody.viz.viewer.record import render_frames
    from unibody.viz.viewer.tracks import MAX_SPACING, check_spacing

    assert check_spacing(np.float32(2)) == 2.0 and check_spacing(MAX_SPACING) == MAX_SPACING
    for bad in (0, -1.0, 1e20, math.inf, math.nan, True, "2"):
        with pytest.raises(ValueError, match="spacing: expected metres between items in"):
            check_spacing(bad)
    with pytest.raises(ValueError, match="spacing"):
        next(render_frames([SceneItem("box", bodies=(BoxBody(),))], spacing=1e300))
    if __import__("importlib").util.find_spec("viser") is not None:
        from unibody.viz.viewer.app import Viewer

        with pytest.raises(ValueError, match="spacing"):  # before a server starts
            Viewer([SceneItem("box", bodies=(BoxBody(),))], port=0, spacing=-2.0)


def test_view_refuses_hostile_mesh_files_and_endless_recordings(tmp_path, capsys):
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    verts = np.random.default_rng(0).random((2, 4, 3)).astype(np.float32)
    cases = [  # (fields, exit code, message); each used to be drawn, or hang, or fail unnamed
        ({"faces": faces + 0.5}, 3, "faces: expected (F, 3) integer indices, F >= 1, got (2, 3) float64"),
        ({"faces": np.zeros((0, 3), np.int64)}, 3, "faces: expected (F, 3) integer indices, F >= 1, got (0, 3)"),
        ({"vertices": verts + 1e30}, 3, "vertices: expected positions within 100000 m of the origin"),
        ({"fps": np.asarray(1e-5)}, 2, "--record: m.npz lasts 1e+05 s (1e-05 fps) makes 3000001 images at --fps 30"),
    ]
    for fields, code, message in cases:
        path = tmp_path / "m.npz"
        np.savez(path, **({"vertices": verts, "faces": faces, "topology": np.asarray("custom")} | fields))
        assert main(["view", str(path), "--record", str(tmp_path / "x.png")]) == code, fields
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and message in err, err
        assert not list(tmp_path.glob("x*.png"))


def test_view_draws_a_glb_posed_as_it_stands(tmp_path, capsys):
    from unibody.cli.view_sources import load_item
    from unibody.convert import ConvertOptions
    from unibody.convert._body import body_for
    from unibody.convert.export import write_glb
    from unibody.motion import Motion

    rng = np.random.default_rng(5)
    pose = (rng.normal(size=(2, 77, 3)) * 0.3).astype(np.float32)
    motion = Motion(pose, np.array([[0, 1, 0], [1, 1, 0]], np.float32))
    write_glb(motion, tmp_path / "take.glb", ConvertOptions())
    item = load_item(tmp_path / "take.glb", {})
    ((verts, faces),) = item.still
    layer, prepared = body_for(motion)
    with torch.no_grad():
        posed = layer.pose(prepared, torch.as_tensor(motion.pose), transl=torch.as_tensor(motion.transl)).vertices
    assert np.abs(verts - posed[0].numpy()).max() < 5e-4  # frame 0, as the file's nodes stand (0.5 mm)
    np.testing.assert_array_equal(faces, layer.faces.numpy())
    assert item.glb == (tmp_path / "take.glb").read_bytes()  # the browser gets the file as it is
    # `--record` drew nothing of a GLB and failed: "meshes: expected at least one MeshSpec"
    assert main(["view", str(tmp_path / "take.glb"), "--record", str(tmp_path / "x.png"), "--size", "96x64"]) == 0
    from PIL import Image

    assert _background_share(np.asarray(Image.open(tmp_path / "x.png"))) < 0.97
    broken = tmp_path / "broken.glb"
    broken.write_bytes((tmp_path / "take.glb").read_bytes()[:5000])
    capsys.readouterr()
    assert main(["view", str(broken), "--record", str(tmp_path / "y.png")]) == 3
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "broken.glb: not a glTF file the viewer reads (truncated GLB file" in err


# --------------------------------------------------------------------------- recording


def _background_share(img: np.ndarray) -> float:
    """Share of pixels that are the renderer's grey-blue background or ground (no hue)."""
    spread = img.max(-1).astype(int) - img.min(-1)
    return float((spread < 25).mean())


def test_record_png_frames_of_a_motion(tmp_path):
    from unibody.viz.viewer.record import record, render_frames

    body = BoxBody(num_frames=7, fps=30.0)
    items = [SceneItem("box", bodies=(body,))]
    images = list(render_frames(items, fps=10, width=96, height=64))
    assert len(images) == 3  # 7 frames at 30 fps last 0.2 s: pictures at 0, 0.1 and 0.2 s
    assert sorted(set(body.asked)) == [0, 3, 6]
    written = record(iter(images), tmp_path / "walk.png", fps=10, count=3)
    assert [p.name for p in written] == ["walk_0000.png", "walk_0001.png", "walk_0002.png"]
    from PIL import Image

    a, b = (np.asarray(Image.open(p)) for p in written[:2])
    assert a.shape == (64, 96, 3)
    assert _background_share(a) < 0.97  # the box is drawn
    assert np.abs(a.astype(int) - b).sum() > 0  # and it moves


def test_record_turntable_mp4_from_the_command_line(tmp_path, capsys):
    pytest.importorskip("imageio_ffmpeg")
    from unibody.motion import Motion, save_motion

    pose = np.zeros((4, 77, 3), np.float32)
    motion = tmp_path / "still.npz"
    save_motion(motion, Motion(pose, np.tile([[0.0, 0.95, 0.0]], (4, 1)).astype(np.float32), 30.0,
                               np.zeros(8, np.float32), "pca"))  # fmt: skip
    out = tmp_path / "turn.mp4"
    args = ["view", str(motion), "--record", str(out), "--turntable", "0.3", "--fps", "10", "--size", "64x48"]
    assert main(args) == 0
    assert "wrote" in capsys.readouterr().out
    data = out.read_bytes()
    assert data[4:8] == b"ftyp" and len(data) > 1000
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(out))
    meta = next(reader)
    frames = [np.frombuffer(f, np.uint8).reshape(48, 64, 3) for f in reader]
    assert meta["size"] == (64, 48) and len(frames) == 3
    assert np.abs(frames[0].astype(int) - frames[1]).mean() > 0.5  # the camera turns
    assert main(args) == 4  # exists: refused without --force


# --------------------------------------------------------------------------- browser

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")


def _browser_missing() -> str | None:
    import importlib.util

    if importlib.util.find_spec("viser") is None:
        return "viser not installed (pip install '.[viewer]')"
    if importlib.util.find_spec("selenium") is None:
        return "selenium not installed (pip install '.[test]')"
    if CHROMIUM is None or CHROMEDRIVER is None:
        return "no headless browser: apt-get install chromium chromium-driver"
    return None


def _screenshot(driver) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB")).astype(np.int64)


def _near(img: np.ndarray, rgb, tol: int) -> np.ndarray:
    return np.abs(img - np.asarray(rgb)).max(-1) <= tol


def _skin(img: np.ndarray) -> np.ndarray:
    """Pixels of the first body colour (217, 140, 115) under any lighting: red over green over blue.

    Only in the 3D view: not the axes gizmo (bottom left) nor the GUI panel (right).
    """
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    out = (r - g > 30) & (g - b > 5) & (r > 60) & (r - b < 200)
    h, w = out.shape
    out[h - 90 :, :90] = False
    out[:, w - 360 :] = False
    return out


@pytest.mark.skipif(_browser_missing() is not None, reason=str(_browser_missing()))
def test_headless_chromium_draws_body_and_markers_and_follows_the_slider(pca_body):
    from PIL import Image
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    from unibody.viz.viewer.app import Viewer

    label = "LFHD"
    colour = marker_color(label)
    pts = np.tile(np.array([[[0.45, 1.2, 0.2], [0.0, 2.6, 0.0]]], np.float32), (8, 1, 1))
    pts[:, 0, 1] -= np.linspace(0, 0.6, 8)  # the marker drops 60 cm over the take
    track = MarkerTrack("take", pts, (label, "*1"), np.array([[LABELLED, GHOST]] * 8), 30.0)
    item = SceneItem("pca", bodies=(pca_body,), markers=(track,))
    viewer = Viewer([item], port=0)
    for m in viewer._markers:
        m.cloud.point_size = 0.06  # big enough to count pixels at any window size
    opts = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader", "--window-size=800,520", "--disable-extensions"):  # fmt: skip
        opts.add_argument(arg)
    opts.binary_location = CHROMIUM
    driver = webdriver.Chrome(options=opts, service=Service(CHROMEDRIVER))
    try:
        driver.set_page_load_timeout(30)
        driver.get(viewer.url)
        deadline = time.monotonic() + 40
        while time.monotonic() < deadline and not viewer.server.get_clients():  # cheap: no screenshot
            time.sleep(0.2)
        time.sleep(1.0)  # the scene arrives right after the connection; a screenshot costs seconds
        img = _screenshot(driver)

        def drawn(img: np.ndarray) -> bool:  # the body and both point clouds (they may arrive apart)
            return _skin(img).sum() >= 500 and min(_near(img, c, 12).sum() for c in (colour, GHOST_COLOR)) >= 10

        while time.monotonic() < deadline and not drawn(img):
            time.sleep(0.5)
            img = _screenshot(driver)
        h, w = img.shape[:2]
        if os.environ.get("UNIBODY_VIEWER_SHOTS"):  # a folder to keep the screenshots in, to look at
            Image.fromarray(img.astype(np.uint8)).save(Path(os.environ["UNIBODY_VIEWER_SHOTS"]) / "browser_0.png")
        body = _skin(img)
        assert body.sum() >= 500, "the body was not drawn within 40 s"
        ys, xs = np.nonzero(body)
        # The body sits in the middle of the view (the camera is framed on it).
        assert w * 0.2 < xs.mean() < w * 0.8 and h * 0.15 < ys.mean() < h * 0.85
        marker = _near(img, colour, 12)
        assert marker.sum() >= 10, f"no pixel of {label}'s colour {colour}"
        assert _near(img, GHOST_COLOR, 12).sum() >= 10, "the ghost point is not magenta"
        my_before = np.nonzero(marker)[0].mean()

        thumb = driver.find_element(By.CSS_SELECTOR, "[role='slider']")  # the first slider: Frame
        driver.execute_script("arguments[0].focus();", thumb)  # a click would also drag it
        thumb.send_keys(Keys.END)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and viewer.frame != viewer.num_frames - 1:
            time.sleep(0.2)
        assert viewer.frame == viewer.num_frames - 1, "the browser's slider did not reach the server"
        changed = 0.0
        while time.monotonic() < deadline and changed < 0.002:
            time.sleep(0.5)
            after = _screenshot(driver)
            changed = float((np.abs(after - img)[:, : w - 360].max(-1) > 40).mean())  # the 3D view, not the GUI
        assert changed >= 0.002, "the picture did not change with the frame slider"
        if os.environ.get("UNIBODY_VIEWER_SHOTS"):
            Image.fromarray(after.astype(np.uint8)).save(Path(os.environ["UNIBODY_VIEWER_SHOTS"]) / "browser_1.png")
        moved = _near(after, colour, 12)
        assert moved.sum() >= 10 and np.nonzero(moved)[0].mean() > my_before + 5  # the marker went down
    finally:
        driver.quit()
        viewer.stop()
    assert not viewer._thread.is_alive()
    with pytest.raises(ConnectionRefusedError):  # nothing listens on the port any more
        socket.create_connection(("127.0.0.1", viewer.port), timeout=5).close()


@pytest.fixture(autouse=True)
def _no_grad():
    with torch.no_grad():
        yield


def test_record_reads_a_marker_take(tmp_path):
    from unibody.mocap.c3d import MarkerSequence, write_npz
    from unibody.viz.viewer.record import render_frames

    pts = np.full((2, 3, 3), np.nan)
    pts[:, 0] = [[0.0, 0.0, 1.0]]
    pts[:, 1] = [[0.2, 0.0, 1.2]]
    pts[1, 2] = [2.0, 0.0, 1.0]
    take = tmp_path / "take.npz"
    write_npz(take, MarkerSequence(pts, ("LFHD", "*1", "*2"), ("", "", ""), 100.0))
    from unibody.cli.view_sources import load_item

    item = load_item(Path(take), {}, up="z")
    (track,) = item.markers
    assert track.labels == ("LFHD", "*1", "*2")
    assert track.kinds[0, 0] == LABELLED and track.kinds[0, 1] == UNLABELLED and track.kinds[1, 2] == GHOST
    np.testing.assert_allclose(track.points[0, 0], [0.0, 1.0, 0.0])  # Z-up lab -> Y up
    (img,) = list(render_frames([item], fps=1, width=200, height=160))
    assert _near(img.astype(np.int64), marker_color("LFHD"), 60).sum() >= 2


def test_record_frames_a_take_on_its_subject_through_glitches_and_gaps(tmp_path, capsys):
    from unibody.mocap.c3d import MarkerSequence, write_npz

    rng = np.random.default_rng(2)
    pts = rng.normal(scale=0.2, size=(40, 12, 3)) + [0.0, 0.0, 1.0]  # Z-up lab
    pts[:, 0] = [1e27, 0.0, 0.0]  # a labelled column glitched 1e27 m away: the recorder hung
    pts[:, 11] = [8.0, 0.0, 1.0]  # a reflection 8 m away
    pts[30:] = np.nan  # the subject walked out: a frame with nothing to draw failed the recording
    labels = tuple(f"M{i}" for i in range(11)) + ("*1",)
    take = tmp_path / "take.npz"
    write_npz(take, MarkerSequence(pts, labels, ("",) * 12, 40.0))
    from unibody.cli.view_sources import load_item
    from unibody.viz.viewer.record import render_frames

    (track,) = load_item(take, {}).markers
    assert (track.kinds[:30, 0] == GHOST).all() and (track.kinds[:30, 11] == GHOST).all()
    assert (track.kinds[:30, 1:11] == LABELLED).all()
    images = np.stack(list(render_frames([load_item(take, {})], fps=40, width=160, height=120)))
    assert len(images) == 40
    drawn = (np.abs(images.astype(int) - images[-1]).sum(-1) > 30).any(-1)  # (T, W): columns of markers
    assert drawn[:30].any(1).all() and not drawn[30:].any()  # the subject, then the empty floor
    rows = np.flatnonzero((np.abs(images[0].astype(int) - images[-1]).sum(-1) > 30).any(1))
    assert rows.max() - rows.min() > 40  # framed on the subject (0.2 m spread), not on the glitch
    assert main(["view", str(take), "--record", str(tmp_path / "x.png"), "--fps", "4", "--size", "64x48"]) == 0
    write_npz(take, MarkerSequence(np.full((3, 2, 3), np.nan), ("A", "B"), ("", ""), 40.0))
    capsys.readouterr()
    assert main(["view", str(take), "--record", str(tmp_path / "y.png")]) == 3
    assert "take.npz: no marker is visible within 100000 m of the origin in any of its 3 frames" in (
        capsys.readouterr().err
    )


def test_mesh_sequences_show_their_own_meshes(tmp_path):
    from unibody.cli._common import InputError
    from unibody.cli.view_sources import load_item

    box = BoxBody(num_frames=4)
    verts = box.frames(np.arange(4))[0]
    path = tmp_path / "boxes.npz"
    np.savez(path, vertices=verts, topology=np.array("box"), faces=box.faces.astype(np.int64), fps=np.array(60.0))
    (body,) = load_item(path, {}).bodies
    assert body.num_frames == 4 and body.fps == 60.0
    np.testing.assert_array_equal(body.frames(np.array([2]))[0][0], verts[2])
    bare = tmp_path / "bare.npz"
    np.savez(bare, vertices=verts, topology=np.array("box"))
    with pytest.raises(InputError, match="bare.npz: a 'box' mesh sequence without a faces field"):
        load_item(bare, {})


class TwoBoxes(BoxBody):
    """Two boxes: the second starts inside the first and slides 10 cm a frame out along +X."""

    def frames(self, index):
        one, joints = BoxBody.frames(self, np.zeros(len(np.asarray(index)), np.int64))
        two = one + np.array([0.2, 0.3, 0.0], np.float32)
        two[:, :, 0] += 0.1 * np.asarray(index, np.float32)[:, None]
        return np.concatenate([one, two], 1), joints

    def __init__(self) -> None:
        super().__init__(num_frames=8)
        self.faces = np.concatenate([self.faces, self.faces + 8]).astype(np.uint32)


@needs_viser
def test_self_intersections_are_drawn_in_red_when_paused():
    from unibody.viz.viewer.app import Viewer

    with Viewer([SceneItem("boxes", bodies=(TwoBoxes(),))], port=0) as viewer:
        body = viewer._bodies[0]
        viewer.gui.intersections.value = True
        # Frame 0: the second box cuts the first one's top and side faces (and they cut it).
        assert body.num_hits >= 4 and body.hits.visible
        assert len(body.hits.faces) == body.num_hits
        assert tuple(body.hits.color) == (230, 20, 20)
        np.testing.assert_array_equal(body.hits.vertices, body.mesh.vertices)
        viewer.show(7)  # 0.9 m further: apart
        assert body.num_hits == 0 and not body.hits.visible
        viewer.show(0)
        viewer.play()
        viewer.show(1)  # while playing the exact test is skipped
        assert not body.hits.visible
        viewer.play(False)  # pausing draws them for the frame shown
        assert body.hits.visible == (body.num_hits > 0)
        viewer.gui.intersections.value = False
        assert not body.hits.visible


@pytest.mark.slow
def test_resolve_moves_an_arm_out_of_the_chest(pca_body):
    from unibody.cli.view_sources import LayerBody, resolved_item
    from unibody.geometry.intersect import intersecting_pairs
    from unibody.rig import joint_index

    pose = np.zeros((1, 77, 3), np.float32)
    pose[0, joint_index("LeftArm") - 1] = [0.0, 0.0, -1.75]  # the upper arm into the chest
    pose[0, joint_index("LeftForeArm") - 1] = [0.0, -1.5, 0.0]
    transl = np.array([[0.0, 0.95, 0.0]], np.float32)
    body = LayerBody("arm", pca_body.layer, np.zeros(16, np.float32), pose, transl, 30.0, None)
    (fixed,) = resolved_item(SceneItem("arm", bodies=(body,))).bodies
    faces = torch.from_numpy(body.faces.astype(np.int64))
    count = [len(intersecting_pairs(torch.from_numpy(b.frames([0])[0][0]), faces)) for b in (body, fixed)]
    assert count[1] < 0.85 * count[0]
    assert fixed.name == "arm (resolved)"


@needs_viser
def test_a_click_on_the_body_picks_the_joint_nearest_the_ray(pca_body):
    from types import SimpleNamespace

    from unibody.rig import joint_index
    from unibody.viz.viewer.app import Viewer

    with Viewer([SceneItem("box", bodies=(BoxBody(),)), SceneItem("pca", bodies=(pca_body,))], port=0) as viewer:
        body = viewer._bodies[1]
        for name in ("Head", "LeftForeArm", "RightFoot"):
            target = body.joints[joint_index(name)] + body.offset  # world: the item sits 1.5 m along +X
            click = SimpleNamespace(ray_origin=tuple(target + [0.3, 0.2, 3.0]), ray_direction=(-0.3, -0.2, -3.0))
            body.mesh._impl.click_cb[0].callback(click)
            assert viewer.gui.joint.value == name
            assert viewer.gui.body.value == "1: pca"


@pytest.mark.slow
def test_panoman_fit_is_shown_with_its_handles(pca_body):
    from unibody.cli.view_sources import panoman_item

    item = panoman_item(SceneItem("pca", bodies=(pca_body,)), 3)
    (fit,), (handles,) = item.bodies, item.markers
    target = pca_body.frames(np.array([3]))[0][0]
    assert fit.num_frames == 1 and handles.points.shape == (1, 21, 3)
    np.testing.assert_allclose(handles.points[0], target[::900], atol=1e-6)  # the handles sit on the body
    assert np.nanmean(handles.residual) < 0.02  # and the fit reaches them (m)
    assert np.abs(fit.frames(np.array([0]))[0][0] - target).mean() < 0.03
