// Admin pages (admin role; the navigation hides them from others and the API refuses them):
// user accounts, rigs with their channel maps, and the audit log.

import { all, get, patch, post } from "../api.js";
import { field, fmtDateTime, h, messageBox, oneAtATime, showRefusal, table } from "../dom.js";
import { shownOnce } from "./account.js";

const ROLES = ["viewer", "staff", "admin"];
const PASSWORD_ALPHABET = "abcdefghijkmnpqrstuvwxyzABCDEFGHJKLMNPQRSTUVWXYZ23456789";
const ONE_TIME_PASSWORD_CHARS = 16;

/** A random password from the browser's CSPRNG (no look-alike characters). */
export function oneTimePassword(n = ONE_TIME_PASSWORD_CHARS) {
  const bytes = crypto.getRandomValues(new Uint8Array(n * 2));
  let out = "";
  for (const b of bytes) {
    if (b < 256 - (256 % PASSWORD_ALPHABET.length)) out += PASSWORD_ALPHABET[b % PASSWORD_ALPHABET.length];
    if (out.length === n) break;
  }
  return out.length === n ? out : oneTimePassword(n);
}

function adminOnly(root, user) {
  if (user.role === "admin") return false;
  root.append(h("h1", {}, "Admins only"),
    h("p", { class: "message error", role: "alert" }, `This page is for admins; you are signed in as ${user.role}.`));
  return true;
}

// -- users ---------------------------------------------------------------------------------

function createUserForm(onCreated) {
  const email = h("input", { type: "email", name: "email", required: true, maxlength: 320, autocomplete: "off" });
  const role = h("select", { name: "role" }, ROLES.map((r) => h("option", { value: r, selected: r === "staff" }, r)));
  const fields = { email: field("E-mail", email), role: field("Role", role) };
  const message = messageBox();
  const submit = h("button", { type: "submit", class: "btn primary" }, "Create account");
  const form = h("form", { class: "card", id: "user-form", "aria-labelledby": "user-form-title", novalidate: true },
    h("h2", { id: "user-form-title" }, "New account"),
    h("p", { class: "muted small" }, "A one-time password is made here and shown once: give it to the person, who changes it under Your account."),
    ...Object.values(fields), submit, message);
  form.addEventListener("submit", oneAtATime([submit], async () => {
    for (const f of Object.values(fields)) f.setError("");
    message.clear();
    const password = oneTimePassword();
    try {
      const user = await post("/api/v1/users", { email: email.value, password, role: role.value });
      email.value = "";
      await onCreated(user, password);
    } catch (err) {
      showRefusal(err, fields, message);
    }
    return null;
  }));
  return form;
}

export async function usersPage(root, { user: me }) {
  document.title = "Users · Brain-guided RL platform";
  if (adminOnly(root, me)) return;
  const message = messageBox();
  const secret = h("div", { id: "one-time-password" });
  const list = h("div");

  function roleCell(u) {
    const select = h("select", { "aria-label": `Role of ${u.email}`, name: "role" },
      ROLES.map((r) => h("option", { value: r, selected: r === u.role }, r)));
    select.addEventListener("change", oneAtATime([select], async () => {
      message.clear();
      try {
        await patch(`/api/v1/users/${u.id}`, { role: select.value });
        message.show(`${u.email} is now ${select.value}.`);
      } catch (err) {
        select.value = u.role;
        message.error(err);
      }
      await load();
    }));
    return select;
  }

  function actionsCell(u) {
    const toggle = h("button", { type: "button", class: `btn small${u.active ? " danger" : ""}` },
      u.active ? "Deactivate" : "Reactivate");
    toggle.addEventListener("click", oneAtATime([toggle], async () => {
      message.clear();
      try {
        await patch(`/api/v1/users/${u.id}`, { active: !u.active });
        message.show(u.active ? `${u.email} deactivated: they can no longer sign in.` : `${u.email} can sign in again.`);
        await load();
      } catch (err) {
        message.error(err);
      }
    }));
    const reset = h("button", { type: "button", class: "btn small" }, "Reset password");
    reset.addEventListener("click", oneAtATime([reset], async () => {
      message.clear();
      const password = oneTimePassword();
      try {
        await patch(`/api/v1/users/${u.id}`, { password });
        secret.replaceChildren(shownOnce(`New password of ${u.email}`, password));
        message.show(`Password of ${u.email} reset: their sessions end now.`);
      } catch (err) {
        message.error(err);
      }
    }));
    return [toggle, " ", reset];
  }

  async function load() {
    const users = await all("/api/v1/users");
    list.replaceChildren(table(users, [
      { label: "E-mail", cell: (u) => [u.email, u.id === me.id ? h("span", { class: "muted small" }, " (you)") : null] },
      { label: "Role", cell: roleCell },
      { label: "Status", cell: (u) => h("span", { class: `badge ${u.active ? "" : "status-cancelled"}` }, u.active ? "active" : "deactivated") },
      { label: "Created", cell: (u) => fmtDateTime(u.created_at) },
      { label: "Last sign-in", cell: (u) => fmtDateTime(u.last_login_at) },
      { label: "", cell: actionsCell },
    ], { caption: `${users.length} account(s)` }));
  }

  const form = createUserForm(async (user, password) => {
    secret.replaceChildren(shownOnce(`One-time password of ${user.email}`, password));
    message.show(`Account ${user.email} (${user.role}) created.`);
    await load();
  });
  root.append(h("h1", {}, "Users"), secret, message,
    h("div", { class: "columns" }, h("section", { class: "wide scroll-x" }, list), h("aside", {}, form)));
  await load();
}

