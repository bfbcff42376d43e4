// precimap's status dashboard: a read-only view of the REST API (reads need no token), plus
// cancelling a running campaign with the writer token. Every value from the server enters the
// page as text (textContent, attributes), never as markup: campaign names are user input.
"use strict";

const LIST_PERIOD_MS = 3000;
const DETAIL_PERIOD_MS = 2000;
const EVENTS_KEPT = 300;
const SVG_NS = "http://www.w3.org/2000/svg";
const ITERATING = ["estimate", "field", "solve", "accelerate", "combine"]; // the stages of one iteration

const $ = (id) => document.getElementById(id);

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v !== undefined && v !== null) node.setAttribute(k, v);
  }
  for (const c of children) node.append(c instanceof Node ? c : String(c));
  return node;
}

function svg(tag, attrs) {
  const node = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs || {})) node.setAttribute(k, v);
  return node;
}

async function getJson(path) {
  const response = await fetch(path, { headers: { Accept: "application/json" }, cache: "no-store" });
  const body = await response.json().catch(() => null);
  if (!response.ok) {
    throw new Error((body && body.error) || `${response.status} ${response.statusText}`);
  }
  return body;
}

// ---------------------------------------------------------------- formatting

function pad(n) {
  return String(n).padStart(2, "0");
}

function formatTime(ms) {
  const d = new Date(ms);
  return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
}

function formatDuration(ms) {
  const s = Math.max(0, Math.round(ms / 1000));
  if (s < 60) return `${s} s`;
  if (s < 3600) return `${Math.floor(s / 60)} min ${pad(s % 60)} s`;
  return `${Math.floor(s / 3600)} h ${pad(Math.floor((s % 3600) / 60))} min`;
}

// The tooltip of an iteration's field cell: the largest heading and tilt the field gave an
// anchor, where it solved them.
function fieldRotationTitle(it) {
  const parts = [];
  if (it.common_mode_heading_max_deg > 0) parts.push(`heading up to ${(1000 * it.common_mode_heading_max_deg).toFixed(2)} mdeg`);
  if (it.common_mode_tilt_max_deg > 0) parts.push(`tilt up to ${(1000 * it.common_mode_tilt_max_deg).toFixed(2)} mdeg`);
  return parts.length ? parts.join(", ") : null;
}

function mm(metres, digits) {
  return typeof metres === "number" ? `${(metres * 1000).toFixed(digits)} mm` : "–";
}

function cm(metres) {
  return typeof metres === "number" ? `${+(metres * 100).toFixed(1)} cm` : "–";
}

function count(n) {
  return typeof n === "number" ? n.toLocaleString("en-US") : "–";
}

function duration(c) {
  const end = c.finished_at_ms || (c.state === "running" ? Date.now() : null);
  return end ? formatDuration(end - c.created_at_ms) : "";
}

// ---------------------------------------------------------------- campaign list

let selected = null; // campaign id shown in the detail view

function stageLabel(c) {
  return ITERATING.includes(c.stage) ? `${c.stage} ${c.iteration}` : c.stage;
}

function renderList(campaigns) {
  const body = $("campaigns").tBodies[0];
  const rows = campaigns.map((c) => {
    const row = el(
      "tr",
      { "data-id": c.id, class: c.id === selected ? "selected" : null },
      el("td", {}, el("a", { href: `#${c.id}` }, c.name)),
      el("td", {}, el("span", { class: `state ${c.state}` }, c.state)),
      el("td", {}, stageLabel(c)),
      el("td", {}, iterationCell(c)),
      el("td", {}, formatTime(c.created_at_ms)),
      el("td", {}, duration(c)),
    );
    row.addEventListener("click", (e) => {
      if (e.target.tagName !== "A") location.hash = c.id;
    });
    return row;
  });
  body.replaceChildren(...rows);
  $("no-campaigns").hidden = campaigns.length > 0;
}

// The iteration meter only while iterating: before, nothing has run; after, the campaign's page
// lists every iteration (an early stop runs fewer than planned).
function iterationCell(c) {
  if (c.state !== "running" || !ITERATING.includes(c.stage)) return "";
  const planned = Math.max(1, c.iterations_planned);
  const meter = el("meter", { min: 0, max: planned, value: Math.min(c.iteration, planned), title: `iteration ${c.iteration} of at most ${planned}` });
  return el("span", { class: "iteration" }, meter, ` ${c.iteration}/${c.iterations_planned}`);
}

