// Steering λ: the slider sets one λ everywhere (debounced; only the newest value is sent), the
// brush paints rects over the current map, undo and clear re-send what is left. All go through
// one ordered channel to PUT /jobs/{id}/lambda; the server re-denoises from cached features and
// answers the preview version that shows the change.

import { api } from "./api.js";
import { Stroke, drawStrokes } from "./brush.js";

const DEBOUNCE_MS = 150;

/** Sends λ updates one at a time, in order. A global value replaces the whole map, so it
 * drops every update still waiting before it: under a burst only the newest value is sent. */
class LambdaChannel {
  constructor(onApplied, onError) {
    this.onApplied = onApplied;
    this.onError = onError;
    this.queue = [];
    this.busy = false;
  }

  reset() {
    this.queue = [];
  }

  value(jobId, value) {
    this.queue = [{jobId, body: {value}}];
    this.drain();
  }

  rects(jobId, rects, chunk) {
    for (let i = 0; i < rects.length; i += chunk) this.queue.push({jobId, body: {rects: rects.slice(i, i + chunk)}});
    this.drain();
  }

  async drain() {
    if (this.busy) return;
    this.busy = true;
    while (this.queue.length) {
      const {jobId, body} = this.queue.shift();
      try {
        const result = await api.setLambda(jobId, body);
        this.onApplied(jobId, result, body, this.queue.length === 0);
      } catch (error) {
        this.queue = this.queue.filter((item) => item.jobId !== jobId);  // the rest builds on what failed
        this.onError(error);
      }
    }
    this.busy = false;
  }

  get idle() {
    return !this.busy && this.queue.length === 0;
  }
}

export class LambdaControls {
  /** hooks: viewer, onError(error), onApplied(jobId, lambdaValue) */
  constructor(hooks) {
    this.hooks = hooks;
    this.el = Object.fromEntries(["lambda-slider", "lambda-value", "brush-size", "brush-value", "brush-undo",
      "brush-clear", "strokes"].map((id) => [id, document.getElementById(id)]));
    this.range = [1, 10];
    this.maxRects = 1024;
    this.job = null;
    this.strokes = [];  // painted since the last global λ, oldest first
    this.pending = [];  // strokes sent, not yet visible in the server's λ layer
    this.current = null;
    this.timer = null;
    this.channel = new LambdaChannel((jobId, result, body, last) => this.applied(jobId, result, body, last),
      (error) => hooks.onError(error));
    const slider = this.el["lambda-slider"];
    slider.addEventListener("input", () => {
      this.el["lambda-value"].textContent = slider.value;
      clearTimeout(this.timer);
      this.timer = setTimeout(() => this.setGlobal(Number(slider.value)), DEBOUNCE_MS);
    });
    this.el["brush-undo"].addEventListener("click", () => this.undo());
    this.el["brush-clear"].addEventListener("click", () => this.clear());
  }

  /** λ range and the rect cap from the server's schema (LambdaUpdate; models/lambda_range.py). */
  configure(schema) {
    const value = schema.properties && schema.properties.value;
    const bounds = value && (value.anyOf || [value]).find((s) => s.minimum !== undefined);
    if (bounds) this.range = [bounds.minimum, bounds.maximum];
    const rects = schema.properties && schema.properties.rects;
    const list = rects && (rects.anyOf || [rects]).find((s) => s.maxItems !== undefined);
    if (list) this.maxRects = list.maxItems;
    for (const id of ["lambda-slider", "brush-value"]) {
      this.el[id].min = this.range[0];
      this.el[id].max = this.range[1];
    }
  }

  /** The selected job (or null); λ steers only jobs that have rendered and can still change. */
  setJob(job) {
    const changed = !this.job || !job || job.id !== this.job.id;
    this.job = job;
    if (changed) {
      this.channel.reset();
      this.strokes = [];
      this.pending = [];
      this.redraw();
      const lam = job ? (job.lambda_value ?? job.spec.lambda ?? 1) : 1;
      this.el["lambda-slider"].value = lam;
      this.el["lambda-value"].textContent = String(lam);
    }
    const usable = Boolean(job) && job.preview_version > 0 && !["failed", "canceled"].includes(job.state);
    for (const id of ["lambda-slider", "brush-undo", "brush-clear"]) this.el[id].disabled = !usable;
    this.el["brush-undo"].disabled = !usable || this.strokes.length === 0;
  }

  usable() {
    return Boolean(this.job) && !this.el["lambda-slider"].disabled;
  }

  base() {
    return Number(this.el["lambda-slider"].value);
  }

  setGlobal(value) {
    if (!this.usable()) return;
    this.strokes = [];  // one λ everywhere replaces the painted map
    this.pending = [];
    this.redraw();
    this.channel.value(this.job.id, value);
    this.setJob(this.job);
  }

  // -- the brush (viewer.js calls these with image points) --

  begin(point) {
    if (!this.usable()) {
      this.hooks.onError(new Error("λ can be painted once the job has a preview (and while it is not canceled or failed)"));
      return;
    }
    const size = this.hooks.viewer.size;
    this.current = new Stroke(Number(this.el["brush-size"].value) || 1, this.brushValue(), size);
    this.current.to(point);
    this.redraw();
  }

  brushValue() {
    const value = Number(this.el["brush-value"].value);
    return Math.min(this.range[1], Math.max(this.range[0], Number.isFinite(value) ? value : this.range[1]));
  }

  move(point) {
    if (!this.current) return;
    this.current.to(point);
    this.redraw();
  }

  end() {
    const stroke = this.current;
    this.current = null;
    if (!stroke || stroke.rects.length === 0) return;
    this.strokes.push(stroke);
    this.pending.push(stroke);
    this.channel.rects(this.job.id, stroke.rects, this.maxRects);
    this.setJob(this.job);
  }

  undo() {
    if (!this.usable() || this.strokes.length === 0) return;
    this.strokes.pop();
    this.resend();
  }

  clear() {
    if (!this.usable()) return;
    this.strokes = [];
    this.resend();
  }

  /** The map again from the slider's λ and the strokes left (rects paint over, so start flat). */
  resend() {
    this.pending = [...this.strokes];
    this.redraw();
    this.channel.value(this.job.id, this.base());
    const rects = this.strokes.flatMap((stroke) => stroke.rects);
    if (rects.length) this.channel.rects(this.job.id, rects, this.maxRects);
    this.setJob(this.job);
  }

  applied(jobId, result, body, last) {
    if (!this.job || jobId !== this.job.id) return;
    const lambdaValue = body.value !== undefined ? body.value : null;
    if (last) this.hooks.onApplied(jobId, lambdaValue, result.version);
  }

  /** The viewer loaded a λ layer: strokes sent before it are now drawn by the server. */
  lambdaLoaded() {
    if (this.channel.idle) {
      this.pending = [];
      this.redraw();
    }
  }

  redraw() {
    drawStrokes(this.el.strokes, this.current ? [...this.pending, this.current] : this.pending, this.range);
  }
}