// -- rigs ----------------------------------------------------------------------------------

/** A channel map typed as lines "DEVICE = STANDARD" (or pasted as JSON) -> an object. */
export function parseChannelMap(text) {
  const trimmed = text.trim();
  if (!trimmed) return {};
  if (trimmed.startsWith("{")) {
    let parsed;
    try {
      parsed = JSON.parse(trimmed);
    } catch (err) {
      throw new Error(`not valid JSON: ${err.message}`);
    }
    if (typeof parsed !== "object" || parsed === null || Array.isArray(parsed)) throw new Error("give a JSON object");
    return parsed;
  }
  const map = {};
  trimmed.split(/\r?\n/).forEach((line, i) => {
    if (!line.trim()) return;
    const parts = line.split(/\s*(?:=|->|:|\t)\s*/);
    if (parts.length !== 2 || !parts[0].trim() || !parts[1].trim()) {
      throw new Error(`line ${i + 1} (${line.trim()}): write DEVICE = STANDARD, e.g. A1 = Fp1`);
    }
    const device = parts[0].trim();
    if (device in map) throw new Error(`line ${i + 1}: ${device} is mapped twice`);
    map[device] = parts[1].trim();
  });
  return map;
}

function channelMapText(map) {
  return Object.entries(map || {}).map(([device, standard]) => `${device} = ${standard}`).join("\n");
}

function rigForm(rig, onSaved) {
  const name = h("input", { name: "name", required: true, maxlength: 100, value: rig?.name || "" });
  const location = h("input", { name: "location", maxlength: 200, value: rig?.location || "" });
  const description = h("input", { name: "description", maxlength: 10000, value: rig?.description || "" });
  const active = h("input", { type: "checkbox", name: "active", checked: rig ? rig.active : true });
  const map = h("textarea", { name: "channel_map", rows: 6, spellcheck: "false", placeholder: "A1 = Fp1\nA2 = AF7\n…" }, channelMapText(rig?.channel_map));
  const fields = {
    name: field("Name", name),
    location: field("Location", location, "room or lab"),
    description: field("Description", description),
    channel_map: field("Channel map", map, "one line per amplifier channel: DEVICE = STANDARD 10-20/10-10 name (or Status for the trigger). Empty: the stream's names are standard."),
  };
  const message = messageBox();
  const submit = h("button", { type: "submit", class: "btn primary" }, rig ? "Save rig" : "Add rig");
  const form = h("form", { class: "card rig-form", "aria-label": rig ? `Edit rig ${rig.name}` : "New rig" },
    rig ? null : h("h2", {}, "New rig"),
    ...Object.values(fields), h("label", { class: "check" }, active, " Active (sessions can be scheduled on it)"),
    submit, message);
  form.addEventListener("submit", oneAtATime([submit], async () => {
    for (const f of Object.values(fields)) f.setError("");
    message.clear();
    let channelMap;
    try {
      channelMap = parseChannelMap(map.value);
    } catch (err) {
      fields.channel_map.setError(err.message);
      return null;
    }
    const body = {
      name: name.value, location: location.value, description: description.value,
      active: active.checked, channel_map: channelMap,
    };
    try {
      const saved = rig ? await patch(`/api/v1/rigs/${rig.id}`, body)
        : await post("/api/v1/rigs", { ...body, channel_map: Object.keys(channelMap).length ? channelMap : null });
      await onSaved(saved, rig ? "saved" : "added");
      if (!rig) {
        name.value = ""; location.value = ""; description.value = ""; map.value = "";
      }
    } catch (err) {
      const fieldName = Object.keys(err.fields || {}).find((k) => k.startsWith("channel_map"));
      if (fieldName) fields.channel_map.setError(err.fields[fieldName]);
      showRefusal(err, fields, message);
    }
    return null;
  }));
  return form;
}

