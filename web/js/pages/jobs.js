// Jobs: submit (staff), a list with live progress, cancel and retry.

import { get, post } from "../api.js";
import { fmtShort, h, messageBox, oneAtATime, SHORT_ID_CHARS, shortId, statusBadge } from "../dom.js";
import { FINAL, progressBar, watchJob } from "../live.js";
import { jobForm, jobKinds } from "./jobform.js";

const PAGE = 50;
const LIST_REFRESH_MS = 15_000;
const STATUSES = ["queued", "running", "succeeded", "failed", "cancelled"];

/** One line saying what a job runs: its kind's summary, which the API sends. */
export function jobSummary(job) {
  return job.summary ?? "";
}

/** Kinds whose progress is environment steps (the others: "–" under Steps). */
const STEP_KINDS = new Set(["guided_ppo", "reproduce", "reproduce_run", "reproduce_batch"]);

/** A job's steps as the list shows them. */
export function jobSteps(job) {
  return STEP_KINDS.has(job.kind) ? job.steps_done.toLocaleString("en") : "–";
}

/** Cancel / Retry buttons for a job (staff), reporting in ``message``. */
export function jobActions(job, canEdit, message, onChange) {
  if (!canEdit) return [];
  const buttons = [];
  if (!FINAL.has(job.status)) {
    const cancel = h("button", { type: "button", class: "btn small danger" }, "Cancel");
    cancel.addEventListener("click", oneAtATime([cancel], async () => {
      try {
        const changed = await post(`/api/v1/jobs/${job.id}/cancel`);
        message.show(`Cancel requested for job ${job.id.slice(0, SHORT_ID_CHARS)}.`);
        onChange(changed);
      } catch (err) {
        message.error(err);
      }
    }));
    buttons.push(cancel);
  } else if ((job.status === "failed" || job.status === "cancelled") && !job.parent_id) {
    const retry = h("button", { type: "button", class: "btn small" }, "Retry");
    retry.addEventListener("click", oneAtATime([retry], async () => {
      try {
        const changed = await post(`/api/v1/jobs/${job.id}/retry`);
        message.show(`Job ${job.id.slice(0, SHORT_ID_CHARS)} queued again.`);
        onChange(changed);
      } catch (err) {
        message.error(err);
      }
    }));
    buttons.push(retry);
  }
  return buttons;
}

/** The values of a new job's config given in the address (``/jobs?new=session_replay&
 *  session_id=7``, the links from a session's page): the kind's top-level fields, as numbers
 *  where the schema says so. */
function prefill(kind, query) {
  const values = {};
  for (const [name, prop] of Object.entries(kind?.config_schema?.properties || {})) {
    const text = query.get(name);
    if (text === null) continue;
    const types = [prop.type, ...(prop.anyOf || []).map((p) => p.type)];
    values[name] = types.includes("integer") || types.includes("number") ? Number(text) : text;
  }
  return values;
}

