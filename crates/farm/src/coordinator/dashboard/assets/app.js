// Live updates and the preview's exposure. Every element with data-live="URL" is kept
// current by the server-sent events at URL: `jobs` events replace a table's rows, `job`
// events a job's status block (and reload the preview when its iteration or state moved).
"use strict";

function live(el) {
  const source = new EventSource(el.dataset.live);
  source.addEventListener("jobs", (e) => {
    el.querySelector("tbody").innerHTML = e.data;
  });
  source.addEventListener("job", (e) => {
    el.innerHTML = e.data;
    const mark = el.querySelector("[data-version]");
    const img = document.getElementById("preview");
    if (mark && img && img.dataset.version !== mark.dataset.version) {
      img.dataset.version = mark.dataset.version;
      img.src = img.src.split("?")[0] + "?v=" + encodeURIComponent(mark.dataset.version);
    }
    if (mark && !img && mark.dataset.preview === "true") {
      location.reload();
    }
  });
}

function exposure() {
  const range = document.getElementById("exposure");
  const img = document.getElementById("preview");
  if (!range || !img) return;
  const out = document.getElementById("ev");
  range.addEventListener("input", () => {
    img.style.filter = "brightness(" + Math.pow(2, Number(range.value)) + ")";
    out.textContent = range.value;
  });
}

document.addEventListener("DOMContentLoaded", () => {
  document.querySelectorAll("[data-live]").forEach(live);
  exposure();
});
