"""The artist's page at `/`, driven in a real headless Chromium against a real server: submit,
watch the preview follow the events, steer λ with the slider and the brush, cancel, delete,
download, and the token field. Small jobs (32², the shipped networks) keep it to seconds each."""
from __future__ import annotations

import zipfile

import httpx
import numpy as np
import pytest

from browser_harness import Page, start_browser, wait_until
from service.exr import exr_channels_from_bytes
from service_harness import REPO, Server, wait_for

pytestmark = pytest.mark.requires("chromium")

SMALL = {"scene": "cornell-box", "width": 32, "height": 32}
TOKEN = "page-token"


@pytest.fixture(scope="module")
def server(module_server):
    return module_server


@pytest.fixture(scope="module")
def driver(tmp_path_factory):
    browser = start_browser(tmp_path_factory.mktemp("downloads"))
    yield browser
    browser.quit()


@pytest.fixture
def page(driver, server) -> Page:
    return Page(driver, server.url).open()


@pytest.fixture
def api(server):
    with httpx.Client(base_url=server.url, timeout=60) as client:
        yield client


def finished_job(api: httpx.Client, **spec) -> dict:
    created = api.post("/jobs", json={**SMALL, "max_iterations": 2, **spec}).json()
    return wait_for(api, created["id"], lambda job: job["state"] == "completed")


def lambda_layer(api: httpx.Client, job_id: str) -> np.ndarray:
    response = api.get(f"/jobs/{job_id}/preview", params={"layer": "lambda", "format": "exr"})
    assert response.status_code == 200, response.text
    channels = exr_channels_from_bytes(response.content, max_pixels=32 * 32)
    return next(iter(channels.values()))


def test_submitting_a_32px_job_shows_each_new_preview_version_pushed_by_the_events(page, api):
    page.js("""window.versionsSeen = [];
        new MutationObserver(() => window.versionsSeen.push(document.getElementById('preview-version').dataset.version))
          .observe(document.getElementById('preview-version'), {attributes: true});""")
    job_id = page.submit(width=32, height=32, max_iterations=8, spp_first=32)
    wait_until(lambda: page.state(job_id) == "completed", "the row to say completed")
    final = api.get(f"/jobs/{job_id}").json()
    wait_until(lambda: page.shown_version() == final["preview_version"], "the last preview version on screen")
    seen = [int(v) for v in page.js("return window.versionsSeen") if v]
    assert len(set(seen)) >= 2 and seen == sorted(seen), f"the preview did not move on while rendering: {seen}"
    assert (final["spec"]["width"], final["spec"]["max_iterations"], final["spec"]["spp_first"]) == (32, 8, 32)
    row = page.row_text(job_id)
    assert "completed" in row and f"{final['spp']:.1f}" in row and f"{final['predicted_error']:.4f}" in row
    urls = page.resource_urls()
    assert any(url.endswith(f"/jobs/{job_id}/events") for url in urls), "no event stream was opened"
    assert not any(url.endswith(f"/jobs/{job_id}") for url in urls), "the page polled the job instead of its events"
    assert page.script_errors() == []


def test_dragging_the_lambda_slider_ends_on_the_last_value_and_shows_a_new_preview(page, api):
    job = finished_job(api)
    page.select(job["id"])
    wait_until(lambda: page.shown_version() == job["preview_version"], "the finished job's preview")
    slider = page.find("#lambda-slider")
    wait_until(lambda: slider.is_enabled(), "the λ slider to be enabled")
    page.drag("#lambda-slider", 40, 0)
    wanted = float(slider.get_attribute("value"))
    assert wanted > 1.0
    wait_until(lambda: page.shown_version() > job["preview_version"], "a preview after the λ change")
    status = wait_until(lambda: (s := api.get(f"/jobs/{job['id']}").json())["lambda_value"] == wanted and s,
                        f"the server to hold λ {wanted}")
    assert page.shown_version() == status["preview_version"]
    assert np.allclose(lambda_layer(api, job["id"]), wanted)
    puts = [url for url in page.resource_urls() if url.endswith("/lambda")]
    assert 1 <= len(puts) <= 3, f"the slider was not debounced: {len(puts)} requests for one drag"


