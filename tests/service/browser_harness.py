"""A real headless Chromium (Debian's `chromium` + `chromium-driver`, driven by Selenium) for
the page's tests, and helpers that act as a person would: type, click, drag on the preview.
scripts/ensure-chromium.sh installs the browser; without it the tests fail and say so (skip under
ALLOW_SKIP=1: tests/required_components.py)."""
from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any, Callable

from required_components import require_component

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
WAIT_SECONDS = 60.0

try:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.actions.action_builder import ActionBuilder
    from selenium.webdriver.common.by import By
    from selenium.common.exceptions import StaleElementReferenceException
    from selenium.webdriver.remote.webdriver import WebDriver
    from selenium.webdriver.remote.webelement import WebElement
except ImportError:  # the dev extra is not installed: require_component("chromium") says so
    webdriver = None


def start_browser(download_dir: Path) -> "WebDriver":
    require_component("chromium")
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM if CHROMIUM.exists() else shutil.which("chromium"))
    # --no-sandbox: CI runs as root, where Chromium's sandbox refuses to start.
    for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1400,900",
                     "--disable-gpu", "--force-device-scale-factor=1"):
        options.add_argument(argument)
    options.add_experimental_option("prefs", {"download.default_directory": str(download_dir),
                                              "download.prompt_for_download": False})
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver_path = CHROMEDRIVER if CHROMEDRIVER.exists() else Path(shutil.which("chromedriver"))
    return webdriver.Chrome(service=Service(str(driver_path)), options=options)


def wait_until(condition: Callable[[], Any], what: str, timeout: float = WAIT_SECONDS) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")


class Page:
    """The page at `url` in `driver`, with the moves a person makes."""

    def __init__(self, driver: "WebDriver", url: str) -> None:
        self.driver = driver
        self.url = url

    def open(self) -> "Page":
        self.driver.get(self.url + "/")
        self.driver.execute_script("sessionStorage.clear()")
        self.driver.get(self.url + "/")
        self.driver.get_log("browser")  # drained: script_errors reports this page's only
        return self

    def find(self, css: str) -> "WebElement":
        return self.driver.find_element(By.CSS_SELECTOR, css)

    def finds(self, css: str) -> list["WebElement"]:
        return self.driver.find_elements(By.CSS_SELECTOR, css)

    def js(self, script: str, *args: Any) -> Any:
        return self.driver.execute_script(script, *args)

    def click(self, css: str) -> None:
        """Click the element; the job list redraws rows on every event, so find it afresh."""
        def clicked() -> bool:
            try:
                self.find(css).click()
                return True
            except StaleElementReferenceException:
                return False
        wait_until(clicked, f"a clickable {css}")

    def type(self, name: str, value: str | int) -> None:
        field = self.find(f"#submit-form [name={name}]")
        field.clear()
        field.send_keys(str(value))

    def wait_for_scenes(self) -> None:
        wait_until(lambda: self.finds("#scene-select option"), "the scene list")

    def submit(self, **fields: str | int) -> str:
        """Fill the form, press Render, return the new job's id (the page selects it)."""
        self.wait_for_scenes()
        before = set(self.job_ids())
        for name, value in fields.items():
            self.type(name, value)
        self.find("#submit-button").click()
        return wait_until(lambda: next((i for i in self.job_ids() if i not in before), None), "the new job's row")

    def job_ids(self) -> list[str]:
        return self.js("return [...document.querySelectorAll('#jobs-table tbody tr')].map(r => r.dataset.jobId)")

    def row_css(self, job_id: str) -> str:
        return f'#jobs-table tr[data-job-id="{job_id}"]'

    def row_text(self, job_id: str) -> str:
        return self.js("const r = document.querySelector(arguments[0]); return r ? r.innerText : ''", self.row_css(job_id))

    def state(self, job_id: str) -> str | None:
        return self.js("const r = document.querySelector(arguments[0]); return r ? r.dataset.state : null",
                       self.row_css(job_id))

    def row_action(self, job_id: str, action: str) -> None:
        self.click(f'{self.row_css(job_id)} [data-action="{action}"]')

    def select(self, job_id: str) -> None:
        """Click the job's row; a job submitted elsewhere appears after the list's ↻ button."""
        if not self.state(job_id):
            self.click("#jobs-refresh")
        wait_until(lambda: self.state(job_id), f"job {job_id} in the list")
        self.click(f"{self.row_css(job_id)} td:nth-child(2)")
        wait_until(lambda: self.find("#viewer-title").text == job_id, "the viewer to show the job")

    def shown_version(self, image: str = "#image-a") -> int:
        return int(self.find(image).get_attribute("data-version") or 0)

    def messages(self) -> str:
        return self.find("#messages").text

    def image_to_screen(self, x: float, y: float) -> tuple[float, float]:
        """Window coordinates of image pixel (x, y), through the viewer's zoom and pan."""
        box = self.js("const r = document.getElementById('stage').getBoundingClientRect();"
                      "const i = document.getElementById('image-a');"
                      "return [r.left, r.top, r.width / i.naturalWidth];")
        left, top, scale = box
        return left + x * scale, top + y * scale

    def drag_on_image(self, points: list[tuple[float, float]]) -> None:
        """Press at the first image pixel, move through the others, release (a brush stroke)."""
        actions = ActionBuilder(self.driver)
        pointer = actions.pointer_action
        pointer.move_to_location(*map(round, self.image_to_screen(*points[0])))
        pointer.pointer_down()
        for point in points[1:]:
            pointer.move_to_location(*map(round, self.image_to_screen(*point)))
        pointer.pointer_up()
        actions.perform()

    def drag(self, css: str, dx: int, dy: int) -> None:
        """Press on the element's centre, move by (dx, dy), release: a slider or a pan."""
        ActionChains(self.driver).drag_and_drop_by_offset(self.find(css), dx, dy).perform()

    def image_pixel(self, image: str, x: int, y: int) -> list[int]:
        """RGBA of one pixel of an <img> as the browser decoded it."""
        return self.js("""
            const img = document.querySelector(arguments[0]);
            const canvas = document.createElement('canvas');
            canvas.width = img.naturalWidth; canvas.height = img.naturalHeight;
            const context = canvas.getContext('2d');
            context.drawImage(img, 0, 0);
            return Array.from(context.getImageData(arguments[1], arguments[2], 1, 1).data);""", image, x, y)

    def resource_urls(self) -> list[str]:
        return self.js("return performance.getEntriesByType('resource').map(e => e.name)")

    def script_errors(self) -> list[str]:
        """Uncaught exceptions and console.error lines (a refused request's own line aside)."""
        return [entry["message"] for entry in self.driver.get_log("browser")
                if entry["level"] == "SEVERE" and "Failed to load resource" not in entry["message"]]