async function refreshList() {
  try {
    const [health, campaigns] = await Promise.all([getJson("/healthz"), getJson("/v1/campaigns?limit=200")]);
    $("health").textContent = `server ${health.status} · store ${health.store}`;
    $("health").className = "ok";
    renderList(campaigns);
    $("updated").textContent = `updated ${formatTime(Date.now())}`;
    document.body.dataset.listReady = "1";
  } catch (e) {
    $("health").textContent = `server unreachable: ${e.message}`;
    $("health").className = "error";
  }
}

// ---------------------------------------------------------------- one campaign

let detailTimer = null;
let lastEventId = 0;
let resultsShown = null;

function select(id) {
  if (detailTimer) clearTimeout(detailTimer);
  selected = id;
  lastEventId = 0;
  resultsShown = null;
  $("events").replaceChildren();
  $("results").hidden = true;
  $("qc").replaceChildren();
  $("result-list").replaceChildren();
  $("action-message").textContent = "";
  delete document.body.dataset.detailReady;
  for (const row of $("campaigns").tBodies[0].rows) {
    row.classList.toggle("selected", row.dataset.id === id);
  }
  $("detail").hidden = !id;
  if (id) refreshDetail();
}

function bar(node, counts) {
  const total = ["done", "leased", "queued", "dead", "cancelled"].reduce((s, k) => s + counts[k], 0);
  const parts = ["done", "leased", "queued", "dead", "cancelled"]
    .filter((k) => counts[k] > 0)
    .map((k) => {
      const part = el("span", { class: k, title: `${counts[k]} ${k}` });
      part.style.width = `${(100 * counts[k]) / total}%`;
      return part;
    });
  node.replaceChildren(...parts);
  return total;
}

function countsText(counts) {
  return ["done", "leased", "queued", "dead", "cancelled"]
    .filter((k) => counts[k] > 0)
    .map((k) => `${count(counts[k])} ${k === "leased" ? "running" : k}`)
    .join(" · ");
}

function renderStatus(s) {
  $("d-name").textContent = s.name;
  $("d-state").textContent = s.state;
  $("d-state").className = `state ${s.state}`;
  $("d-id").textContent = s.id;
  const finished = s.finished_at_ms ? ` · finished ${formatTime(s.finished_at_ms)}` : "";
  $("d-times").textContent = `submitted ${formatTime(s.created_at_ms)}${finished} · ${duration(s)}`;
  $("d-error").hidden = !s.error;
  $("d-error").textContent = s.error || "";
  $("cancel").hidden = s.state !== "running";

  $("d-stage").textContent = s.state === "running" ? stageLabel(s) : `${stageLabel(s)} (last)`;
  const stageTotal = bar($("stage-bar"), s.tasks.stage);
  $("stage-counts").textContent = `${countsText(s.tasks.stage)} of ${count(stageTotal)}`;
  const total = bar($("task-bar"), s.tasks);
  $("task-counts").textContent = `${countsText(s.tasks)} of ${count(total)}`;

  const rows = s.iterations.map((it, i) => {
    const used = it.points_in_tiles > 0 ? `${((100 * it.points_used) / it.points_in_tiles).toFixed(1)} %` : "–";
    return el(
      "tr",
      {},
      iterationNumber(it, i),
      el("td", {}, cm(it.grid_m)),
      el("td", {}, mm(it.threshold_m, it.threshold_m >= 0.1 ? 0 : 1)),
      el("td", {}, count(it.points_used)),
      el("td", {}, used),
      el("td", {}, mm(it.residual_std_m, 2)),
      // Where the largest change is (a tooltip: the place that keeps the campaign from converging).
      el(
        "td",
        { title: it.max_correction_change_at ? `${it.max_correction_change_at.trajectory} at ${Math.round(it.max_correction_change_at.along_m)} m` : null },
        mm(it.max_correction_change_m, 2),
      ),
      el("td", {}, mm(it.median_correction_change_m, 3)),
      // The field's largest shift; its largest heading and tilt (parameters.common_mode_heading,
      // common_mode_tilt) as a tooltip.
      el(
        "td",
        { title: fieldRotationTitle(it) },
        it.common_mode_field_max_m > 0 ? mm(it.common_mode_field_max_m, 2) : "–",
      ),
      el("td", {}, typeof it.seconds === "number" ? it.seconds.toFixed(1) : "–"),
    );
  });
  $("iterations").tBodies[0].replaceChildren(...rows);
  renderSigmaChart(s.iterations);
}

