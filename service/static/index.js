// The volume list (GET /volumes), each linked to its viewer.

import { apiJson, ApiError } from "./api.js";

const cell = (text) => {
  const td = document.createElement("td");
  td.textContent = text;
  return td;
};

async function main() {
  const body = document.getElementById("volumes");
  try {
    const volumes = await apiJson("/volumes");
    body.replaceChildren();
    for (const v of volumes) {
      const tr = document.createElement("tr");
      const name = document.createElement("td");
      const a = document.createElement("a");
      a.href = `/volumes/${encodeURIComponent(v.id)}/view`;
      a.textContent = v.id;
      name.append(a);
      tr.append(name);
      if (v.error) {
        const td = cell(v.error);
        td.colSpan = 4;
        td.className = "error";
        tr.append(td);
      } else {
        const mb = (v.bytes_on_disk / 1e6).toFixed(1);
        const range = v.value_range.map((x) => (x === null ? "–" : String(Number(x.toPrecision(5)))));
        tr.append(cell(v.shape.join(" × ")), cell(v.dtype), cell(range.join(" … ")), cell(`${mb} MB`));
      }
      body.append(tr);
    }
    if (!volumes.length) body.replaceChildren(Object.assign(document.createElement("tr"), { innerHTML: '<td colspan="5">no volumes under the store root yet: <code>lodcast ingest SRC ROOT/NAME</code></td>' }));
  } catch (e) {
    const s = document.getElementById("status");
    s.textContent = e instanceof ApiError ? `${e.status}: ${e.detail}` : String(e);
    s.className = "error";
  }
}

main();