export async function rigsPage(root, { user }) {
  document.title = "Rigs · Brain-guided RL platform";
  if (adminOnly(root, user)) return;
  const message = messageBox();
  const list = h("div");
  async function saved(rig, how) {
    message.show(`Rig ${rig.name} ${how}.`);
    await load();
  }
  async function load() {
    const rigs = await all("/api/v1/rigs");
    list.replaceChildren(...(rigs.length ? rigs.map((rig) => h("details", { class: "rig", "data-rig": rig.id },
      h("summary", {}, h("strong", {}, rig.name), ` ${rig.location || ""} `,
        h("span", { class: "badge" }, rig.active ? "active" : "inactive"), " ",
        h("span", { class: "muted small" }, rig.channel_map ? `${Object.keys(rig.channel_map).length} channel${Object.keys(rig.channel_map).length === 1 ? "" : "s"} mapped` : "standard channel names")),
      rigForm(rig, saved))) : [h("p", { class: "muted" }, "No rigs yet.")]));
  }
  root.append(h("h1", {}, "Rigs"), message,
    h("p", { class: "muted" }, "A live session on a rig reads its amplifier's LSL stream through the rig's channel map; the EEG service checks the map against the stream when the session starts and names what does not fit."),
    h("div", { class: "columns" }, h("section", { class: "wide" }, list), h("aside", {}, rigForm(null, saved))));
  await load();
}

// -- audit log -----------------------------------------------------------------------------

const AUDIT_PAGE = 50;
/** The actions the API records (a hint while typing: the filter takes any). */
const AUDIT_ACTIONS = [
  "job.submit", "job.cancel", "job.retry", "recording.upload", "recording.validate", "recording.delete",
  "rig.create", "rig.update", "rig.delete", "session.create", "session.update", "session.cancel",
  "session.start", "session.stop", "subject.create", "subject.update", "subject.delete",
  "token.create", "token.revoke", "user.create", "user.update", "user.password",
];

export async function auditPage(root, { user, query }) {
  document.title = "Audit log · Brain-guided RL platform";
  if (adminOnly(root, user)) return;
  const users = await all("/api/v1/users");
  const action = h("input", {
    id: "audit-action", name: "action", value: query.get("action") || "", placeholder: "e.g. job.submit", maxlength: 64,
    list: "audit-actions",
  });
  const actions = h("datalist", { id: "audit-actions" }, AUDIT_ACTIONS.map((a) => h("option", { value: a })));
  const actor = h("select", { id: "audit-actor", name: "actor_id" }, h("option", { value: "" }, "anyone"),
    users.map((u) => h("option", { value: u.id, selected: String(u.id) === query.get("actor_id") }, u.email)));
  const targetType = h("input", { id: "audit-target-type", name: "target_type", value: query.get("target_type") || "", placeholder: "e.g. job", maxlength: 32 });
  const targetId = h("input", { id: "audit-target-id", name: "target_id", value: query.get("target_id") || "", maxlength: 64 });
  const message = messageBox();
  const list = h("div");
  const pager = h("div", { class: "pager" });
  let offset = 0;
  const filters = () => ({ action: action.value.trim(), actor_id: actor.value, target_type: targetType.value.trim(), target_id: targetId.value.trim() });

  async function load() {
    message.clear();
    let page;
    try {
      page = await get("/api/v1/audit", { ...filters(), limit: AUDIT_PAGE, offset });
    } catch (err) {
      message.error(err);
      return;
    }
    list.replaceChildren(table(page.items, [
      { label: "When", cell: (e) => fmtDateTime(e.at) },
      { label: "Who", cell: (e) => e.actor_email || "–" },
      { label: "Action", cell: (e) => h("code", {}, e.action) },
      { label: "Target", cell: (e) => `${e.target_type} ${e.target_id ?? ""}` },
      { label: "Detail", cell: (e) => Object.entries(e.detail || {}).map(([k, v]) => `${k}: ${typeof v === "string" ? v : JSON.stringify(v)}`).join(", ") || "–" },
    ], { caption: `${page.total} entr${page.total === 1 ? "y" : "ies"}`, empty: "No entries match." }));
    const newer = h("button", { type: "button", class: "btn small", disabled: offset === 0 }, "Newer");
    const older = h("button", { type: "button", class: "btn small", disabled: offset + AUDIT_PAGE >= page.total }, "Older");
    newer.addEventListener("click", () => { offset = Math.max(0, offset - AUDIT_PAGE); load(); });
    older.addEventListener("click", () => { offset += AUDIT_PAGE; load(); });
    pager.replaceChildren(...(page.total > AUDIT_PAGE ? [newer, " ", older] : []));
  }
  const form = h("form", { class: "inline", id: "audit-filters", "aria-label": "Filter the audit log" },
    h("label", { for: "audit-action" }, "Action"), action, actions,
    h("label", { for: "audit-actor" }, "By"), actor,
    h("label", { for: "audit-target-type" }, "Target type"), targetType,
    h("label", { for: "audit-target-id" }, "Target id"), targetId,
    h("button", { type: "submit", class: "btn small" }, "Filter"));
  form.addEventListener("submit", (event) => {
    event.preventDefault();
    offset = 0;
    const params = new URLSearchParams(Object.entries(filters()).filter(([, v]) => v));
    history.replaceState(null, "", `/admin/audit${params.size ? `?${params}` : ""}`);
    load();
  });
  actor.addEventListener("change", () => form.requestSubmit());
  root.append(h("h1", {}, "Audit log"), form, message, h("section", { class: "scroll-x" }, list), pager);
  await load();
}
