// One job: live status and progress, its learning curves (in the page and as the API's PNG),
// and its downloads (policy, curve CSV/JSON, results files and plots).

import { ApiError, all, get, imageUrl } from "../api.js";
import { lineChart, meanHalfStd } from "../chart.js";
import {
  SHORT_ID_CHARS, downloadButton, fmtBytes, fmtDateTime, h, localTimes, messageBox, shortId, statusBadge, table,
} from "../dom.js";
import { FINAL, progressBar, watchJob } from "../live.js";
import { jobActions, jobSteps, jobSummary } from "./jobs.js";

/** Links from a job to what it worked on: its session, recording, classifier. */
function workedOn(job, classifiers) {
  const c = job.config || {};
  const links = [];
  if (c.session_id) links.push(h("a", { href: `/sessions/${c.session_id}/live` }, `session ${c.session_id}`));
  if (c.recording_id) links.push(h("a", { href: `/recordings?recording=${c.recording_id}` }, `recording #${c.recording_id}`));
  for (const classifier of classifiers) {
    links.push(h("a", { href: `/classifiers/${classifier.id}` }, `classifier ${classifier.name}`));
  }
  return links.length ? links.flatMap((link, i) => (i ? [", ", link] : [link])) : null;
}

function facts(job, classifiers = []) {
  const made = workedOn(job, classifiers);
  const rows = [
    ["Id", shortId(job.id)],
    ["Kind", job.kind],
    ["What", jobSummary(job)],
    made ? ["Linked", made] : null,
    ["Attempts", `${job.attempts} of ${job.max_attempts}`],
    ["Steps done", jobSteps(job)],
    ["Resumed from step", job.resumed_from_step ?? "–"],
    ["Submitted", fmtDateTime(job.created_at)],
    ["Started", fmtDateTime(job.started_at)],
    ["Finished", fmtDateTime(job.finished_at)],
  ];
  return h("dl", { class: "facts" }, rows.filter(Boolean).map(([k, v]) => [h("dt", {}, k), h("dd", {}, v)]));
}

/** The job's events (GET /log): who submitted, cancelled, retried it; started; ended. */
async function history(job) {
  const log = await get(`/api/v1/jobs/${job.id}/log`);
  return table(log.items, [
    { label: "When", cell: (e) => fmtDateTime(e.at) },
    { label: "Event", cell: (e) => e.event },
    { label: "By", cell: (e) => e.actor_email || "–" },
    { label: "Detail", cell: (e) => localTimes(e.detail) || "–" },
  ], { caption: "History", empty: "No events." });
}

/** A figure from the API (PNG), fetched with the token. */
async function apiImage(path, alt) {
  try {
    return h("img", { src: await imageUrl(path), alt, class: "plot" });
  } catch (err) {
    if (err instanceof ApiError && err.status === 404) return h("p", { class: "muted" }, err.message);
    throw err;
  }
}

function hfLine(label, spl, xMax) {
  return { label, points: [[0, spl], [xMax, spl]], dashed: true };
}

