// The progressive preview: the selected layer of the selected job as the server renders it
// (GET /jobs/{id}/preview, reloaded when the job's preview_version moves), exposure, fit or
// 1:1 / 2:1 / 4:1 zoom with drag-to-pan, an A/B split between noisy and denoised, and the
// per-pixel λ as an overlay. Pointer strokes in brush mode go to the λ brush (brush.js).

import { api, request } from "./api.js";

const RADIANCE = ["denoised", "noisy"];

export class Viewer {
  /** hooks: onError(error), onStroke: {begin(point), move(point), end()}, onLambdaLoaded(version) */
  constructor(hooks) {
    this.hooks = hooks;
    this.el = Object.fromEntries(["viewport", "stage", "image-a", "image-b", "image-lambda", "strokes", "split-line",
      "viewer-empty", "viewer-title", "viewer-info", "preview-version", "exposure", "exposure-value", "frame",
      "split", "split-position", "lambda-overlay"].map((id) => [id, document.getElementById(id)]));
    this.job = null;
    this.version = 0;  // the newest preview version known to exist
    this.layer = "denoised";
    this.zoom = "fit";
    this.pan = {x: 0, y: 0};
    this.tool = "pan";
    this.size = null;  // {w, h} of the image, once one loaded
    this.loads = 0;  // a counter so a stale image's load event changes nothing
    this.bindControls();
    this.bindPointer();
    new ResizeObserver(() => this.place()).observe(this.el.viewport);
  }

  bindControls() {
    document.querySelectorAll("input[name=layer]").forEach((radio) => radio.addEventListener("change", () => {
      this.layer = radio.value;
      this.reload();
    }));
    this.el.exposure.addEventListener("input", () => {
      this.el["exposure-value"].textContent = this.el.exposure.value;
    });
    this.el.exposure.addEventListener("change", () => this.reload());
    this.el.frame.addEventListener("change", () => this.reload());
    this.el.split.addEventListener("change", () => this.reload());
    this.el["split-position"].addEventListener("input", () => this.placeSplit());
    this.el["lambda-overlay"].addEventListener("change", () => this.reload());
    document.querySelectorAll("#zoom-buttons button").forEach((button) => button.addEventListener("click", () => {
      document.querySelectorAll("#zoom-buttons button").forEach((b) => b.classList.toggle("active", b === button));
      this.zoom = button.dataset.zoom === "fit" ? "fit" : Number(button.dataset.zoom);
      this.pan = {x: 0, y: 0};
      this.place();
    }));
  }

  bindPointer() {
    const viewport = this.el.viewport;
    let drag = null;
    viewport.addEventListener("pointerdown", (event) => {
      if (!this.size || event.button !== 0) return;
      viewport.setPointerCapture(event.pointerId);
      if (this.tool === "brush") {
        drag = {brush: true};
        this.hooks.onStroke.begin(this.imagePoint(event));
      } else {
        drag = {x: event.clientX - this.pan.x, y: event.clientY - this.pan.y};
      }
      event.preventDefault();
    });
    viewport.addEventListener("pointermove", (event) => {
      if (!drag) return;
      if (drag.brush) this.hooks.onStroke.move(this.imagePoint(event));
      else {
        this.pan = {x: event.clientX - drag.x, y: event.clientY - drag.y};
        this.place();
      }
    });
    const finish = () => {
      if (drag && drag.brush) this.hooks.onStroke.end();
      drag = null;
    };
    viewport.addEventListener("pointerup", finish);
    viewport.addEventListener("pointercancel", finish);
  }

  setTool(tool) {
    this.tool = tool;
    this.el.viewport.classList.toggle("brush", tool === "brush");
    this.reload();
  }

  /** Image pixel (fractional) under a pointer event. */
  imagePoint(event) {
    const box = this.el.stage.getBoundingClientRect();
    return {x: (event.clientX - box.left) / box.width * this.size.w, y: (event.clientY - box.top) / box.height * this.size.h};
  }

  frame() {
    return Math.max(0, Number(this.el.frame.value) || 0);
  }

  show(job) {
    this.job = job;
    this.version = job ? job.preview_version : 0;
    this.size = null;
    this.pan = {x: 0, y: 0};
    this.el["viewer-title"].textContent = job ? job.id : "select a job";
    this.el.frame.max = job && job.spec.frames ? job.spec.frames - 1 : 0;
    if (this.frame() > Number(this.el.frame.max)) this.el.frame.value = 0;
    this.reload();
  }

