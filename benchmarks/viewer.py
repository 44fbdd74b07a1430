"""How responsive `stgc view` is on this machine (issue #16): the interactive frame rate of a free camera at the
dataset's size and while moving (half per axis), and the time from a frame-slider move in a real browser to the new
full-resolution image leaving the server.

    .venv/bin/python benchmarks/viewer.py RUN [--views 20] [--moves 10] [--threads 2] [--screenshot page.png]

RUN: a trained run (or .stgc). Free-camera renders follow a small orbit around the first test camera. The slider
part drives headless Chromium (Debian's chromium + chromium-driver) through the page, as tests/test_viewer.py does;
without it that part is skipped. Prints a table (and --json one line).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import time
from typing import Any

from stgc import machine
from stgc.viewer import Viewer, ViewerScene, camera_from_view, free_port, view_of_camera


def _orbit(scene: ViewerScene, views: int, width: int, height: int) -> list[Any]:
    """Browser cameras around the first test camera: its pose turned by up to +-10 degrees about its own y axis."""
    from viser import transforms

    camera = scene.cameras[sorted(scene.test_names)[0]]
    position, wxyz, fov = view_of_camera(camera)
    out = []
    for k in range(views):
        angle = math.radians(10.0) * math.sin(2 * math.pi * k / views)
        turned = transforms.SO3(wxyz) @ transforms.SO3.from_y_radians(angle)
        out.append(camera_from_view(position, turned.wxyz, fov, width, height, camera.near))
    return out


def render_rates(scene: ViewerScene, views: int) -> dict[str, float]:
    camera = scene.cameras[sorted(scene.test_names)[0]]
    rows: dict[str, float] = {}
    for label, scale in (("full", 1.0), ("moving", 0.5)):
        width, height = round(camera.width * scale), round(camera.height * scale)
        cameras = _orbit(scene, views, width, height)
        scene.render(cameras[0], float(scene.frames[0]))  # warm-up (numba compiled, caches)
        times = []
        for k, cam in enumerate(cameras):
            frame = float(scene.frames[k % len(scene.frames)])
            t0 = time.perf_counter()
            scene.render(cam, frame)
            times.append(time.perf_counter() - t0)
        ms = 1000 * statistics.median(times)
        rows[f"{label}_{width}x{height}_ms"] = round(ms, 1)
        rows[f"{label}_fps"] = round(1000 / ms, 1)
    return rows


def slider_latency(scene: ViewerScene, moves: int, screenshot: str | None = None) -> dict[str, float] | None:
    """Median seconds from the keypress that moves the frame to the full image of that frame being sent; then, with
    `screenshot`, the page with the ground truth beside the render saved there."""
    if not (shutil.which("chromium") and shutil.which("chromedriver")):
        return None
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    options = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1000,700", "--force-device-scale-factor=1"):
        options.add_argument(arg)
    viewer = Viewer(scene, port=free_port())
    driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
    try:
        driver.get(viewer.url)
        _wait(lambda: viewer.clients)
        view = next(iter(viewer.clients.values()))
        label = driver.find_element(By.XPATH, "//label[normalize-space()='camera']")
        driver.find_element(By.ID, label.get_attribute("for")).click()
        _wait(lambda: [o for o in driver.find_elements(By.XPATH, "//*[@role='option']")
                       if o.text == sorted(scene.test_names)[0]])[0].click()
        _wait(lambda: view.snapped_name() is not None and view.full_done, 120)
        box = driver.find_elements(By.XPATH, "//label[normalize-space()='frame']/ancestor::div[1]"
                                             "/following-sibling::*//input[not(@type='hidden')]")[-1]
        latencies = []
        for k in range(moves):
            frame = float(scene.frames[(k + 1) % len(scene.frames)])
            box.send_keys(Keys.CONTROL, "a")
            t0 = time.perf_counter()
            box.send_keys(Keys.BACKSPACE, f"{frame:g}", Keys.ENTER)
            _wait(lambda: view.drawn == (frame, True) and view.full_done, 60)
            latencies.append(time.perf_counter() - t0)
        if screenshot:
            label = driver.find_element(By.XPATH, "//label[normalize-space()='ground truth']")
            driver.find_element(By.ID, label.get_attribute("for")).click()
            _wait(lambda: viewer.show_ground_truth and view.full_done, 60)
            for close in driver.find_elements(By.XPATH, "//button[contains(@class, 'Notification-close')]"):
                close.click()
            time.sleep(1.5)
            driver.save_screenshot(screenshot)
        return {"slider_to_image_s_median": round(statistics.median(latencies), 3),
                "slider_to_image_s_max": round(max(latencies), 3)}
    finally:
        driver.quit()
        viewer.stop()


def _wait(condition: Any, seconds: float = 30.0) -> Any:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.005)
    raise TimeoutError("the viewer did not answer in time")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run")
    parser.add_argument("--views", type=int, default=20)
    parser.add_argument("--moves", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2,
                        help="torch's and numba's threads (0 leaves their defaults, as `stgc view` does)")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--screenshot", help="also save the page (a test camera, ground truth beside) to this PNG")
    args = parser.parse_args()
    machine.use_threads(args.threads)  # torch's and numba's
    row: dict[str, Any] = {"machine": machine.one_line()}  # the load before the timings
    scene = ViewerScene.open(args.run)
    row.update({"run": args.run, "gaussians": scene.segments[0].model.num_gaussians,
                "threads": args.threads or "default"})
    row.update(render_rates(scene, args.views))
    row.update(slider_latency(scene, args.moves, args.screenshot) or {"slider_to_image": "skipped: no chromium"})
    row["load_avg_1min"] = round(os.getloadavg()[0], 2)
    width = max(len(k) for k in row)
    for key, value in row.items():
        print(f"{key:<{width}}  {value}")
    if args.json:
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
