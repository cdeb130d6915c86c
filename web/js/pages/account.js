// Your account (every signed-in user): change your password, and your API tokens for
// scripts (create: shown once; list; revoke).

import { all, post, request, signOut, toSignIn } from "../api.js";
import { field, fmtDateTime, h, messageBox, oneAtATime, showRefusal, table } from "../dom.js";

const MIN_PASSWORD_CHARS = 12; // the API's minimum (accounts.MIN_PASSWORD_CHARS)

/** A secret shown this once, with a copy button and a warning that it is not shown again. */
export function shownOnce(label, secret) {
  const value = h("input", { class: "secret", value: secret, readonly: true, "aria-label": label, size: Math.min(secret.length, 60) });
  const copy = h("button", { type: "button", class: "btn small" }, "Copy");
  copy.addEventListener("click", async () => {
    value.select();
    try {
      await navigator.clipboard.writeText(secret);
      copy.textContent = "Copied";
    } catch {
      copy.textContent = "Press Ctrl+C"; // selected above
    }
  });
  return h("div", { class: "message warning shown-once", role: "status" },
    h("strong", {}, label), " (shown this once: copy it now) ", value, " ", copy);
}

function passwordForm(message) {
  const current = h("input", { type: "password", name: "current_password", autocomplete: "current-password", required: true });
  const next = h("input", { type: "password", name: "new_password", autocomplete: "new-password", required: true, minlength: MIN_PASSWORD_CHARS });
  const again = h("input", { type: "password", name: "repeat", autocomplete: "new-password", required: true });
  const fields = {
    current_password: field("Current password", current),
    new_password: field("New password", next, `at least ${MIN_PASSWORD_CHARS} characters`),
    repeat: field("New password again", again),
  };
  const submit = h("button", { type: "submit", class: "btn primary" }, "Change password");
  const form = h("form", { class: "card", id: "password-form", "aria-labelledby": "password-title" },
    h("h2", { id: "password-title" }, "Change your password"), ...Object.values(fields), submit);
  form.addEventListener("submit", oneAtATime([submit], async () => {
    for (const f of Object.values(fields)) f.setError("");
    message.clear();
    if (next.value !== again.value) {
      fields.repeat.setError("the two new passwords differ");
      return null;
    }
    try {
      await request("/api/v1/users/me/password", {
        method: "POST", json: { current_password: current.value, new_password: next.value },
      });
    } catch (err) {
      showRefusal(err, fields, message);
      return null;
    }
    // the API ends every access token issued before the change: sign in with the new one
    signOut();
    toSignIn("Password changed: sign in with the new one.");
    return "leaving";
  }));
  return form;
}

function tokenSection(user) {
  const message = messageBox();
  const list = h("div");
  const created = h("div");
  async function load() {
    const tokens = (await all("/api/v1/tokens")).filter((t) => t.user_id === user.id);
    list.replaceChildren(table(tokens, [
      { label: "Name", cell: (t) => t.name },
      { label: "Starts with", cell: (t) => h("code", {}, `${t.token_prefix}…`) },
      { label: "Created", cell: (t) => fmtDateTime(t.created_at) },
      { label: "Expires", cell: (t) => (t.expires_at ? fmtDateTime(t.expires_at) : "never") },
      { label: "Last used", cell: (t) => fmtDateTime(t.last_used_at) },
      {
        label: "",
        cell: (t) => {
          if (t.revoked_at) return h("span", { class: "muted" }, `revoked ${fmtDateTime(t.revoked_at)}`);
          const revoke = h("button", { type: "button", class: "btn small danger" }, "Revoke");
          revoke.addEventListener("click", oneAtATime([revoke], async () => {
            try {
              await request(`/api/v1/tokens/${t.id}`, { method: "DELETE" });
              message.show(`Token ${t.name} revoked: it stops working at once.`);
              await load();
            } catch (err) {
              message.error(err);
            }
          }));
          return revoke;
        },
      },
    ], { caption: "Your API tokens", empty: "No API tokens: scripts and `bgrl login` create them." }));
  }
  const name = h("input", { name: "name", required: true, maxlength: 100, placeholder: "e.g. analysis laptop" });
  const days = h("input", { type: "number", name: "expires_in_days", min: 1, max: 3650, value: 90 });
  const fields = { name: field("Name", name), expires_in_days: field("Days valid", days, "empty: never expires") };
  const submit = h("button", { type: "submit", class: "btn primary" }, "Create token");
  const form = h("form", { class: "inline-form", id: "token-form", "aria-label": "Create an API token" },
    ...Object.values(fields), submit);
  form.addEventListener("submit", oneAtATime([submit], async () => {
    for (const f of Object.values(fields)) f.setError("");
    message.clear();
    try {
      const token = await post("/api/v1/tokens", {
        name: name.value, expires_in_days: days.value ? Number(days.value) : null,
      });
      created.replaceChildren(shownOnce(`API token ${token.name}`, token.token));
      name.value = "";
      await load();
    } catch (err) {
      showRefusal(err, fields, message);
    }
    return null;
  }));
  return { node: h("section", { "aria-labelledby": "tokens-title" },
    h("h2", { id: "tokens-title" }, "API tokens"),
    h("p", { class: "muted" }, "A token acts as you, with your role, for scripts and the CLI ",
      "(header Authorization: Bearer TOKEN, or BGRL_API_TOKEN for bgrl)."),
    form, message, created, list), load };
}

export async function accountPage(root, { user }) {
  document.title = "Your account · Brain-guided RL platform";
  const message = messageBox();
  const tokens = tokenSection(user);
  root.append(
    h("h1", {}, "Your account"),
    h("p", {}, `${user.email}, role ${user.role}; last sign-in ${fmtDateTime(user.last_login_at)}.`),
    h("div", { class: "columns" }, h("section", { class: "wide" }, tokens.node),
      h("aside", {}, passwordForm(message), message)),
  );
  await tokens.load();
}
