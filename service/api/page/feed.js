// Live job status from the server-sent events (GET /jobs/{id}/events): one EventSource per
// unfinished job, at most MAX_STREAMS at once because a browser keeps only 6 connections per
// server over HTTP/1.1 and the previews and λ edits need the rest. A job not followed is seen
// again whenever a followed one ends (the list is reloaded then). Polling only where EventSource is missing.

import { api } from "./api.js";

const MAX_STREAMS = 2;
const POLL_MS = 1000;

export class JobFeed {
  /** onStatus(status) on every status event; onEnd(id) when a stream ends or is refused. */
  constructor({onStatus, onEnd}) {
    this.onStatus = onStatus;
    this.onEnd = onEnd;
    this.streams = new Map();  // id → EventSource, interval handle, or null while its signed URL is fetched
  }

  /** Follow these job ids (most wanted first); stop following the others. */
  follow(ids) {
    const wanted = new Set(ids.slice(0, MAX_STREAMS));
    for (const id of [...this.streams.keys()]) if (!wanted.has(id)) this.stop(id);
    for (const id of wanted) if (!this.streams.has(id)) this.start(id);
  }

  following(id) {
    return this.streams.has(id);
  }

  stopAll() {
    for (const id of [...this.streams.keys()]) this.stop(id);
  }

  stop(id) {
    const stream = this.streams.get(id);
    if (stream === undefined) return;
    if (typeof stream === "number") clearInterval(stream);
    else if (stream !== null) stream.close();
    this.streams.delete(id);
  }

  start(id) {
    if (typeof EventSource === "undefined") {
      this.streams.set(id, setInterval(() => this.poll(id), POLL_MS));
      return;
    }
    this.streams.set(id, null);
    api.eventsURL(id).then((url) => {
      if (this.streams.get(id) === null) this.open(id, url);  // else stopped meanwhile
    }, () => { if (this.streams.get(id) === null) this.finish(id); });
  }

  open(id, url) {
    const source = new EventSource(url);
    source.addEventListener("status", (event) => this.onStatus(JSON.parse(event.data)));
    source.addEventListener("end", () => this.finish(id));  // else EventSource reconnects
    source.addEventListener("error", () => {
      // CLOSED: refused (401, 404, 429; an expired link) and not retried; CONNECTING: the
      // browser retries itself. A finished stream is followed again with a fresh link.
      if (source.readyState === EventSource.CLOSED) this.finish(id);
    });
    this.streams.set(id, source);
  }

  finish(id) {
    this.stop(id);
    this.onEnd(id);
  }

  async poll(id) {
    try {
      const status = await api.job(id);
      this.onStatus(status);
      if (["completed", "failed", "canceled"].includes(status.state)) this.finish(id);
    } catch (_) {
      this.finish(id);
    }
  }
}
