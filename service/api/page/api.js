// The HTTP API as the page uses it: the bearer token on every fetch, and every refusal turned
// into an ApiError carrying the server's message. Where a browser cannot send headers
// (EventSource, <img>) the page asks GET /jobs/{id}/links for short-lived signed URLs: the
// token never goes into a URL (the server refuses it there).

const TOKEN_KEY = "renderloop.token";

export class ApiError extends Error {
  constructor(status, detail) {
    super(`${status} ${statusText(status)}: ${detail}`);
    this.status = status;
    this.detail = detail;
  }
}

function statusText(status) {
  const names = {400: "bad request", 401: "token needed", 404: "not found", 409: "not now",
                 413: "too large", 415: "wrong content type", 422: "invalid input"};
  return names[status] || (status >= 500 ? "server error" : "refused");
}

let tokenListeners = [];

export function token() {
  return sessionStorage.getItem(TOKEN_KEY) || "";
}

export function setToken(value) {
  if (value) sessionStorage.setItem(TOKEN_KEY, value);
  else sessionStorage.removeItem(TOKEN_KEY);
  forgetLinks();
}

/** `listener(error)` runs on every 401, so the page can ask for a (new) token. */
export function onUnauthorized(listener) {
  tokenListeners.push(listener);
}

async function errorOf(response) {
  let detail = response.statusText || "no message";
  try {
    const body = await response.json();
    if (body && body.detail !== undefined) detail = typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail);
  } catch (_) { /* not JSON: keep the status text */ }
  return new ApiError(response.status, detail);
}

/** fetch() with the token; resolves to the Response for 2xx/3xx, throws ApiError otherwise. */
export async function request(method, path, {json, form} = {}) {
  const headers = {};
  const t = token();
  if (t) headers["Authorization"] = `Bearer ${t}`;
  let body;
  if (json !== undefined) {
    headers["Content-Type"] = "application/json";
    body = JSON.stringify(json);
  } else if (form !== undefined) {
    body = form;  // the browser sets multipart/form-data with its boundary
  }
  let response;
  try {
    response = await fetch(path, {method, headers, body, cache: "no-store"});
  } catch (err) {
    throw new ApiError(0, `the server cannot be reached (${err.message})`);
  }
  if (response.ok || response.status === 304) return response;
  const error = await errorOf(response);
  if (error.status === 401) tokenListeners.forEach((listener) => listener(error));
  throw error;
}

export async function getJSON(path) {
  return (await request("GET", path)).json();
}

export async function sendJSON(method, path, json) {
  const response = await request(method, path, {json});
  return response.status === 204 ? null : response.json();
}

// Signed links are reused until this close to their expiry (seconds), then asked for again.
const LINK_MARGIN_S = 60;
const links = new Map();  // job id → Promise of {events, preview, expires}

function freshLinks(id) {
  const cached = links.get(id);
  if (cached) return cached;
  const pending = getJSON(`/jobs/${encodeURIComponent(id)}/links`).then((answer) => {
    // A null expiry: the server has no token and its links never expire.
    const ttl = answer.expires === null ? Infinity : (answer.expires - Date.now() / 1000 - LINK_MARGIN_S) * 1000;
    if (ttl !== Infinity) setTimeout(() => { if (links.get(id) === pending) links.delete(id); }, Math.max(ttl, 0));
    return answer;
  });
  links.set(id, pending);
  pending.catch(() => { if (links.get(id) === pending) links.delete(id); });
  return pending;
}

/** Forget every signed link (the token changed: they were signed under the old one). */
export function forgetLinks() {
  links.clear();
}

/** A URL for elements that cannot send headers: the job's signed link plus `params`. */
export async function browserURL(id, kind, params = {}) {
  const url = new URL((await freshLinks(id))[kind], window.location.href);
  for (const [name, value] of Object.entries(params)) url.searchParams.set(name, value);
  return url.pathname + url.search;
}

export const api = {
  scenes: () => getJSON("/scenes"),
  info: () => getJSON("/info"),
  openapi: () => getJSON("/openapi.json"),
  jobs: () => getJSON("/jobs?limit=200"),
  job: (id) => getJSON(`/jobs/${encodeURIComponent(id)}`),
  submitJSON: (spec) => sendJSON("POST", "/jobs", spec),
  submitBundle: async (spec, zip) => {
    const form = new FormData();
    form.append("spec", JSON.stringify(spec));
    form.append("bundle", zip, zip.name || "scene.zip");
    return (await request("POST", "/jobs", {form})).json();
  },
  cancel: (id) => sendJSON("POST", `/jobs/${encodeURIComponent(id)}/cancel`),
  remove: (id) => sendJSON("DELETE", `/jobs/${encodeURIComponent(id)}`),
  setLambda: (id, body) => sendJSON("PUT", `/jobs/${encodeURIComponent(id)}/lambda`, body),
  result: (id, frame) => request("GET", `/jobs/${encodeURIComponent(id)}/result.exr?frame=${frame}`),
  eventsURL: (id) => browserURL(id, "events"),
  previewURL: (id, params) => browserURL(id, "preview", params),
};