// An iteration that started from Anderson's combination of the settling iterations before it
// (parameters.anderson_depth) is marked, with the combination's coefficients as a tooltip.
function iterationNumber(it, i) {
  const number = it.iteration ?? i + 1;
  const coefficients = Array.isArray(it.anderson_coefficients) ? it.anderson_coefficients : [];
  if (coefficients.length === 0) return el("td", {}, number);
  const gammas = coefficients.map((g) => Number(g).toPrecision(3)).join(", ");
  const title = `started from Anderson's combination of the last ${coefficients.length + 1} iterations (γ = ${gammas})`;
  return el("td", {}, `${number} `, el("abbr", { class: "accelerated", title }, "A"));
}

// Residual σ and the outlier threshold per iteration on a log axis: the picture of convergence.
function renderSigmaChart(iterations) {
  const box = $("sigma-chart");
  const points = iterations.filter((it) => it.residual_std_m > 0 && it.threshold_m > 0);
  if (points.length === 0) {
    box.replaceChildren(el("p", { class: "muted" }, "after the first iteration"));
    return;
  }
  const width = 320, height = 140, left = 54, right = 8, top = 8, bottom = 22;
  const values = points.flatMap((it) => [it.residual_std_m, it.threshold_m]);
  const lo = Math.log10(Math.min(...values)) - 0.1;
  const hi = Math.log10(Math.max(...values)) + 0.1;
  const x = (i) => left + (points.length === 1 ? 0.5 : i / (points.length - 1)) * (width - left - right);
  const y = (v) => top + ((hi - Math.log10(v)) / (hi - lo)) * (height - top - bottom);
  const chart = svg("svg", { viewBox: `0 0 ${width} ${height}`, width, height, role: "img" });
  chart.append(svg("rect", { x: left, y: top, width: width - left - right, height: height - top - bottom, class: "frame" }));
  for (let e = Math.ceil(lo); e <= Math.floor(hi); e++) {
    const v = 10 ** e;
    chart.append(svg("line", { x1: left, x2: width - right, y1: y(v), y2: y(v), class: "grid" }));
    const label = svg("text", { x: left - 4, y: y(v) + 4, "text-anchor": "end" });
    label.textContent = v >= 1e-3 ? `${+(v * 1000).toFixed(0)} mm` : `${+(v * 1000).toFixed(1)} mm`;
    chart.append(label);
  }
  const line = (key, cls) => {
    const path = points.map((it, i) => `${x(i).toFixed(1)},${y(it[key]).toFixed(1)}`).join(" ");
    chart.append(svg("polyline", { points: path, class: cls }));
  };
  line("threshold_m", "threshold");
  line("residual_std_m", "sigma");
  const last = points[points.length - 1];
  const caption = svg("text", { x: left, y: height - 6 });
  caption.textContent = `σ ${(last.residual_std_m * 1000).toFixed(2)} mm · threshold ${(last.threshold_m * 1000).toFixed(1)} mm (dashed)`;
  chart.append(caption);
  box.replaceChildren(chart);
}

function renderEvents(events) {
  const list = $("events");
  for (const e of events) {
    lastEventId = Math.max(lastEventId, e.id);
    const task = e.task_id ? ` task ${e.task_id}` : "";
    list.prepend(
      el(
        "li",
        { class: `event ${e.kind}` },
        el("time", {}, formatTime(e.at_ms)),
        " ",
        el("strong", {}, e.kind),
        task,
        e.message ? ` — ${e.message}` : "",
      ),
    );
  }
  while (list.children.length > EVENTS_KEPT) list.lastElementChild.remove();
}

// QC plots first (convergence, residuals, then each trajectory's corrections), then every file.
function qcOrder(name) {
  if (name.endsWith("convergence.svg")) return 0;
  if (name.endsWith("residuals.svg")) return 1;
  return 2;
}