/** Fig. 3 per task from a reproduction's runs: mean ± ½ std per configuration, pi_HF dashed. */
async function reproductionCharts(job) {
  const runs = await all("/api/v1/jobs", { parent_id: job.id });
  const curves = await Promise.all(runs.map(async (run) => {
    if (run.result?.curve) return run.result.curve;
    if (run.status === "queued") return [];
    return (await get(`/api/v1/jobs/${run.id}/curve`)).curve;
  }));
  const groups = new Map();
  runs.forEach((run, i) => {
    const c = run.config;
    const label = c.method === "hf_sparse"
      ? `${c.method} C=${c.accuracy}${c.hf_treatment && c.hf_treatment !== "authors" ? ` [${c.hf_treatment}]` : ""}`
      : c.method;
    const key = `${c.task}|${label}`;
    if (!groups.has(key)) groups.set(key, { task: c.task, method: c.method, label, curves: [], hf: [] });
    const group = groups.get(key);
    if (curves[i].length) group.curves.push(curves[i]);
    if (typeof run.result?.hf_policy_spl === "number") group.hf.push(run.result.hf_policy_spl);
  });
  const order = (g) => [["rl_sparse", "rl_rich", "hf_sparse"].indexOf(g.method), g.label];
  const sorted = [...groups.values()].sort((a, b) => {
    const [ma, la] = order(a);
    const [mb, lb] = order(b);
    return ma - mb || la.localeCompare(lb);
  });
  const tasks = [...new Set(sorted.map((g) => g.task))].sort();
  const done = runs.filter((r) => FINAL.has(r.status)).length;
  const figures = tasks.map((task) => {
    const members = sorted.filter((g) => g.task === task);
    const series = [];
    for (const g of members) {
      const { points, band } = meanHalfStd(g.curves);
      if (points.length) series.push({ label: `${g.label} (${g.curves.length} seeds)`, points, band, group: g });
    }
    const xMax = Math.max(1, ...series.flatMap((s) => s.points.map((p) => p[0])));
    series.forEach((s, i) => { s.colour = i; });
    members.forEach((g) => {
      const drawn = series.find((s) => s.group === g);
      if (g.hf.length) {
        const mean = g.hf.reduce((a, b) => a + b, 0) / g.hf.length;
        series.push({ ...hfLine(`π_HF ${g.label}`, mean, xMax), colour: drawn?.colour });
      }
    });
    return lineChart(series, { title: `${task.toUpperCase()}: SPL of greedy π_RL (mean ± ½ std; dashed: π_HF)` });
  });
  return [h("p", { class: "muted" }, `${done} of ${runs.length} run(s) finished.`), ...figures,
    table(runs, [
      { label: "Run", cell: (r) => shortId(r.id, `/jobs/${r.id}`) },
      { label: "What", cell: (r) => jobSummary(r) },
      { label: "Status", cell: (r) => statusBadge(r.status) },
      { label: "Progress", cell: (r) => progressBar(r) },
    ], { caption: "Runs" })];
}

/** Jobs that learn a policy: a learning curve (GET /curve) and its PNG (GET /plot.png). */
const hasCurve = (job) => job.kind === "guided_ppo" || job.kind === "reproduce_run";

async function curveSection(job, curve) {
  if (job.kind === "reproduce") return reproductionCharts(job);
  if (!hasCurve(job)) return [h("p", { class: "muted" }, `${job.kind} jobs have no learning curve.`)];
  if (!curve.length) return [h("p", { class: "muted" }, "No evaluation yet.")];
  const series = [{ label: "greedy π_RL", points: curve }];
  if (typeof job.result?.hf_policy_spl === "number") {
    series.push(hfLine("π_HF", job.result.hf_policy_spl, curve[curve.length - 1][0]));
  }
  return [lineChart(series, { title: `${jobSummary(job)}: SPL vs steps` })];
}

/** Which of a training job's two policies a file is: the best evaluation's (the job's
 *  model, what "Download model" gives) or the last step's. */
export function policyNote(job, artifact) {
  if (artifact.kind !== "model") return null;
  if (artifact.id === job.model_artifact_id || artifact.id === job.result?.model_artifact_id) {
    return h("span", { class: "badge best" }, "best evaluation: the job's model");
  }
  if (artifact.id === job.result?.last_model_artifact_id) return h("span", { class: "badge" }, "last step");
  return null;
}

async function downloads(job) {
  const artifacts = await all("/api/v1/artifacts", { job_id: job.id });
  const items = [];
  if (job.model_artifact_id && job.kind !== "eeg_calibration") {
    items.push(h("li", {}, "Trained policy (TorchScript; the best evaluation's, policy.pt) ",
      downloadButton("Download model", `/api/v1/jobs/${job.id}/model`, `policy-${job.id}.pt`)));
  }
  if (hasCurve(job)) {
    items.push(h("li", {}, "Learning curve ",
      downloadButton("CSV", `/api/v1/jobs/${job.id}/curve?format=csv`, `job-${job.id}-curve.csv`), " ",
      downloadButton("JSON", `/api/v1/jobs/${job.id}/curve`, `job-${job.id}-curve.json`)));
  }
  const files = table(artifacts, [
    { label: "File", cell: (a) => [a.relpath.split("/").pop(), " ", policyNote(job, a)] },
    { label: "Kind", cell: (a) => a.kind },
    { label: "Size", cell: (a) => fmtBytes(a.size_bytes) },
    { label: "SHA-256", cell: (a) => h("code", { title: a.sha256 }, `${a.sha256.slice(0, 12)}…`) },
    { label: "", cell: (a) => downloadButton("Download", `/api/v1/artifacts/${a.id}/download`, a.relpath.split("/").pop()) },
  ], { caption: "Files of this job", empty: "No files yet." });
  return [items.length ? h("ul", { class: "plain" }, items) : null, files];
}

