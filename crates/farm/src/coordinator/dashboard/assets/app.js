// Live updates and the preview's exposure. Every element with data-live="URL" is kept
// current by the server-sent events at URL: `jobs` events replace a table's rows, `job`
// events a job's status block (and reload the preview when its iteration or state moved),
// `iterations` and `log` events its iterations' chart and table and its last log lines.
"use strict";

function live(el) {
  const source = new EventSource(el.dataset.live);
  source.addEventListener("jobs", (e) => {
    el.querySelector("tbody").innerHTML = e.data;
  });
  source.addEventListener("workers", (e) => {
    el.innerHTML = e.data;
  });
  for (const part of ["iterations", "log"]) {
    source.addEventListener(part, (e) => {
      const section = document.getElementById(part);
      if (!section) return;
      section.innerHTML = e.data;
      const pre = section.querySelector("pre");
      if (pre) pre.scrollTop = pre.scrollHeight;
    });
  }
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

// Clicking the preview asks for the guide's picture at the pixel clicked.
function guideOnClick() {
  const img = document.getElementById("preview");
  const guide = document.getElementById("guide");
  if (!img || !guide) return;
  const caption = document.getElementById("guide-caption");
  const names = document.getElementById("guide-names");
  img.addEventListener("click", (e) => {
    const x = Math.floor(e.offsetX * img.naturalWidth / img.clientWidth);
    const y = Math.floor(e.offsetY * img.naturalHeight / img.clientHeight);
    const url = "/jobs/" + encodeURIComponent(guide.dataset.job) + "/guide.png?x=" + x + "&y=" + y;
    caption.textContent = "Pixel " + x + ", " + y + ": loading the guide...";
    fetch(url).then((r) => {
      if (!r.ok) return r.text().then((t) => { throw new Error(t); });
      return r.blob();
    }).then((b) => {
      if (guide.src.startsWith("blob:")) URL.revokeObjectURL(guide.src);
      guide.src = URL.createObjectURL(b);
      guide.hidden = false;
      names.hidden = false;
      caption.textContent = "Pixel " + x + ", " + y + ":";
    }).catch((err) => {
      guide.hidden = true;
      names.hidden = true;
      caption.textContent = "Pixel " + x + ", " + y + ": " + err.message;
    });
  });
}

document.addEventListener("DOMContentLoaded", () => {
  document.querySelectorAll("[data-live]").forEach(live);
  exposure();
  guideOnClick();
});