  /** A status event: reload when the preview moved on. */
  update(job) {
    if (!this.job || job.id !== this.job.id) return;
    const overlayBefore = this.overlayWanted();
    this.job = job;
    if (job.preview_version > this.version) this.showVersion(job.preview_version);
    else if (overlayBefore !== this.overlayWanted()) this.reload();
  }

  showVersion(version) {
    if (version <= this.version) return;  // shown already, or an older answer arriving late
    this.version = version;
    this.reload();
  }

  overlayWanted() {
    const job = this.job;
    return Boolean(job) && this.el["lambda-overlay"].checked && this.layer !== "lambda" &&
      (this.tool === "brush" || job.lambda_value === null);
  }

  url(layer) {
    const params = {frame: this.frame(), layer, format: "png", v: this.version};
    if (RADIANCE.includes(layer)) params.exposure = this.el.exposure.value;
    return api.previewURL(this.job.id, params);
  }

  reload() {
    const split = this.el.split.checked;
    this.el["split-position"].hidden = !split;
    this.el["split-line"].hidden = !split || !this.job || this.version === 0;
    const [a, b, lambda] = [this.el["image-a"], this.el["image-b"], this.el["image-lambda"]];
    if (!this.job || this.version === 0) {
      [a, b, lambda].forEach((img) => { img.hidden = true; img.removeAttribute("src"); });
      this.el["viewer-empty"].hidden = false;
      this.el["viewer-empty"].textContent = this.job ? "No preview yet: the first iteration is rendering." : "No job selected.";
      this.el["preview-version"].textContent = "";
      return;
    }
    this.el["viewer-empty"].hidden = true;
    const load = ++this.loads;
    this.loadImage(a, this.url(split ? "noisy" : this.layer), load, true);
    b.hidden = !split;
    if (split) this.loadImage(b, this.url("denoised"), load, false);
    lambda.hidden = !this.overlayWanted();
    if (!lambda.hidden) this.loadImage(lambda, this.url("lambda"), load, false);
    this.placeSplit();
  }

  /** `url`: a Promise of the signed preview URL (api.previewURL). */
  async loadImage(img, url, load, main) {
    const version = this.version;
    try {
      url = await url;
    } catch (error) {
      if (load === this.loads) this.hooks.onError(error);
      return;
    }
    if (load !== this.loads) return;  // a newer reload started while the link was fetched
    img.onload = () => {
      if (load !== this.loads) return;
      img.dataset.version = String(version);
      img.hidden = false;
      if (main) this.loaded(img, version);
      if (img === this.el["image-lambda"]) this.hooks.onLambdaLoaded(version);
    };
    img.onerror = () => {
      if (load === this.loads) this.explain(url);
    };
    img.src = url;
  }

  loaded(img, version) {
    const size = {w: img.naturalWidth, h: img.naturalHeight};
    const resized = !this.size || this.size.w !== size.w || this.size.h !== size.h;
    this.size = size;
    if (resized) this.place();
    this.el["preview-version"].textContent = `preview v${version}`;
    this.el["preview-version"].dataset.version = String(version);
    const job = this.job;
    this.el["viewer-info"].textContent = `${size.w}×${size.h}, iteration ${job.iteration}, ${job.spp.toFixed(1)} spp` +
      (job.lambda_value !== null ? `, λ ${job.lambda_value}` : ", λ map");
  }

  /** An <img> cannot read the status: ask again with fetch to say why it failed. */
  async explain(url) {
    try {
      const response = await request("GET", url);
      if (response.status === 204) this.el["viewer-info"].textContent = "no preview yet";
    } catch (error) {
      this.el["viewer-info"].textContent = error.detail || error.message;
      this.hooks.onError(error);
    }
  }

  place() {
    if (!this.size) return;
    const {w, h} = this.size;
    const view = this.el.viewport.getBoundingClientRect();
    const scale = this.zoom === "fit" ? Math.min(view.width / w, view.height / h) : this.zoom;
    const x = (view.width - w * scale) / 2 + this.pan.x;
    const y = (view.height - h * scale) / 2 + this.pan.y;
    const stage = this.el.stage;
    stage.style.width = `${w}px`;
    stage.style.height = `${h}px`;
    stage.style.transform = `translate(${x}px, ${y}px) scale(${scale})`;
    stage.dataset.scale = String(scale);
    const canvas = this.el.strokes;
    if (canvas.width !== w || canvas.height !== h) {
      canvas.width = w;
      canvas.height = h;
    }
  }

  placeSplit() {
    const position = Number(this.el["split-position"].value);
    this.el["image-b"].style.clipPath = `inset(0 0 0 ${position}%)`;
    this.el["split-line"].style.left = `${position}%`;
  }
}