def test_a_brush_stroke_paints_its_value_into_the_lambda_layer_and_undo_takes_it_back(page, api):
    job = finished_job(api)
    page.select(job["id"])
    wait_until(lambda: page.shown_version() == job["preview_version"], "the finished job's preview")
    page.find('#tool-buttons [data-tool="brush"]').click()
    for field, value in (("#brush-size", 4), ("#brush-value", 10)):
        page.find(field).clear()
        page.find(field).send_keys(str(value))
    page.drag_on_image([(4, 16), (12, 16), (20, 16), (28, 16)])
    wait_until(lambda: page.shown_version("#image-lambda") > job["preview_version"], "the λ overlay after the stroke")
    lam = lambda_layer(api, job["id"])
    assert np.allclose(lam[15:17, 4:28], 10.0) and np.allclose(lam[:8], 1.0), "the stroke is not where it was drawn"
    page.click('#layer-buttons label:has(input[value="lambda"])')
    wait_until(lambda: page.find("#image-a").get_attribute("src").find("layer=lambda") > 0, "the λ layer")
    wait_until(lambda: page.shown_version() > job["preview_version"], "the λ layer to load")
    assert page.image_pixel("#image-a", 16, 16) != page.image_pixel("#image-a", 16, 2), "the λ layer shows no stroke"
    before = page.shown_version()
    page.find("#brush-undo").click()
    wait_until(lambda: page.shown_version() > before, "the λ layer after undo")
    assert np.allclose(lambda_layer(api, job["id"]), 1.0)
    assert page.image_pixel("#image-a", 16, 16) == page.image_pixel("#image-a", 16, 2)


def test_cancel_stops_a_running_job_and_delete_removes_it(page, api):
    job_id = page.submit(width=256, height=256, max_iterations=8, spp_first=64)
    wait_until(lambda: page.state(job_id) == "running", "the job to run")
    page.row_action(job_id, "cancel")
    wait_until(lambda: page.state(job_id) == "canceled", "the row to say canceled")
    assert api.get(f"/jobs/{job_id}").json()["state"] == "canceled"
    page.row_action(job_id, "delete")
    wait_until(lambda: page.state(job_id) is None, "the row to go")
    assert api.get(f"/jobs/{job_id}").status_code == 404


def test_the_exr_button_downloads_the_result(page, api, driver, tmp_path):
    driver.execute_cdp_cmd("Page.setDownloadBehavior", {"behavior": "allow", "downloadPath": str(tmp_path)})
    job = finished_job(api)
    page.click("#jobs-refresh")
    wait_until(lambda: page.finds(f'tr[data-job-id="{job["id"]}"] [data-action="download"]'), "the EXR button")
    page.row_action(job["id"], "download")
    path = wait_until(lambda: next(iter(tmp_path.glob("*.exr")), None), "the downloaded EXR")
    expected = api.get(f"/jobs/{job['id']}/result.exr").content
    # Polled rather than read once after a fixed pause: a slow browser may still be writing it.
    wait_until(lambda: path.read_bytes() == expected, "the downloaded EXR to equal result.exr")


def test_a_zipped_scene_folder_chosen_in_the_drop_zone_is_uploaded_and_rendered(page, api, tmp_path):
    folder = REPO / "scenes" / "dev" / "fine_texture"  # scene.xml + the texture it names
    archive = tmp_path / "fine_texture.zip"
    with zipfile.ZipFile(archive, "w") as zf:
        for path in folder.iterdir():
            zf.write(path, f"fine_texture/{path.name}")
    page.wait_for_scenes()
    page.find("#bundle-input").send_keys(str(archive))
    wait_until(lambda: "fine_texture.zip" in page.find("#drop-label").text, "the zip to be chosen")
    assert not page.find("#scene-select").is_enabled()
    job_id = page.submit(width=32, height=32, max_iterations=1)
    wait_until(lambda: page.state(job_id) == "completed", "the uploaded scene to render")
    assert api.get(f"/jobs/{job_id}").json()["spec"]["bundle_scene"] == "scene.xml"


