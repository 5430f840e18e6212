// The page's wiring: load the schema, scenes and jobs; follow the live jobs' events; route
// selections, actions, λ edits and 401s between the parts.

import { api, onUnauthorized, setToken, token } from "./api.js";
import { JobFeed } from "./feed.js";
import { JobTable, etaText } from "./jobs.js";
import { LambdaControls } from "./lambda.js";
import { clearErrors, showError, showNote } from "./messages.js";
import { SubmitForm } from "./submit.js";
import { Viewer } from "./viewer.js";

let selected = null;
const ETA_TICK_MS = 1000;

const tokenForm = document.getElementById("token-form");
const tokenInput = document.getElementById("token-input");

function askForToken(error) {
  const label = tokenForm.querySelector("label");
  label.textContent = token() ? "The token was refused; enter the right one" : "This server needs a token";
  tokenForm.title = error.detail;
  if (tokenForm.hidden) {
    tokenForm.hidden = false;
    tokenInput.focus();
  }
}

/** Every failure ends here: a 401 opens the token field, anything else is shown as said. */
function fail(error, context) {
  if (error && error.status === 401) return;  // askForToken (onUnauthorized) says it
  console.error(error);
  showError(error, context);
}

const lambda = new LambdaControls({
  get viewer() { return viewer; },
  onError: (error) => fail(error, "λ"),
  onApplied: (jobId, lambdaValue, version) => {
    const job = table.get(jobId);
    if (job) {
      const updated = {...job, lambda_value: lambdaValue, preview_version: Math.max(job.preview_version, version)};
      table.update(updated);
      viewer.update(updated);
    }
    viewer.showVersion(version);
  },
});

const viewer = new Viewer({
  onError: (error) => fail(error, "preview"),
  onStroke: lambda,
  onLambdaLoaded: () => lambda.lambdaLoaded(),
});

const table = new JobTable(document.getElementById("jobs-table"), document.getElementById("jobs-empty"), {
  onSelect: (id) => select(id),
  onAction: (action, id) => act(action, id).catch((error) => fail(error, `${action} ${id.slice(0, 8)}`)),
});

const feed = new JobFeed({
  onStatus: (status) => {
    if (!table.update(status)) refreshJobs();
    if (status.id === selected) {
      viewer.update(status);
      lambda.setJob(status);
      summarize(status);
    }
  },
  onEnd: () => refreshJobs(),
});

const form = new SubmitForm(document.getElementById("submit-form"), {
  onSubmitted: async (created) => {
    clearErrors();
    showNote(`job ${created.id.slice(0, 8)} ${created.state}`);
    selected = created.id;
    await refreshJobs();
  },
  onError: (error) => fail(error, "submit"),
});

function select(id) {
  selected = id;
  table.select(id);
  const job = table.get(id) || null;
  viewer.show(job);
  lambda.setJob(job);
  summarize(job);
  feed.follow(table.live());
}

/** The selected job in words: its name, seed and parameters, its ETA or why it stopped. */
function summarize(job) {
  const line = document.getElementById("job-summary");
  if (!job) {
    line.textContent = "";
    return;
  }
  const spec = job.spec || {};
  const params = Object.entries(spec.params || {}).map(([name, value]) => `${name}=${value}`).join(" ");
  const parts = [job.name || spec.scene, `seed ${spec.seed ?? 0}`];
  if (params) parts.push(params);
  const eta = etaText(job);
  if (eta) parts.push(eta);
  if (job.stop_message) parts.push(job.stop_message);
  else if (job.error) parts.push(job.error);
  line.textContent = parts.join(" · ");
  line.title = job.eta_basis || "";
}

function tick() {
  table.tick();
  const job = selected ? table.get(selected) : null;
  if (job && job.state === "running") summarize(job);
}

/** GET /info's device and variant in the header; a server without it still loads the page. */
async function showServer() {
  const element = document.getElementById("server-info");
  try {
    const info = await api.info();
    element.textContent = `${info.device} · ${info.variant}`;
    element.title = info.summary;
  } catch (error) {
    if (error && error.status === 401) throw error;  // the token field asks; loadAll reruns
    element.textContent = "";
    console.warn("no server info", error);
  }
}

async function refreshJobs() {
  try {
    const {jobs} = await api.jobs();
    table.setAll(jobs);
    if (selected && !table.get(selected)) selected = null;
    if (!selected && jobs.length) selected = jobs[0].id;
    const job = selected ? table.get(selected) : null;
    table.select(selected);
    if (!job || !viewer.job || viewer.job.id !== job.id) viewer.show(job);
    else viewer.update(job);
    lambda.setJob(job);
    summarize(job);
    feed.follow(table.live());
  } catch (error) {
    fail(error, "job list");
  }
}

async function download(id) {
  const frame = id === selected ? viewer.frame() : 0;
  const response = await api.result(id, frame);
  const blob = await response.blob();
  const disposition = response.headers.get("content-disposition") || "";
  const match = disposition.match(/filename="?([^";]+)"?/);
  const link = document.createElement("a");
  link.href = URL.createObjectURL(blob);
  link.download = match ? match[1] : `${id}_frame${String(frame).padStart(3, "0")}.exr`;
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(link.href), 10000);
}

async function act(action, id) {
  if (action === "cancel") {
    const status = await api.cancel(id);
    table.update(status);
    showNote(`job ${id.slice(0, 8)} ${status.state}`);
  } else if (action === "delete") {
    feed.stop(id);
    await api.remove(id);
    table.remove(id);
    showNote(`job ${id.slice(0, 8)} deleted`);
  } else if (action === "download") {
    await download(id);
    return;
  }
  await refreshJobs();
}

async function loadAll() {
  try {
    const schema = await api.openapi();
    const schemas = schema.components.schemas;
    form.configure(schemas.JobCreate);
    lambda.configure(schemas.LambdaUpdate);
    form.setScenes((await api.scenes()).scenes);
    await showServer();
    tokenForm.hidden = true;
    await refreshJobs();
  } catch (error) {
    fail(error, "loading");
  }
}

function bindTools() {
  document.querySelectorAll("#tool-buttons button").forEach((button) => button.addEventListener("click", () => {
    document.querySelectorAll("#tool-buttons button").forEach((b) => b.classList.toggle("active", b === button));
    viewer.setTool(button.dataset.tool);
  }));
  document.getElementById("jobs-refresh").addEventListener("click", () => refreshJobs());
  // Jobs submitted elsewhere (CLI, scripts) have no stream here yet: look again on coming back.
  document.addEventListener("visibilitychange", () => {
    if (document.visibilityState === "visible") refreshJobs();
  });
  tokenForm.addEventListener("submit", (event) => {
    event.preventDefault();
    setToken(tokenInput.value.trim());
    tokenInput.value = "";
    clearErrors();
    feed.stopAll();  // streams opened without the token were refused
    loadAll();
  });
}

onUnauthorized(askForToken);
bindTools();
setInterval(tick, ETA_TICK_MS);
viewer.show(null);
lambda.setJob(null);
loadAll();