async function plots(job, artifacts, curve) {
  if (hasCurve(job)) {
    // no evaluation yet (or a run that failed first): the API has no figure to draw
    if (!curve.length) return [h("p", { class: "muted" }, "The learning curve's PNG comes with its first evaluation.")];
    return [await apiImage(`/api/v1/jobs/${job.id}/plot.png`, `Learning curve of job ${job.id} (PNG from the API)`)];
  }
  const pngs = artifacts.filter((a) => a.relpath.endsWith(".png"));
  return Promise.all(pngs.map((a) => apiImage(`/api/v1/artifacts/${a.id}/download`, a.relpath.split("/").pop())));
}

export async function jobPage(root, { canEdit }, jobId) {
  let job = await get(`/api/v1/jobs/${jobId}`);
  document.title = `Job ${job.id.slice(0, SHORT_ID_CHARS)} · Brain-guided RL platform`;
  const message = messageBox();
  const bar = progressBar(job);
  const badge = h("span", {}, statusBadge(job.status));
  const error = h("p", { class: "message error", role: "alert", hidden: !job.error }, job.error || "");
  const actions = h("span", { class: "actions" });
  const classifiers = job.kind === "eeg_calibration"
    ? (await all("/api/v1/classifiers")).filter((c) => c.job_id === job.id) : [];
  const factBox = h("div", {}, facts(job, classifiers));
  const events = h("section", { "aria-label": "History" });
  const curves = h("section", { "aria-labelledby": "curves-title" });
  const files = h("section", { "aria-labelledby": "files-title" });
  const pngs = h("section", { "aria-labelledby": "png-title" });

  async function refreshResults() {
    const artifacts = await all("/api/v1/artifacts", { job_id: job.id });
    const curve = hasCurve(job) ? (await get(`/api/v1/jobs/${job.id}/curve`)).curve : [];
    curves.replaceChildren(h("h2", { id: "curves-title" }, "Learning curves"), ...(await curveSection(job, curve)));
    files.replaceChildren(h("h2", { id: "files-title" }, "Downloads"),
      ...(await downloads(job)).filter(Boolean));
    events.replaceChildren(await history(job));
    const images = await plots(job, artifacts, curve);
    pngs.replaceChildren(h("h2", { id: "png-title" }, "Figures from the API (PNG)"),
      ...(images.length ? images : [h("p", { class: "muted" }, "No figures yet.")]));
  }

  let refreshing = null;
  let lastRefresh = 0;
  /** Redraw the results every few seconds at most while the job runs, and when it ends. */
  function scheduleRefresh() {
    if (refreshing) return;
    const every = job.kind === "reproduce" ? 10_000 : 3000; // a sweep reads every run's curve
    const wait = FINAL.has(job.status) ? 0 : Math.max(0, lastRefresh + every - Date.now());
    refreshing = setTimeout(async () => {
      lastRefresh = Date.now();
      try {
        await refreshResults();
      } catch (err) {
        message.error(err);
      } finally {
        refreshing = null;
      }
    }, wait);
  }

  function update(next) {
    const changed = next.updated_at !== job.updated_at || next.status !== job.status;
    job = next;
    bar.set(job);
    badge.replaceChildren(statusBadge(job.status));
    error.hidden = !job.error;
    error.textContent = job.error || "";
    factBox.replaceChildren(facts(job, classifiers));
    actions.replaceChildren(...jobActions(job, canEdit, message, (changed) => {
      update(changed);
      if (!FINAL.has(changed.status)) stop = watchJob(changed.id, update);
    }));
    if (changed) scheduleRefresh();
  }

  root.append(
    h("p", { class: "crumbs" }, h("a", { href: "/jobs" }, "Jobs"), " / ", job.id.slice(0, SHORT_ID_CHARS),
      job.parent_id ? [" (run of ", shortId(job.parent_id, `/jobs/${job.parent_id}`), ")"] : ""),
    h("h1", {}, `Job ${job.id.slice(0, SHORT_ID_CHARS)} `, badge),
    h("div", { class: "inline" }, bar, actions),
    message,
    error,
    factBox,
    h("details", {}, h("summary", {}, "Configuration"), h("pre", {}, JSON.stringify(job.config, null, 2))),
    h("div", { class: "figures" }, curves, pngs),
    files,
    events,
  );
  let stop = FINAL.has(job.status) ? () => {} : watchJob(job.id, update);
  update(job);
  lastRefresh = Date.now();
  await refreshResults();
  window.addEventListener("pagehide", () => stop());
}
