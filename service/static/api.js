// Every request the viewer makes goes through apiFetch: once the server has answered 401 (LODCAST_TOKEN is set),
// the page asks for the token and sends it as `Authorization: Bearer` on every request from then on.

const KEY = "lodcast.token";
let asking = null; // one dialog for all the requests that met a 401 at once

export class ApiError extends Error {
  constructor(status, detail) {
    super(`${status}: ${detail}`);
    this.status = status;
    this.detail = detail;
  }
}

export function token() {
  return sessionStorage.getItem(KEY) || "";
}

function withToken(headers) {
  const h = new Headers(headers || {});
  const t = token();
  if (t) h.set("Authorization", `Bearer ${t}`);
  return h;
}

// The token dialog, one markup for every page that imports this module (added to the page as it loads).
const DIALOG = `<form method="dialog">
    <p>This server needs its access token (LODCAST_TOKEN).</p>
    <p id="token-wrong" class="error" hidden>That token was not accepted.</p>
    <input type="password" id="token-input" autocomplete="off" aria-label="token">
    <button value="ok" id="token-ok">use token</button>
    <button value="cancel" formnovalidate>cancel</button>
  </form>`;
if (!document.getElementById("token-dialog")) {
  const dialog = document.createElement("dialog");
  dialog.id = "token-dialog";
  dialog.innerHTML = DIALOG;
  document.body.append(dialog);
}

function askToken(wrong) {
  if (asking) return asking;
  const dialog = document.getElementById("token-dialog");
  const input = document.getElementById("token-input");
  document.getElementById("token-wrong").hidden = !wrong;
  input.value = "";
  asking = new Promise((resolve, reject) => {
    const done = () => {
      dialog.removeEventListener("close", done);
      asking = null;
      if (dialog.returnValue === "ok" && input.value.trim()) resolve(input.value.trim());
      else reject(new ApiError(401, "no token given: the server needs one (LODCAST_TOKEN)"));
    };
    dialog.addEventListener("close", done);
  });
  dialog.showModal();
  input.focus();
  return asking;
}

// fetch(url, opts) with the token; a 401 asks for the token (again, if the one sent was wrong) and retries.
export async function apiFetch(url, opts = {}) {
  for (;;) {
    const sent = token();
    const r = await fetch(url, { ...opts, headers: withToken(opts.headers) });
    if (r.status !== 401) return r;
    if (token() !== sent) continue; // another request's dialog got a new token meanwhile
    sessionStorage.setItem(KEY, await askToken(Boolean(sent)));
  }
}

export async function errorDetail(r) {
  try {
    const body = await r.json();
    const d = body.detail;
    if (Array.isArray(d)) return d.map((e) => e.msg || JSON.stringify(e)).join("; ");
    return typeof d === "string" ? d : JSON.stringify(body);
  } catch {
    return r.statusText;
  }
}

export async function apiJson(url, opts) {
  const r = await apiFetch(url, opts);
  if (!r.ok) throw new ApiError(r.status, await errorDetail(r));
  return r.json();
}