// Files at the top (report.json) as links, each folder (strips/, latent/: one file per tile…)
// folded under its name and count, so a campaign of thousands of tiles stays one screen.
function resultGroups(results) {
  const link = (r) => el("li", {}, el("a", { href: r.href, download: "" }, r.name));
  const folders = new Map();
  const files = [];
  for (const r of results) {
    const slash = r.name.indexOf("/");
    if (slash < 0) {
      files.push(link(r));
      continue;
    }
    const folder = r.name.slice(0, slash);
    if (!folders.has(folder)) folders.set(folder, []);
    folders.get(folder).push(r);
  }
  const groups = [...folders].map(([folder, members]) =>
    el(
      "li",
      {},
      el("details", { "data-folder": folder }, el("summary", {}, `${folder}/ (${members.length} files)`), el("ul", {}, ...members.map(link))),
    ),
  );
  return [...files, ...groups];
}

async function showResults(id) {
  const results = await getJson(`/v1/campaigns/${id}/results`);
  if (selected !== id) return;
  const plots = results
    .filter((r) => r.name.startsWith("qc/") && r.name.endsWith(".svg"))
    .sort((a, b) => qcOrder(a.name) - qcOrder(b.name) || a.name.localeCompare(b.name));
  $("qc").replaceChildren(
    ...plots.map((r) => {
      const img = el("img", { src: r.href, alt: r.name, loading: "eager" });
      img.addEventListener("load", () => (img.dataset.loaded = img.naturalWidth > 0 ? "1" : "0"));
      img.addEventListener("error", () => (img.dataset.loaded = "0"));
      return el("figure", {}, el("a", { href: r.href, target: "_blank", rel: "noopener" }, img), el("figcaption", {}, r.name));
    }),
  );
  $("result-list").replaceChildren(...resultGroups(results));
  $("results").hidden = false;
  resultsShown = id;
}

async function refreshDetail() {
  if (detailTimer) clearTimeout(detailTimer);
  const id = selected;
  if (!id) return;
  let running = true;
  try {
    const [status, events] = await Promise.all([
      getJson(`/v1/campaigns/${id}`),
      // Open with the newest events, then follow the log.
      getJson(`/v1/campaigns/${id}/events?${lastEventId ? `after=${lastEventId}&limit=1000` : `tail=${EVENTS_KEPT}`}`),
    ]);
    if (selected !== id) return;
    renderStatus(status);
    renderEvents(events.events);
    running = status.state === "running";
    if (status.state === "succeeded" && resultsShown !== id) await showResults(id);
    if (selected === id) document.body.dataset.detailReady = id;
  } catch (e) {
    if (selected !== id) return;
    $("d-error").hidden = false;
    $("d-error").textContent = `could not load campaign ${id}: ${e.message}`;
  }
  // A finished campaign does not change (except by deletion); poll it rarely.
  if (selected === id) detailTimer = setTimeout(refreshDetail, running ? DETAIL_PERIOD_MS : 10 * DETAIL_PERIOD_MS);
}

// ---------------------------------------------------------------- writing: cancel

async function cancelSelected() {
  const id = selected;
  const token = $("token").value.trim();
  const message = $("action-message");
  if (!token) {
    $("token-box").open = true;
    message.textContent = "Cancelling needs the server's writer token (PRECIMAP_TOKEN): enter it above.";
    return;
  }
  if (!confirm("Cancel this campaign? Its open tasks stop and it cannot be resumed.")) return;
  try {
    const response = await fetch(`/v1/campaigns/${id}/cancel`, {
      method: "POST",
      headers: { Authorization: `Bearer ${token}` },
    });
    const body = await response.json().catch(() => ({}));
    message.textContent = response.ok ? "cancelled" : `not cancelled: ${body.error || response.status}`;
  } catch (e) {
    message.textContent = `not cancelled: ${e.message}`;
  }
  refreshDetail();
}

// ---------------------------------------------------------------- start

function route() {
  const id = location.hash.replace(/^#/, "");
  select(/^[0-9a-f-]{36}$/i.test(id) ? id.toLowerCase() : null);
}

document.addEventListener("DOMContentLoaded", () => {
  $("token").value = sessionStorage.getItem("precimap-token") || "";
  $("token").addEventListener("change", () => sessionStorage.setItem("precimap-token", $("token").value.trim()));
  $("cancel").addEventListener("click", cancelSelected);
  $("routine").addEventListener("change", () => $("events").classList.toggle("hide-routine", !$("routine").checked));
  window.addEventListener("hashchange", route);
  route();
  refreshList();
  setInterval(refreshList, LIST_PERIOD_MS);
});
