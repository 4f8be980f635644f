"""The web page in a real browser: Debian's chromium, headless, driven by Playwright, with the internet cut
off. Upload a video through the page, watch the progress bar move, see the 3-D viewer load the GLB."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import pytest

from tests.helpers import ARTIFACTS, QUICK_JOB

CHROMIUM = Path("/usr/bin/chromium")
LAUNCH_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
               "--no-first-run", "--use-gl=swiftshader", "--enable-unsafe-swiftshader"]


@pytest.fixture
def browser_page() -> Any:
    playwright_api = pytest.importorskip("playwright.sync_api")
    if not CHROMIUM.exists():
        pytest.skip("no /usr/bin/chromium")
    with playwright_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=LAUNCH_ARGS)
        context = browser.new_context(viewport={"width": 1400, "height": 1300})
        try:
            yield context.new_page()
        finally:
            context.close()
            browser.close()


@pytest.mark.browser
@pytest.mark.slow
def test_page_uploads_shows_progress_and_loads_the_glb(embedded_server: Any, tiny_video: Path,
                                                       browser_page: Any) -> None:
    page = browser_page
    outside: list[str] = []
    glb_responses: list[Any] = []

    def local_only(route: Any) -> None:
        host = urlparse(route.request.url).hostname
        if host in ("127.0.0.1", "localhost"):
            route.continue_()
        else:  # the page must work with no internet: record and refuse anything else
            outside.append(route.request.url)
            route.abort()

    page.route("**/*", local_only)
    page.on("response", lambda r: glb_responses.append(r) if r.url.split("?")[0].endswith(".glb") else None)
    page.goto(embedded_server.url + "/", wait_until="load")
    page.wait_for_selector("#neudf-submit")

    page.set_input_files("#neudf-upload input[type=file]", str(tiny_video))
    page.wait_for_selector("#neudf-upload :text('orbit.mp4')", timeout=30_000)  # the upload finished
    page.click("#neudf-options button, #neudf-options >> text=Options")  # open the options
    fields = {"iters": "Iterations", "frames": "Frames", "mesh_resolution": "Mesh resolution",
              "mesh_threshold": "Mesh threshold", "mesh_min_faces": "Smallest piece (faces)",
              "mesh_min_seen": "Share of cameras that must see a face", "texture_size": "Texture size (px)"}
    for key, label in fields.items():
        page.get_by_label(label).fill(QUICK_JOB[key])
    page.click("#neudf-submit")

    # The progress bar: sample its value until the job ends.
    values: list[float] = []
    deadline = time.monotonic() + 300
    state = "none"
    while time.monotonic() < deadline:
        bar = page.query_selector("#neudf-progress")
        job = page.query_selector("#neudf-job")
        if bar is not None:
            values.append(float(bar.get_attribute("value")))
        state = job.get_attribute("data-state") if job else "none"
        if state in ("succeeded", "failed", "cancelled"):
            break
        time.sleep(0.3)
    ARTIFACTS.mkdir(exist_ok=True)
    if state != "succeeded":
        page.screenshot(path=str(ARTIFACTS / f"page_job_{state}.png"), full_page=True)
    assert state == "succeeded", page.inner_text("#neudf-status") + "\n" + embedded_server.log_tails()
    # The state and the bar are separate elements: the bar may reach 100% one refresh after the state.
    settle = time.monotonic() + 15
    while values and values[-1] < 1.0 and time.monotonic() < settle:
        time.sleep(0.3)
        bar = page.query_selector("#neudf-progress")
        if bar is not None:
            values.append(float(bar.get_attribute("value")))
    moved = sorted(set(values))
    assert len(moved) >= 3 and moved[0] < 0.5 and moved[-1] == 1.0, values
    assert all(b >= a for a, b in zip(values, values[1:])), values

    # The 3-D viewer fetches the GLB and draws it on a canvas; the download button appears.
    page.wait_for_selector("#neudf-model canvas", timeout=60_000)
    deadline = time.monotonic() + 30
    while not any(r.status == 200 for r in glb_responses) and time.monotonic() < deadline:
        page.wait_for_timeout(200)
    ok = [r for r in glb_responses if r.status == 200]
    assert ok and ok[0].body()[:4] == b"glTF"
    page.wait_for_selector("#neudf-download", state="visible", timeout=30_000)
    page.wait_for_selector("#neudf-frames img", timeout=30_000)  # the chosen frames
    page.wait_for_timeout(1500)  # let the viewer finish its first frames before the picture
    page.screenshot(path=str(ARTIFACTS / "page_job_succeeded.png"), full_page=True)
    assert outside == [], f"the page asked the internet for: {outside}"
