"""docs/page.png: the page with finished jobs, the A/B split and a λ brush stroke, taken in
headless Chromium against a real server. Slow-marked (it renders larger images than the page's
tests); run it with `make page-screenshot` and commit the picture."""
from __future__ import annotations

import httpx
import pytest
from PIL import Image

from browser_harness import Page, start_browser, wait_until
from service_harness import REPO, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.requires("chromium")]

SCREENSHOT = REPO / "docs" / "page.png"


def test_a_screenshot_of_the_page_with_a_finished_job_is_written_to_docs(server, tmp_path):
    driver = start_browser(tmp_path)
    try:
        with httpx.Client(base_url=server.url, timeout=60) as api:
            other = api.post("/jobs", json={"scene": "glossy-spheres", "width": 96, "height": 96}).json()
            wait_for(api, other["id"], lambda job: job["state"] == "completed", timeout=600)
        page = Page(driver, server.url).open()
        job_id = page.submit(width=192, height=192, max_iterations=5)
        wait_until(lambda: page.state(job_id) == "completed", "the job to complete", timeout=600)
        page.click('#tool-buttons [data-tool="brush"]')
        for field, value in (("#brush-size", 10), ("#brush-value", 10)):
            page.find(field).clear()
            page.find(field).send_keys(str(value))
        before = page.shown_version()
        page.drag_on_image([(60, 150), (100, 140), (140, 150)])
        wait_until(lambda: page.shown_version("#image-lambda") > before, "the λ overlay with the stroke")
        page.click("#split")
        wait_until(lambda: page.find("#image-b").is_displayed(), "the A/B split")
        driver.save_screenshot(str(SCREENSHOT))
    finally:
        driver.quit()
    with Image.open(SCREENSHOT) as image:
        assert image.width >= 1200 and len(image.getcolors(1 << 20) or range(1 << 20)) > 1000
