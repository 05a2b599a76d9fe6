// Progressive renders (POST /volumes/{id}/render?progressive=true: NDJSON, one line per stage, coarse to fine).
// One Stream per page: its requests carry the page's X-Lodcast-Session, so the server stops rendering the stages
// still to come of the previous request as soon as a new one arrives; the page also aborts the previous fetch (a
// dropped connection cancels its stages too), so nothing superseded is read or shown.

import { apiFetch, errorDetail, ApiError } from "./api.js";

function sessionId() {
  if (crypto.randomUUID) return crypto.randomUUID();
  return Array.from(crypto.getRandomValues(new Uint8Array(16)), (b) => b.toString(16).padStart(2, "0")).join("");
}

export class Stream {
  constructor(volume) {
    this.url = `/volumes/${encodeURIComponent(volume)}/render?progressive=true`;
    this.session = sessionId();
    this.controller = null;
    this.serial = 0;
  }

  abort() {
    if (this.controller) this.controller.abort();
    this.controller = null;
  }

  // Render `scene` (at most `stages` of its stages: a preview asks for the first alone, so that no later stage
  // keeps a render slot after it); onStage(line) for each stage line while this is the newest request; resolves
  // when the stream ends (false when superseded or aborted), rejects with ApiError on a refusal or an error line.
  async run(scene, onStage, stages = null) {
    this.abort();
    const controller = new AbortController();
    this.controller = controller;
    const serial = ++this.serial;
    const current = () => serial === this.serial && !controller.signal.aborted;
    try {
      const r = await apiFetch(stages ? `${this.url}&stages=${stages}` : this.url, {
        method: "POST",
        body: JSON.stringify(scene),
        headers: { "Content-Type": "application/json", "X-Lodcast-Session": this.session },
        signal: controller.signal,
      });
      if (!r.ok) throw new ApiError(r.status, await errorDetail(r));
      const reader = r.body.getReader();
      const decoder = new TextDecoder();
      let buf = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (!current()) {
          reader.cancel().catch(() => {});
          return false;
        }
        buf += decoder.decode(value || new Uint8Array(), { stream: !done });
        let nl;
        while ((nl = buf.indexOf("\n")) >= 0) {
          const line = buf.slice(0, nl).trim();
          buf = buf.slice(nl + 1);
          if (!line) continue;
          const msg = JSON.parse(line);
          if (msg.error) throw new ApiError(msg.error.status, typeof msg.error.detail === "string" ? msg.error.detail : JSON.stringify(msg.error.detail));
          if ((await onStage(msg)) === false || !current()) {
            if (this.controller === controller) this.abort();
            return false;
          }
        }
        if (done) return current();
      }
    } catch (e) {
      if (e.name === "AbortError" || !current()) return false;
      throw e;
    } finally {
      if (this.controller === controller && serial === this.serial) this.controller = null;
    }
  }
}
