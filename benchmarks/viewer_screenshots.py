"""The pictures of docs/viewer.md: ``unibody view`` in headless Chromium, screenshot by selenium.

  viewer_motion.png     two CMU walks (BVH, converted on load) side by side, skeleton on
  viewer_mocap.png      a Plug-in Gait take (BTKData walk) with its solved body and marker names
  viewer_identity.png   an identity sweep: five Anny bodies, age 0 -> 1 (the other phenotypes at 0.5)
  viewer_resolve.png    a PCA body with its upper arm in the chest, before and after
                        resolve_self_intersections, self-intersecting triangles in red

Needs Debian's chromium and chromium-driver, selenium and viser (the README's install), and the
data under ../shared (CMU BVH and the evaluation C3D files).

    python benchmarks/viewer_screenshots.py [--out docs] [--shared ../shared] [--only motion|mocap|identity|resolve]
"""

from __future__ import annotations

import argparse
import io
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image


def _browser(width: int, height: int):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader", f"--window-size={width},{height}", "--hide-scrollbars"):  # fmt: skip
        opts.add_argument(arg)
    return webdriver.Chrome(options=opts, service=Service("/usr/bin/chromedriver"))


def _shoot(viewer, out: Path, setup=None, width: int = 1400, height: int = 800, settle: float = 10.0) -> None:
    driver = _browser(width, height)
    try:
        driver.get(viewer.url)
        deadline = time.monotonic() + 60
        while not viewer.server.get_clients() and time.monotonic() < deadline:
            time.sleep(0.3)
        time.sleep(2.0)
        # Close viser's "software WebGL" notice: it is about the headless browser, not the viewer.
        driver.execute_script("document.querySelectorAll('.mantine-Notification-closeButton').forEach(b => b.click())")
        if setup is not None:
            setup(viewer)
        time.sleep(settle)
        png = driver.get_screenshot_as_png()
    finally:
        driver.quit()
    Image.open(io.BytesIO(png)).convert("RGB").save(out, optimize=True)
    print(f"wrote {out}")


def _motion(args, layers: dict) -> None:
    from unibody.cli.view_sources import load_item
    from unibody.viz.viewer.app import Viewer

    bvh = args.shared / "motions/cmu/bvh"
    walks = [next(bvh.rglob(name)) for name in ("02_01.bvh", "02_02.bvh")]
    with Viewer([load_item(p, layers) for p in walks], port=0, spacing=1.2) as viewer:

        def setup(v):
            v.gui.skeleton.value = True
            v.gui.frame.value = 150
            joints = [b.frames(np.array([150]))[1][0, 1] + [1.2 * i, 0, 0] for i, b in enumerate(v.bodies)]
            centre = np.mean(joints, axis=0)
            for client in v.server.get_clients().values():
                client.camera.look_at = centre
                client.camera.position = centre + np.array([0.8, 0.5, 3.0])

        _shoot(viewer, args.out / "viewer_motion.png", setup)


def _mocap(args, layers: dict) -> None:
    from unibody.cli.view_sources import load_item
    from unibody.viz.viewer.app import Viewer

    take = args.shared / "evaldata/c3d/btkdata_PiG_Motion-FlatFoot-Full.c3d"
    with Viewer([load_item(take, layers, solve="pig35")], port=0) as viewer:

        def setup(v):
            v.gui.frame.value = 120
            v.gui.marker_names.value = True
            pts = v.items[0].markers[0].points[120]
            centre = np.nanmean(pts, axis=0)
            for client in v.server.get_clients().values():  # closer than the framing of the whole walk
                client.camera.look_at = centre
                client.camera.position = centre + np.array([1.2, 0.3, 1.6])

        _shoot(viewer, args.out / "viewer_mocap.png", setup)


def _identity(args, layers: dict) -> None:
    from unibody.cli.view_sources import default_body
    from unibody.viz.viewer.app import Viewer
    from unibody.viz.viewer.tracks import SceneItem

    items = []
    for age in np.linspace(0.0, 1.0, 5):
        (body,) = default_body("anny", layers, np.array([0.5, age, 0.5, 0.5, 0.5, 0.5])).bodies
        body.name = f"age {age:.2f}"
        items.append(SceneItem(body.name, bodies=(body,)))
    with Viewer(items, port=0, spacing=1.75) as viewer:
        _shoot(viewer, args.out / "viewer_identity.png")


def _resolve(args, layers: dict) -> None:
    from unibody.body import BodyLayer
    from unibody.cli.view_sources import LayerBody, resolved_item
    from unibody.rig import joint_index
    from unibody.viz.viewer.app import Viewer
    from unibody.viz.viewer.tracks import SceneItem

    pose = np.zeros((1, 77, 3), np.float32)
    pose[0, joint_index("LeftArm") - 1] = [0.0, 0.0, -1.75]  # the upper arm into the chest
    pose[0, joint_index("LeftForeArm") - 1] = [0.0, -1.5, 0.0]
    layer = BodyLayer.from_pca(num_components=16)
    body = LayerBody("arm in chest", layer, np.zeros(16), pose, np.array([[0.0, 0.95, 0.0]]), 30.0, None)
    item = SceneItem(body.name, bodies=(body,))
    with Viewer([item, resolved_item(item)], port=0, spacing=1.2) as viewer:

        def setup(v):
            v.gui.intersections.value = True
            for client in v.server.get_clients().values():
                client.camera.look_at = np.array([0.6, 1.2, 0.0])
                client.camera.position = np.array([0.9, 1.6, 2.6])

        _shoot(viewer, args.out / "viewer_resolve.png", setup)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("docs"))
    ap.add_argument("--shared", type=Path, default=Path("../shared"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--only", choices=("motion", "mocap", "identity", "resolve"), help="make one picture only")
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    layers: dict = {}
    for name, make in (("motion", _motion), ("mocap", _mocap), ("identity", _identity), ("resolve", _resolve)):
        if args.only in (None, name):
            make(args, layers)


if __name__ == "__main__":
    with torch.no_grad():
        main()