def test_zoom_pan_split_and_exposure_change_what_the_viewer_shows(page, api):
    job = finished_job(api)
    page.select(job["id"])
    wait_until(lambda: page.shown_version() == job["preview_version"], "the preview")
    stage = page.find("#stage")
    assert float(stage.get_attribute("data-scale")) > 4  # 32² fitted to the viewport
    page.click('#zoom-buttons [data-zoom="1"]')
    wait_until(lambda: stage.get_attribute("data-scale") == "1", "1:1 zoom")
    start = stage.rect
    page.drag("#viewport", 40, 25)
    moved = stage.rect
    assert (round(moved["x"] - start["x"]), round(moved["y"] - start["y"])) == (40, 25)
    page.click("#split")
    wait_until(lambda: page.find("#image-b").is_displayed(), "the A/B split")
    assert "layer=noisy" in page.find("#image-a").get_attribute("src")
    assert "layer=denoised" in page.find("#image-b").get_attribute("src")
    page.drag("#exposure", 60, 0)
    exposure = page.find("#exposure").get_attribute("value")
    assert float(exposure) > 0
    wait_until(lambda: f"exposure={exposure}&" in page.find("#image-b").get_attribute("src") + "&",
               "a preview at the new exposure")


def test_a_refused_submit_shows_the_servers_message(page):
    page.wait_for_scenes()
    page.type("width", 99999)
    page.find("#submit-button").click()
    message = wait_until(lambda: page.finds("#messages .error"), "an error message")[0]
    assert message.get_attribute("data-status") == "422"
    assert "width" in message.text and "4096" in message.text


@pytest.fixture
def token_server(tmp_path):
    server = Server(tmp_path / "data", tmp_path / "server.log", env={"RENDERLOOP_TOKEN": TOKEN}).start()
    yield server
    server.stop()


def test_with_a_token_the_page_asks_for_it_and_then_renders(driver, token_server):
    page = Page(driver, token_server.url).open()
    wait_until(lambda: page.find("#token-form").is_displayed(), "the token field")
    assert "needs a token" in page.find("#token-form").text
    page.find("#token-input").send_keys("wrong")
    page.find("#token-form button").click()
    wait_until(lambda: "refused" in page.find("#token-form label").text, "the wrong token to be refused")
    page.find("#token-input").send_keys(TOKEN)
    page.find("#token-form button").click()
    wait_until(lambda: not page.find("#token-form").is_displayed(), "the token field to close")
    job_id = page.submit(width=32, height=32, max_iterations=2)
    wait_until(lambda: page.state(job_id) == "completed", "the job to complete")
    wait_until(lambda: page.shown_version() == 2, "the preview, fetched with a signed URL")
    urls = page.resource_urls()  # the token rides in headers only, never in a URL
    assert not any(TOKEN in url for url in urls) and any("sig=" in url and "/preview" in url for url in urls), urls
    assert not page.finds("#messages .error"), page.messages()
    assert page.script_errors() == []


def test_the_automatic_allocator_lets_a_job_without_the_denoiser_run(page, api):
    options = page.js("return [...document.querySelectorAll('select[name=allocator] option')].map(o => o.value)")
    assert options == ["", "error", "variance", "uniform"]  # "" = the server's default for the job
    page.js("document.querySelector('input[name=denoise]').checked = false")
    job_id = page.submit(width=32, height=32, max_iterations=2)
    job = wait_for(api, job_id, lambda job: job["state"] in ("completed", "failed"))
    assert job["state"] == "completed" and job["spec"]["allocator"] == "variance", job


PARAM_SCENE = """<scene version="3.0.0">
    <default name="albedo" value="0.5"/>
    <default name="light" value="2"/>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
    </sensor>
    <shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="$albedo"/></bsdf></shape>
    <emitter type="constant"><rgb name="radiance" value="$light"/></emitter>
</scene>
"""


def renders_as_missing_glyph(page: Page, text: str) -> list[str]:
    """The characters of `text` the browser draws as its missing-glyph box: drawn on a canvas
    in the table's font, pixel for pixel the same as a private-use code point no font has."""
    return page.js("""
        const font = getComputedStyle(document.querySelector('#jobs-table td') || document.body).font;
        const canvas = document.createElement('canvas'); canvas.width = 40; canvas.height = 40;
        const ctx = canvas.getContext('2d', {willReadFrequently: true});
        const draw = (c) => { ctx.clearRect(0, 0, 40, 40); ctx.font = font; ctx.fillStyle = '#fff';
                              ctx.fillText(c, 4, 28); return ctx.getImageData(0, 0, 40, 40).data.join(); };
        const tofu = draw('\\u{10FFFD}');
        return [...new Set([...arguments[0]])].filter((c) => c.trim() && draw(c) === tofu);""", text)


