// The job list: one row per job with its state, iteration, spp, predicted error and a
// progress bar toward its stopping rule; cancel, delete and download the EXR.

export const FINISHED = ["completed", "failed", "canceled"];

/** Fraction done toward the nearest stopping rule, or null when none says (target error only). */
export function progress(job) {
  if (job.state === "completed") return 1;
  const spec = job.spec || {};
  const fractions = [];
  if (spec.max_iterations) fractions.push(job.iteration / spec.max_iterations);
  if (spec.spp_budget) fractions.push(job.spp / spec.spp_budget);
  if (spec.time_limit && job.started_at) {
    const end = job.finished_at ? Date.parse(job.finished_at) : Date.now();
    fractions.push((end - Date.parse(job.started_at)) / 1000 / spec.time_limit);
  }
  if (fractions.length === 0) return job.state === "queued" ? 0 : null;
  return Math.min(1, Math.max(...fractions));
}

/** The job's name (the server's, else its scene), its size and frames. */
export function sceneName(job) {
  const spec = job.spec || {};
  const size = spec.width && spec.height ? ` ${spec.width}×${spec.height}` : "";
  const frames = spec.frames > 1 ? ` ×${spec.frames}f` : "";
  return `${job.name || spec.scene || "?"}${size}${frames}`;
}

/** Seconds left by the server's ETA, counted down to now; null when it has none. */
export function secondsLeft(job) {
  if (job.state !== "running" || job.eta_seconds === null || job.eta_seconds === undefined) return null;
  if (!job.eta_finish_at) return job.eta_seconds;
  return Math.max(0, (Date.parse(job.eta_finish_at) - Date.now()) / 1000);
}

export function etaText(job) {
  const left = secondsLeft(job);
  if (left === null) return job.state === "running" && job.eta_basis ? "ETA unknown" : "";
  if (left < 1) return "finishing";
  const minutes = Math.floor(left / 60);
  return minutes ? `~${minutes} min ${Math.round(left % 60)} s left` : `~${Math.ceil(left)} s left`;
}

function nameCell(job) {
  const td = document.createElement("td");
  if ((job.spec || {}).bundle_scene) {
    // a text badge, not an emoji: headless and minimal systems have no emoji font (a "tofu" box)
    const badge = document.createElement("span");
    badge.className = "badge";
    badge.textContent = "upload";
    badge.title = `uploaded bundle: ${job.spec.bundle_scene}`;
    td.append(badge);
  }
  td.append(sceneName(job));
  return td;
}

function cell(text, className) {
  const td = document.createElement("td");
  td.textContent = text;
  if (className) td.className = className;
  return td;
}

function button(label, action, title) {
  const b = document.createElement("button");
  b.type = "button";
  b.className = "small";
  b.textContent = label;
  b.dataset.action = action;
  b.title = title;
  return b;
}

function progressCell(job) {
  const td = document.createElement("td");
  const bar = document.createElement("progress");
  const fraction = progress(job);
  bar.max = 1;
  if (fraction !== null) bar.value = fraction;  // no value: the indeterminate bar
  bar.title = fraction === null ? "until the target error" : `${Math.round(fraction * 100)} %`;
  const eta = document.createElement("span");
  eta.className = "eta";
  eta.textContent = etaText(job);
  eta.title = job.eta_basis || "";
  td.append(bar, eta);
  return td;
}

function row(job, selected) {
  const tr = document.createElement("tr");
  tr.dataset.jobId = job.id;
  tr.dataset.state = job.state;
  tr.classList.toggle("selected", job.id === selected);
  const state = cell(job.state, `state ${job.state}`);
  if (job.error) state.title = job.error;
  if (job.stop_reason) state.title = job.stop_message || `stopped by ${job.stop_reason}`;
  const error = job.predicted_error === null ? "—" : job.predicted_error.toFixed(4);
  tr.append(cell(job.id.slice(0, 8), "mono"), nameCell(job), state, cell(String(job.iteration), "num"),
            cell(job.spp.toFixed(1), "num"), cell(error, "num"), progressCell(job));
  const actions = document.createElement("td");
  actions.className = "actions";
  if (!FINISHED.includes(job.state)) actions.append(button("Cancel", "cancel", "stop after the current chunk"));
  if (job.state === "completed" || job.state === "canceled") actions.append(button("EXR", "download", "download result.exr"));
  actions.append(button("Delete", "delete", "cancel if running, then remove the job and its files"));
  tr.append(actions);
  return tr;
}

export class JobTable {
  /** onSelect(id), onAction(action, id) */
  constructor(table, empty, {onSelect, onAction}) {
    this.body = table.querySelector("tbody");
    this.empty = empty;
    this.jobs = new Map();
    this.selected = null;
    this.body.addEventListener("click", (event) => {
      const tr = event.target.closest("tr[data-job-id]");
      if (!tr) return;
      const action = event.target.closest("button[data-action]");
      if (action) onAction(action.dataset.action, tr.dataset.jobId);
      else onSelect(tr.dataset.jobId);
    });
  }

  setAll(jobs) {
    this.jobs = new Map(jobs.map((job) => [job.id, job]));
    this.render();
  }

  update(job) {
    if (!this.jobs.has(job.id)) return false;
    this.jobs.set(job.id, job);
    const old = this.body.querySelector(`tr[data-job-id="${CSS.escape(job.id)}"]`);
    if (old) old.replaceWith(row(job, this.selected));
    return true;
  }

  remove(id) {
    this.jobs.delete(id);
    this.render();
  }

  select(id) {
    this.selected = id;
    this.render();
  }

  get(id) {
    return this.jobs.get(id);
  }

  /** Unfinished jobs, the selected one first, then running before queued. */
  live() {
    const rank = (job) => (job.id === this.selected ? 0 : job.state === "running" ? 1 : 2);
    return [...this.jobs.values()].filter((job) => !FINISHED.includes(job.state))
      .sort((a, b) => rank(a) - rank(b)).map((job) => job.id);
  }

  render() {
    this.body.replaceChildren(...[...this.jobs.values()].map((job) => row(job, this.selected)));
    this.empty.hidden = this.jobs.size > 0;
  }

  /** Count the running jobs' ETAs down between their status events. */
  tick() {
    for (const tr of this.body.querySelectorAll("tr[data-state=running]")) {
      const job = this.jobs.get(tr.dataset.jobId);
      const eta = tr.querySelector(".eta");
      if (job && eta) eta.textContent = etaText(job);
    }
  }
}