export async function jobsPage(root, { canEdit, query }) {
  document.title = "Jobs · Brain-guided RL platform";
  const kinds = await jobKinds();
  const status = h("select", { id: "filter-status", name: "status" },
    h("option", { value: "" }, "any"), STATUSES.map((s) => h("option", { value: s, selected: query.get("status") === s }, s)));
  const kind = h("select", { id: "filter-kind", name: "kind" },
    h("option", { value: "" }, "any"), kinds.map((k) => h("option", { value: k.name, selected: query.get("kind") === k.name }, k.name)));
  const message = messageBox();
  const tbody = h("tbody");
  const caption = h("caption");
  const watchers = new Map();
  let offset = 0;
  const pager = h("div", { class: "pager" });

  function row(job) {
    const bar = progressBar(job);
    const badge = h("td", {}, statusBadge(job.status));
    const steps = h("td", { class: "num" }, jobSteps(job));
    const actions = h("td");
    const tr = h("tr", { "data-job": job.id },
      h("td", {}, shortId(job.id, `/jobs/${job.id}`),
        h("div", { class: "muted small" }, job.kind),
        job.parent_id ? h("div", { class: "muted small" }, "run of ",
          shortId(job.parent_id, `/jobs/${job.parent_id}`)) : ""),
      h("td", {}, jobSummary(job)),
      badge,
      h("td", {}, bar),
      steps,
      h("td", { class: "when" }, fmtShort(job.created_at)),
      actions);
    const update = (j) => {
      bar.set(j);
      badge.replaceChildren(statusBadge(j.status));
      steps.textContent = jobSteps(j);
      actions.replaceChildren(...jobActions(j, canEdit, message, (changed) => {
        update(changed);
        watch(changed, update);
      }));
    };
    update(job);
    watch(job, update);
    return tr;
  }

  function watch(job, update) {
    if (FINAL.has(job.status) || watchers.has(job.id)) return;
    watchers.set(job.id, watchJob(job.id, (j) => {
      update(j);
      if (FINAL.has(j.status)) watchers.delete(j.id);
    }));
  }

  async function load() {
    for (const stop of watchers.values()) stop();
    watchers.clear();
    const page = await get("/api/v1/jobs", { status: status.value, kind: kind.value, limit: PAGE, offset });
    caption.textContent = `${page.total} job(s)`;
    tbody.replaceChildren(...page.items.map(row));
    const prev = h("button", { type: "button", class: "btn small", disabled: offset === 0 }, "Newer");
    const next = h("button", { type: "button", class: "btn small", disabled: offset + PAGE >= page.total }, "Older");
    prev.addEventListener("click", () => { offset = Math.max(0, offset - PAGE); load(); });
    next.addEventListener("click", () => { offset += PAGE; load(); });
    pager.replaceChildren(...(page.total > PAGE ? [prev, " ", next] : []));
  }
  /** The filters in the address, so a reload, a shared link or Back shows the same list. */
  function remember() {
    const params = new URLSearchParams();
    if (status.value) params.set("status", status.value);
    if (kind.value) params.set("kind", kind.value);
    const search = params.toString();
    history.replaceState(null, "", `/jobs${search ? `?${search}` : ""}`);
  }
  status.addEventListener("change", () => { offset = 0; remember(); load(); });
  kind.addEventListener("change", () => { offset = 0; remember(); load(); });

  const list = h("section", { class: "wide scroll-x" },
    h("div", { class: "inline" },
      h("label", { for: "filter-status" }, "Status"), status,
      h("label", { for: "filter-kind" }, "Kind"), kind),
    message,
    h("table", { class: "grid", id: "jobs-table" }, caption,
      h("thead", {}, h("tr", {}, ["Job", "What", "Status", "Progress", "Steps", "Submitted", ""]
        .map((label) => h("th", { scope: "col" }, label)))),
      tbody),
    pager);
  let form = null;
  if (canEdit) {
    const asked = kinds.find((k) => k.submittable && k.name === query.get("new"));
    form = h("aside", {}, await jobForm(kinds, {
      kind: asked?.name, values: prefill(asked, query),
      onSubmitted(job, note) {
        offset = 0;
        status.value = "";
        kind.value = "";
        remember();
        load();
        note.show(`Job ${job.id.slice(0, SHORT_ID_CHARS)} queued: `);
        note.append(h("a", { href: `/jobs/${job.id}` }, "follow it"), ".");
        message.show(`Job ${job.id.slice(0, SHORT_ID_CHARS)} submitted.`);
      },
    }));
  }
  root.append(h("h1", {}, "Jobs"), h("div", { class: "columns" }, list, form));
  await load();
  if (form && query.get("new")) form.querySelector("#job-form")?.scrollIntoView();
  // jobs submitted elsewhere (other users, scripts) appear within LIST_REFRESH_MS
  const refresh = setInterval(async () => {
    try {
      const page = await get("/api/v1/jobs", { status: status.value, kind: kind.value, limit: PAGE, offset });
      const shown = [...tbody.querySelectorAll("tr[data-job]")].map((tr) => tr.dataset.job).join();
      if (page.items.map((j) => j.id).join() !== shown) await load();
    } catch {
      // the next round tries again
    }
  }, LIST_REFRESH_MS);
  window.addEventListener("pagehide", () => {
    clearInterval(refresh);
    for (const stop of watchers.values()) stop();
  });
}