def test_scene_parameters_and_the_seed_set_on_the_page_reach_the_submitted_job(page, api, tmp_path):
    archive = tmp_path / "spheres.zip"
    with zipfile.ZipFile(archive, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("spheres/scene.xml", PARAM_SCENE)
    page.wait_for_scenes()
    assert "declare no" in page.find("#params-note").text  # a built-in scene: none
    page.find("#bundle-input").send_keys(str(archive))
    field = '#params-list input[data-param="albedo"]'
    wait_until(lambda: page.finds(field), "the zip's parameters")
    assert page.find(field).get_attribute("value") == "0.5"
    assert page.find('#params-list input[data-param="light"]').get_attribute("value") == "2"
    page.find(field).clear()
    page.find(field).send_keys("0.25")
    job_id = page.submit(seed=7, max_iterations=1)
    job = wait_for(api, job_id, lambda job: job["state"] in ("completed", "failed"))
    assert job["state"] == "completed", job
    assert (job["spec"]["params"], job["spec"]["seed"]) == ({"albedo": "0.25"}, 7)  # light kept its default
    row = page.row_text(job_id)
    assert "upload" in row and "scene.xml" in row
    assert renders_as_missing_glyph(page, row) == [], row
    assert renders_as_missing_glyph(page, "📦") == ["📦"]  # the check can fail: the old marker was a box here


def test_the_page_says_what_device_the_server_renders_on(page, api):
    info = api.get("/info").json()
    assert info["device"] in ("CPU", "GPU") and info["variant"].endswith("_rgb")
    shown = wait_until(lambda: page.find("#server-info").text, "the device line")
    assert info["device"] in shown and info["variant"] in shown


def test_at_1400px_every_field_of_the_new_job_form_lies_inside_its_box(page):
    page.wait_for_scenes()
    assert page.js("return window.innerWidth") >= 1380  # the harness's window: 1400 px wide
    outside = page.js("""
        const out = [];
        for (const input of document.querySelectorAll('#submit-form input:not([type=file]), #submit-form select')) {
          if (!input.offsetParent) continue;  // hidden
          const box = input.getBoundingClientRect(), frame = input.closest('fieldset').getBoundingClientRect();
          if (box.left < frame.left || box.right > frame.right) out.push(input.name || input.id);
        }
        return out;""")
    assert outside == []
    assert page.js("""const box = document.querySelector('#submit-form [name=lambda]').getBoundingClientRect();
                      const panel = document.querySelector('#submit-panel').getBoundingClientRect();
                      return box.right <= panel.right && box.width > 20""")


def test_the_eta_shows_while_a_job_runs_and_the_stop_message_when_it_ends(page, api):
    # Ten doubling iterations at 64² (up to 32 768 spp) outlast any machine's first ETA by far;
    # the job is canceled once the ETA is seen, and the page then says so in words.
    job_id = page.submit(width=64, height=64, max_iterations=10, spp_first=64, time_limit=600)
    wait_until(lambda: "left" in page.row_text(job_id) or page.state(job_id) == "completed",
               "an ETA in the job's row", timeout=180)
    assert page.state(job_id) != "completed", "the job ended before any ETA was shown"
    assert "left" in page.find("#job-summary").text or "finishing" in page.find("#job-summary").text
    assert api.post(f"/jobs/{job_id}/cancel").status_code == 200
    wait_until(lambda: page.state(job_id) == "canceled", "the job to be canceled", timeout=120)
    stop_message = api.get(f"/jobs/{job_id}").json()["stop_message"]
    assert stop_message.startswith("canceled after")
    wait_until(lambda: stop_message in page.find("#job-summary").text, "the stop message")
    assert "seed 0" in page.find("#job-summary").text
    assert page.script_errors() == []
